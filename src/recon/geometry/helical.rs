//! Helical (spiral) cone-beam CT: the source turns around the z axis while the table moves the object
//! through the gantry, so that in the object's frame the source climbs a helix. Clinical scanners have a
//! cylindrical detector and often a flying focal spot; both are described here and converted into the
//! canonical per-view form ([`Views3`]).
//!
//! View `k` of `n = round(turns · views_per_turn)` has the angle `β_k = start + s·2π·k/views_per_turn`
//! (`s = +1` for `"rotation": "ccw"`, seen from +z as every ctrecon angle, `−1` for `"cw"`), the source
//! at `(DSO sin β_k, −DSO cos β_k, z_start + feed·k/views_per_turn)` and the detector centre `DSD` further
//! along the central ray `(−sin β, cos β, 0)`, its u axis `(cos β, sin β, 0)` and its v axis +z: the
//! circular cone beam's view, lifted to the source's height. The table feed per turn is
//! `feed_mm_per_turn`, or `pitch` times the detector's height at the rotation axis (`nv·dv·DSO/DSD`), and
//! is positive: the source climbs toward +z (a scan in the other direction is the same data with the
//! object turned over).
//!
//! A flying focal spot moves the source, not the detector: view `k` takes offset `k mod m` of the list
//! of `m` offsets, which turns the source by `phi_deg` about the z axis and lifts it by `z_mm`. On a
//! cylindrical detector the canonical form centres the arc on each view's own source, so a φ offset is
//! exact only on a flat panel (the shift of the arc's centre is below a thousandth of an element for the
//! offsets of clinical scanners).

use serde::{Deserialize, Serialize};

use super::angles::MAX_VIEWS;
use super::check_distances;
use super::vectors::{Detector2, PanelShape, View3, Views3};
use crate::recon::error::{GeometryError, count, finite, positive};
use crate::recon::grid::MAX_AXIS;

/// Fewest views per turn accepted: fewer cannot sample a helix for any reconstruction.
pub const MIN_VIEWS_PER_TURN: usize = 16;

/// Longest scan accepted (turns).
pub const MAX_TURNS: f64 = 1e4;

/// Rotation direction of the gantry, seen from +z.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Rotation {
    /// Counter-clockwise: view angles increase (as every other ctrecon geometry).
    #[default]
    Ccw,
    /// Clockwise: view angles decrease.
    Cw,
}

/// The detector of a helical scan: the cone beam's panel plus its shape.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HelicalDetector {
    pub nu: usize,
    pub nv: usize,
    /// Column pitch (mm): along the panel, or along the arc of a cylindrical detector at radius DSD.
    pub du_mm: f64,
    pub dv_mm: f64,
    #[serde(default)]
    pub offset_u_mm: f64,
    #[serde(default)]
    pub offset_v_mm: f64,
    #[serde(default)]
    pub shape: PanelShape,
}

/// One flying-focal-spot position: the source turned by `phi_deg` about z and lifted by `z_mm`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FocalSpotOffset {
    #[serde(default)]
    pub phi_deg: f64,
    #[serde(default)]
    pub z_mm: f64,
}

/// A flying focal spot: the offsets views take in turn.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlyingFocalSpot {
    pub offsets: Vec<FocalSpotOffset>,
}

/// Most positions a flying focal spot cycles through.
pub const MAX_FOCAL_SPOTS: usize = 16;

/// Helical cone beam; see the module docs. JSON: `{"type": "helical", "dso_mm", "dsd_mm", "pitch" |
/// "feed_mm_per_turn", "turns", "views_per_turn", "start_deg", "z_start_mm", "rotation", "detector",
/// "flying_focal_spot"}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Helical {
    pub dso_mm: f64,
    pub dsd_mm: f64,
    /// Table feed per turn over the detector's height at the rotation axis (`nv·dv·DSO/DSD`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch: Option<f64>,
    /// Table feed per turn (mm); give this or `pitch`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_mm_per_turn: Option<f64>,
    /// Length of the scan in turns (need not be whole).
    pub turns: f64,
    pub views_per_turn: usize,
    /// Angle of view 0 (degrees).
    #[serde(default)]
    pub start_deg: f64,
    /// Height of the source at view 0 (mm).
    #[serde(default)]
    pub z_start_mm: f64,
    #[serde(default)]
    pub rotation: Rotation,
    pub detector: HelicalDetector,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub flying_focal_spot: Option<FlyingFocalSpot>,
}

fn invalid(msg: impl Into<String>) -> GeometryError {
    GeometryError::Invalid(msg.into())
}

impl Helical {
    /// The detector's height at the rotation axis (mm): rows times pitch, scaled by DSO/DSD.
    pub fn collimation_mm(&self) -> f64 {
        self.detector.nv as f64 * self.detector.dv_mm * self.dso_mm / self.dsd_mm
    }

