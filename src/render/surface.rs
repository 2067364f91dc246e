//! Shaded surface display: the iso-surfaces each ray crosses, found between samples and refined by secant steps
//! on the trilinear field, Phong-shaded with the gradient as normal, dimmed with depth and composited front to
//! back by their opacities. A clip that cuts into a solid shows the cut as a flat cap facing the clip.
//!
//! Why ray casting and not rasterising the mesh product: the rays sample the same trilinear field the mesh
//! approximates, so the hit is sub-voxel without a mesh of millions of triangles, clips and caps come for free
//! from the ray intervals, and VR and SSD share the camera, bricks and tiles.

use serde::{Deserialize, Serialize};

use super::bricks::{BrickMask, RayDir, Samples};
use super::clip::Span;
use super::composite::same_size;
use super::image::{Shade, render_frames};
use super::occupancy::Occupancy;
use super::scene::Scene;
use super::{Clip, RenderError, RgbImage, Sampler, Shading, V3, ViewRays, dot};

/// One iso-surface: `iso` in the volume's units (inside is at or above; a finite 32-bit float), its RGB colour
/// (0–1) and opacity (0–1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Surface {
    pub iso: f64,
    #[serde(default = "ivory")]
    pub color: [f64; 3],
    #[serde(default = "opaque")]
    pub opacity: f64,
}

fn ivory() -> [f64; 3] {
    [0.95, 0.92, 0.84]
}
fn opaque() -> f64 {
    1.0
}

/// What a shaded surface display shows besides the camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SsdOptions {
    pub surfaces: Vec<Surface>,
    pub shading: Shading,
    /// Dimming from the front to the back of the volume's bounding sphere: 0 none, 1 black at the back.
    pub depth_cue: f64,
    pub clip: Clip,
    pub background: [f64; 3],
    pub step_mm: Option<f64>,
}

/// Largest number of iso-surfaces in one rendering.
pub const MAX_SURFACES: usize = 8;

impl SsdOptions {
    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |name, reason: &str| {
            Err(RenderError::InvalidParameter {
                name,
                reason: reason.into(),
            })
        };
        if self.surfaces.is_empty() || self.surfaces.len() > MAX_SURFACES {
            return bad("surfaces", "give 1 to 8 iso-surfaces");
        }
        let unit = |v: f64| v.is_finite() && (0.0..=1.0).contains(&v);
        for s in &self.surfaces {
            // Rays compare 32-bit samples with the iso-value.
            if !(s.iso as f32).is_finite() || !unit(s.opacity) || !s.color.iter().all(|&c| unit(c))
            {
                return bad(
                    "surfaces",
                    "iso a finite 32-bit float, colour and opacity within [0, 1]",
                );
            }
        }
        if !unit(self.depth_cue) {
            return bad("depth_cue", "must be within [0, 1]");
        }
        if !self.background.iter().all(|&c| unit(c)) {
            return bad("background", "RGB values within [0, 1]");
        }
        self.shading.validate()?;
        self.clip.validate()
    }
}

/// A surface crossing on a ray: where, which surface, and the normal to shade with.
struct Hit {
    t: f64,
    surface: usize,
    normal: V3,
}

/// Render the iso-surfaces of `scene` for `rays`. The depth of a pixel is its first hit.
pub fn surface_render(
    scene: &Scene<'_>,
    rays: &ViewRays,
    opts: &SsdOptions,
) -> Result<RgbImage, RenderError> {
    let mut frames = surface_render_frames(scene, std::slice::from_ref(rays), opts)?;
    frames.pop().ok_or(RenderError::BadVolume)
}

