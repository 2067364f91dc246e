//! 2D phantom tests: exact projections against closed forms and a numeric line integral, rasterisation
//! against analytic areas, and the table's conventions.

use proptest::prelude::*;

use super::*;
use crate::recon::geometry::{Angles, FanBeam, FanDetector, ParallelBeam, Views2};
use crate::recon::grid::ImageGrid;

fn parallel(count: usize, det: usize, spacing: f64, offset: f64) -> Views2 {
    ParallelBeam {
        angles: Angles::uniform(count, 180.0),
        det_count: det,
        det_spacing_mm: spacing,
        det_offset_mm: offset,
    }
    .to_views()
    .unwrap()
}

const DSO: f64 = 300.0;
const DSD: f64 = 500.0;

fn fan(arc: bool) -> Views2 {
    FanBeam {
        angles: Angles::uniform(10, 360.0),
        dso_mm: DSO,
        dsd_mm: DSD,
        detector: if arc {
            FanDetector::Arc {
                count: 61,
                spacing_deg: 0.5,
                offset_deg: 0.1,
            }
        } else {
            FanDetector::Flat {
                count: 61,
                spacing_mm: 3.0,
                offset_mm: 1.0,
            }
        },
        centre_mm: [0.0, 0.0],
    }
    .to_views()
    .unwrap()
}

fn disc(value: f64, r: f64) -> Ellipse {
    Ellipse {
        value,
        a: r,
        b: r,
        x0: 0.0,
        y0: 0.0,
        phi_deg: 0.0,
    }
}

/// μ at `(x, y)` mm written straight from the definition of [`Ellipse`], independent of the chord code.
fn inside_value(ellipses: &[Ellipse], scale: f64, x: f64, y: f64) -> f64 {
    let (x, y) = (x / scale, y / scale);
    ellipses
        .iter()
        .filter(|e| {
            let (s, c) = e.phi_deg.to_radians().sin_cos();
            let xr = (x - e.x0) * c + (y - e.y0) * s;
            let yr = -(x - e.x0) * s + (y - e.y0) * c;
            xr * xr / (e.a * e.a) + yr * yr / (e.b * e.b) <= 1.0
        })
        .map(|e| e.value)
        .sum()
}

/// Numeric line integral of a piecewise-constant `f` over `λ ∈ [lo, hi]`: steps of `h`, every change
/// of value located by bisection to 1e-12 mm.
pub(super) fn numeric_line_integral(f: impl Fn(f64) -> f64, lo: f64, hi: f64, h: f64) -> f64 {
    let steps = ((hi - lo) / h).ceil() as usize;
    let mut total = 0.0;
    let (mut t0, mut v0) = (lo, f(lo));
    for i in 1..=steps {
        let t1 = (lo + i as f64 * h).min(hi);
        let v1 = f(t1);
        if v1 == v0 {
            total += v0 * (t1 - t0);
        } else {
            let (mut a, mut b) = (t0, t1);
            while b - a > 1e-12 {
                let m = 0.5 * (a + b);
                if f(m) == v0 { a = m } else { b = m }
            }
            total += v0 * (a - t0) + v1 * (t1 - a);
        }
        (t0, v0) = (t1, v1);
    }
    total
}

fn assert_close(got: f64, want: f64, tol: f64, what: &str) {
    assert!(
        (got - want).abs() <= tol,
        "{what}: got {got}, want {want} (tolerance {tol})"
    );
}

#[test]
fn a_centred_disc_projects_to_its_closed_form_chord_in_every_2d_geometry() {
    // Disc of radius R = 0.6 × 100 mm and μ = 0.02 /mm: p = 2μ√(R² − t²) with t the ray's distance
    // from the centre: t = u (parallel), DSO·sin γ (arc), DSO·|u|/√(DSD² + u²) (flat).
    let (rho, r) = (0.02, 60.0);
    let ph = Phantom2::new(vec![disc(rho, 0.6)], 100.0).unwrap();
    let chord = |t: f64| 2.0 * rho * (r * r - t * t).max(0.0).sqrt();
    let tol = 1e-6 * 2.0 * rho * r;
    type Case<'a> = (&'a str, Views2, &'a dyn Fn(f64) -> f64);
    let cases: [Case; 3] = [
        ("parallel", parallel(12, 41, 3.0, 0.7), &|u| u),
        ("fan arc", fan(true), &|g: f64| DSO * g.sin()),
        ("fan flat", fan(false), &|u: f64| DSO * u / DSD.hypot(u)),
    ];
    for (name, views, distance) in cases {
        let p = ph.project(&views);
        assert_eq!(p.shape(), &[views.views.len(), views.detector.count]);
        for ((_, k), &v) in p.indexed_iter() {
            let want = chord(distance(views.detector.coord(k)));
            assert_close(v as f64, want, tol, name);
        }
    }
}

