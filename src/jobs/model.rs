//! The job and dataset model: statuses and their transitions, the typed job and simulation requests,
//! stored records and results.
//!
//! Job states: `queued → running → succeeded | failed | canceled`, plus `queued → canceled`. `running →
//! queued` happens two ways: a graceful hand-back (the server stops and the job stops with it), which spends
//! no attempt, and recovery after a crash, which keeps the attempt the claim counted (and fails the job with
//! `attempts_exhausted` once `max_attempts` starts were spent). Terminal states never change. Every
//! transition is one guarded update in [`super::repo::Db`].

use serde::{Deserialize, Serialize};

use crate::error_code::Problem;
use crate::mesh::MeshStats;
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid};
use crate::recon::geometry::Geometry;
use crate::recon::geometry::vectors::cross3;
use crate::recon::grid::VolumeGrid;
use crate::recon::phantom::PhantomSpec;
use crate::storage::{DatasetId, JobId, SeriesId, UploadId};
use crate::volume::{Frame, ImagePlane, ScreenSides};

use super::volume_spec::VolumeJobRequest;

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    Failed,
    Canceled,
}

impl JobStatus {
    pub const ALL: [JobStatus; 5] = [
        JobStatus::Queued,
        JobStatus::Running,
        JobStatus::Succeeded,
        JobStatus::Failed,
        JobStatus::Canceled,
    ];
    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Canceled => "canceled",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|x| x.as_str() == s)
    }
    /// Succeeded, failed and canceled jobs never change again.
    pub fn is_terminal(self) -> bool {
        matches!(
            self,
            JobStatus::Succeeded | JobStatus::Failed | JobStatus::Canceled
        )
    }
}

/// What a job produces besides the volume (which every reconstruction writes).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OutputKind {
    /// The reconstructed volume (`.npy`); slices, projections and meshes derive from it.
    Volume,
    /// RMSE, PSNR and SSIM against the phantom (simulated inputs only).
    Metrics,
}

fn default_outputs() -> Vec<OutputKind> {
    vec![OutputKind::Volume]
}

/// `POST /v1/jobs`: reconstruct dataset `input` with `algorithm` on `grid`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobRequest {
    pub input: DatasetId,
    pub algorithm: AlgorithmSpec,
    /// `{nx, ny, dx_mm, dy_mm}` for 2D geometries, `{nx, ny, nz, spacing_mm}` for cone beams.
    pub grid: OutputGrid,
    #[serde(default = "default_outputs")]
    pub outputs: Vec<OutputKind>,
    /// Row order of the reconstructed images.
    #[serde(default, skip_serializing_if = "ImageConvention::is_ctrecon")]
    pub image_convention: ImageConvention,
}

/// Row order of reconstructed images (volumes without a patient).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageConvention {
    /// ctrecon's `[y][x]`: row 0 at the smallest y, y growing down the image.
    #[default]
    Ctrecon,
    /// ASTRA's and scikit-image's: row 0 at the largest y (y up on screen).
    Astra,
}

impl ImageConvention {
    fn is_ctrecon(&self) -> bool {
        *self == ImageConvention::Ctrecon
    }
}

impl JobRequest {
    pub fn wants_metrics(&self) -> bool {
        self.outputs.contains(&OutputKind::Metrics)
    }
}

/// Kind of a job that reconstructs a projection dataset.
pub const KIND_RECONSTRUCTION: &str = "reconstruction";
/// Kind of a job that processes a volume (a CT series or a reconstruction) in the image domain.
pub const KIND_VOLUME: &str = "volume";

/// What a job does: reconstruct projections, or process a volume. Stored as the request JSON; which one it
/// is follows from the job's `kind`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum JobSpec {
    Volume(VolumeJobRequest),
    Reconstruction(JobRequest),
}

impl JobSpec {
    pub fn kind(&self) -> &'static str {
        match self {
            JobSpec::Reconstruction(_) => KIND_RECONSTRUCTION,
            JobSpec::Volume(_) => KIND_VOLUME,
        }
    }
    /// The id of the input (a dataset, a series or a job).
    pub fn input_id(&self) -> String {
        match self {
            JobSpec::Reconstruction(r) => r.input.to_string(),
            JobSpec::Volume(v) => v.input.to_string(),
        }
    }
}