/// [`surface_render`] for each of `rays` (pictures of one size, a turning sequence), rendered together as
/// [`volume_render_frames`](super::volume_render_frames) does.
pub fn surface_render_frames(
    scene: &Scene<'_>,
    rays: &[ViewRays],
    opts: &SsdOptions,
) -> Result<Vec<RgbImage>, RenderError> {
    opts.validate()?;
    let (width, height) = same_size(rays)?;
    let step = scene.step(opts.step_mm)?;
    let samples = Samples::new(step);
    let isos: Vec<f32> = opts.surfaces.iter().map(|s| s.iso as f32).collect();
    let mut key = vec![1];
    key.extend(isos.iter().map(|iso| u64::from(iso.to_bits())));
    let prepared = scene.prepared(
        key,
        || {
            scene
                .bricks
                .mask(|lo, hi| isos.iter().any(|&iso| lo <= iso && iso <= hi))
        },
        isos.iter().map(|&iso| (iso, iso)).collect(),
    );
    let shaders: Vec<SsdShader<'_>> = rays
        .iter()
        .map(|rays| SsdShader {
            rays,
            s: &scene.sampler,
            opts,
            mask: &prepared.mask,
            cells: prepared.cells.as_ref(),
            samples,
            isos: isos.clone(),
            bg: opts.background.map(|c| c as f32),
            centre: scene.centre,
            radius: scene.radius,
        })
        .collect();
    Ok(render_frames(width, height, &shaders))
}

/// What [`surface_render`] needs for each pixel.
struct SsdShader<'a> {
    rays: &'a ViewRays,
    s: &'a Sampler<'a>,
    opts: &'a SsdOptions,
    mask: &'a BrickMask,
    cells: Option<&'a Occupancy>,
    samples: Samples,
    isos: Vec<f32>,
    bg: [f32; 3],
    centre: V3,
    radius: f64,
}

