//! Tests of the per-view steps: normalisation, pixel repair, binning and cropping, stripes, linearisation.

use ndarray::{Array2, array};

use super::*;
use crate::recon::geometry::vectors::{cross3, dot3, sub3};
use crate::recon::geometry::{Angles, ConeBeam, Panel, Vec3, Views3};
use crate::recon::phantom::{Phantom2, Table2};

#[test]
fn flat_field_normalisation_matches_hand_computed_values_and_counts_clamps() {
    // Dark 10, flats 1010 before and 2010 after a scan of 3 views: view 1 sees F − D = 1500.
    let dark = Array2::from_elem((2, 2), 10.0f32);
    let pre = Array2::from_elem((2, 2), 1010.0f32);
    let post = Array2::from_elem((2, 2), 2010.0f32);
    let field = FlatField::new(dark, pre, Some(post), 3).unwrap();
    let step = Normalise::FlatField { floor_counts: 1.0 };
    let mut view = array![[760.0f32, 385.0], [1510.0, 5.0]];
    let clamped = step.apply_view(Some(&field), 1, view.view_mut()).unwrap();
    assert_eq!(clamped, 1, "I − D = −5 is below the floor");
    let want = [2f32.ln(), 4f32.ln(), 0.0, 1500f32.ln()];
    for (got, want) in view.iter().zip(want) {
        assert!((got - want).abs() < 1e-5, "{got} against {want}");
    }
    // View 0 uses the pre-scan flat alone: F − D = 1000.
    let mut v0 = Array2::from_elem((2, 2), 510.0f32);
    assert_eq!(step.apply_view(Some(&field), 0, v0.view_mut()).unwrap(), 0);
    assert!(v0.iter().all(|p| (p - 2f32.ln()).abs() < 1e-5));
    // A view past the scan, a missing field and a wrong shape are refused.
    assert!(step.apply_view(Some(&field), 3, v0.view_mut()).is_err());
    assert!(step.apply_view(None, 0, v0.view_mut()).is_err());
    let mut wrong = Array2::<f32>::zeros((3, 2));
    assert!(step.apply_view(Some(&field), 0, wrong.view_mut()).is_err());
}

