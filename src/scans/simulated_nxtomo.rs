//! A simulated parallel-beam scan written as a synchrotron beamline writes one: a NeXus NXtomo HDF5 file
//! (`/entry`, `definition` = `NXtomo`) holding raw 16-bit frames — darks, a flat series before and after the
//! projections, the projections themselves (`dark + (flat − dark) · e^(−line integral)`) — with their
//! `image_key`, the `rotation_angle` of every frame in degrees and the pixel size in metres. It is the exact
//! inverse of [`super::nxtomo`]'s mapping: θ = −β, image row 0 the detector's top.
//!
//! The panel's u offset is deliberately not written (NXtomo's own key for it, `x_rotation_axis_pixel_position`,
//! is not read either): a scan whose axis does not project onto the panel's centre column is what the import's
//! centre search is for.

use std::path::{Path, PathBuf};

use hdf5_pure::{AttrValue, FileBuilder};
use ndarray::ArrayView3;

use super::{Orientation, ScanError};
use crate::recon::geometry::Geometry;

/// The dark level written (counts).
pub const DARK_LEVEL: f64 = 100.0;
/// The open-beam level written (counts).
pub const FLAT_LEVEL: f64 = 40_000.0;
/// Dark frames, then flat frames before and again after the projections.
const DARKS: usize = 2;
const FLATS: usize = 2;
/// The sample-to-detector distance written (metres); a parallel beam has no magnification.
const DISTANCE_M: f64 = 0.1;

/// What [`write_nxtomo`] wrote.
#[derive(Debug, Clone)]
pub struct WrittenNx {
    pub file: PathBuf,
    /// Projection frames (besides the darks and flats).
    pub projections: usize,
    /// Pixels whose count was clipped to the 16-bit range.
    pub clipped: usize,
}

fn err(file: &Path, what: impl Into<String>) -> ScanError {
    ScanError::Unsupported {
        file: file.to_path_buf(),
        what: what.into(),
    }
}

/// Write `projections` (`[view][v][u]` line integrals measured with `geometry`, a 3D parallel beam) as an
/// NXtomo file at `file`.
pub fn write_nxtomo(
    file: &Path,
    geometry: &Geometry,
    projections: ArrayView3<'_, f32>,
) -> Result<WrittenNx, ScanError> {
    let Geometry::Parallel3d(par) = geometry else {
        return Err(err(
            file,
            "an NXtomo scan is a 3D parallel beam: give a geometry of type parallel3d",
        ));
    };
    let p = &par.detector;
    let (n, nv, nu) = projections.dim();
    if (nv, nu) != (p.nv, p.nu) {
        return Err(ScanError::mismatch(
            file,
            "detector",
            format!("projections are {nv} × {nu}, the panel {} × {}", p.nv, p.nu),
        ));
    }
    let betas = par
        .angles
        .radians(180.0, 0.0)
        .map_err(|e| err(file, e.to_string()))?;
    if betas.len() != n {
        return Err(ScanError::mismatch(
            file,
            "angles",
            format!("{n} projections, {} angles", betas.len()),
        ));
    }
    let frames = DARKS + 2 * FLATS + n;
    // Each frame's key (2 dark, 1 flat, 0 projection) and angle: darks and flats at θ = 0, each projection
    // at θ = −β.
    let keys: Vec<i32> = [(2, DARKS), (1, FLATS), (0, n), (1, FLATS)]
        .iter()
        .flat_map(|&(key, count)| std::iter::repeat_n(key, count))
        .collect();
    let theta: Vec<f64> = std::iter::repeat_n(0.0, DARKS + FLATS)
        .chain(betas.iter().map(|b| -b.to_degrees()))
        .chain(std::iter::repeat_n(0.0, FLATS))
        .collect();
    let counts = |value: f64| value.round().clamp(0.0, 65535.0) as u16;
    let mut data: Vec<u16> = Vec::with_capacity(frames * nv * nu);
    data.extend(std::iter::repeat_n(counts(DARK_LEVEL), DARKS * nv * nu));
    data.extend(std::iter::repeat_n(counts(FLAT_LEVEL), FLATS * nv * nu));
    let mut clipped = 0;
    let mut image = vec![0.0f32; nv * nu];
    for view in projections.outer_iter() {
        let flat: Vec<f32> = view.iter().copied().collect();
        // Reversing the rows is its own inverse.
        Orientation::ROWS_UP.apply(&flat, nv, nu, &mut image);
        for &q in &image {
            let c = DARK_LEVEL + (FLAT_LEVEL - DARK_LEVEL) * (-f64::from(q)).exp();
            if !(0.0..=65535.0).contains(&c.round()) {
                clipped += 1;
            }
            data.push(counts(c));
        }
    }
    data.extend(std::iter::repeat_n(counts(FLAT_LEVEL), FLATS * nv * nu));

    let mut fb = FileBuilder::new();
    let mut entry = fb.create_group("entry");
    entry.set_attr("NX_class", AttrValue::AsciiString("NXentry".into()));
    entry
        .create_dataset("definition")
        .with_ascii_strings(&["NXtomo"])
        .map_err(|e| h5(file, e))?;
    let mut instrument = entry.create_group("instrument");
    instrument.set_attr("NX_class", AttrValue::AsciiString("NXinstrument".into()));
    let mut detector = instrument.create_group("detector");
    detector.set_attr("NX_class", AttrValue::AsciiString("NXdetector".into()));
    detector
        .create_dataset("data")
        .with_u16_data(&data)
        .with_shape(&[frames as u64, nv as u64, nu as u64]);
    detector.create_dataset("image_key").with_i32_data(&keys);
    detector
        .create_dataset("image_key_control")
        .with_i32_data(&keys);
    for (name, mm) in [("x_pixel_size", p.du_mm), ("y_pixel_size", p.dv_mm)] {
        detector
            .create_dataset(name)
            .with_f64_data(&[mm * 1e-3])
            .set_attr("units", AttrValue::AsciiString("m".into()));
    }
    detector
        .create_dataset("distance")
        .with_f64_data(&[DISTANCE_M])
        .set_attr("units", AttrValue::AsciiString("m".into()));
    instrument.add_group(detector.finish());
    entry.add_group(instrument.finish());
    let mut sample = entry.create_group("sample");
    sample.set_attr("NX_class", AttrValue::AsciiString("NXsample".into()));
    sample
        .create_dataset("rotation_angle")
        .with_f64_data(&theta)
        .set_attr("units", AttrValue::AsciiString("degree".into()));
    entry.add_group(sample.finish());
    fb.add_group(entry.finish());
    if let Some(dir) = file.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| ScanError::io(dir, e))?;
    }
    fb.write(file).map_err(|e| h5(file, e))?;
    Ok(WrittenNx {
        file: file.to_path_buf(),
        projections: n,
        clipped,
    })
}