impl Shade for SsdShader<'_> {
    /// The spans of a ray and the hits of one step.
    type Scratch = (Vec<Span>, Vec<Hit>);

    fn scratch(&self) -> Self::Scratch {
        (Vec::new(), Vec::new())
    }

    #[inline(always)]
    fn shade(&self, scratch: &mut Self::Scratch, r: usize, c: usize) -> ([f32; 3], f32) {
        let (spans, hits) = scratch;
        let (s, opts, samples, mask, cells, isos) = (
            self.s,
            self.opts,
            &self.samples,
            self.mask,
            self.cells,
            &self.isos,
        );
        let (bg, centre, radius) = (self.bg, self.centre, self.radius);
        let (o, d) = self.rays.ray(r as f64, c as f64);
        let Some((b0, b1)) = s.box_interval(o, d) else {
            return (bg, f32::NAN);
        };
        opts.clip.spans(o, d, b0.max(0.0), b1, spans);
        let io = s.index(o);
        let id = s.index_direction(d);
        let ray_dir = RayDir::new(id);
        let at = |t: f64| -> [f32; 3] { std::array::from_fn(|a| (io[a] + t * id[a]) as f32) };
        let value = |t: f64| s.at_index(at(t));
        // Depth cue over the bounding sphere as seen along this ray.
        let mid = dot([centre[0] - o[0], centre[1] - o[1], centre[2] - o[2]], d);
        let (near, far) = (mid - radius, mid + radius);
        let view = d.map(|x| -x);
        let (mut acc, mut alpha, mut depth) = ([0.0f32; 3], 0.0f32, f32::NAN);
        let add = |h: &Hit, acc: &mut [f32; 3], alpha: &mut f32, depth: &mut f32| {
            let sf = &opts.surfaces[h.surface];
            let (lit, spec) = opts.shading.light(h.normal, view);
            let cue = 1.0 - opts.depth_cue * ((h.t - near) / (far - near)).clamp(0.0, 1.0);
            let w = (1.0 - *alpha) * sf.opacity as f32;
            for (a, c) in acc.iter_mut().zip(sf.color) {
                *a += w * ((c as f32 * lit + spec) * cue as f32);
            }
            *alpha += w;
            if depth.is_nan() {
                *depth = h.t as f32;
            }
        };
        'spans: for sp in spans.iter() {
            // A span that starts inside a solid shows the cut face.
            let (mut t_prev, mut v_prev) = (sp.t0, value(sp.t0));
            // Whether `v_prev` is the sample's value; else a corner of a cell that no iso-value crosses, on
            // the same side of every iso-value as the sample.
            let mut prev_exact = true;
            hits.clear();
            for (i, &iso) in isos.iter().enumerate() {
                if v_prev >= iso {
                    hits.push(Hit {
                        t: sp.t0,
                        surface: i,
                        normal: sp.face.unwrap_or(d),
                    });
                }
            }
            hits.sort_by(|a, b| {
                opts.surfaces[a.surface]
                    .iso
                    .total_cmp(&opts.surfaces[b.surface].iso)
            });
            for h in hits.iter() {
                add(h, &mut acc, &mut alpha, &mut depth);
                if alpha >= super::composite::EARLY_TERMINATION {
                    break 'spans;
                }
            }
            let mut k = 1u64;
            // Samples up to this `t` lie in a busy brick already checked.
            let mut busy_until = f64::NEG_INFINITY;
            loop {
                let t = (sp.t0 + samples.offset(k)).min(sp.t1);
                let idx = at(t);
                if t > busy_until && t < sp.t1 {
                    let (busy, exit) = mask.step(idx, &ray_dir);
                    if !busy {
                        let exit = (t + exit).min(sp.t1);
                        // The field keeps its side of every iso-value through quiet bricks.
                        t_prev = exit;
                        v_prev = value(exit);
                        prev_exact = true;
                        k = (k + 1).max(samples.first_beyond(exit, sp.t0));
                        continue;
                    }
                    busy_until = t + exit;
                }
                let (cell, f) = s.cell(idx);
                let (v, exact) = match cells {
                    Some(o) if !o.busy(cell) => (s.corner(cell), false),
                    _ => (s.at_cell(cell, f), true),
                };
                hits.clear();
                for (i, &iso) in isos.iter().enumerate() {
                    if (v_prev < iso) != (v < iso) {
                        if !prev_exact {
                            v_prev = value(t_prev);
                            prev_exact = true;
                        }
                        let vt = if exact { v } else { value(t) };
                        let th = refine(&value, iso, (t_prev, v_prev), (t, vt));
                        hits.push(Hit {
                            t: th,
                            surface: i,
                            normal: s.gradient(at(th)),
                        });
                    }
                }
                hits.sort_by(|a, b| a.t.total_cmp(&b.t));
                for h in hits.iter() {
                    add(h, &mut acc, &mut alpha, &mut depth);
                    if alpha >= super::composite::EARLY_TERMINATION {
                        break 'spans;
                    }
                }
                if t >= sp.t1 {
                    break;
                }
                (t_prev, v_prev, prev_exact) = (t, v, exact);
                k += 1;
            }
        }
        (
            std::array::from_fn(|ch| acc[ch] + (1.0 - alpha) * bg[ch]),
            depth,
        )
    }
}

/// The crossing of `iso` between `(ta, va)` and `(tb, vb)` (values on opposite sides), by four secant steps
/// kept inside the bracket.
fn refine(value: &impl Fn(f64) -> f32, iso: f32, a: (f64, f32), b: (f64, f32)) -> f64 {
    let (mut ta, mut va, mut tb, mut vb) = (a.0, a.1 as f64, b.0, b.1 as f64);
    let iso = iso as f64;
    let mut t = ta;
    for _ in 0..4 {
        let dv = vb - va;
        t = if dv.abs() > 1e-20 {
            ta + (iso - va) / dv * (tb - ta)
        } else {
            (ta + tb) / 2.0
        };
        let v = value(t) as f64;
        if (v < iso) == (va < iso) {
            (ta, va) = (t, v);
        } else {
            (tb, vb) = (t, v);
        }
    }
    t
}
