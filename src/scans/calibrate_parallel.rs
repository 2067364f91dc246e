//! The centre of rotation of a 3D parallel-beam scan (`parallel3d`), from views half a turn apart.
//!
//! For parallel rays the view at β + π is exactly the mirror image of the view at β about the column onto
//! which the rotation axis projects, so the opposite-view registration of `recon::prep::centre` applies
//! with no approximation: it reads only the views' angles and the panel, which are handed to it as a
//! canonical cone geometry whose source is far away (its distances are never used by the registration).
//!
//! A scan of a full turn, or of a half turn with both ends (0° … 180°), has such pairs. A half turn
//! without its last view (0° … 180° − step, the usual synchrotron scan) has none: the view at
//! `β₀ + π` is then extrapolated linearly from the last two views (an error of second order in the angular
//! step), and registered against the first.

use ndarray::{Array2, ArrayViewMut2};

use crate::recon::ReconError;
use crate::recon::geometry::{Angles, ConeBeam, Parallel3d};
use crate::recon::prep::{CentreEstimate, CentreOptions, ViewSource, find_centre};

/// Source distance of the stand-in cone (mm): the registration reads angles and the panel only.
const FAR_MM: f64 = 1e9;
/// Largest extrapolation (in angular steps) to the view half a turn after the first.
const MAX_EXTRAPOLATION_STEPS: f64 = 1.5;
/// Angles closer than this (radians) count as the same.
const SAME_ANGLE_RAD: f64 = 1e-4;

/// The views of the scan and, where the half turn lacks its end, one more: the view at `β₀ + π`
/// extrapolated from the last two.
struct HalfTurnEnd<'a> {
    inner: &'a dyn ViewSource,
    /// `(t, last, before last)`: the extra view is `last + t·(last − before)`.
    extra: Option<(f32, usize, usize)>,
}

impl ViewSource for HalfTurnEnd<'_> {
    fn view_count(&self) -> usize {
        self.inner.view_count() + usize::from(self.extra.is_some())
    }
    fn read_view(&self, index: usize, mut out: ArrayViewMut2<'_, f32>) -> Result<(), ReconError> {
        match self.extra {
            Some((t, last, before)) if index == self.inner.view_count() => {
                let mut b = Array2::<f32>::zeros(out.dim());
                self.inner.read_view(last, out.view_mut())?;
                self.inner.read_view(before, b.view_mut())?;
                out.zip_mut_with(&b, |o, &p| *o += t * (*o - p));
                Ok(())
            }
            _ => self.inner.read_view(index, out),
        }
    }
}

/// Find the u offset (the value `Panel::offset_u_mm` must hold) of a parallel-beam scan from its views.
pub fn find_centre_parallel(
    geometry: &Parallel3d,
    projections: &dyn ViewSource,
) -> Result<CentreEstimate, ReconError> {
    let mut angles = geometry.angles.radians(180.0, 0.0)?;
    let n = angles.len();
    if projections.view_count() != n {
        return Err(ReconError::ShapeMismatch {
            expected: vec![n],
            got: vec![projections.view_count()],
        });
    }
    let pi = std::f64::consts::PI;
    let mut extra = None;
    if n >= 3 {
        let (first, last, before) = (angles[0], angles[n - 1], angles[n - 2]);
        let sense = if last >= first { 1.0 } else { -1.0 };
        let target = first + sense * pi;
        let step = last - before;
        let paired = angles.iter().any(|&a| {
            ((a - target).rem_euclid(2.0 * pi)).min((target - a).rem_euclid(2.0 * pi))
                < SAME_ANGLE_RAD
        });
        let t = if step != 0.0 {
            (target - last) / step
        } else {
            f64::INFINITY
        };
        if !paired && t > 0.0 && t <= MAX_EXTRAPOLATION_STEPS {
            extra = Some((t as f32, n - 1, n - 2));
            angles.push(target);
        }
    }
    let mut detector = geometry.detector;
    detector.offset_u_mm = 0.0;
    let stand_in = ConeBeam {
        angles: Angles::List {
            degrees: angles.iter().map(|a| a.to_degrees()).collect(),
        },
        dso_mm: FAR_MM,
        dsd_mm: 2.0 * FAR_MM,
        detector,
    };
    let views = stand_in.to_views()?;
    let source = HalfTurnEnd {
        inner: projections,
        extra,
    };
    let opts = CentreOptions {
        tilt: false,
        ..CentreOptions::default()
    };
    find_centre(&views, &source, &opts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::geometry::Geometry;
    use crate::recon::phantom::{Ellipsoid, Phantom3};

    fn ball(value: f64, r: f64, x0: f64, y0: f64, z0: f64) -> Ellipsoid {
        Ellipsoid {
            value,
            a: r,
            b: r,
            c: r,
            x0,
            y0,
            z0,
            phi_deg: 0.0,
            theta_deg: 0.0,
            psi_deg: 0.0,
        }
    }

    fn parallel3d(views: usize, range_deg: f64, offset_u_mm: f64) -> Parallel3d {
        let g: Geometry = serde_json::from_value(serde_json::json!({
            "type": "parallel3d", "angles": {"count": views, "range_deg": range_deg},
            "detector": {"nu": 96, "nv": 24, "du_mm": 0.25, "dv_mm": 0.25, "offset_u_mm": offset_u_mm}
        }))
        .unwrap();
        match g {
            Geometry::Parallel3d(p) => p,
            other => panic!("{other:?}"),
        }
    }

    /// An object with no symmetry about the axis, projected on a panel whose axis is `offset_px` off its
    /// centre, is found back within 0.1 px with the scan's offset forgotten.
    fn finds(views: usize, range_deg: f64, offset_px: f64) -> CentreEstimate {
        let du = 0.25;
        let object = Phantom3::new(
            vec![
                ball(1.0, 0.25, 0.2, -0.1, 0.0),
                ball(0.5, 0.15, -0.3, 0.25, 0.05),
                ball(2.0, 0.08, 0.05, 0.4, -0.05),
            ],
            20.0 / 4.0,
        )
        .unwrap();
        let truth = parallel3d(views, range_deg, offset_px * du);
        let data = object.project_parallel(&truth.to_views().unwrap());
        let forgotten = parallel3d(views, range_deg, 0.0);
        let found = find_centre_parallel(&forgotten, &data.view()).unwrap();
        assert!(
            (found.offset_u_px - offset_px).abs() < 0.1,
            "{views} views over {range_deg}°: found {:.3} px, truth {offset_px} px",
            found.offset_u_px
        );
        assert!((found.offset_u_mm - offset_px * du).abs() < 0.1 * du);
        found
    }

    #[test]
    fn a_half_turn_without_its_end_is_centred_from_the_extrapolated_end() {
        // 0°, 1°, … 179°: no view at 180°, one pair with the extrapolated view.
        assert_eq!(finds(180, 180.0, 3.4).views_used, 1);
        finds(180, 180.0, -7.25);
    }

    #[test]
    fn a_full_turn_is_centred_from_opposite_views() {
        let e = finds(120, 360.0, 5.6);
        assert!(e.views_used > 1);
    }
}
