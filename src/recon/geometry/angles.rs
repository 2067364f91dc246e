//! View-angle specifications.

use serde::{Deserialize, Serialize};

use crate::recon::error::{GeometryError, count, finite};

/// Most views any geometry accepts.
pub const MAX_VIEWS: usize = 100_000;

/// How the view angles of a scan are given. JSON: `{"count": 360, "range_deg": 360}` (equally spaced,
/// end excluded), `{"count": 200, "short_scan": true}` (π + fan angle, both ends included) or
/// `{"degrees": [0, 1.5, …]}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(
    untagged,
    deny_unknown_fields,
    expecting = "angles: {\"count\": N} with optional \"start_deg\" and \"range_deg\" (equally spaced), \
                 {\"count\": N, \"short_scan\": true}, or {\"degrees\": [a, b, …]}"
)]
pub enum Angles {
    Uniform {
        count: usize,
        #[serde(default)]
        start_deg: f64,
        /// Angular range in degrees (negative turns clockwise); default a full scan for the geometry
        /// (180° parallel, 360° fan and cone). Ignored for a short scan.
        #[serde(default)]
        range_deg: Option<f64>,
        /// Cover exactly π + fan angle with both ends included (fan and cone beams).
        #[serde(default)]
        short_scan: bool,
    },
    List {
        degrees: Vec<f64>,
    },
}

impl Angles {
    /// `count` views equally spaced over `range_deg`, end excluded.
    pub fn uniform(count: usize, range_deg: f64) -> Self {
        Angles::Uniform {
            count,
            start_deg: 0.0,
            range_deg: Some(range_deg),
            short_scan: false,
        }
    }
    /// `count` views over π + fan angle, both ends included.
    pub fn short_scan(count: usize) -> Self {
        Angles::Uniform {
            count,
            start_deg: 0.0,
            range_deg: None,
            short_scan: true,
        }
    }

    /// Number of views.
    pub fn count(&self) -> usize {
        match self {
            Angles::Uniform { count, .. } => *count,
            Angles::List { degrees } => degrees.len(),
        }
    }

    pub(crate) fn is_short_scan(&self) -> bool {
        matches!(
            self,
            Angles::Uniform {
                short_scan: true,
                ..
            }
        )
    }

    /// The angles in radians. `full_range_deg` is the default range; `fan_angle_rad` (2δ) sets the
    /// short-scan range π + 2δ.
    pub fn radians(
        &self,
        full_range_deg: f64,
        fan_angle_rad: f64,
    ) -> Result<Vec<f64>, GeometryError> {
        let out: Vec<f64> = match self {
            Angles::Uniform {
                count: n,
                start_deg,
                range_deg,
                short_scan,
            } => {
                let n = count("angles.count", *n, MAX_VIEWS)?;
                let start = finite("angles.start_deg", *start_deg)?.to_radians();
                if *short_scan {
                    let range = std::f64::consts::PI + fan_angle_rad;
                    if n < 2 {
                        return Err(GeometryError::Invalid(
                            "a short scan needs at least 2 views".into(),
                        ));
                    }
                    (0..n)
                        .map(|k| start + range * k as f64 / (n - 1) as f64)
                        .collect()
                } else {
                    let range = finite("angles.range_deg", range_deg.unwrap_or(full_range_deg))?;
                    if range == 0.0 {
                        return Err(GeometryError::NonPositive {
                            field: "angles.range_deg",
                            value: range,
                        });
                    }
                    let range = range.to_radians();
                    (0..n)
                        .map(|k| start + range * k as f64 / n as f64)
                        .collect()
                }
            }
            Angles::List { degrees } => {
                count("angles.degrees", degrees.len(), MAX_VIEWS)?;
                for &d in degrees {
                    finite("angles.degrees", d)?;
                }
                degrees.iter().map(|d| d.to_radians()).collect()
            }
        };
        check_monotonic(&out)?;
        Ok(out)
    }
}

fn check_monotonic(a: &[f64]) -> Result<(), GeometryError> {
    if a.len() < 2 {
        return Ok(());
    }
    let up = a[1] > a[0];
    for k in 1..a.len() {
        let step = a[k] - a[k - 1];
        if step == 0.0 || (step > 0.0) != up {
            return Err(GeometryError::AnglesNotMonotonic { index: k });
        }
    }
    Ok(())
}

/// Total angle swept by `angles` including one step (radians): π/K·K = π for K views over [0, π).
pub fn coverage(angles: &[f64]) -> f64 {
    super::vectors::angular_steps(angles).iter().sum()
}
