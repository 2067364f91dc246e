//! The job and dataset model: statuses and their transitions, the typed job and simulation requests,
//! stored records and results.
//!
//! Job states: `queued → running → succeeded | failed | canceled`, plus `queued → canceled`. `running →
//! queued` happens two ways: a graceful hand-back (the server stops and the job stops with it), which spends
//! no attempt, and recovery after a crash, which keeps the attempt the claim counted (and fails the job with
//! `attempts_exhausted` once `max_attempts` starts were spent). Terminal states never change. Every
//! transition is one guarded update in [`super::database::Database`].

use serde::{Deserialize, Serialize};

use crate::error_code::Problem;
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid};
use crate::storage::{DatasetId, JobId};

mod instances;
mod records;
mod render_request;
mod result;
mod volume_request;

pub use instances::*;
pub use records::*;
pub use render_request::*;
pub use result::*;
pub use volume_request::*;

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
#[serde(
    untagged,
    expecting = "a job: a reconstruction {\"input\": <dataset id>, \"algorithm\", \"grid\"} or a volume job \
                 {\"kind\": \"volume\", \"input\": <series or job id>, \"steps\", \"products\"}"
)]
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
mod tests;