#[test]
fn white_level_input_is_divided_and_clamped() {
    let step: Normalise =
        serde_json::from_str(r#"{"method": "white_level", "white_level": 60000}"#).unwrap();
    let mut view = array![[30000.0f32, 60000.0], [15000.0, 0.0]];
    let clamped = step.apply_view(None, 0, view.view_mut()).unwrap();
    assert_eq!(clamped, 1);
    let want = [2f32.ln(), 0.0, 4f32.ln(), -(1e-6f32).ln()];
    for (got, want) in view.iter().zip(want) {
        assert!((got - want).abs() < 1e-4, "{got} against {want}");
    }
    assert!(
        serde_json::from_str::<Normalise>(r#"{"method": "white_level", "white_level": 1, "x": 2}"#)
            .is_err()
    );
}

#[test]
fn several_flats_are_averaged() {
    let a = Array2::from_elem((2, 3), 1.0f32);
    let b = Array2::from_elem((2, 3), 3.0f32);
    let mean = average_frames(&[a.view(), b.view()]).unwrap();
    assert!(mean.iter().all(|&x| x == 2.0));
    assert!(average_frames(&[]).is_err());
    assert!(average_frames(&[a.view(), Array2::zeros((3, 2)).view()]).is_err());
}

/// A smooth flat with ±1 count of deterministic noise.
fn flat(n: usize) -> Array2<f32> {
    let mut seed = 12345u32;
    Array2::from_shape_fn((n, n), |(r, c)| {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        let noise = (seed >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0;
        1000.0 + 10.0 * (0.3 * r as f32).sin() + 5.0 * (0.2 * c as f32).cos() + noise
    })
}

#[test]
fn planted_dead_and_hot_pixels_are_found_and_repaired() {
    let clean = flat(40);
    let mut data = clean.clone();
    let planted = [
        (5, 7, 1500.0),
        (20, 20, 0.0),
        (21, 20, 0.0),
        (0, 39, 3000.0),
        (33, 2, 900.0),
    ];
    for &(r, c, v) in &planted {
        data[[r, c]] = v;
    }
    let mask = find_outliers(data.view(), RepairPixels::default().k_mad).unwrap();
    let found: Vec<(usize, usize)> = mask
        .indexed_iter()
        .filter(|(_, b)| **b)
        .map(|(i, _)| i)
        .collect();
    let mut want: Vec<(usize, usize)> = planted.iter().map(|&(r, c, _)| (r, c)).collect();
    want.sort();
    assert_eq!(found, want);
    assert_eq!(
        repair_pixels(data.view_mut(), mask.view()).unwrap(),
        planted.len()
    );
    for &(r, c, _) in &planted {
        let err = (data[[r, c]] - clean[[r, c]]).abs();
        assert!(
            err < 4.0,
            "pixel ({r}, {c}) repaired to {} against {}",
            data[[r, c]],
            clean[[r, c]]
        );
    }
    let untouched = data.iter().zip(&clean).filter(|(a, b)| a != b).count();
    assert_eq!(untouched, planted.len(), "only the bad pixels change");
}

#[test]
fn binning_averages_blocks_and_drops_the_remainder() {
    let view = Array2::from_shape_fn((4, 7), |(r, c)| (10 * r + c) as f32);
    let out = Bin { u: 3, v: 2 }.apply_view(view.view()).unwrap();
    // Block rows 0–1, columns 0–2: mean of 0,1,2,10,11,12 = 6.
    assert_eq!(out, array![[6.0, 9.0], [26.0, 29.0]]);
    assert!(Bin { u: 0, v: 1 }.apply_view(view.view()).is_err());
    assert!(Bin { u: 8, v: 1 }.apply_view(view.view()).is_err());
}

/// Fractional (row, column) where the point `x` projects in view `k`.
fn project_point(views: &Views3, k: usize, x: Vec3) -> (f64, f64) {
    let v = &views.views[k];
    let w = cross3(v.det_u, v.det_v);
    let d = sub3(x, v.source);
    let t = dot3(sub3(v.det_centre, v.source), w) / dot3(d, w);
    let p: Vec3 = std::array::from_fn(|i| v.source[i] + t * d[i] - v.det_centre[i]);
    (
        views.detector.row_of(dot3(p, v.det_v)),
        views.detector.col_of(dot3(p, v.det_u)),
    )
}

fn cone_with(panel: Panel) -> ConeBeam {
    ConeBeam {
        angles: Angles::uniform(12, 360.0),
        dso_mm: 300.0,
        dsd_mm: 500.0,
        detector: panel,
    }
}

#[test]
fn binned_and_cropped_panels_keep_every_point_on_its_pixel() {
    let panel = Panel {
        nu: 101,
        nv: 64,
        du_mm: 0.7,
        dv_mm: 0.9,
        offset_u_mm: 1.3,
        offset_v_mm: -2.1,
    };
    let full = cone_with(panel).to_views().unwrap();
    let bin = Bin { u: 2, v: 3 };
    let binned = cone_with(bin.panel(&panel).unwrap()).to_views().unwrap();
    let crop = Crop {
        u0: 9,
        v0: 5,
        nu: 70,
        nv: 41,
    };
    let cropped = cone_with(crop.panel(&panel).unwrap()).to_views().unwrap();
    for (k, x) in [
        (0, [3.0, -4.0, 5.0]),
        (5, [-11.0, 7.5, -6.0]),
        (9, [0.5, 12.0, 9.0]),
    ] {
        let (r, c) = project_point(&full, k, x);
        let (rb, cb) = project_point(&binned, k, x);
        assert!(
            ((c + 0.5) / 2.0 - 0.5 - cb).abs() < 1e-9,
            "binned column {cb} of {c}"
        );
        assert!(
            ((r + 0.5) / 3.0 - 0.5 - rb).abs() < 1e-9,
            "binned row {rb} of {r}"
        );
        let (rc, cc) = project_point(&cropped, k, x);
        assert!((c - 9.0 - cc).abs() < 1e-9 && (r - 5.0 - rc).abs() < 1e-9);
    }
    let view = Array2::from_shape_fn((64, 101), |(r, c)| (r * 1000 + c) as f32);
    let window = crop.apply_view(view.view()).unwrap();
    assert_eq!(window.dim(), (41, 70));
    assert_eq!(window[[0, 0]], 5009.0);
    assert!(
        Crop {
            u0: 40,
            v0: 0,
            nu: 70,
            nv: 10
        }
        .panel(&panel)
        .is_err()
    );
}

#[test]
fn angle_subsets_keep_every_nth_view() {
    let sub = AngleSubset {
        start: 1,
        step: 3,
        count: Some(3),
    };
    assert_eq!(sub.indices(20).unwrap(), vec![1, 4, 7]);
    let radians: Vec<f64> = (0..6).map(|k| (k as f64 * 30.0).to_radians()).collect();
    let every = AngleSubset {
        start: 0,
        step: 2,
        count: None,
    };
    let Angles::List { degrees } = every.apply_angles(&radians).unwrap() else {
        panic!("a list");
    };
    assert!(
        degrees
            .iter()
            .zip([0.0, 60.0, 120.0])
            .all(|(a, b)| (a - b).abs() < 1e-9)
    );
    assert!(
        AngleSubset {
            start: 0,
            step: 0,
            count: None
        }
        .indices(5)
        .is_err()
    );
    assert!(
        AngleSubset {
            start: 5,
            step: 1,
            count: None
        }
        .indices(5)
        .is_err()
    );
}

#[test]
fn polynomial_linearisation_applies_the_coefficients() {
    let step: Linearise = serde_json::from_str(r#"{"coefficients": [0.1, 1, 0.5]}"#).unwrap();
    let mut view = array![[0.0f32, 2.0], [1.0, -1.0]];
    step.apply_view(view.view_mut()).unwrap();
    let want = [0.1, 4.1, 1.6, -0.4];
    assert!(
        view.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{view}"
    );
    assert!(
        Linearise {
            coefficients: vec![]
        }
        .apply_view(view.view_mut())
        .is_err()
    );
    assert!(
        Linearise {
            coefficients: vec![f64::NAN]
        }
        .apply_view(view.view_mut())
        .is_err()
    );
}

/// Root mean square over columns of the mean over views of `a − b`: the stripe content.
fn stripe_rms(a: &Array2<f32>, b: &Array2<f32>) -> f64 {
    let d = a - b;
    let profile = d.mean_axis(ndarray::Axis(0)).unwrap();
    (profile.iter().map(|&x| (x as f64).powi(2)).sum::<f64>() / profile.len() as f64).sqrt()
}

fn rms(a: &Array2<f32>, b: &Array2<f32>) -> f64 {
    ((a - b).iter().map(|&x| (x as f64).powi(2)).sum::<f64>() / a.len() as f64).sqrt()
}

#[test]
fn the_sorting_filter_removes_planted_column_gains_and_keeps_the_sinogram() {
    let views = crate::recon::geometry::ParallelBeam {
        angles: Angles::uniform(360, 180.0),
        det_count: 256,
        det_spacing_mm: 0.8,
        det_offset_mm: 0.0,
    }
    .to_views()
    .unwrap();
    let raw = Phantom2::from_table(Table2::ModifiedSheppLogan, 90.0).project(&views);
    // Line integrals up to 2, as a scan of a real sample gives.
    let clean = &raw * (2.0 / raw.iter().fold(0f32, |m, &x| m.max(x)));
    let peak = 2.0f32;
    // Gains of ±5 % on one column in six: p' = p − ln g.
    let mut seed = 7u32;
    let mut striped = clean.clone();
    for u in (3..256).step_by(6) {
        seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        let g = 0.95 + 0.1 * (seed >> 8) as f32 / (1u32 << 24) as f32;
        striped.column_mut(u).mapv_inplace(|p| p - g.ln());
    }
    // The window of Algotom's default (21 columns) suits 2000-wide detectors; this one is 256 wide.
    let filter = SortingStripeFilter { size: 3 };
    let mut fixed = striped.clone();
    filter.apply(fixed.view_mut()).unwrap();
    let before = stripe_rms(&striped, &clean);
    let after = stripe_rms(&fixed, &clean);
    let mut kept = clean.clone();
    filter.apply(kept.view_mut()).unwrap();
    let change = rms(&kept, &clean) / peak as f64;
    println!(
        "stripe rms {before:.2e} → {after:.2e} (×{:.1}); clean sinogram changed by {change:.2e} of its peak",
        before / after
    );
    assert!(
        after * 2.5 < before,
        "stripes reduced {:.1}×",
        before / after
    );
    assert!(
        change < 4e-3,
        "the clean sinogram moved by {change:.2e} of its peak"
    );
    assert!(
        SortingStripeFilter { size: 4 }
            .apply(fixed.view_mut())
            .is_err()
    );
}