fn h5(file: &Path, e: impl std::fmt::Display) -> ScanError {
    err(file, format!("writing HDF5: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::geometry::{Angles, Panel, Parallel3d};
    use crate::recon::phantom::{Ellipsoid, Phantom3};
    use crate::scans::{convert, nxtomo};

    fn geometry() -> Geometry {
        Geometry::Parallel3d(Parallel3d {
            angles: Angles::Uniform {
                count: 12,
                start_deg: 10.0,
                range_deg: Some(180.0),
                short_scan: false,
            },
            detector: Panel {
                nu: 24,
                nv: 10,
                du_mm: 0.5,
                dv_mm: 0.8,
                offset_u_mm: 0.0,
                offset_v_mm: 0.0,
            },
        })
    }

    #[test]
    fn a_simulated_nxtomo_reads_back_as_the_line_integrals_it_was_made_from() {
        let g = geometry();
        let Geometry::Parallel3d(par) = &g else {
            unreachable!()
        };
        // Two balls off the axis, line integrals up to ~1.3: 16-bit counts resolve them finely.
        let ball = |value: f64, r: f64, x0: f64, z0: f64| -> Ellipsoid {
            serde_json::from_value(serde_json::json!(
                {"value": value, "a": r, "b": r, "c": r, "x0": x0, "z0": z0}))
            .expect("a ball")
        };
        let phantom = Phantom3::new(
            vec![ball(0.3, 0.5, 0.2, 0.1), ball(0.4, 0.2, -0.4, -0.3)],
            4.0,
        )
        .expect("a phantom");
        let truth = phantom.project_parallel(&par.to_views().expect("geometry"));
        let dir = tempfile::tempdir().expect("dir");
        let file = dir.path().join("sim.nx");
        let w = write_nxtomo(&file, &g, truth.view()).expect("written");
        assert_eq!((w.projections, w.clipped), (12, 0));

        let mut scan = nxtomo::open(&file).expect("read back");
        let Geometry::Parallel3d(read) = &scan.geometry else {
            panic!("{:?}", scan.geometry)
        };
        let (want, got) = (
            par.angles.radians(180.0, 0.0).expect("angles"),
            read.angles.radians(180.0, 0.0).expect("angles"),
        );
        assert_eq!(want.len(), got.len());
        for (a, b) in want.iter().zip(&got) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
        assert_eq!(
            (read.detector.nu, read.detector.nv),
            (par.detector.nu, par.detector.nv)
        );
        assert!((read.detector.du_mm - 0.5).abs() < 1e-12);
        assert!((read.detector.dv_mm - 0.8).abs() < 1e-12);
        let back = convert::line_integrals(&mut scan, 1 << 30).expect("line integrals");
        assert_eq!(back.projections.dim(), truth.dim());
        // Rounding to whole counts moves a line integral by at most 0.5 / counts: under 1e-4 here.
        let worst = back
            .projections
            .iter()
            .zip(truth.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        let peak = truth.iter().copied().fold(0.0f32, f32::max);
        println!(
            "NXtomo round trip: largest difference {worst:.2e} (line integrals up to {peak:.2})"
        );
        assert!(peak > 0.5, "the phantom is seen: {peak}");
        assert!(worst < 1e-4, "{worst}");
    }

    #[test]
    fn only_a_parallel_beam_is_written_as_nxtomo() {
        let dir = tempfile::tempdir().expect("dir");
        let cone: Geometry = serde_json::from_value(serde_json::json!({
            "type": "cone", "angles": {"count": 4}, "dso_mm": 100, "dsd_mm": 200,
            "detector": {"nu": 4, "nv": 4, "du_mm": 1, "dv_mm": 1}}))
        .expect("a cone geometry");
        let e = write_nxtomo(
            &dir.path().join("x.nx"),
            &cone,
            ndarray::Array3::<f32>::zeros((4, 4, 4)).view(),
        )
        .expect_err("refused");
        assert!(e.to_string().contains("parallel3d"), "{e}");
    }
}
