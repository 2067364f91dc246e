//! The bounds the API checks at submission, as `GET /v1/limits` tells clients (forms take their min/max
//! from it). Every number is read from the constant or setting the validator itself uses, so the two
//! cannot drift apart.

use serde::Serialize;

use crate::config::Settings;
use crate::jobs::model::{
    MAX_CURVE_POINTS, MAX_ITEMS, MAX_RENDER_FRAMES, MAX_ROTATING_FRAMES, MAX_SIGMA_MM,
};
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::grid::MAX_AXIS;
use crate::recon::iterative::params::{MAX_ITERATIONS, MAX_TV_ITERATIONS};
use crate::recon::phantom::{MAX_BODIES, MAX_INCIDENT_PHOTONS};
use crate::volume::MAX_SIDE;

/// Values an uploaded or simulated array may hold: the memory budget in float32 values.
pub fn max_array_values(settings: &Settings) -> u64 {
    settings.memory_budget_bytes / 4
}

/// The bounds of `GET /v1/limits`. Counts are inclusive maxima (minimum 1 unless said otherwise).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ApiLimits {
    pub geometry: GeometryLimits,
    pub grid: GridLimits,
    pub algorithm: AlgorithmLimits,
    pub simulation: SimulationLimits,
    pub volume_job: VolumeJobLimits,
    pub uploads: UploadLimits,
    /// Memory a job may need at most (bytes); a larger one is refused with `job_too_large`.
    pub memory_budget_bytes: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GeometryLimits {
    /// Detector elements along one detector axis (`det_count`, `detector.count`, `nu`, `nv`).
    pub max_detector_elements: usize,
    /// Views (`angles.count`, or the length of `angles.degrees`).
    pub max_views: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GridLimits {
    /// Samples along one axis of an output grid (`nx`, `ny`, `nz`).
    pub max_side: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AlgorithmLimits {
    /// `iterations` of an iterative algorithm.
    pub max_iterations: usize,
    /// `tv_iterations` of TV.
    pub max_tv_iterations: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SimulationLimits {
    /// Ellipses or ellipsoids of a phantom.
    pub max_bodies: usize,
    /// `noise.incident_photons` (above 0).
    pub max_incident_photons: f64,
    /// Values of the projections (views × detector elements); more is `array_too_large` (413).
    pub max_values: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VolumeJobLimits {
    pub max_steps: usize,
    pub max_products: usize,
    /// `sigma_mm` of a Gaussian step (from 0).
    pub max_sigma_mm: f64,
    /// `frames` of a rotating projection.
    pub max_rotating_frames: usize,
    /// `frames` of a volume or surface rendering.
    pub max_render_frames: usize,
    /// Width and height of a rendering (`size`).
    pub max_render_side: usize,
    /// Width and height of a reformatted image.
    pub max_image_side: usize,
    /// Points of a curved reformat's polyline (from 2).
    pub max_curve_points: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct UploadLimits {
    /// Bytes of one uploaded file (`.npy`, DICOM file or ZIP).
    pub max_upload_bytes: u64,
    /// Bytes of a JSON request body.
    pub max_json_bytes: usize,
}

impl ApiLimits {
    /// The bounds under `settings`.
    pub fn of(settings: &Settings) -> Self {
        Self {
            geometry: GeometryLimits {
                max_detector_elements: MAX_AXIS,
                max_views: MAX_VIEWS,
            },
            grid: GridLimits { max_side: MAX_AXIS },
            algorithm: AlgorithmLimits {
                max_iterations: MAX_ITERATIONS,
                max_tv_iterations: MAX_TV_ITERATIONS,
            },
            simulation: SimulationLimits {
                max_bodies: MAX_BODIES,
                max_incident_photons: MAX_INCIDENT_PHOTONS,
                max_values: max_array_values(settings),
            },
            volume_job: VolumeJobLimits {
                max_steps: MAX_ITEMS,
                max_products: MAX_ITEMS,
                max_sigma_mm: MAX_SIGMA_MM,
                max_rotating_frames: MAX_ROTATING_FRAMES,
                max_render_frames: MAX_RENDER_FRAMES,
                max_render_side: settings.render_max_side,
                max_image_side: MAX_SIDE,
                max_curve_points: MAX_CURVE_POINTS,
            },
            uploads: UploadLimits {
                max_upload_bytes: settings.max_upload_bytes,
                max_json_bytes: settings.max_json_bytes,
            },
            memory_budget_bytes: settings.memory_budget_bytes,
        }
    }
}