/// A stored job.
#[derive(Debug, Clone, PartialEq)]
pub struct Job {
    pub id: JobId,
    pub kind: String,
    pub status: JobStatus,
    /// 0–100.
    pub progress: u8,
    pub stage: String,
    pub request: JobSpec,
    pub estimate_bytes: u64,
    pub attempts: u32,
    pub cancel_requested: bool,
    pub error: Option<Problem>,
    pub result: Option<JobResult>,
    pub created_us: i64,
    pub started_us: Option<i64>,
    pub finished_us: Option<i64>,
}

/// What a job list shows of a job: its state and timestamps, and what its result links need.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobSummary {
    pub id: JobId,
    pub kind: String,
    pub status: JobStatus,
    /// 0–100.
    pub progress: u8,
    pub stage: String,
    pub created_us: i64,
    pub started_us: Option<i64>,
    pub finished_us: Option<i64>,
    /// The result holds quality metrics.
    pub has_metrics: bool,
    /// Indexes of the result's products, in order.
    pub product_indexes: Vec<usize>,
}

impl JobSummary {
    /// The summary of a whole job.
    pub fn of(job: &Job) -> Self {
        Self {
            id: job.id,
            kind: job.kind.clone(),
            status: job.status,
            progress: job.progress,
            stage: job.stage.clone(),
            created_us: job.created_us,
            started_us: job.started_us,
            finished_us: job.finished_us,
            has_metrics: job.result.as_ref().is_some_and(|r| r.metrics.is_some()),
            product_indexes: job
                .result
                .iter()
                .flat_map(|r| r.products.iter().map(|p| p.index))
                .collect(),
        }
    }
}

/// A file written by a job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileInfo {
    pub bytes: u64,
    pub sha256: String,
}

/// Image quality against the phantom, on the output grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quality {
    pub rmse: f64,
    /// dB, data range = the truth's max − min; `None` (JSON null) when the images are identical.
    pub psnr_db: Option<f64>,
    pub ssim: f64,
    /// Supersampling of the rasterised truth (per axis).
    pub truth_supersample: usize,
}

/// Units of a result volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VolumeUnits {
    /// Linear attenuation μ in 1/mm (reconstructions; phantom units for simulations).
    #[default]
    MuPerMm,
    /// Hounsfield units (CT series and what is derived from them).
    Hu,
}

/// Something a job or an assembly wants the user to know that did not stop it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Notice {
    pub code: String,
    pub message: String,
}

impl From<&crate::series::Warning> for Notice {
    fn from(w: &crate::series::Warning) -> Self {
        Self {
            code: w.code.to_string(),
            message: w.message.clone(),
        }
    }
}

/// What a succeeded job wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobResult {
    /// `[nz, ny, nx]`; 2D reconstructions have nz = 1.
    pub shape: [usize; 3],
    /// The reconstruction grid (2D: one slice of thickness `dx_mm`); for volume jobs the sample counts,
    /// spacing and centre of `frame`.
    pub grid: VolumeGrid,
    pub volume: FileInfo,
    pub min: f32,
    pub max: f32,
    pub mean: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metrics: Option<Quality>,
    #[serde(default)]
    pub units: VolumeUnits,
    /// Placement in patient space (LPS, mm) when it is not the axis-aligned frame of `grid` (series).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<Frame>,
    /// The CT series the volume derives from (its study and patient are kept in DICOM results).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_series: Option<SeriesId>,
    /// Images and meshes a volume job made, in request order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub products: Vec<ProductResult>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<Notice>,
}

impl JobResult {
    /// The volume's placement in patient space.
    pub fn frame(&self) -> Frame {
        self.frame.unwrap_or_else(|| Frame::from_grid(&self.grid))
    }
}

/// One product of a volume job: an image stack (`[frames, rows, columns]`, volume units) or a mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProductResult {
    pub index: usize,
    /// The product's `type` in the request (`projection`, `mpr`, `curved`, `rotating`, `mesh`,
    /// `volume_render`, `surface_render`).
    #[serde(rename = "type")]
    pub kind: String,
    /// Image stacks: `[frames, rows, columns]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape: Option<[usize; 3]>,
    /// Image stacks: pixel size (mm) along rows and columns.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<MeshStats>,
    /// Image stacks: the patient directions at the screen sides of the first frame (`R`/`L`, `A`/`P`,
    /// `S`/`I`; the volume axes `±x`, `±y`, `±z` for a reconstruction without a patient).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orientation: Option<ScreenSides>,
    /// Planar image stacks: where the first frame lies in patient space (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<ImagePlane>,
    /// Planar stacks of several frames: the step (mm) from one frame to the next along the normal
    /// `row_direction × column_direction`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_spacing_mm: Option<f64>,
    /// Rotating projections and renderings of several frames (a sequence turning about the superior or the
    /// camera's up axis): the screen sides of every frame, the first being `orientation`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frame_orientations: Vec<ScreenSides>,
    /// Renderings: what the picture shows (preset or surfaces, camera), as written to DICOM
    /// DerivationDescription.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    pub file: FileInfo,
}

