use super::*;
use crate::recon::control::unattended;

/// A 3×4 slice at normal position `z` (axial), filled with `value` stored units, slope 1, intercept −1024.
fn axial(z: f64, shift: [f64; 2], value: f32) -> Slice {
    Slice {
        rows: 3,
        columns: 4,
        stored: vec![value; 12],
        rescale_slope: 1.0,
        rescale_intercept: -1024.0,
        position_mm: Some([-10.0 + shift[0], -20.0 + shift[1], z]),
        orientation: Some([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
        pixel_spacing_mm: Some([0.5, 0.25]),
        slice_thickness_mm: Some(2.0),
        padding: None,
        label: format!("z={z}"),
    }
}

#[test]
fn shuffled_slices_are_sorted_along_the_normal() {
    let zs = [4.0, 0.0, 8.0, 2.0, 6.0];
    let slices = zs
        .iter()
        .map(|&z| axial(z, [0.0; 2], z as f32 * 10.0))
        .collect();
    let a = assemble(slices, &AssemblyOptions::default(), unattended()).unwrap();
    assert_eq!(a.volume.data.dim(), (5, 3, 4));
    for k in 0..5 {
        // HU = 10·z − 1024 with z = 2k, exact in f32.
        assert_eq!(a.volume.data[[k, 1, 1]], 20.0 * k as f32 - 1024.0);
    }
    let f = a.volume.frame;
    assert_eq!(f.spacing_mm, [0.25, 0.5, 2.0]);
    assert_eq!(f.origin_mm, [-10.0, -20.0, 0.0]);
    assert!(a.tilt_deg.abs() < 1e-9 && a.warnings.is_empty());
}

#[test]
fn a_tilted_series_keeps_a_sheared_slice_axis() {
    // 2 mm along the normal, 0.5 mm posterior shift per slice: tilt = atan(0.25) = 14.036°.
    let slices = (0..4)
        .map(|k| axial(2.0 * k as f64, [0.0, 0.5 * k as f64], 0.0))
        .collect();
    let a = assemble(slices, &AssemblyOptions::default(), unattended()).unwrap();
    assert!((a.tilt_deg - 0.25f64.atan().to_degrees()).abs() < 1e-9);
    let f = a.volume.frame;
    assert!((f.spacing_mm[2] - (4.0f64 + 0.25).sqrt()).abs() < 1e-12);
    let p = f.position(3.0, 0.0, 0.0);
    assert!((p[1] - (-18.5)).abs() < 1e-9 && (p[2] - 6.0).abs() < 1e-9);
    assert!(a.warnings.iter().any(|w| w.code == "gantry_tilt"));
}

#[test]
fn a_missing_slice_is_refused_or_interpolated() {
    let slices: Vec<Slice> = [0.0, 2.0, 6.0, 8.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], z as f32))
        .collect();
    let e = assemble(slices.clone(), &AssemblyOptions::default(), unattended()).unwrap_err();
    assert_eq!(e.code(), "series_missing_slices");
    assert!(e.to_string().contains("1 slice(s) missing"), "{e}");
    let opts = AssemblyOptions {
        uneven: UnevenPolicy::Resample,
        ..Default::default()
    };
    let a = assemble(slices, &opts, unattended()).unwrap();
    assert_eq!(a.volume.data.dim().0, 5);
    // Linear interpolation of stored = z at z = 4: exact.
    assert_eq!(a.volume.data[[2, 0, 0]], 4.0 - 1024.0);
    assert!(
        a.warnings
            .iter()
            .any(|w| w.code == "missing_slices_interpolated")
    );
}

#[test]
fn uneven_spacing_is_refused_and_duplicates_are_dropped_or_refused() {
    let s: Vec<Slice> = [0.0, 2.0, 3.1, 5.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], 0.0))
        .collect();
    let e = assemble(s, &AssemblyOptions::default(), unattended()).unwrap_err();
    assert_eq!(e.code(), "series_uneven_spacing");

    let mut s: Vec<Slice> = [0.0, 2.0, 4.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], 1.0))
        .collect();
    s.push(axial(2.0, [0.0; 2], 1.0));
    let a = assemble(s.clone(), &AssemblyOptions::default(), unattended()).unwrap();
    assert_eq!(a.volume.data.dim().0, 3);
    assert!(
        a.warnings
            .iter()
            .any(|w| w.code == "duplicate_slice_dropped")
    );
    s[3].stored[0] = 7.0;
    let e = assemble(s, &AssemblyOptions::default(), unattended()).unwrap_err();
    assert_eq!(e.code(), "series_duplicate_position");
}

