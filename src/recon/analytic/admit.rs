//! Everything FBP and FDK would refuse about a geometry and its parameters, checked without data: the
//! orbit, the redundancy weighting the scan needs, and the padded length of the rows as they will be filtered
//! (offset detectors are filtered on extended rows). A job passes this at submission or it fails later.

use super::fbp2d::{fan_extent, parallel_beam};
use super::filter::padded_len;
use super::orbit::{cone_frames, fan_frames};
use super::weights::{Redundancy, extension, parallel_factor};
use crate::recon::algorithm::FbpParams;
use crate::recon::error::ReconError;
use crate::recon::geometry::{DetectorShape, Views, Views2, Views3};

/// Check `params` against `views` as [`super::fbp_2d`] and [`super::fdk`] will.
pub fn check(views: &Views, params: &FbpParams) -> Result<(), ReconError> {
    params.validate()?;
    match views {
        Views::D2(v) => check_2d(v, params),
        Views::D3(v) => check_cone(v, params),
        // Reconstructed slice by slice with the 2D parallel-beam FBP of its rows.
        Views::Slices(v) => check_2d(&v.rows, params),
    }
}

fn check_2d(views: &Views2, params: &FbpParams) -> Result<(), ReconError> {
    let parallel = parallel_beam(views)?;
    let angles: Vec<f64> = views.views.iter().map(|v| v.angle_rad).collect();
    let det = views.detector;
    let n = det.count;
    if parallel {
        parallel_factor(&angles)?;
        padded_len(n, params.padded_len)?;
        return Ok(());
    }
    let frames = fan_frames(views)?;
    let f0 = frames[0];
    let ends = (det.coord(0) + f0.u0, det.coord(n - 1) + f0.u0);
    let flat = det.shape == DetectorShape::Flat;
    let (gmin, gmax, element) = fan_extent(ends, det.spacing, flat.then_some(f0.dsd));
    let redundancy = Redundancy::classify(&angles, gmin, gmax, element)?;
    let (lo, hi) = extension(&redundancy, (ends.0 + ends.1) / det.spacing);
    padded_len(n + lo + hi, params.padded_len)?;
    Ok(())
}

fn check_cone(views: &Views3, params: &FbpParams) -> Result<(), ReconError> {
    if views.views.is_empty() {
        return Err(ReconError::param("geometry", "no views"));
    }
    if !super::orbit::is_planar(views) {
        return super::helical::check(views, params);
    }
    let det = views.detector;
    let frames = cone_frames(views)?;
    let f0 = frames[0];
    let angles: Vec<f64> = frames.iter().map(|f| f.angle_rad).collect();
    let ends = (det.u(0) + f0.u0, det.u(det.nu - 1) + f0.u0);
    let (gmin, gmax, element) = fan_extent(ends, det.du_mm, Some(f0.dsd));
    let redundancy = Redundancy::classify(&angles, gmin, gmax, element)?;
    let (lo, hi) = extension(&redundancy, (ends.0 + ends.1) / det.du_mm);
    padded_len(det.nu + lo + hi, params.padded_len)?;
    Ok(())
}
