//! The stored inputs of jobs: series, uploads and datasets (with the simulation request that makes one), and
//! the timestamps they carry.

use serde::{Deserialize, Serialize};

use super::result::{FileInfo, Notice};
use crate::recon::geometry::Geometry;
use crate::recon::phantom::PhantomSpec;
use crate::storage::{DatasetId, SeriesId, UploadId};
use crate::volume::Frame;

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
    /// Imported from a scanner's files (`POST /v1/scans`).
    Scan,
}

impl DatasetKind {
    pub fn as_str(self) -> &'static str {
        match self {
            DatasetKind::Upload => "upload",
            DatasetKind::Simulation => "simulation",
            DatasetKind::Scan => "scan",
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
    /// An imported scan: where its values came from and what was done to its views.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan: Option<ScanRecord>,
    #[serde(skip)]
    pub created_us: i64,
}

/// What an imported scan's dataset records of its origin.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanRecord {
    /// `nikon_xtek`, `bruker_skyscan` or `tiff_stack`.
    pub format: String,
    /// Every value taken from the scanner's files, with the file and key it came from.
    pub provenance: Vec<ScanValue>,
    /// Values read but not applied.
    pub notes: Vec<String>,
    /// The steps applied to the views, in order, each with its parameters (`{"step": "minus_log", …}`).
    pub preprocessing: Vec<serde_json::Value>,
    /// The centre of rotation in the dataset's geometry: found from the views, read from the files or
    /// pinned by the client.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration: Option<crate::scans::calibrate::Calibration>,
}

/// One value read from a scanner's file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanValue {
    pub key: String,
    pub value: String,
    /// `file [section] key`.
    pub origin: String,
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
