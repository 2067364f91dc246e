//! Scan geometries. Each parametric geometry ([`ParallelBeam`], [`FanBeam`], [`ConeBeam`], and
//! [`MatlabFan`] for MATLAB `fanbeam` conventions) validates itself and converts into the canonical
//! per-view form of [`vectors`], which is all that projectors and algorithms read.
//!
//! Angle convention (see the crate docs of [`crate::recon`]): at view angle β the source sits at
//! `c + DSO·(sin β, −cos β)` around the rotation centre `c`, the central ray runs along `(−sin β, cos β)`,
//! the detector u axis is `(cos β, sin β)`; cone beams add a v axis along +z.

pub mod angles;
pub mod helical;
pub mod matlab;
pub mod parallel3d;
pub mod per_view;
pub mod rtk;
pub mod vectors;

use serde::{Deserialize, Serialize};

pub use angles::Angles;
pub use helical::{FlyingFocalSpot, FocalSpotOffset, Helical, HelicalDetector, Rotation};
pub use matlab::{MatlabFan, MatlabSensors};
pub use parallel3d::{Parallel3d, SliceViews};
pub use per_view::{ConeVectors, FanVectors, VectorPanel, VectorRow, cone_vectors, fan_vectors};
pub use vectors::{
    Detector1, Detector2, DetectorShape, PanelShape, Ray2, Ray3, Source2, Vec2, Vec3, View2, View3,
    Views2, Views3, angular_steps,
};

use super::error::{GeometryError, count, finite, positive};
use super::grid::MAX_AXIS;

/// 2D parallel beam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParallelBeam {
    /// Default range 180°.
    pub angles: Angles,
    pub det_count: usize,
    pub det_spacing_mm: f64,
    /// Detector coordinate of the detector centre (mm): shifts every element by this amount.
    #[serde(default)]
    pub det_offset_mm: f64,
}

impl ParallelBeam {
    pub fn to_views(&self) -> Result<Views2, GeometryError> {
        count("det_count", self.det_count, MAX_AXIS)?;
        positive("det_spacing_mm", self.det_spacing_mm)?;
        finite("det_offset_mm", self.det_offset_mm)?;
        if self.angles.is_short_scan() {
            return Err(GeometryError::Invalid(
                "a parallel beam has no short scan".into(),
            ));
        }
        let angles = self.angles.radians(180.0, 0.0)?;
        let views = angles
            .iter()
            .map(|&t| View2 {
                angle_rad: t,
                source: Source2::Parallel {
                    direction: [-t.sin(), t.cos()],
                },
                det_centre: [0.0, 0.0],
                det_u: [t.cos(), t.sin()],
            })
            .collect();
        let detector = Detector1 {
            count: self.det_count,
            spacing: self.det_spacing_mm,
            offset: self.det_offset_mm,
            shape: DetectorShape::Flat,
        };
        Ok(Views2 { detector, views })
    }
}

/// Detector of a fan beam.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum FanDetector {
    /// Equiangular arc centred on the source.
    Arc {
        count: usize,
        spacing_deg: f64,
        #[serde(default)]
        offset_deg: f64,
    },
    /// Flat (equispaced) detector at distance DSD from the source.
    Flat {
        count: usize,
        spacing_mm: f64,
        #[serde(default)]
        offset_mm: f64,
    },
}

impl FanDetector {
    fn sampling(&self) -> Result<Detector1, GeometryError> {
        Ok(match *self {
            FanDetector::Arc {
                count: n,
                spacing_deg,
                offset_deg,
            } => Detector1 {
                count: count("detector.count", n, MAX_AXIS)?,
                spacing: positive("detector.spacing_deg", spacing_deg)?.to_radians(),
                offset: finite("detector.offset_deg", offset_deg)?.to_radians(),
                shape: DetectorShape::Arc,
            },
            FanDetector::Flat {
                count: n,
                spacing_mm,
                offset_mm,
            } => Detector1 {
                count: count("detector.count", n, MAX_AXIS)?,
                spacing: positive("detector.spacing_mm", spacing_mm)?,
                offset: finite("detector.offset_mm", offset_mm)?,
                shape: DetectorShape::Flat,
            },
        })
    }
}

/// Largest |fan angle| (radians) seen by a detector: out to the outer edge of the outer element.
pub fn half_fan_angle(det: &Detector1, dsd_mm: f64) -> f64 {
    let edge = det.coord(0).abs().max(det.coord(det.count - 1).abs()) + det.spacing / 2.0;
    match det.shape {
        DetectorShape::Arc => edge,
        DetectorShape::Flat => (edge / dsd_mm).atan(),
    }
}

