//! Calibration of an imported scan: the centre of rotation (the detector's u offset) found from the views
//! themselves when the scan's metadata states none, read from the metadata when it does, or pinned by the
//! user; the result says which. A full turn is calibrated from opposite views, a shorter scan from the
//! consistency of conjugate rays (`recon::prep`). The in-plane tilt is not estimated yet (the estimate
//! misses its goal, see `recon::prep::centre`): the panel keeps its roll of 0.

use ndarray::ArrayView3;
use serde::Serialize;

use super::Provenance;
use crate::recon::ReconError;
use crate::recon::geometry::Geometry;
use crate::recon::prep::{
    CentreEstimate, CentreOptions, ConjugateOptions, find_centre, find_centre_conjugate,
};

/// How the centre of rotation of a scan is settled.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CentrePolicy {
    /// Found from the views unless the metadata states a calibrated centre (the default).
    Auto,
    /// Found from the views whatever the metadata says.
    Find,
    /// As the metadata gives it (0 where it gives none).
    Read,
    /// This u offset (mm at the detector), as `Panel::offset_u_mm`.
    Pinned(f64),
}

/// What was done: the u offset now in the geometry, whether it was `found`, `read` or `pinned`, and the
/// estimate with its residual when it was found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Calibration {
    pub offset_u_mm: f64,
    pub centre: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimate: Option<CentreEstimate>,
}

/// Keys by which a format states a calibrated centre of rotation.
const CENTRE_KEYS: [&str; 3] = [
    "CentreOfRotationTop",
    "CentreOfRotationBottom",
    "offset_u_mm",
];

/// Whether the scan's metadata states its centre of rotation.
pub fn states_centre(provenance: &[Provenance]) -> bool {
    provenance
        .iter()
        .any(|p| CENTRE_KEYS.iter().any(|k| p.key.ends_with(k)))
}

/// Settle the centre of rotation of a cone-beam `geometry` for its `projections` (`[view][v][u]`, line
/// integrals) under `policy`, and write it into the geometry.
pub fn calibrate(
    geometry: &mut Geometry,
    projections: ArrayView3<'_, f32>,
    provenance: &[Provenance],
    policy: CentrePolicy,
) -> Result<Calibration, ReconError> {
    let Geometry::Cone(cone) = geometry else {
        return Err(ReconError::param(
            "geometry",
            "the centre of rotation is calibrated for cone-beam scans only",
        ));
    };
    let read = cone.detector.offset_u_mm;
    let find = match policy {
        CentrePolicy::Auto => !states_centre(provenance),
        CentrePolicy::Find => true,
        CentrePolicy::Read => false,
        CentrePolicy::Pinned(mm) => {
            cone.detector.offset_u_mm = mm;
            cone.to_views()?;
            return Ok(Calibration {
                offset_u_mm: mm,
                centre: "pinned",
                estimate: None,
            });
        }
    };
    if !find {
        return Ok(Calibration {
            offset_u_mm: read,
            centre: "read",
            estimate: None,
        });
    }
    let views = cone.to_views()?;
    let estimate = if full_turn(&views.views.iter().map(|v| v.angle_rad).collect::<Vec<_>>()) {
        find_centre(&views, &projections, &CentreOptions::default())?
    } else {
        find_centre_conjugate(
            &views,
            cone.dsd_mm,
            &projections,
            &ConjugateOptions::default(),
        )?
    };
    cone.detector.offset_u_mm = estimate.offset_u_mm;
    Ok(Calibration {
        offset_u_mm: estimate.offset_u_mm,
        centre: "found",
        estimate: Some(estimate),
    })
}

/// Whether the view angles cover a full turn (the last view one step short of 2π from the first).
fn full_turn(angles: &[f64]) -> bool {
    let (Some(first), Some(last)) = (angles.first(), angles.last()) else {
        return false;
    };
    let n = angles.len();
    if n < 4 {
        return false;
    }
    let span = (last - first).abs();
    let step = span / (n - 1) as f64;
    span + step >= 2.0 * std::f64::consts::PI * (1.0 - 1e-3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_turn_is_told_from_a_short_scan() {
        let turn: Vec<f64> = (0..360).map(|i| (i as f64).to_radians()).collect();
        assert!(full_turn(&turn));
        let back: Vec<f64> = (0..360).map(|i| -(i as f64).to_radians()).collect();
        assert!(full_turn(&back));
        let short: Vec<f64> = (0..200).map(|i| (i as f64).to_radians()).collect();
        assert!(!full_turn(&short));
        assert!(!full_turn(&[]));
    }

    #[test]
    fn a_stated_centre_is_read_and_a_missing_one_is_found() {
        let p = |key: &str| Provenance {
            key: key.into(),
            value: "1".into(),
            origin: "scan.xtekct".into(),
        };
        assert!(states_centre(&[p("CentreOfRotationTop")]));
        assert!(!states_centre(&[p("ObjectOffsetX"), p("SrcToObject")]));
    }
}