#[test]
fn inconsistent_slices_and_padding() {
    let mut s: Vec<Slice> = [0.0, 2.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], 0.0))
        .collect();
    s[1].orientation = Some([0.0, 1.0, 0.0, 1.0, 0.0, 0.0]);
    let e = assemble(s, &AssemblyOptions::default(), unattended()).unwrap_err();
    assert_eq!(e.code(), "series_orientation_mismatch");
    let mut s: Vec<Slice> = [0.0, 2.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], 0.0))
        .collect();
    s[1].rows = 5;
    assert_eq!(
        assemble(s, &AssemblyOptions::default(), unattended())
            .unwrap_err()
            .code(),
        "series_size_mismatch"
    );
    let mut s = vec![axial(0.0, [0.0; 2], 5.0)];
    s[0].stored[3] = -2000.0;
    s[0].padding = Some((-2000.0, -2000.0));
    let a = assemble(s, &AssemblyOptions::default(), unattended()).unwrap();
    assert_eq!(a.volume.data[[0, 0, 3]], PADDING_HU);
    assert_eq!(a.volume.data[[0, 0, 2]], 5.0 - 1024.0);
    let w: Vec<&Warning> = a
        .warnings
        .iter()
        .filter(|w| w.code == "pixel_padding_replaced")
        .collect();
    assert_eq!(w.len(), 1, "{:?}", a.warnings);
    assert!(w[0].message.starts_with("1 pixels"), "{}", w[0].message);
    let e = assemble(
        vec![axial(0.0, [0.0; 2], 0.0), axial(2.0, [0.0; 2], 0.0)],
        &AssemblyOptions {
            max_voxels: 10,
            ..Default::default()
        },
        unattended(),
    )
    .unwrap_err();
    assert_eq!(e.code(), "series_too_large");
}

/// Slices 2 mm apart along z whose in-plane position drifts by `shift_mm` per slice along y.
fn drifting(n: usize, shift_mm: f64) -> Vec<Slice> {
    (0..n)
        .map(|k| axial(2.0 * k as f64, [0.0, shift_mm * k as f64], 0.0))
        .collect()
}

#[test]
fn rounding_noise_in_positions_is_not_a_tilt_but_five_degrees_is() {
    // 0.02° over 2 mm: 0.0007 mm of drift per slice, as rounded positions show.
    let noise = (0.02f64).to_radians().tan() * 2.0;
    let a = assemble(
        drifting(6, noise),
        &AssemblyOptions::default(),
        unattended(),
    )
    .unwrap();
    assert!((a.tilt_deg - 0.02).abs() < 1e-6, "{}", a.tilt_deg);
    assert!(a.warnings.is_empty(), "{:?}", a.warnings);
    let real = (5.0f64).to_radians().tan() * 2.0;
    let a = assemble(drifting(6, real), &AssemblyOptions::default(), unattended()).unwrap();
    assert!((a.tilt_deg - 5.0).abs() < 1e-6, "{}", a.tilt_deg);
    let w: Vec<&str> = a.warnings.iter().map(|w| w.code).collect();
    assert_eq!(w, ["gantry_tilt"]);
    assert!(
        stale_after_resample("gantry_tilt") && !stale_after_resample("missing_slices_interpolated")
    );
}

#[test]
fn two_stacks_77_mm_apart_are_refused_even_with_resample_but_four_missing_slices_are_bridged() {
    // 1.25 mm slices: 0 … 10 mm, then 87.25 … 97.25 mm.
    let zs: Vec<f64> = (0..9)
        .map(|k| 1.25 * k as f64)
        .chain((0..9).map(|k| 87.25 + 1.25 * k as f64))
        .collect();
    let slices: Vec<Slice> = zs.iter().map(|&z| axial(z, [0.0; 2], 0.0)).collect();
    let resample = AssemblyOptions {
        uneven: UnevenPolicy::Resample,
        ..Default::default()
    };
    for opts in [AssemblyOptions::default(), resample] {
        let e = assemble(slices.clone(), &opts, unattended()).unwrap_err();
        assert_eq!(e.code(), "series_spacing_jump", "{opts:?}");
        let msg = e.to_string();
        assert!(
            msg.contains("77.250 mm") && msg.contains("z=10") && msg.contains("z=87.25"),
            "{msg}"
        );
    }
    // Four missing 2 mm slices (a 10 mm gap) are still interpolated on request, with a warning.
    let slices: Vec<Slice> = [0.0, 2.0, 4.0, 14.0, 16.0, 18.0]
        .iter()
        .map(|&z| axial(z, [0.0; 2], z as f32))
        .collect();
    let a = assemble(slices.clone(), &resample, unattended()).unwrap();
    assert_eq!(a.volume.data.dim().0, 10);
    assert!(
        a.warnings
            .iter()
            .any(|w| w.code == "missing_slices_interpolated")
    );
    // Five missing slices are a jump.
    let mut wider = slices;
    for s in wider.iter_mut().skip(3) {
        let p = s.position_mm.as_mut().unwrap();
        p[2] += 2.0;
    }
    assert_eq!(
        assemble(wider, &resample, unattended()).unwrap_err().code(),
        "series_spacing_jump"
    );
}

#[test]
fn a_lone_slice_without_placement_says_what_was_assumed() {
    let mut s = axial(0.0, [0.0; 2], 0.0);
    s.position_mm = None;
    s.orientation = None;
    s.slice_thickness_mm = None;
    let a = assemble(vec![s], &AssemblyOptions::default(), unattended()).unwrap();
    let codes: Vec<&str> = a.warnings.iter().map(|w| w.code).collect();
    assert_eq!(
        codes,
        [
            "orientation_assumed",
            "position_assumed",
            "slice_thickness_assumed"
        ]
    );
    assert_eq!(a.volume.frame.origin_mm, [0.0; 3]);
    // A placed lone slice assumes nothing.
    let a = assemble(
        vec![axial(0.0, [0.0; 2], 0.0)],
        &AssemblyOptions::default(),
        unattended(),
    )
    .unwrap();
    assert!(a.warnings.is_empty(), "{:?}", a.warnings);
}
