//! The synthetic patient: three cube markers at known LPS points on a lattice, and the CT series that store
//! it in every acquisition order, plus one with a gantry tilt.

use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;
use serde_json::Value;

use crate::common::TestApp;

/// Samples per patient axis (x left, y posterior, z superior) and their spacing (mm); lower corner.
pub const N: [usize; 3] = [18, 14, 10];
pub const S: [f64; 3] = [0.8, 1.0, 2.0];
pub const O: [f64; 3] = [-7.0, -5.0, 40.0];

/// Marker cubes (3 samples a side) centred on lattice indices `[x, y, z]`, with their HU. The second is
/// the patient's leftmost, the third the brightest.
pub const MARKERS: [([usize; 3], f32); 3] =
    [([3, 3, 2], 300.0), ([13, 4, 6], 600.0), ([8, 10, 5], 900.0)];

/// LPS position (mm) of lattice index `c`.
pub fn lps(c: [usize; 3]) -> [f64; 3] {
    std::array::from_fn(|a| O[a] + c[a] as f64 * S[a])
}

/// HU of the patient at LPS point `p`: a marker inside its cube, 0 elsewhere.
pub fn patient(p: [f64; 3]) -> f32 {
    for (c, v) in MARKERS {
        if (0..3).all(|a| (((p[a] - O[a]) / S[a]) - c[a] as f64).abs() <= 1.5) {
            return v;
        }
    }
    0.0
}

/// A series of the patient whose index axes (column, row, slice) point along `direction` (signed patient
/// axes); every sample lies on the patient lattice.
pub fn acquisition(direction: [[f64; 3]; 3]) -> Volume {
    let axis = |d: [f64; 3]| (0..3).find(|&c| d[c] != 0.0).unwrap_or(0);
    let n: [usize; 3] = std::array::from_fn(|a| N[axis(direction[a])]);
    let mut origin = O;
    for d in direction {
        let c = axis(d);
        if d[c] < 0.0 {
            origin[c] = O[c] + (N[c] - 1) as f64 * S[c];
        }
    }
    let frame = Frame {
        spacing_mm: std::array::from_fn(|a| S[axis(direction[a])]),
        origin_mm: origin,
        direction,
    };
    let data = Array3::from_shape_fn((n[2], n[1], n[0]), |(k, j, i)| {
        patient(frame.position(k as f64, j as f64, i as f64))
    });
    Volume { data, frame }
}

/// A 12° gantry tilt: rows along x, columns posterior and inferior, slices stepping along z.
pub fn tilted() -> Volume {
    let t = 12f64.to_radians();
    let frame = Frame {
        spacing_mm: [S[0], S[1], S[2]],
        origin_mm: [O[0], O[1] - 1.0, O[2] + 1.5],
        direction: [[1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, 1.0]],
    };
    let data = Array3::from_shape_fn((N[2] + 2, N[1] + 2, N[0]), |(k, j, i)| {
        patient(frame.position(k as f64, j as f64, i as f64))
    });
    Volume { data, frame }
}

pub const X: [f64; 3] = [1.0, 0.0, 0.0];
pub const Y: [f64; 3] = [0.0, 1.0, 0.0];
pub const Z: [f64; 3] = [0.0, 0.0, 1.0];
pub fn neg(v: [f64; 3]) -> [f64; 3] {
    v.map(|c| -c)
}

/// The acquisitions: name, index axes (column, row, slice), files in reverse order. Head-first supine
/// comes first: the others are compared with it.
pub fn acquisitions() -> Vec<(&'static str, [[f64; 3]; 3], bool)> {
    vec![
        ("head-first supine", [X, Y, Z], false),
        (
            "feet-first supine (rows right to left)",
            [neg(X), Y, neg(Z)],
            false,
        ),
        ("head-first prone", [neg(X), neg(Y), Z], false),
        ("feet-first prone", [X, neg(Y), neg(Z)], false),
        ("rows stored right to left", [neg(X), Y, Z], false),
        ("columns stored bottom to top", [X, neg(Y), Z], false),
        ("slices stored superior to inferior", [X, Y, Z], true),
        ("coronal images", [X, neg(Z), Y], false),
        ("sagittal images", [Y, neg(Z), neg(X)], true),
    ]
}

pub fn meta(description: &str) -> SeriesMeta {
    SeriesMeta {
        study_uid: Some("1.2.826.0.1.3680043.8.498.77".into()),
        frame_of_reference_uid: Some("1.2.826.0.1.3680043.8.498.78".into()),
        patient_id: Some("MARKERS".into()),
        series_description: description.into(),
        series_number: 3,
        ..Default::default()
    }
}

/// Upload `vol` as a ZIP of CT files; returns the series JSON.
pub async fn upload(app: &TestApp, vol: &Volume, name: &str, reverse: bool) -> Value {
    let mut files = write_ct_series(vol, &meta(name)).unwrap().files;
    if reverse {
        files.reverse();
    }
    let zip = write_zip(&files).unwrap();
    let r = app
        .client
        .post(app.url("/v1/series"))
        .header("content-type", "application/zip")
        .body(zip)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{name}: {}", r.text().await.unwrap());
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["series"][0]["status"], "ready", "{name}: {v}");
    v["series"][0]["series"].clone()
}
