//! The NXtomo geometry mapping (module docs of `scans::nxtomo`): an off-centre point lands where the
//! documented conventions put it — the sample turned by `rotation_angle` counter-clockwise seen from above
//! (ctrecon's β = −θ), image row 0 at the top, columns along +u — on a file written here with hdf5-pure.

use std::path::Path;

use hdf5_pure::{AttrValue, FileBuilder};

use super::{Orientation, nxtomo};
use crate::recon::geometry::Geometry;

/// An NXtomo file of `n` projections at `degrees` (nv × nu frames of zeros), pixel `pixel_m` metres.
fn write(path: &Path, degrees: &[f64], nv: usize, nu: usize, pixel_m: f64) {
    let n = degrees.len();
    let mut b = FileBuilder::new();
    let mut entry = b.create_group("entry");
    entry.set_attr("NX_class", AttrValue::String("NXentry".into()));
    entry
        .create_dataset("definition")
        .with_strings(&["NXtomo"])
        .unwrap();
    let mut instrument = entry.create_group("instrument");
    let mut detector = instrument.create_group("detector");
    detector
        .create_dataset("data")
        .with_f32_data(&vec![0.0; n * nv * nu])
        .with_shape(&[n as u64, nv as u64, nu as u64]);
    detector
        .create_dataset("image_key")
        .with_i32_data(&vec![0; n]);
    for k in ["x_pixel_size", "y_pixel_size"] {
        detector
            .create_dataset(k)
            .with_f64_data(&[pixel_m])
            .set_attr("units", AttrValue::String("m".into()));
    }
    instrument.add_group(detector.finish());
    entry.add_group(instrument.finish());
    let mut sample = entry.create_group("sample");
    sample
        .create_dataset("rotation_angle")
        .with_f64_data(degrees)
        .set_attr("units", AttrValue::String("degree".into()));
    entry.add_group(sample.finish());
    b.add_group(entry.finish());
    std::fs::write(path, b.finish().unwrap()).unwrap();
}

#[test]
fn an_off_centre_point_lands_where_the_nxtomo_conventions_put_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("scan.nx");
    let thetas = [0.0, 30.0, 90.0, 135.0, 250.0];
    let (nv, nu, px) = (20, 32, 0.05);
    write(&file, &thetas, nv, nu, px * 1e-3);
    let scan = nxtomo::open(&file).unwrap();
    assert_eq!(scan.orientation, Orientation::ROWS_UP);
    let Geometry::Parallel3d(g) = &scan.geometry else {
        panic!("{:?}", scan.geometry)
    };
    let sv = g.to_views().unwrap();
    for q in [[0.31, -0.12, 0.22], [-0.2, 0.4, -0.35], [0.0, 0.0, 0.0]] {
        for (i, &theta) in thetas.iter().enumerate() {
            // ctrecon: u = x cos β + y sin β, v = z, detector row 0 at the bottom.
            let b = sv.rows.views[i].angle_rad;
            let col = sv.rows.detector.index_of(q[0] * b.cos() + q[1] * b.sin());
            let row = (nv - 1) as f64 - sv.row_of(q[2]);
            // NXtomo: the sample turned by θ counter-clockwise seen from above, seen along the beam (+y)
            // with +x to the right; image row 0 at the top.
            let t = f64::to_radians(theta);
            let want_col = (nu as f64 - 1.0) / 2.0 + (q[0] * t.cos() - q[1] * t.sin()) / px;
            let want_row = (nv as f64 - 1.0) / 2.0 - q[2] / px;
            assert!(
                (col - want_col).abs() < 1e-9 && (row - want_row).abs() < 1e-9,
                "θ = {theta}°, point {q:?}: image ({row}, {col}), expected ({want_row}, {want_col})"
            );
        }
    }
    // The sense matters: at θ = 90° a point on +y lands left of the axis, by y/px columns.
    let b = sv.rows.views[2].angle_rad;
    let col = sv.rows.detector.index_of(0.4 * b.sin());
    assert!(
        (col - ((nu as f64 - 1.0) / 2.0 - 8.0)).abs() < 1e-9,
        "{col}"
    );
}