#[test]
fn an_off_centre_rotated_ellipse_matches_the_kak_slaney_parallel_projection() {
    // Kak & Slaney (3.2): p_θ(t) = 2ρab/s²·√(s² − t'²), s² = a²cos²(θ − φ) + b²sin²(θ − φ),
    // t' = t − (x0 cos θ + y0 sin θ), everything in mm.
    let e = Ellipse {
        value: 0.03,
        a: 0.35,
        b: 0.15,
        x0: 0.25,
        y0: -0.3,
        phi_deg: 35.0,
    };
    let scale = 80.0;
    let views = parallel(36, 101, 1.3, -0.4);
    let p = Phantom2::new(vec![e], scale).unwrap().project(&views);
    let (a, b, x0, y0) = (e.a * scale, e.b * scale, e.x0 * scale, e.y0 * scale);
    let peak = 2.0 * e.value * a;
    for ((i, k), &v) in p.indexed_iter() {
        let th = views.views[i].angle_rad;
        let d = th - e.phi_deg.to_radians();
        let s2 = a * a * d.cos().powi(2) + b * b * d.sin().powi(2);
        let t = views.detector.coord(k) - (x0 * th.cos() + y0 * th.sin());
        let want = 2.0 * e.value * a * b / s2 * (s2 - t * t).max(0.0).sqrt();
        assert_close(v as f64, want, 1e-6 * peak, "Kak–Slaney");
    }
}

#[test]
fn rotated_off_centre_ellipses_match_a_numeric_line_integral_in_every_2d_geometry() {
    // Two overlapping ellipses, one negative; the numeric integral uses only the inside test.
    let ellipses = vec![
        Ellipse {
            value: 0.03,
            a: 0.35,
            b: 0.15,
            x0: 0.25,
            y0: -0.3,
            phi_deg: 35.0,
        },
        Ellipse {
            value: -0.01,
            a: 0.1,
            b: 0.2,
            x0: 0.3,
            y0: -0.25,
            phi_deg: -60.0,
        },
    ];
    let scale = 80.0;
    let ph = Phantom2::new(ellipses.clone(), scale).unwrap();
    let f = |x: f64, y: f64| inside_value(&ellipses, scale, x, y);
    let peak = 2.0 * 0.03 * 0.35 * scale;
    for (name, views) in [
        ("parallel", parallel(12, 41, 3.0, 0.7)),
        ("fan arc", fan(true)),
        ("fan flat", fan(false)),
    ] {
        let p = ph.project(&views);
        let mut hits = 0;
        for ((i, k), &v) in p.indexed_iter() {
            let ray = views.ray(&views.views[i], k);
            let (o, d) = (ray.origin, ray.direction);
            let at = |l: f64| f(o[0] + l * d[0], o[1] + l * d[1]);
            // The phantom lies within 120 mm of the origin; the ray origin within DSO of it.
            let want = numeric_line_integral(at, -450.0, 450.0, 0.05);
            // 1e-6 relative to the value, or to the peak for values near zero (f32 output).
            let tol = 1e-6 * want.abs().max(1e-2 * peak);
            assert_close(v as f64, want, tol, name);
            hits += usize::from(want.abs() > 0.1);
        }
        assert!(hits > 20, "{name}: only {hits} rays cross the ellipses");
    }
}

