//! The back projectors are the exact adjoints of the forward projectors:
//! |⟨Ax, y⟩ − ⟨x, Aᵀy⟩| / (‖Ax‖‖y‖) < 1e-5 for random x, y on parallel, fan arc, fan flat and cone beams
//! (dot products in f64), also for random geometries (proptest). And the MATLAB `fanbeam` convention: an
//! off-centre bright pixel projects to the fan angle MATLAB's definition predicts.

use ctrecon::recon::geometry::{
    Angles, ConeBeam, FanBeam, FanDetector, MatlabFan, Panel, ParallelBeam, Views2, Views3,
};
use ctrecon::recon::grid::{ImageGrid, VolumeGrid};
use ctrecon::recon::projector::{back_2d, back_3d, forward_2d, forward_3d};
use ndarray::{Array2, Array3};
use proptest::prelude::*;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const TOL: f64 = 1e-5;

fn dot(a: impl Iterator<Item = f32>, b: impl Iterator<Item = f32>) -> f64 {
    a.zip(b).map(|(p, q)| p as f64 * q as f64).sum()
}

fn mismatch_2d(views: &Views2, grid: &ImageGrid, seed: u64) -> f64 {
    let mut rng = StdRng::seed_from_u64(seed);
    let x = Array2::from_shape_fn(grid.shape(), |_| rng.random::<f32>());
    let y = Array2::from_shape_fn(views.shape(), |_| rng.random::<f32>() - 0.3);
    let ax = forward_2d(views, x.view(), grid);
    let aty = back_2d(views, y.view(), grid);
    let lhs = dot(ax.iter().copied(), y.iter().copied());
    let rhs = dot(x.iter().copied(), aty.iter().copied());
    let n_ax = dot(ax.iter().copied(), ax.iter().copied()).sqrt();
    let n_y = dot(y.iter().copied(), y.iter().copied()).sqrt();
    (lhs - rhs).abs() / (n_ax * n_y)
}

fn mismatch_3d(views: &Views3, grid: &VolumeGrid, seed: u64) -> f64 {
    let mut rng = StdRng::seed_from_u64(seed);
    let x = Array3::from_shape_fn(grid.shape(), |_| rng.random::<f32>());
    let y = Array3::from_shape_fn(views.shape(), |_| rng.random::<f32>() - 0.3);
    let ax = forward_3d(views, x.view(), grid);
    let aty = back_3d(views, y.view(), grid);
    let lhs = dot(ax.iter().copied(), y.iter().copied());
    let rhs = dot(x.iter().copied(), aty.iter().copied());
    let n_ax = dot(ax.iter().copied(), ax.iter().copied()).sqrt();
    let n_y = dot(y.iter().copied(), y.iter().copied()).sqrt();
    (lhs - rhs).abs() / (n_ax * n_y)
}

fn fan(detector: FanDetector, views: usize) -> Views2 {
    FanBeam {
        angles: Angles::uniform(views, 360.0),
        dso_mm: 200.0,
        dsd_mm: 350.0,
        detector,
        centre_mm: [1.5, -2.0],
    }
    .to_views()
    .unwrap()
}

#[test]
fn back_projection_is_the_adjoint_on_a_parallel_beam() {
    let grid = ImageGrid {
        nx: 70,
        ny: 50,
        dx_mm: 1.2,
        dy_mm: 0.9,
        centre_mm: [3.0, -1.0],
    };
    let views = ParallelBeam {
        angles: Angles::uniform(37, 180.0),
        det_count: 101,
        det_spacing_mm: 0.8,
        det_offset_mm: 0.4,
    }
    .to_views()
    .unwrap();
    let e = mismatch_2d(&views, &grid, 1);
    assert!(e < TOL, "parallel: {e}");
}

#[test]
fn back_projection_is_the_adjoint_on_fan_beams() {
    let grid = ImageGrid::square(64, 1.0);
    let arc = fan(
        FanDetector::Arc {
            count: 97,
            spacing_deg: 0.3,
            offset_deg: 0.1,
        },
        41,
    );
    let flat = fan(
        FanDetector::Flat {
            count: 120,
            spacing_mm: 1.1,
            offset_mm: -0.6,
        },
        41,
    );
    let (ea, ef) = (mismatch_2d(&arc, &grid, 2), mismatch_2d(&flat, &grid, 3));
    assert!(ea < TOL, "fan arc: {ea}");
    assert!(ef < TOL, "fan flat: {ef}");
}

