//! The column-ordered pair against the ray walks of [`joseph3`] (the same pairs up to f32 rounding of
//! the positions), its forms against each other (equal bit for bit), and the exact transpose, on
//! geometries with detector offsets, anisotropic voxels, steep rays (walks along z) and a tilted panel.
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use crate::recon::geometry::{Angles, ConeBeam, Panel};

pub(crate) fn grid() -> VolumeGrid {
    VolumeGrid {
        nx: 21,
        ny: 18,
        nz: 40,
        spacing_mm: [1.0, 1.1, 1.3],
        centre_mm: [0.5, -0.5, 1.0],
    }
}

/// A cone beam over 360° whose tallest rays are steeper than 45° when `steep`.
pub(crate) fn cone(steep: bool) -> Views3 {
    let (dso, dsd, nv, dv) = if steep {
        (14.0, 30.0, 48, 1.5)
    } else {
        (60.0, 110.0, 64, 1.6)
    };
    ConeBeam {
        angles: Angles::uniform(17, 360.0),
        dso_mm: dso,
        dsd_mm: dsd,
        detector: Panel {
            nu: 40,
            nv,
            du_mm: 1.2,
            dv_mm: dv,
            offset_u_mm: 0.7,
            offset_v_mm: -1.3,
        },
    }
    .to_views()
    .unwrap()
}

fn random(n: usize, seed: u64) -> Vec<f32> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n).map(|_| rng.random::<f32>()).collect()
}

/// Walk-based forward and back projections of every view.
fn by_walks(views: &Views3, grid: &VolumeGrid, x: &[f32], y: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let m = views.detector.nu * views.detector.nv;
    let mut ax = vec![0.0f32; views.views.len() * m];
    let mut aty = vec![0.0f32; x.len()];
    for v in 0..views.views.len() {
        joseph3::forward_view(views, v, grid, x, &mut ax[v * m..(v + 1) * m]);
        joseph3::back_view(views, v, grid, &y[v * m..(v + 1) * m], &mut aty);
    }
    (ax, aty)
}

fn by_columns(
    form: Form,
    views: &Views3,
    grid: &VolumeGrid,
    x: &[f32],
    y: &[f32],
) -> (Vec<f32>, Vec<f32>) {
    let all: Vec<usize> = (0..views.views.len()).collect();
    let mut ax = vec![f32::NAN; y.len()];
    let mut aty = vec![f32::NAN; x.len()];
    let never = Cancel::new();
    let plans = Plans::new(views, grid, &all);
    forward_with(form, views, grid, &plans, x, &mut ax, &never).unwrap();
    back_with(form, views, grid, &plans, y, &mut aty, &never).unwrap();
    (ax, aty)
}

fn max_abs(a: &[f32]) -> f32 {
    a.iter().fold(0.0f32, |m, v| m.max(v.abs()))
}

fn assert_close(got: &[f32], want: &[f32], what: &str) {
    let scale = max_abs(want);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= 2e-5 * scale,
            "{what}[{i}]: {g} vs {w} (scale {scale})"
        );
    }
}

#[test]
fn columns_give_the_walks_values_and_every_form_the_same_bits() {
    let grid = grid();
    for steep in [false, true] {
        let views = cone(steep);
        let m = views.detector.nu * views.detector.nv * views.views.len();
        let x = random(grid.voxels() as usize, 1);
        let y = random(m, 2);
        let (ax, aty) = by_walks(&views, &grid, &x, &y);
        let forms = Form::available();
        let (ax0, aty0) = by_columns(forms[0], &views, &grid, &x, &y);
        assert_close(&ax0, &ax, "forward");
        assert_close(&aty0, &aty, "back");
        for &form in &forms[1..] {
            let (axf, atyf) = by_columns(form, &views, &grid, &x, &y);
            assert_eq!(axf, ax0, "{form:?} forward");
            assert_eq!(atyf, aty0, "{form:?} back");
        }
        for form in [Form::Avx2, Form::Avx512] {
            if !forms.contains(&form) {
                println!("skipped: {form:?} (this CPU lacks it)");
            }
        }
    }
}

