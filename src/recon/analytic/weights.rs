//! Redundancy weights of divergent-beam scans: which formula a scan needs (one full turn, a Parker short
//! scan, a Wang offset detector), and the weights themselves.
//!
//! Every weight here multiplies the full-scan formula, which already halves each ray because a full turn
//! measures every line twice: a full turn has weight 1, a short scan 2·w_Parker, an offset detector
//! w_Wang ∈ [0, 2].
//!
//! Sign conventions: in ctrecon's frame (see [`crate::recon`]) the ray at fan angle γ of view β runs along
//! the angle β + π/2 − γ, so the line measured by (β, γ) is measured again by (β + π − 2γ, −γ). Parker's
//! formula is written for (β + π + 2γ, −γ); it is evaluated at −γ for counter-clockwise scans and at +γ
//! for clockwise ones (mirror image).

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4, PI};

use crate::recon::error::{GeometryError, ReconError};
use crate::recon::geometry::angular_steps;

/// Parker's short-scan weight for view angle `beta` ∈ [0, π + 2δ] (from the start of the scan) and fan
/// angle `gamma` (Parker's sign convention), half scan angle `delta` ≥ |γ|.
pub fn parker(beta: f64, gamma: f64, delta: f64) -> f64 {
    let end = PI + 2.0 * delta;
    if !(0.0..=end).contains(&beta) {
        return 0.0;
    }
    if beta < 2.0 * delta - 2.0 * gamma {
        let s = (FRAC_PI_4 * beta / (delta - gamma)).sin();
        s * s
    } else if beta <= PI - 2.0 * gamma {
        1.0
    } else {
        let s = (FRAC_PI_4 * (end - beta) / (delta + gamma)).sin();
        s * s
    }
}

/// Wang's offset-detector weight (already doubled) for fan angle `gamma` on the long side's sign
/// convention (the detector reaches far toward +γ) with overlap half-angle `overlap` > 0:
/// 0 below −overlap, 2 above overlap, 1 + sin((π/2)·γ/overlap) between.
pub fn wang(gamma: f64, overlap: f64) -> f64 {
    if gamma <= -overlap {
        0.0
    } else if gamma >= overlap {
        2.0
    } else {
        1.0 + (FRAC_PI_2 * gamma / overlap).sin()
    }
}

/// What a divergent-beam scan needs to be reconstructed exactly once per line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Redundancy {
    /// One full turn, symmetric detector.
    Full,
    /// Less than a turn but at least π + fan angle: Parker weights.
    Short {
        start_rad: f64,
        /// +1 counter-clockwise, −1 clockwise.
        sense: f64,
        /// Half of (scan range − π), at least the half fan angle.
        delta: f64,
    },
    /// One full turn with a detector reaching further on one side: Wang weights.
    Offset {
        /// +1 when the long side is toward +γ.
        side: f64,
        /// Fan angle covered on both sides.
        overlap: f64,
    },
}

impl Redundancy {
    /// Classify a scan from its view angles and the fan angles of the detector's outer edges (relative
    /// to the central ray). `min_step` is the fan angle of one detector element near the centre.
    pub fn classify(
        angles: &[f64],
        gamma_min: f64,
        gamma_max: f64,
        element: f64,
    ) -> Result<Self, ReconError> {
        let coverage: f64 = angular_steps(angles).iter().sum();
        let turn = 2.0 * PI;
        if gamma_min >= 0.0 || gamma_max <= 0.0 {
            return Err(ReconError::param(
                "geometry",
                "the detector must contain the central ray",
            ));
        }
        let asymmetry = gamma_max + gamma_min;
        let offset = asymmetry.abs() > 0.5 * element;
        if (coverage - turn).abs() <= 1e-3 * turn {
            return Ok(if offset {
                Redundancy::Offset {
                    side: asymmetry.signum(),
                    overlap: gamma_min.abs().min(gamma_max),
                }
            } else {
                Redundancy::Full
            });
        }
        if coverage > turn {
            return Err(ReconError::param(
                "geometry",
                "scans of more than one turn are not supported by FBP/FDK",
            ));
        }
        if offset {
            return Err(ReconError::param(
                "geometry",
                "a short scan with an offset detector is not supported (Parker and Wang weights do not combine)",
            ));
        }
        let first = angles.first().copied().unwrap_or(0.0);
        let last = angles.last().copied().unwrap_or(0.0);
        let span = (last - first).abs();
        let half_fan = gamma_max.max(-gamma_min);
        let needed = PI + 2.0 * half_fan;
        if span < needed - 1e-6 {
            return Err(GeometryError::ShortScanTooShort {
                needed_deg: needed.to_degrees(),
                covered_deg: span.to_degrees(),
            }
            .into());
        }
        Ok(Redundancy::Short {
            start_rad: first,
            sense: if last >= first { 1.0 } else { -1.0 },
            delta: ((span - PI) / 2.0).max(half_fan),
        })
    }

    /// The weight of the ray at fan angle `gamma` (relative to the central ray, positive toward the
    /// detector u axis) in the view at `angle_rad`.
    pub fn weight(&self, angle_rad: f64, gamma: f64) -> f64 {
        match *self {
            Redundancy::Full => 1.0,
            Redundancy::Short {
                start_rad,
                sense,
                delta,
            } => 2.0 * parker(sense * (angle_rad - start_rad), -sense * gamma, delta),
            Redundancy::Offset { side, overlap } => wang(side * gamma, overlap),
        }
    }
}