fn check_distances(dso_mm: f64, dsd_mm: f64) -> Result<(), GeometryError> {
    positive("dso_mm", dso_mm)?;
    positive("dsd_mm", dsd_mm)?;
    if dsd_mm <= dso_mm {
        return Err(GeometryError::DetectorInsideOrbit { dso_mm, dsd_mm });
    }
    Ok(())
}

/// 2D fan beam with an arc or flat detector.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FanBeam {
    /// Default range 360°; `short_scan` covers π + fan angle.
    pub angles: Angles,
    /// Source to rotation centre (mm).
    pub dso_mm: f64,
    /// Source to detector (mm); must exceed `dso_mm` (use `dsd_mm = dso_mm` + ε for a virtual detector).
    pub dsd_mm: f64,
    pub detector: FanDetector,
    /// Rotation centre in image coordinates (mm).
    #[serde(default)]
    pub centre_mm: [f64; 2],
}

impl FanBeam {
    pub fn to_views(&self) -> Result<Views2, GeometryError> {
        check_distances(self.dso_mm, self.dsd_mm)?;
        let detector = self.detector.sampling()?;
        finite("centre_mm[0]", self.centre_mm[0])?;
        finite("centre_mm[1]", self.centre_mm[1])?;
        let delta = half_fan_angle(&detector, self.dsd_mm);
        if delta >= std::f64::consts::FRAC_PI_2 {
            return Err(GeometryError::FanTooWide {
                half_fan_deg: delta.to_degrees(),
            });
        }
        let angles = self.angles.radians(360.0, 2.0 * delta)?;
        let c = self.centre_mm;
        let views = angles
            .iter()
            .map(|&b| fan_view(b, self.dso_mm, self.dsd_mm, c))
            .collect();
        Ok(Views2 { detector, views })
    }
}

pub(crate) fn fan_view(beta: f64, dso: f64, dsd: f64, c: Vec2) -> View2 {
    let (s, co) = beta.sin_cos();
    let source = [c[0] + dso * s, c[1] - dso * co];
    let dir = [-s, co];
    View2 {
        angle_rad: beta,
        source: Source2::Point { position: source },
        det_centre: [source[0] + dsd * dir[0], source[1] + dsd * dir[1]],
        det_u: [co, s],
    }
}

/// Flat panel of a cone beam.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Panel {
    pub nu: usize,
    pub nv: usize,
    pub du_mm: f64,
    pub dv_mm: f64,
    #[serde(default)]
    pub offset_u_mm: f64,
    #[serde(default)]
    pub offset_v_mm: f64,
}

/// 3D circular cone beam with a flat panel. The orbit lies in the plane z = 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConeBeam {
    pub angles: Angles,
    pub dso_mm: f64,
    pub dsd_mm: f64,
    pub detector: Panel,
}

impl ConeBeam {
    pub fn to_views(&self) -> Result<Views3, GeometryError> {
        check_distances(self.dso_mm, self.dsd_mm)?;
        let p = &self.detector;
        let detector = Detector2 {
            nu: count("detector.nu", p.nu, MAX_AXIS)?,
            nv: count("detector.nv", p.nv, MAX_AXIS)?,
            du_mm: positive("detector.du_mm", p.du_mm)?,
            dv_mm: positive("detector.dv_mm", p.dv_mm)?,
            offset_u_mm: finite("detector.offset_u_mm", p.offset_u_mm)?,
            offset_v_mm: finite("detector.offset_v_mm", p.offset_v_mm)?,
            shape: PanelShape::Flat,
        };
        let row = Detector1 {
            count: detector.nu,
            spacing: detector.du_mm,
            offset: detector.offset_u_mm,
            shape: DetectorShape::Flat,
        };
        let delta = half_fan_angle(&row, self.dsd_mm);
        let angles = self.angles.radians(360.0, 2.0 * delta)?;
        let views = angles
            .iter()
            .map(|&b| {
                let v = fan_view(b, self.dso_mm, self.dsd_mm, [0.0, 0.0]);
                let Source2::Point { position } = v.source else {
                    unreachable!("fan views have a point source")
                };
                View3 {
                    angle_rad: b,
                    source: [position[0], position[1], 0.0],
                    det_centre: [v.det_centre[0], v.det_centre[1], 0.0],
                    det_u: [v.det_u[0], v.det_u[1], 0.0],
                    det_v: [0.0, 0.0, 1.0],
                }
            })
            .collect();
        Ok(Views3 { detector, views })
    }
}

