//! MATLAB `fanbeam` conventions, reproduced as a [`FanBeam`].
//!
//! MATLAB measures in pixels with the image y axis pointing up and rotates the fan by θ counter-clockwise
//! on screen. Its `para2fan` (which `fanbeam` calls) reads the fan ray at rotation θ and sensor angle γ from
//! the parallel ray at angle θ + γ and distance D·sin γ, so the source sits at D·(−sin θ, cos θ) in its
//! y-up frame. In ctrecon's frame (y down the rows) that is the source at D·(sin β, −cos β) with β = −θ and
//! the same γ: rotation angles map to β = −θ and sensor angles are unchanged. The rotation centre is
//! MATLAB's centre pixel `floor((size+1)/2)` (1-based), half a pixel up-left of the grid centre for even
//! sizes.
//!
//! Sensors: `arc` puts sensors at γ = kΔ (degrees), `line` at positions kΔ (pixels) on the x′ axis through
//! the rotation centre (a flat detector at the isocentre, stored as one at 2D with spacing 2Δ, which
//! measures the same rays). In both cases k runs over the integers with |kΔ| within the reach MATLAB
//! computes from the radon transform of the image: ρ = ceil(√Σ(size − floor((size−1)/2) − 1)²) + 2 pixels,
//! γ_max = asin(ρ/D). Note: MATLAB's own implementation spaces `line` samples by D·sin γ rather than by the
//! documented x′ position; ctrecon follows the documentation (a true flat detector).

use serde::{Deserialize, Serialize};

use super::angles::MAX_VIEWS;
use super::{Angles, FanBeam, FanDetector};
use crate::recon::error::{GeometryError, count, positive};
use crate::recon::grid::MAX_AXIS;

/// MATLAB `FanSensorGeometry` with its `FanSensorSpacing`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(
    tag = "sensor_geometry",
    rename_all = "snake_case",
    deny_unknown_fields
)]
pub enum MatlabSensors {
    /// Spacing in degrees.
    Arc { sensor_spacing: f64 },
    /// Spacing in pixels along x′.
    Line { sensor_spacing: f64 },
}

/// `fanbeam(I, D, 'FanSensorGeometry', …, 'FanSensorSpacing', …, 'FanRotationIncrement', …)` for an
/// image of `rows × cols` pixels of `pixel_mm`. JSON: `{"rows", "cols", "d_px", "sensor_geometry": "arc" |
/// "line", "sensor_spacing", "rotation_increment_deg", "pixel_mm"}`; unknown fields are refused.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(from = "MatlabFanJson")]
pub struct MatlabFan {
    pub rows: usize,
    pub cols: usize,
    /// Distance from the fan vertex to the rotation centre, in pixels.
    pub d_px: f64,
    #[serde(flatten)]
    pub sensors: MatlabSensors,
    /// `FanRotationIncrement` in degrees; must divide 360.
    #[serde(default = "one")]
    pub rotation_increment_deg: f64,
    #[serde(default = "one")]
    pub pixel_mm: f64,
}

fn one() -> f64 {
    1.0
}

/// `sensor_geometry` as JSON spells it.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum SensorGeometry {
    Arc,
    Line,
}

/// The JSON form of [`MatlabFan`], flat, so that unknown fields can be refused (serde cannot refuse them
/// beside a flattened enum).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct MatlabFanJson {
    rows: usize,
    cols: usize,
    d_px: f64,
    sensor_geometry: SensorGeometry,
    sensor_spacing: f64,
    #[serde(default = "one")]
    rotation_increment_deg: f64,
    #[serde(default = "one")]
    pixel_mm: f64,
}

impl From<MatlabFanJson> for MatlabFan {
    fn from(j: MatlabFanJson) -> Self {
        let sensor_spacing = j.sensor_spacing;
        Self {
            rows: j.rows,
            cols: j.cols,
            d_px: j.d_px,
            sensors: match j.sensor_geometry {
                SensorGeometry::Arc => MatlabSensors::Arc { sensor_spacing },
                SensorGeometry::Line => MatlabSensors::Line { sensor_spacing },
            },
            rotation_increment_deg: j.rotation_increment_deg,
            pixel_mm: j.pixel_mm,
        }
    }
}

impl MatlabFan {
    /// Arc sensors, MATLAB's defaults otherwise.
    pub fn arc(
        rows: usize,
        cols: usize,
        d_px: f64,
        spacing_deg: f64,
        rotation_increment_deg: f64,
    ) -> Self {
        Self {
            rows,
            cols,
            d_px,
            sensors: MatlabSensors::Arc {
                sensor_spacing: spacing_deg,
            },
            rotation_increment_deg,
            pixel_mm: 1.0,
        }
    }

