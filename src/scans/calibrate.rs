//! Calibration of an imported scan: the centre of rotation (the detector's u offset) found from the views
//! themselves when the scan's metadata states none, read from the metadata when it does, or pinned by the
//! user; the result says which. A full turn is calibrated from opposite views, a shorter scan from the
//! consistency of conjugate rays (`recon::prep`); a parallel beam (`parallel3d`) from views half a turn
//! apart, mirrored (`calibrate_parallel`). The in-plane tilt is not estimated yet (the estimate
//! misses its goal, see `recon::prep::centre`): the panel keeps its roll of 0.

use std::os::unix::fs::FileExt;

use ndarray::ArrayViewMut2;
use serde::{Deserialize, Serialize};

use super::Provenance;
use crate::recon::ReconError;
use crate::recon::geometry::Geometry;
use crate::recon::prep::{
    CentreEstimate, CentreOptions, ConjugateOptions, ViewSource, find_centre, find_centre_conjugate,
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
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    pub offset_u_mm: f64,
    /// `found`, `read` or `pinned`.
    pub centre: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimate: Option<CentreEstimate>,
    /// Why a centre that was to be found was read instead (`auto` on views that allow no estimate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

impl CentrePolicy {
    /// `auto`, `find`, `read` or a u offset in mm.
    pub fn parse(text: &str) -> Option<Self> {
        Some(match text {
            "auto" => CentrePolicy::Auto,
            "find" => CentrePolicy::Find,
            "read" => CentrePolicy::Read,
            other if plain_decimal(other) => CentrePolicy::Pinned(other.parse().ok()?),
            _ => return None,
        })
    }
}

/// `-?[0-9]+(\.[0-9]+)?`: a number as the API states it (no exponent, sign or infinity).
fn plain_decimal(text: &str) -> bool {
    let digits = |s: &str| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit());
    let t = text.strip_prefix('-').unwrap_or(text);
    match t.split_once('.') {
        Some((whole, fraction)) => digits(whole) && digits(fraction),
        None => digits(t),
    }
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

/// Settle the centre of rotation of a cone-beam or 3D parallel-beam `geometry` for its `projections`
/// (`[view][v][u]`, line integrals) under `policy`, and write it into the geometry's panel
/// (`offset_u_mm`).
pub fn calibrate(
    geometry: &mut Geometry,
    projections: &dyn ViewSource,
    provenance: &[Provenance],
    policy: CentrePolicy,
) -> Result<Calibration, ReconError> {
    let read = match geometry {
        Geometry::Cone(cone) => cone.detector.offset_u_mm,
        Geometry::Parallel3d(p) => p.detector.offset_u_mm,
        _ => {
            return Err(ReconError::param(
                "geometry",
                "the centre of rotation is calibrated for cone-beam and parallel3d scans only",
            ));
        }
    };
    let find = match policy {
        CentrePolicy::Auto => !states_centre(provenance),
        CentrePolicy::Find => true,
        CentrePolicy::Read => false,
        CentrePolicy::Pinned(mm) => {
            set_offset(geometry, mm)?;
            return Ok(Calibration {
                offset_u_mm: mm,
                centre: "pinned".into(),
                estimate: None,
                note: None,
            });
        }
    };
    if !find {
        return Ok(Calibration {
            offset_u_mm: read,
            centre: "read".into(),
            estimate: None,
            note: None,
        });
    }
    let found = match geometry {
        Geometry::Cone(cone) => {
            let views = cone.to_views()?;
            if full_turn(&views.views.iter().map(|v| v.angle_rad).collect::<Vec<_>>()) {
                find_centre(&views, projections, &CentreOptions::default())
            } else {
                find_centre_conjugate(
                    &views,
                    cone.dsd_mm,
                    projections,
                    &ConjugateOptions::default(),
                )
            }
        }
        Geometry::Parallel3d(p) => super::calibrate_parallel::find_centre_parallel(p, projections),
        _ => Err(ReconError::param(
            "geometry",
            "no centre search for this geometry",
        )),
    };
    let estimate = match found {
        // The tilt estimate misses its goal (recon::prep::centre) and a cone's panel has no roll: not
        // reported, so that nobody takes it for a measured value.
        Ok(e) => CentreEstimate {
            tilt_deg: None,
            ..e
        },
        // Asked for by default, not by the user: the value read stands, and the answer says why.
        Err(e) if policy == CentrePolicy::Auto => {
            return Ok(Calibration {
                offset_u_mm: read,
                centre: "read".into(),
                estimate: None,
                note: Some(format!("the centre could not be found from the views: {e}")),
            });
        }
        Err(e) => return Err(e),
    };
    set_offset(geometry, estimate.offset_u_mm)?;
    Ok(Calibration {
        offset_u_mm: estimate.offset_u_mm,
        centre: "found".into(),
        estimate: Some(estimate),
        note: None,
    })
}

/// Write `mm` into the panel's `offset_u_mm` and check the geometry still holds.
fn set_offset(geometry: &mut Geometry, mm: f64) -> Result<(), ReconError> {
    match geometry {
        Geometry::Cone(cone) => {
            cone.detector.offset_u_mm = mm;
            cone.to_views()?;
        }
        Geometry::Parallel3d(p) => {
            p.detector.offset_u_mm = mm;
            p.to_views()?;
        }
        _ => {
            return Err(ReconError::param(
                "geometry",
                "the centre of rotation is calibrated for cone-beam and parallel3d scans only",
            ));
        }
    }
    Ok(())
}

/// The views of a float32 `.npy` projection file (`[view][v][u]`, little-endian, C order) on disk, read
/// one at a time where the calibration asks for them: an imported scan is calibrated without being held.
pub struct NpyViews {
    file: std::fs::File,
    data_offset: u64,
    views: usize,
    nv: usize,
    nu: usize,
}

impl NpyViews {
    /// `file` holds a header of `data_offset` bytes, then `views × nv × nu` float32 values.
    pub fn new(file: std::fs::File, data_offset: u64, shape: [usize; 3]) -> Self {
        let [views, nv, nu] = shape;
        Self {
            file,
            data_offset,
            views,
            nv,
            nu,
        }
    }
}

impl ViewSource for NpyViews {
    fn view_count(&self) -> usize {
        self.views
    }

    fn read_view(&self, index: usize, mut out: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        let io = |e: std::io::Error| ReconError::param("projections", e.to_string());
        if index >= self.views || out.dim() != (self.nv, self.nu) {
            return Err(ReconError::ShapeMismatch {
                expected: vec![self.views, self.nv, self.nu],
                got: vec![index, out.dim().0, out.dim().1],
            });
        }
        let row_bytes = self.nu * 4;
        let mut bytes = vec![0u8; row_bytes];
        let view_at = self.data_offset + (index * self.nv * row_bytes) as u64;
        for (r, mut row) in out.rows_mut().into_iter().enumerate() {
            self.file
                .read_exact_at(&mut bytes, view_at + (r * row_bytes) as u64)
                .map_err(io)?;
            for (v, b) in row.iter_mut().zip(bytes.chunks_exact(4)) {
                *v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
        Ok(())
    }
}

/// Whether the view angles cover a full turn (the last view one step short of 2π from the first).
pub(crate) fn full_turn(angles: &[f64]) -> bool {
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
    fn policies_parse_as_the_api_states_them() {
        assert_eq!(CentrePolicy::parse("auto"), Some(CentrePolicy::Auto));
        assert_eq!(CentrePolicy::parse("find"), Some(CentrePolicy::Find));
        assert_eq!(CentrePolicy::parse("read"), Some(CentrePolicy::Read));
        assert_eq!(
            CentrePolicy::parse("0.45"),
            Some(CentrePolicy::Pinned(0.45))
        );
        assert_eq!(CentrePolicy::parse("-2"), Some(CentrePolicy::Pinned(-2.0)));
        for bad in ["", "1e3", "+1", ".5", "1.", "inf", "NaN", "middle", "--1"] {
            assert_eq!(CentrePolicy::parse(bad), None, "{bad}");
        }
    }

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
