//! The Joseph forward projector against exact analytic projections: the modified Shepp–Logan phantom and
//! a uniform off-centre disc, rasterised with 4×4 sub-samples per pixel and forward-projected, match the
//! exact line integrals of `recon::phantom` on parallel, fan-arc and fan-flat geometries.

use ctrecon::recon::geometry::{Angles, FanBeam, FanDetector, ParallelBeam, Views2};
use ctrecon::recon::grid::ImageGrid;
use ctrecon::recon::phantom::{Ellipse, Phantom2, Table2};
use ctrecon::recon::projector::forward_2d;

/// Relative L2 error ‖A·raster − exact‖ / ‖exact‖ allowed for the Shepp–Logan phantom (its thin rim
/// and sharp edges on a 1 mm raster dominate: the error halves with the pixel size, see below) and for
/// the ellipse.
const TOL_SHEPP: f64 = 0.035;
const TOL_DISC: f64 = 0.01;

fn grid() -> ImageGrid {
    ImageGrid::square(128, 1.0)
}

fn parallel() -> Views2 {
    ParallelBeam {
        angles: Angles::uniform(90, 180.0),
        det_count: 185,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.3,
    }
    .to_views()
    .unwrap()
}

fn fan_arc() -> Views2 {
    FanBeam {
        angles: Angles::uniform(120, 360.0),
        dso_mm: 300.0,
        dsd_mm: 500.0,
        detector: FanDetector::Arc {
            count: 181,
            spacing_deg: 0.2,
            offset_deg: 0.05,
        },
        centre_mm: [0.0, 0.0],
    }
    .to_views()
    .unwrap()
}

fn fan_flat() -> Views2 {
    FanBeam {
        angles: Angles::uniform(120, 360.0),
        dso_mm: 300.0,
        dsd_mm: 500.0,
        detector: FanDetector::Flat {
            count: 221,
            spacing_mm: 1.5,
            offset_mm: 0.7,
        },
        centre_mm: [2.0, -1.0],
    }
    .to_views()
    .unwrap()
}

fn relative_error(phantom: &Phantom2, views: &Views2) -> f64 {
    relative_error_on(phantom, views, &grid())
}

fn relative_error_on(phantom: &Phantom2, views: &Views2, g: &ImageGrid) -> f64 {
    let g = *g;
    let exact = phantom.project(views);
    let approx = forward_2d(views, phantom.rasterize(&g, 4).view(), &g);
    let mut num = 0.0f64;
    let mut den = 0.0f64;
    for (a, e) in approx.iter().zip(exact.iter()) {
        num += (*a as f64 - *e as f64).powi(2);
        den += (*e as f64).powi(2);
    }
    (num / den).sqrt()
}

fn shepp() -> Phantom2 {
    Phantom2::from_table(Table2::ModifiedSheppLogan, 60.0)
}

fn disc() -> Phantom2 {
    let e = Ellipse {
        value: 0.02,
        a: 0.5,
        b: 0.3,
        x0: 0.15,
        y0: -0.1,
        phi_deg: 25.0,
    };
    Phantom2::new(vec![e], 100.0).unwrap()
}

fn check(name: &str, views: Views2) {
    let es = relative_error(&shepp(), &views);
    let ed = relative_error(&disc(), &views);
    println!("{name}: Shepp–Logan relative error {es:.5}, ellipse {ed:.5}");
    assert!(es < TOL_SHEPP, "{name}: Shepp–Logan relative error {es}");
    assert!(ed < TOL_DISC, "{name}: ellipse relative error {ed}");
}

#[test]
fn parallel_projection_of_a_raster_matches_the_exact_projection() {
    check("parallel", parallel());
}

#[test]
fn fan_arc_projection_of_a_raster_matches_the_exact_projection() {
    check("fan arc", fan_arc());
}

#[test]
fn fan_flat_projection_of_a_raster_matches_the_exact_projection() {
    check("fan flat", fan_flat());
}

#[test]
fn the_discretisation_error_shrinks_with_the_pixel_size() {
    let views = parallel();
    let coarse = relative_error_on(&shepp(), &views, &ImageGrid::square(128, 1.0));
    let fine = relative_error_on(&shepp(), &views, &ImageGrid::square(256, 0.5));
    println!("Shepp–Logan relative error: 1 mm {coarse:.5}, 0.5 mm {fine:.5}");
    assert!(fine < 0.6 * coarse, "1 mm {coarse}, 0.5 mm {fine}");
}

#[test]
fn rays_that_miss_the_grid_project_to_zero_and_a_constant_image_gives_chord_lengths() {
    // A constant image of 1 over a 64 mm square: the central parallel ray at 0° crosses 64 mm, rays
    // beyond the corners see nothing.
    let g = ImageGrid::square(64, 1.0);
    let views = ParallelBeam {
        angles: Angles::uniform(4, 180.0),
        det_count: 201,
        det_spacing_mm: 1.0,
        det_offset_mm: 0.0,
    }
    .to_views()
    .unwrap();
    let ones = ndarray::Array2::<f32>::ones(g.shape());
    let s = forward_2d(&views, ones.view(), &g);
    // Detector element 100 is u = 0: at 0° and 90° the chord is 64 mm; at 45° it is 64·√2 mm.
    assert!((s[[0, 100]] - 64.0).abs() < 1e-3, "{}", s[[0, 100]]);
    assert!((s[[2, 100]] - 64.0).abs() < 1e-3, "{}", s[[2, 100]]);
    assert!(
        (s[[1, 100]] as f64 - 64.0 * 2f64.sqrt()).abs() < 0.75,
        "{}",
        s[[1, 100]]
    );
    assert_eq!(s[[0, 0]], 0.0);
    assert_eq!(s[[1, 200]], 0.0);
}