    /// Table feed per turn (mm), validated: exactly one of `pitch` and `feed_mm_per_turn`, positive.
    pub fn feed_mm(&self) -> Result<f64, GeometryError> {
        match (self.pitch, self.feed_mm_per_turn) {
            (Some(p), None) => Ok(positive("pitch", p)? * self.collimation_mm()),
            (None, Some(f)) => positive("feed_mm_per_turn", f),
            (Some(_), Some(_)) => Err(invalid(
                "give one of `pitch` and `feed_mm_per_turn`, not both",
            )),
            (None, None) => Err(invalid(
                "a helical scan needs `pitch` (feed per turn over the detector's height at the rotation \
                 axis) or `feed_mm_per_turn`",
            )),
        }
    }

    /// Number of views: `turns · views_per_turn`, rounded.
    fn view_count(&self) -> Result<usize, GeometryError> {
        positive("turns", self.turns)?;
        if self.turns > MAX_TURNS {
            return Err(invalid(format!(
                "`turns` = {} exceeds the maximum of {MAX_TURNS}",
                self.turns
            )));
        }
        count("views_per_turn", self.views_per_turn, MAX_VIEWS)?;
        if self.views_per_turn < MIN_VIEWS_PER_TURN {
            return Err(invalid(format!(
                "`views_per_turn` must be at least {MIN_VIEWS_PER_TURN}, got {}",
                self.views_per_turn
            )));
        }
        let n = (self.turns * self.views_per_turn as f64).round();
        if n < 1.0 {
            return Err(invalid("`turns · views_per_turn` rounds to no view at all"));
        }
        if n > MAX_VIEWS as f64 {
            return Err(GeometryError::TooMany {
                field: "turns · views_per_turn",
                value: n as usize,
                max: MAX_VIEWS,
            });
        }
        Ok(n as usize)
    }

    fn sampling(&self) -> Result<Detector2, GeometryError> {
        let p = &self.detector;
        Ok(Detector2 {
            nu: count("detector.nu", p.nu, MAX_AXIS)?,
            nv: count("detector.nv", p.nv, MAX_AXIS)?,
            du_mm: positive("detector.du_mm", p.du_mm)?,
            dv_mm: positive("detector.dv_mm", p.dv_mm)?,
            offset_u_mm: finite("detector.offset_u_mm", p.offset_u_mm)?,
            offset_v_mm: finite("detector.offset_v_mm", p.offset_v_mm)?,
            shape: p.shape,
        })
    }

    fn focal_spots(&self) -> Result<Vec<FocalSpotOffset>, GeometryError> {
        let Some(ffs) = &self.flying_focal_spot else {
            return Ok(vec![FocalSpotOffset {
                phi_deg: 0.0,
                z_mm: 0.0,
            }]);
        };
        count(
            "flying_focal_spot.offsets",
            ffs.offsets.len(),
            MAX_FOCAL_SPOTS,
        )?;
        for o in &ffs.offsets {
            finite("flying_focal_spot.offsets[].phi_deg", o.phi_deg)?;
            finite("flying_focal_spot.offsets[].z_mm", o.z_mm)?;
            if o.phi_deg.abs() > 1.0 {
                return Err(invalid(format!(
                    "a flying focal spot's `phi_deg` must lie within ±1°, got {}",
                    o.phi_deg
                )));
            }
        }
        Ok(ffs.offsets.clone())
    }

    /// Validate and convert into the canonical per-view form.
    pub fn to_views(&self) -> Result<Views3, GeometryError> {
        check_distances(self.dso_mm, self.dsd_mm)?;
        let detector = self.sampling()?;
        let feed = self.feed_mm()?;
        let n = self.view_count()?;
        finite("start_deg", self.start_deg)?;
        finite("z_start_mm", self.z_start_mm)?;
        let spots = self.focal_spots()?;
        let sense = match self.rotation {
            Rotation::Ccw => 1.0,
            Rotation::Cw => -1.0,
        };
        let per_turn = self.views_per_turn as f64;
        let start = self.start_deg.to_radians();
        let (dso, dsd) = (self.dso_mm, self.dsd_mm);
        let views = (0..n)
            .map(|k| {
                let t = k as f64 / per_turn;
                let b = start + sense * std::f64::consts::TAU * t;
                let z = self.z_start_mm + feed * t;
                let spot = spots[k % spots.len()];
                let (s, c) = b.sin_cos();
                let (fs, fc) = (b + spot.phi_deg.to_radians()).sin_cos();
                let nominal = [dso * s, -dso * c, z];
                View3 {
                    angle_rad: b,
                    source: [dso * fs, -dso * fc, z + spot.z_mm],
                    det_centre: [nominal[0] - dsd * s, nominal[1] + dsd * c, z],
                    det_u: [c, s, 0.0],
                    det_v: [0.0, 0.0, 1.0],
                }
            })
            .collect();
        Ok(Views3 { detector, views })
    }
}