/// Any scan geometry. JSON: `{"type": "parallel" | "fan" | "fan_matlab" | "cone" | "fan_vectors" |
/// "cone_vectors" | "parallel3d" | "helical", …}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Geometry {
    Parallel(ParallelBeam),
    Fan(FanBeam),
    FanMatlab(MatlabFan),
    Cone(ConeBeam),
    FanVectors(FanVectors),
    ConeVectors(ConeVectors),
    Parallel3d(Parallel3d),
    Helical(Helical),
}

/// A geometry in canonical form: 2D views, cone-beam views, or a stack of 2D parallel-beam slices (a 3D
/// parallel beam, reconstructed slice by slice).
#[derive(Debug, Clone, PartialEq)]
pub enum Views {
    D2(Views2),
    D3(Views3),
    Slices(SliceViews),
}

impl Views {
    /// Shape of the projection data: `[views, u]` or `[views, v, u]`.
    pub fn data_shape(&self) -> Vec<usize> {
        match self {
            Views::D2(v) => v.shape().to_vec(),
            Views::D3(v) => v.shape().to_vec(),
            Views::Slices(v) => v.shape().to_vec(),
        }
    }
}

impl Geometry {
    /// Validate and convert to canonical per-view form.
    pub fn to_views(&self) -> Result<Views, GeometryError> {
        Ok(match self {
            Geometry::Parallel(g) => Views::D2(g.to_views()?),
            Geometry::Fan(g) => Views::D2(g.to_views()?),
            Geometry::FanMatlab(g) => Views::D2(g.to_fan()?.to_views()?),
            Geometry::Cone(g) => Views::D3(g.to_views()?),
            Geometry::FanVectors(g) => Views::D2(g.to_views()?),
            Geometry::ConeVectors(g) => Views::D3(g.to_views()?),
            Geometry::Parallel3d(g) => Views::Slices(g.to_views()?),
            Geometry::Helical(g) => Views::D3(g.to_views()?),
        })
    }
    /// True for 3D data (`[view][v][u]`): cone beams and 3D parallel beams.
    pub fn is_3d(&self) -> bool {
        matches!(
            self,
            Geometry::Cone(_)
                | Geometry::ConeVectors(_)
                | Geometry::Parallel3d(_)
                | Geometry::Helical(_)
        )
    }
    /// Source-to-isocentre distance, if the geometry has a source (for a per-view geometry, the smallest
    /// distance of a source from the rotation axis).
    pub fn dso_mm(&self) -> Option<f64> {
        match self {
            Geometry::Parallel(_) | Geometry::Parallel3d(_) => None,
            Geometry::Fan(g) => Some(g.dso_mm),
            Geometry::FanMatlab(g) => Some(g.d_px * g.pixel_mm),
            Geometry::Cone(g) => Some(g.dso_mm),
            Geometry::Helical(g) => Some(g.dso_mm),
            Geometry::FanVectors(g) => per_view::nearest_source_2d(g),
            Geometry::ConeVectors(g) => per_view::nearest_source_3d(g),
        }
    }
    /// Refuse a source orbit that passes through a field of view of radius `fov_radius_mm`.
    pub fn check_fov(&self, fov_radius_mm: f64) -> Result<(), GeometryError> {
        match self.dso_mm() {
            Some(dso_mm) if dso_mm <= fov_radius_mm => Err(GeometryError::SourceInsideFov {
                dso_mm,
                fov_radius_mm,
            }),
            _ => Ok(()),
        }
    }
}

/// The geometry fuzz target's entry point (and its regression replay's): JSON as a client sends it, parsed,
/// validated and turned into views as a sinogram upload or a job does. Every outcome but a panic or an
/// allocation sized by the input is fine.
#[doc(hidden)]
pub fn fuzz_entry(data: &[u8]) {
    let Ok(geometry) = serde_json::from_slice::<Geometry>(data) else {
        return;
    };
    let _ = geometry.check_fov(100.0);
    if let Ok(views) = geometry.to_views() {
        let _ = views.data_shape();
    }
}

#[cfg(test)]
mod helical_tests;
#[cfg(test)]
mod per_view_tests;
#[cfg(test)]
mod rtk_tests;
#[cfg(test)]
mod tests;
