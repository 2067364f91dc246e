//! Cut-away meshes: the iso-surface of a volume clipped by planes and boxes, capped so that the cut face is
//! closed.
//!
//! The clip is applied to the field rather than to the triangles: marching cubes runs on
//! g = iso + min(f − iso, s·d), where d is the signed distance (mm) to the kept region ([`Clip::distance`],
//! positive where the volume stays) and s the mean gradient magnitude of f across the iso-surface, so that both
//! terms change at the same rate near the rim. Where the solid is kept g follows f; where it is cut away g is
//! below iso; on the cut, g crosses iso on the clip plane, which marching cubes closes into a flat cap. The
//! result is a closed surface whenever the unclipped one is, with no polygon triangulation to go wrong.

use ndarray::{Array3, Zip};

use crate::render::Clip;
use crate::volume::Volume;

/// Mean |∇f| (value per mm) over the sample pairs that straddle `iso` along the three index axes; 1 when none do.
fn crossing_gradient(vol: &Volume, iso: f32) -> f64 {
    let d = &vol.data;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (axis, sp) in vol.frame.spacing_mm.iter().enumerate() {
        let ax = ndarray::Axis(2 - axis);
        let len = d.len_of(ax);
        if len < 2 {
            continue;
        }
        let a = d.slice_axis(ax, ndarray::Slice::from(0..len - 1));
        let b = d.slice_axis(ax, ndarray::Slice::from(1..len));
        Zip::from(&a).and(&b).for_each(|&x, &y| {
            if (x < iso) != (y < iso) {
                sum += ((y - x) as f64).abs() / sp;
                n += 1;
            }
        });
    }
    if n == 0 || sum <= 0.0 {
        1.0
    } else {
        sum / n as f64
    }
}

/// The field whose iso-surface at `iso` is the surface of `vol` clipped by `clip` and capped on the cut.
pub fn clipped_field(vol: &Volume, iso: f32, clip: &Clip) -> Volume {
    if clip.is_empty() {
        return vol.clone();
    }
    let s = crossing_gradient(vol, iso);
    let f = vol.frame;
    let data = Array3::from_shape_fn(vol.data.dim(), |(k, j, i)| {
        let v = vol.data[[k, j, i]];
        let d = clip.distance(f.position(k as f64, j as f64, i as f64));
        let cut = (s * d) as f32;
        iso + (v - iso).min(cut)
    });
    Volume { data, frame: f }
}