    /// The reach ρ (pixels) of MATLAB's sensors.
    pub fn reach_px(&self) -> f64 {
        let half = |n: usize| (n - (n - 1) / 2 - 1) as f64;
        (half(self.rows).hypot(half(self.cols))).ceil() + 2.0
    }

    /// MATLAB's rotation angles θ in degrees: 0, inc, … < 360 (none past [`MAX_VIEWS`]).
    pub fn rotation_angles_deg(&self) -> Vec<f64> {
        let n = (360.0 / self.rotation_increment_deg).round();
        let n = if n.is_finite() && n >= 0.0 {
            n.min(MAX_VIEWS as f64) as usize
        } else {
            0
        };
        (0..n)
            .map(|k| k as f64 * self.rotation_increment_deg)
            .collect()
    }

    /// Spacing and reach of MATLAB's sensors: degrees (arc) or pixels along x′ (line).
    fn sensor_spacing_and_reach(&self) -> (f64, f64) {
        match self.sensors {
            MatlabSensors::Arc { sensor_spacing } => (
                sensor_spacing,
                (self.reach_px() / self.d_px).asin().to_degrees(),
            ),
            MatlabSensors::Line { sensor_spacing } => (sensor_spacing, self.reach_px()),
        }
    }

    /// Number of MATLAB's sensors, 2k + 1, computed without allocating them; `None` past [`MAX_AXIS`] or when
    /// the spacing and reach give no finite count.
    pub fn sensor_count(&self) -> Option<usize> {
        let (spacing, reach) = self.sensor_spacing_and_reach();
        let k = (reach / spacing + 1e-9).floor();
        (k.is_finite() && k >= 0.0 && 2.0 * k + 1.0 <= MAX_AXIS as f64).then(|| 2 * k as usize + 1)
    }

    /// MATLAB's sensor positions: fan angles in degrees (arc) or x′ positions in pixels (line); empty where
    /// [`Self::sensor_count`] is `None`.
    pub fn sensor_positions(&self) -> Vec<f64> {
        let (spacing, _) = self.sensor_spacing_and_reach();
        let k = self.sensor_count().map_or(-1, |n| (n / 2) as i64);
        (-k..=k).map(|i| i as f64 * spacing).collect()
    }

    /// The equivalent [`FanBeam`] in ctrecon's conventions (mm = pixels × `pixel_mm`).
    pub fn to_fan(&self) -> Result<FanBeam, GeometryError> {
        count("rows", self.rows, MAX_AXIS)?;
        count("cols", self.cols, MAX_AXIS)?;
        let d = positive("d_px", self.d_px)?;
        let px = positive("pixel_mm", self.pixel_mm)?;
        let inc = positive("rotation_increment_deg", self.rotation_increment_deg)?;
        let turns = 360.0 / inc;
        if (turns - turns.round()).abs() > 1e-6 {
            return Err(GeometryError::Invalid(
                "rotation_increment_deg must divide 360".into(),
            ));
        }
        if self.reach_px() >= d {
            return Err(GeometryError::SourceInsideFov {
                dso_mm: d * px,
                fov_radius_mm: self.reach_px() * px,
            });
        }
        let spacing = positive("sensor_spacing", self.sensor_spacing_and_reach().0)?;
        // Counted before anything is allocated: a tiny spacing would ask for more sensors than memory holds.
        let n = self.sensor_count().ok_or_else(|| GeometryError::TooMany {
            field: "sensors (reach / sensor_spacing)",
            value: (2.0 * self.sensor_spacing_and_reach().1 / spacing).min(usize::MAX as f64)
                as usize,
            max: MAX_AXIS,
        })?;
        let detector = match self.sensors {
            MatlabSensors::Arc { sensor_spacing } => FanDetector::Arc {
                count: n,
                spacing_deg: positive("sensor_spacing", sensor_spacing)?,
                offset_deg: 0.0,
            },
            MatlabSensors::Line { sensor_spacing } => FanDetector::Flat {
                count: n,
                spacing_mm: 2.0 * positive("sensor_spacing", sensor_spacing)? * px,
                offset_mm: 0.0,
            },
        };
        // MATLAB's centre pixel floor((n+1)/2) (1-based) relative to the grid centre (n−1)/2 (0-based).
        let centre = |n: usize| n.div_ceil(2) as f64 - 1.0 - (n as f64 - 1.0) / 2.0;
        Ok(FanBeam {
            angles: Angles::Uniform {
                count: turns.round() as usize,
                start_deg: 0.0,
                range_deg: Some(-360.0),
                short_scan: false,
            },
            dso_mm: d * px,
            dsd_mm: 2.0 * d * px,
            detector,
            // Column offset is x; MATLAB's row centre is measured downward like ctrecon's rows.
            centre_mm: [centre(self.cols) * px, centre(self.rows) * px],
        })
    }
}