#[test]
fn phi_turns_the_a_axis_counter_clockwise_from_x_toward_y() {
    // a = 0.4 along φ = 30°: the parallel projection is widest at θ = 30° (support 2a) and narrowest at
    // θ = 120° (support 2b). A clockwise φ would swap 30° and 150°.
    let e = Ellipse {
        value: 1.0,
        a: 0.4,
        b: 0.1,
        x0: 0.0,
        y0: 0.0,
        phi_deg: 30.0,
    };
    let ph = Phantom2::new(vec![e], 10.0).unwrap();
    let support = |theta_deg: f64| {
        let v = ParallelBeam {
            angles: Angles::List {
                degrees: vec![theta_deg],
            },
            det_count: 2001,
            det_spacing_mm: 0.005,
            det_offset_mm: 0.0,
        }
        .to_views()
        .unwrap();
        let p = ph.project(&v);
        p.iter().filter(|&&x| x > 0.0).count() as f64 * 0.005
    };
    assert_close(support(30.0), 8.0, 0.011, "support at 30°");
    assert_close(support(120.0), 2.0, 0.011, "support at 120°");
    assert_close(
        support(150.0),
        2.0 * (16.0f64 * 0.25 + 0.75).sqrt(),
        0.011,
        "support at 150°",
    );
    // And a point on the a axis, 0.3 along 30°, lies inside; its mirror at −30° does not.
    let (s, c) = 30f64.to_radians().sin_cos();
    assert_eq!(ph.value_at(3.0 * c, 3.0 * s), 1.0);
    assert_eq!(ph.value_at(3.0 * c, -3.0 * s), 0.0);
}

#[test]
fn modified_shepp_logan_values_add_where_ellipses_overlap() {
    let ph = Phantom2::from_table(Table2::ModifiedSheppLogan, 100.0);
    // Centre: skull 1 − brain 0.8.
    assert_close(ph.value_at(0.0, 0.0), 0.2, 1e-12, "centre");
    // Inside the right ventricle (0.22, 0): 1 − 0.8 − 0.2.
    assert_close(ph.value_at(22.0, 0.0), 0.0, 1e-12, "ventricle");
    // Inside ellipse 5 at (0, 0.35): 1 − 0.8 + 0.1.
    assert_close(ph.value_at(0.0, 35.0), 0.3, 1e-12, "ellipse 5");
    // In the skull between the two outer ellipses at (0, 0.9): 1.
    assert_close(ph.value_at(0.0, 90.0), 1.0, 1e-12, "skull");
    // The original table: 2 − 0.98 = 1.02 at the centre.
    let sl = Phantom2::from_table(Table2::SheppLogan, 100.0);
    assert_close(sl.value_at(0.0, 0.0), 1.02, 1e-12, "original centre");
    // Rows grow with y: the small ellipse 5 at y = +0.35 shows in the upper half of the rows.
    let img = ph.rasterize(&ImageGrid::square(20, 10.0), 1);
    assert_close(img[[13, 10]] as f64, 0.3, 1e-6, "row 13 is y = +35 mm");
    assert_close(img[[6, 10]] as f64, 0.2, 1e-6, "row 6 is y = −35 mm");
}

#[test]
fn rasterised_area_approaches_the_analytic_area_and_supersampling_helps() {
    // ρ·πab in mm², ab = 0.5·0.3·32² mm² on a 64² grid of 1 mm pixels.
    let e = Ellipse {
        value: 2.0,
        a: 0.5,
        b: 0.3,
        x0: 0.1,
        y0: -0.2,
        phi_deg: 30.0,
    };
    let scale = 32.0;
    let ph = Phantom2::new(vec![e], scale).unwrap();
    let grid = ImageGrid::square(64, 1.0);
    let want = e.value * std::f64::consts::PI * e.a * e.b * scale * scale;
    let err = |s| {
        let img = ph.rasterize(&grid, s);
        assert_eq!(img.shape(), &[64, 64]);
        (img.iter().map(|&v| v as f64).sum::<f64>() - want).abs() / want
    };
    let (e1, e4) = (err(1), err(4));
    assert!(e1 < 1e-2, "supersample 1: relative error {e1}");
    assert!(e4 < 1e-3, "supersample 4: relative error {e4}");
    assert!(e4 < e1, "supersampling must help: {e4} vs {e1}");
}