impl ProductResult {
    pub fn is_mesh(&self) -> bool {
        self.mesh.is_some()
    }

    /// The screen sides of frame `k`: the frames of a rotating projection are seen from 360° k / frames about
    /// the superior axis ([`crate::volume::rotating_axes`]) and those of a turning rendering are listed in
    /// `frame_orientations`, so each has its own; every other stack keeps the sides of its first frame.
    /// `patient` as for [`ImagePlane::sides_for`].
    pub fn frame_sides(&self, k: usize, patient: bool) -> Option<ScreenSides> {
        if let Some(sides) = self.frame_orientations.get(k) {
            return Some(sides.clone());
        }
        let frames = self.shape.map_or(1, |s| s[0]).max(1);
        if self.kind != "rotating" || self.orientation.is_none() {
            return self.orientation.clone();
        }
        let (_, right) = crate::volume::rotating_axes(360.0 * k as f64 / frames as f64);
        Some(
            ImagePlane {
                first_pixel_mm: [0.0; 3],
                row_direction: right,
                column_direction: [0.0, 0.0, -1.0],
                pixel_mm: [1.0; 2],
            }
            .sides_for(patient),
        )
    }

    /// The screen sides every frame shares: the first frame's, unless a frame has others.
    pub fn shared_sides(&self, patient: bool) -> Option<ScreenSides> {
        let frames = self.shape.map_or(1, |s| s[0]).max(1);
        let first = self.frame_sides(0, patient)?;
        (1..frames)
            .all(|k| self.frame_sides(k, patient).as_ref() == Some(&first))
            .then_some(first)
    }

    /// Where frame `k` of a planar stack lies.
    pub fn frame_plane(&self, k: usize) -> Option<ImagePlane> {
        let p = self.plane?;
        let step = self.frame_spacing_mm.unwrap_or(0.0) * k as f64;
        let n = cross3(p.row_direction, p.column_direction);
        Some(ImagePlane {
            first_pixel_mm: std::array::from_fn(|c| p.first_pixel_mm[c] + step * n[c]),
            ..p
        })
    }
}

/// An assembled CT series: where its HU volume sits in patient space, what the upload said about it, and the
/// identity kept in derived DICOM results.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SeriesRecord {
    pub id: SeriesId,
    pub upload_id: UploadId,
    pub series_uid: String,
    pub study_uid: Option<String>,
    pub frame_of_reference_uid: Option<String>,
    pub modality: Option<String>,
    pub description: Option<String>,
    pub patient_name: Option<String>,
    pub patient_id: Option<String>,
    pub instances: usize,
    /// `[nz, ny, nx]`.
    pub shape: [usize; 3],
    pub frame: Frame,
    pub tilt_deg: f64,
    pub normal_spacing_mm: f64,
    pub hu_min: f32,
    pub hu_max: f32,
    pub volume: FileInfo,
    pub transfer_syntaxes: Vec<String>,
    pub warnings: Vec<Notice>,
    #[serde(skip)]
    pub created_us: i64,
}

/// A DICOM upload.
#[derive(Debug, Clone, PartialEq)]
pub struct UploadRecord {
    pub id: UploadId,
    pub open: bool,
    pub instances: u32,
    pub bytes: u64,
    /// The completion's JSON (series made and files refused) once completed.
    pub outcome: Option<serde_json::Value>,
    pub created_us: i64,
}

/// Where a dataset came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DatasetKind {
    Upload,
    Simulation,
}

impl DatasetKind {
    pub fn as_str(self) -> &'static str {
        match self {
            DatasetKind::Upload => "upload",
            DatasetKind::Simulation => "simulation",
        }
    }
}

/// Poisson noise of a simulation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSpec {
    /// Incident photons per detector element (I0).
    pub incident_photons: f64,
    #[serde(default)]
    pub seed: u64,
}