#[test]
fn back_projection_is_the_adjoint_on_a_cone_beam() {
    let grid = VolumeGrid {
        nx: 24,
        ny: 20,
        nz: 16,
        spacing_mm: [1.0, 1.1, 1.3],
        centre_mm: [0.5, -0.5, 2.0],
    };
    let views = ConeBeam {
        angles: Angles::uniform(23, 360.0),
        dso_mm: 80.0,
        dsd_mm: 140.0,
        detector: Panel {
            nu: 40,
            nv: 36,
            du_mm: 1.2,
            dv_mm: 1.1,
            offset_u_mm: 0.7,
            offset_v_mm: -1.3,
        },
    }
    .to_views()
    .unwrap();
    let e = mismatch_3d(&views, &grid, 4);
    assert!(e < TOL, "cone: {e}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn back_projection_is_the_adjoint_for_random_fan_geometries(
        nx in 5usize..40, ny in 5usize..40, px in 0.5f64..2.0,
        views in 1usize..30, count in 5usize..80, spacing in 0.1f64..1.0,
        dso in 100.0f64..300.0, extra in 10.0f64..200.0, arc in any::<bool>(), seed in 0u64..1000,
    ) {
        let grid = ImageGrid { nx, ny, dx_mm: px, dy_mm: px * 1.1, centre_mm: [0.0, 0.0] };
        let detector = if arc {
            FanDetector::Arc { count, spacing_deg: spacing, offset_deg: 0.0 }
        } else {
            FanDetector::Flat { count, spacing_mm: spacing * 3.0, offset_mm: 0.0 }
        };
        let v = FanBeam {
            angles: Angles::uniform(views, 360.0), dso_mm: dso, dsd_mm: dso + extra,
            detector, centre_mm: [0.0, 0.0],
        }.to_views().unwrap();
        let e = mismatch_2d(&v, &grid, seed);
        prop_assert!(e < TOL || e.is_nan(), "{e}");
    }
}

/// MATLAB's fan angle γ of the ray through the point (x, y) (pixels from the centre pixel, y up) at
/// rotation θ: the fan ray (θ, γ) is the parallel ray at angle θ + γ and distance D·sin γ
/// (`para2fan`), so γ solves D sin γ = x cos(θ + γ) + y sin(θ + γ). Bisection on |γ| < asin(r/D) + ε.
fn matlab_gamma(d: f64, x: f64, y: f64, theta: f64) -> f64 {
    let f = |g: f64| d * g.sin() - x * (theta + g).cos() - y * (theta + g).sin();
    let lim = (x.hypot(y) / d).asin() + 1e-3;
    let (mut lo, mut hi) = (-lim, lim);
    assert!(f(lo) * f(hi) <= 0.0);
    for _ in 0..100 {
        let mid = 0.5 * (lo + hi);
        if f(lo) * f(mid) <= 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    0.5 * (lo + hi)
}

#[test]
fn an_off_centre_pixel_projects_to_matlabs_fan_angle() {
    // 64 × 64 image, D = 150 px, arc sensors every 0.1°, rotation increment 1°.
    let m = MatlabFan::arc(64, 64, 150.0, 0.1, 1.0);
    let views = m.to_fan().unwrap().to_views().unwrap();
    let gammas = m.sensor_positions();
    let grid = ImageGrid::square(64, 1.0);
    // The bright pixel at MATLAB (row 12, col 45), 1-based; the centre pixel is (32, 32).
    let (row, col) = (12usize, 45usize);
    let (x, y) = (col as f64 - 32.0, 32.0 - row as f64);
    let mut image = Array2::<f32>::zeros((64, 64));
    image[[row - 1, col - 1]] = 1.0;
    let sino = forward_2d(&views, image.view(), &grid);
    for theta_deg in [0usize, 90, 180, 270] {
        let r = sino.row(theta_deg);
        let total: f64 = r.iter().map(|&v| v as f64).sum();
        let centroid: f64 = r
            .iter()
            .zip(&gammas)
            .map(|(&v, g)| v as f64 * g)
            .sum::<f64>()
            / total;
        let predicted = matlab_gamma(150.0, x, y, (theta_deg as f64).to_radians()).to_degrees();
        println!("θ = {theta_deg}°: centroid {centroid:.4}°, predicted {predicted:.4}°");
        assert!(
            (centroid - predicted).abs() <= 0.05,
            "θ = {theta_deg}°: centroid {centroid}°, predicted {predicted}°"
        );
    }
}