#[test]
fn parallel_projection_at_zero_matches_column_sums_of_a_supersampled_rasterisation() {
    // 128² pixels of 1 mm, phantom scale 64 mm. At θ = 0 the rays run along +y and t = x, so the
    // projection of column i is Σ_j f[j][i]·dy. The rasterisation averages each pixel over its width
    // while the exact projection is taken at the pixel centre, so compare against the mean of 8 exact
    // projections across the pixel width (tight), and the pixel-centre projection (loose, the edges of
    // the skull are steep).
    let ph = Phantom2::from_table(Table2::ModifiedSheppLogan, 64.0);
    let grid = ImageGrid::square(128, 1.0);
    let img = ph.rasterize(&grid, 8);
    let sums: Vec<f64> = (0..128)
        .map(|i| img.column(i).iter().map(|&v| v as f64).sum::<f64>())
        .collect();
    let at_zero = |n: usize, spacing: f64| {
        let v = ParallelBeam {
            angles: Angles::List { degrees: vec![0.0] },
            det_count: n,
            det_spacing_mm: spacing,
            det_offset_mm: 0.0,
        }
        .to_views()
        .unwrap();
        ph.project(&v).row(0).mapv(f64::from).to_vec()
    };
    let centre = at_zero(128, 1.0);
    let fine = at_zero(1024, 0.125);
    let peak = centre.iter().cloned().fold(0.0, f64::max);
    let mut worst_fine = 0.0f64;
    let mut worst_centre = 0.0f64;
    let mut sq_centre = 0.0;
    for i in 0..128 {
        let mean8 = fine[8 * i..8 * i + 8].iter().sum::<f64>() / 8.0;
        worst_fine = worst_fine.max((mean8 - sums[i]).abs());
        worst_centre = worst_centre.max((centre[i] - sums[i]).abs());
        sq_centre += (centre[i] - sums[i]).powi(2);
    }
    let rms_centre = (sq_centre / 128.0).sqrt();
    assert!(peak > 20.0, "peak {peak}");
    assert!(
        worst_fine < 2e-3 * peak,
        "width-averaged: worst {worst_fine}"
    );
    assert!(
        worst_centre < 0.2 * peak,
        "pixel centre: worst {worst_centre} of peak {peak}"
    );
    assert!(rms_centre < 3e-2 * peak, "pixel centre: rms {rms_centre}");
}

fn ellipse_strategy() -> impl Strategy<Value = Ellipse> {
    (
        -2.0..2.0f64,
        0.05..0.8f64,
        0.05..0.8f64,
        -0.3..0.3f64,
        -0.3..0.3f64,
        -180.0..180.0f64,
    )
        .prop_map(|(value, a, b, x0, y0, phi_deg)| Ellipse {
            value,
            a,
            b,
            x0,
            y0,
            phi_deg,
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn translating_an_ellipse_shifts_its_parallel_projection(
        e in ellipse_strategy(),
        dx in -0.2..0.2f64,
        dy in -0.2..0.2f64,
        theta in 0.0..180.0f64,
    ) {
        let scale = 50.0;
        let moved = Ellipse { x0: e.x0 + dx, y0: e.y0 + dy, ..e };
        let views = |offset: f64| ParallelBeam {
            angles: Angles::List { degrees: vec![theta] },
            det_count: 33,
            det_spacing_mm: 3.1,
            det_offset_mm: offset,
        }
        .to_views()
        .unwrap();
        let th = theta.to_radians();
        let shift = (dx * th.cos() + dy * th.sin()) * scale;
        let original = Phantom2::new(vec![e], scale).unwrap().project(&views(0.0));
        let shifted = Phantom2::new(vec![moved], scale).unwrap().project(&views(shift));
        let peak = 2.0 * e.value.abs() * e.a.max(e.b) * scale;
        for (a, b) in original.iter().zip(shifted.iter()) {
            prop_assert!(((a - b) as f64).abs() <= 1e-5 * peak + 1e-6, "{a} vs {b}");
        }
    }

    #[test]
    fn a_chord_is_never_negative_nor_longer_than_the_long_axis(
        e in ellipse_strategy(),
        ox in -100.0..100.0f64,
        oy in -100.0..100.0f64,
        angle in 0.0..std::f64::consts::TAU,
    ) {
        let scale = 50.0;
        let ph = Phantom2::new(vec![Ellipse { value: 1.0, ..e }], scale).unwrap();
        let chord = ph.line_integral([ox, oy], [angle.cos(), angle.sin()]);
        prop_assert!(chord >= 0.0);
        prop_assert!(chord <= 2.0 * e.a.max(e.b) * scale * (1.0 + 1e-12));
    }
}