/// Zero elements to add below and above a detector row before filtering: an offset detector is extended
/// on its short side to the reach of its long side, so that the filtered row (whose ramp-filter tails
/// reach beyond the measured elements) is stored wherever the backprojection reads it.
pub fn extension(redundancy: &Redundancy, asymmetry_elements: f64) -> (usize, usize) {
    match *redundancy {
        Redundancy::Offset { side, .. } => {
            let k = asymmetry_elements.abs().ceil() as usize;
            if side > 0.0 { (k, 0) } else { (0, k) }
        }
        _ => (0, 0),
    }
}

/// The factor of a parallel-beam scan: 1 for a half turn, ½ for a full turn; anything else is refused.
pub fn parallel_factor(angles: &[f64]) -> Result<f64, ReconError> {
    let coverage: f64 = angular_steps(angles).iter().sum();
    if (coverage - PI).abs() <= 1e-3 * PI {
        Ok(1.0)
    } else if (coverage - 2.0 * PI).abs() <= 1e-3 * PI {
        Ok(0.5)
    } else if coverage < PI {
        Err(ReconError::param(
            "geometry",
            format!(
                "parallel-beam FBP needs 180° of views, these cover {:.3}°",
                coverage.to_degrees()
            ),
        ))
    } else {
        Err(ReconError::param(
            "geometry",
            format!(
                "parallel-beam FBP supports 180° or 360° of views, these cover {:.3}°",
                coverage.to_degrees()
            ),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parker_weights_of_a_line_and_its_conjugate_add_to_one() {
        let delta = 0.3;
        for i in 0..=40 {
            let gamma = -0.28 + 0.56 * i as f64 / 40.0;
            for j in 0..=50 {
                let beta = (PI - 2.0 * gamma) * j as f64 / 50.0;
                // In Parker's convention the conjugate of (β, γ) is (β + π + 2γ, −γ).
                let w = parker(beta, gamma, delta) + parker(beta + PI + 2.0 * gamma, -gamma, delta);
                let conj = beta + PI + 2.0 * gamma;
                if conj <= PI + 2.0 * delta {
                    assert!((w - 1.0).abs() < 1e-12, "β={beta} γ={gamma} w={w}");
                }
            }
        }
    }

    #[test]
    fn ctrecon_short_scan_weights_of_conjugate_rays_add_to_two() {
        let delta = 0.25;
        let r = Redundancy::Short {
            start_rad: 0.3,
            sense: 1.0,
            delta,
        };
        // ctrecon's conjugate of (β, γ) is (β + π − 2γ, −γ).
        for (b, g) in [(0.1, 0.2), (0.4, -0.1), (1.0, 0.0), (0.05, -0.24)] {
            let w = r.weight(0.3 + b, g) + r.weight(0.3 + b + PI - 2.0 * g, -g);
            assert!((w - 2.0).abs() < 1e-12, "{b} {g} {w}");
        }
        let cw = Redundancy::Short {
            start_rad: 0.0,
            sense: -1.0,
            delta,
        };
        for (b, g) in [(0.1, 0.2), (0.4, -0.1)] {
            let w = cw.weight(-b, g) + cw.weight(-(b + PI + 2.0 * g), -g);
            assert!((w - 2.0).abs() < 1e-12, "{b} {g} {w}");
        }
    }

    #[test]
    fn wang_weights_of_opposite_rays_add_to_two() {
        for g in [-0.1, -0.03, 0.0, 0.02, 0.09] {
            assert!((wang(g, 0.1) + wang(-g, 0.1) - 2.0).abs() < 1e-12);
        }
        assert_eq!(wang(-0.2, 0.1), 0.0);
        assert_eq!(wang(0.5, 0.1), 2.0);
    }

    #[test]
    fn scans_are_classified_by_range_and_detector_symmetry() {
        let full: Vec<f64> = (0..360).map(|k| (k as f64).to_radians()).collect();
        assert_eq!(
            Redundancy::classify(&full, -0.2, 0.2, 0.001).unwrap(),
            Redundancy::Full
        );
        assert!(matches!(
            Redundancy::classify(&full, -0.05, 0.2, 0.001).unwrap(),
            Redundancy::Offset { side, overlap } if side == 1.0 && overlap == 0.05
        ));
        let short: Vec<f64> = (0..=200).map(|k| (PI + 0.4) * k as f64 / 200.0).collect();
        assert!(matches!(
            Redundancy::classify(&short, -0.2, 0.2, 0.001).unwrap(),
            Redundancy::Short { delta, .. } if (delta - 0.2).abs() < 1e-12
        ));
        assert!(matches!(
            Redundancy::classify(&short, -0.3, 0.3, 0.001),
            Err(ReconError::Geometry(
                GeometryError::ShortScanTooShort { .. }
            ))
        ));
        assert!(Redundancy::classify(&short, -0.05, 0.2, 0.001).is_err());
        let half: Vec<f64> = (0..180).map(|k| (k as f64).to_radians()).collect();
        assert_eq!(parallel_factor(&half).unwrap(), 1.0);
        assert_eq!(parallel_factor(&full).unwrap(), 0.5);
        assert!(parallel_factor(&half[..120]).is_err());
    }
}