#[test]
fn steep_rays_and_tilted_panels_keep_the_walks() {
    let grid = grid();
    let mut views = cone(true);
    let plans: Vec<_> = (0..views.views.len())
        .filter_map(|v| plan(&views, v, &grid))
        .collect();
    assert!(
        plans.iter().map(|p| p.steep.len()).sum::<usize>() > 100,
        "no steep rays"
    );
    // Tilt one panel about its u axis: that view has no column plan.
    let t = 0.2f64;
    let v = &mut views.views[3];
    let n = crate::recon::geometry::vectors::cross3(v.det_u, v.det_v);
    v.det_v = [0, 1, 2].map(|k| v.det_v[k] * t.cos() + n[k] * t.sin());
    assert!(plan(&views, 3, &grid).is_none());
    let m = views.detector.nu * views.detector.nv * views.views.len();
    let (x, y) = (random(grid.voxels() as usize, 3), random(m, 4));
    let (ax, aty) = by_walks(&views, &grid, &x, &y);
    let (axc, atyc) = by_columns(Form::detect(), &views, &grid, &x, &y);
    assert_close(&axc, &ax, "forward");
    assert_close(&atyc, &aty, "back");
}

#[test]
fn back_is_the_transpose_of_forward() {
    let grid = grid();
    let views = cone(false);
    let m = views.detector.nu * views.detector.nv * views.views.len();
    let (x, y) = (random(grid.voxels() as usize, 5), random(m, 6));
    let (ax, aty) = by_columns(Form::detect(), &views, &grid, &x, &y);
    let lhs: f64 = ax.iter().zip(&y).map(|(a, b)| *a as f64 * *b as f64).sum();
    let rhs: f64 = x.iter().zip(&aty).map(|(a, b)| *a as f64 * *b as f64).sum();
    let norm = |v: &[f32]| v.iter().map(|a| (*a as f64).powi(2)).sum::<f64>().sqrt();
    let e = (lhs - rhs).abs() / (norm(&ax) * norm(&y));
    assert!(e < 1e-6, "{e}");
}

#[test]
fn plans_kept_across_passes_give_the_values_of_fresh_ones() {
    // The steep cone: columns whose rows outside the flat ones must be zero in the kept buffers.
    let grid = grid();
    let views = cone(true);
    let m = views.detector.nu * views.detector.nv * views.views.len();
    let all: Vec<usize> = (0..views.views.len()).collect();
    let (x, y1, y2) = (
        random(grid.voxels() as usize, 7),
        random(m, 8),
        random(m, 9),
    );
    let (kept, never, form) = (
        Plans::new(&views, &grid, &all),
        Cancel::new(),
        Form::detect(),
    );
    let mut images = [vec![0.0f32; x.len()], vec![0.0f32; x.len()]];
    for (image, y) in images.iter_mut().zip([&y1, &y2]) {
        back_with(form, &views, &grid, &kept, y, image, &never).unwrap();
    }
    let (_, fresh) = by_columns(form, &views, &grid, &x, &y2);
    assert_eq!(images[1], fresh);
    assert_ne!(images[0], images[1]);
}

#[test]
fn subsets_sharing_the_kept_buffers_give_the_values_of_fresh_plans() {
    // Two subsets of one cache take turns with its one weighted copy of the data: each pass must
    // write every value, the steep rows' zeros included.
    let grid = grid();
    let views = cone(true);
    let n = views.views.len();
    let m = views.detector.nu * views.detector.nv;
    let cache = PlanCache::default();
    let (never, form) = (Cancel::new(), Form::detect());
    let subsets: [Vec<usize>; 2] = [(0..n).rev().collect(), (0..n).step_by(3).collect()];
    for (round, subset) in subsets.iter().chain(subsets.iter()).enumerate() {
        let y = random(m * subset.len(), 20 + round as u64);
        let mut kept = vec![0.0f32; grid.voxels() as usize];
        let plans = cache.get(&views, &grid, subset);
        back_with(form, &views, &grid, &plans, &y, &mut kept, &never).unwrap();
        let mut fresh = vec![0.0f32; kept.len()];
        let plans = Plans::new(&views, &grid, subset);
        back_with(form, &views, &grid, &plans, &y, &mut fresh, &never).unwrap();
        assert_eq!(kept, fresh, "round {round}");
    }
}