/// `POST /v1/simulations`: the exact projections of a phantom for a geometry, optionally noisy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulationRequest {
    pub phantom: PhantomSpec,
    pub geometry: Geometry,
    #[serde(default)]
    pub noise: Option<NoiseSpec>,
}

/// A stored projection dataset.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Dataset {
    pub id: DatasetId,
    pub kind: DatasetKind,
    pub geometry: Geometry,
    pub shape: Vec<usize>,
    pub dtype: String,
    pub bytes: u64,
    pub sha256: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phantom: Option<PhantomSpec>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub noise: Option<NoiseSpec>,
    #[serde(skip)]
    pub created_us: i64,
}

/// Microseconds since the Unix epoch, now.
pub fn now_us() -> i64 {
    (time::OffsetDateTime::now_utc().unix_timestamp_nanos() / 1000) as i64
}

/// RFC 3339 text of a microsecond timestamp.
pub fn rfc3339(us: i64) -> String {
    time::OffsetDateTime::from_unix_timestamp_nanos(us as i128 * 1000)
        .ok()
        .and_then(|t| {
            t.format(&time::format_description::well_known::Rfc3339)
                .ok()
        })
        .unwrap_or_default()
}

/// Microseconds since the epoch of RFC 3339 text.
pub fn parse_rfc3339(s: &str) -> Option<i64> {
    time::OffsetDateTime::parse(s, &time::format_description::well_known::Rfc3339)
        .ok()
        .map(|t| (t.unix_timestamp_nanos() / 1000) as i64)
}

/// Value given to samples outside the input volume: air for HU, nothing for μ.
pub fn fill_value(units: VolumeUnits) -> f32 {
    match units {
        VolumeUnits::Hu => crate::series::PADDING_HU,
        VolumeUnits::MuPerMm => 0.0,
    }
}

/// An Idempotency-Key record to insert with a new resource.
#[derive(Debug, Clone)]
pub struct IdempotencyKey {
    pub route: &'static str,
    pub key: String,
    pub fingerprint: String,
}

/// Outcome of an insert guarded by an Idempotency-Key.
#[derive(Debug, Clone, PartialEq)]
pub enum Inserted {
    New,
    /// The key was already used: the earlier resource id and request fingerprint.
    Existing {
        resource_id: String,
        fingerprint: String,
    },
}

/// Filters of `GET /v1/jobs`.
#[derive(Debug, Clone, Default)]
pub struct JobFilter {
    pub statuses: Vec<JobStatus>,
    pub kind: Option<String>,
    pub created_after_us: Option<i64>,
    pub created_before_us: Option<i64>,
    /// Return jobs older than this one (ids are time-ordered).
    pub before_id: Option<JobId>,
    pub limit: u32,
}

impl Job {
    /// A new job, `queued`, created at `created_us`.
    pub fn queued(request: JobSpec, estimate_bytes: u64, created_us: i64) -> Self {
        Job {
            id: JobId::generate(),
            kind: request.kind().into(),
            status: JobStatus::Queued,
            progress: 0,
            stage: "queued".into(),
            request,
            estimate_bytes,
            attempts: 0,
            cancel_requested: false,
            error: None,
            result: None,
            created_us,
            started_us: None,
            finished_us: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_job_request_takes_typed_specs_and_refuses_unknown_fields() {
        let ok = r#"{"input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
                     "algorithm": {"name": "fbp", "filter": "hann"},
                     "grid": {"nx": 64, "ny": 64, "dx_mm": 1, "dy_mm": 1}}"#;
        let r: JobRequest = serde_json::from_str(ok).unwrap();
        assert_eq!(r.outputs, [OutputKind::Volume]);
        assert!(matches!(r.grid, OutputGrid::Image(_)));
        let extra = ok.replace("\"grid\"", "\"colour\": 1, \"grid\"");
        assert!(serde_json::from_str::<JobRequest>(&extra).is_err());
        let bad_param = ok.replace("\"hann\"", "\"hann\", \"iterations\": 3");
        assert!(serde_json::from_str::<JobRequest>(&bad_param).is_err());
    }

    #[test]
    fn timestamps_round_trip_through_rfc3339() {
        let t = 1_795_000_000_123_456;
        assert_eq!(parse_rfc3339(&rfc3339(t)), Some(t));
        assert!(rfc3339(t).ends_with('Z'));
    }
}
