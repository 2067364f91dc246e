//! DICOM ingestion, run on the worker pool: unpack the uploaded files (ZIP members inflated one by one to a
//! scratch directory, with limits), decode them, split them by SeriesInstanceUID, assemble each series into an
//! HU volume and stage it as a synced temporary file.
//!
//! One series that cannot be assembled (a missing slice, a non-CT modality, …) does not stop the others: each
//! is reported as `ready` (with its new series id) or `refused` (with a problem), and every file or ZIP member
//! that could not be read is listed with its reason. Nothing is staged for refused series. The caller records
//! the series rows and then [`Staged::commit`]s the volumes to `series/<id>.npy` (temporary file → row →
//! rename), so a crash never leaves a volume without its row.

use serde::Serialize;
use sha2::{Digest, Sha256};

use super::model::{FileInfo, Notice, SeriesRecord, now_us};
use crate::dicom::{
    DicomError, ReadLimits, SeriesReport, Unpacked, UploadFile, ZipLimits, read_upload_files,
    unpack_file,
};
use crate::error_code::{ErrorCode, Problem};
use crate::recon::control::Control;
use crate::series::{AssemblyOptions, UnevenPolicy};
use crate::storage::npy::{encode_f32, hex};
use crate::storage::{BlobStore, SeriesId, TempBlob, UploadId};

/// The catalogue problem of a DICOM error (server-side failures become `internal`).
pub fn dicom_problem(e: &DicomError) -> Problem {
    if !e.is_client_error() {
        tracing::error!(error = %e, "DICOM processing failed");
        return Problem::internal();
    }
    Problem::new(ErrorCode::from(e), e.to_string())
}

/// How an upload is turned into series.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IngestOptions {
    pub uneven: UnevenPolicy,
    pub read: ReadLimits,
    pub zip: ZipLimits,
    /// Largest assembled volume (voxels).
    pub max_voxels: usize,
}

/// A file that was not read, and why.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RejectedFile {
    /// The name the client gave (file or ZIP entry name).
    pub file: String,
    pub code: String,
    pub detail: String,
    /// The catalogue code `code` spells.
    #[serde(skip)]
    pub error_code: ErrorCode,
}

/// What became of one series of an upload.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeriesOutcome {
    /// `ready` or `refused`.
    pub status: &'static str,
    pub report: SeriesReport,
    /// The stored series when ready.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub series: Option<SeriesRecord>,
    /// Why it was refused.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<Problem>,
}

/// The outcome of an upload.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ingested {
    pub series: Vec<SeriesOutcome>,
    pub rejected: Vec<RejectedFile>,
}

impl Ingested {
    /// Files read or refused.
    pub fn files(&self) -> usize {
        self.series
            .iter()
            .map(|s| s.report.instances)
            .sum::<usize>()
            + self.rejected.len()
    }

    pub fn ready(&self) -> impl Iterator<Item = &SeriesRecord> {
        self.series.iter().filter_map(|s| s.series.as_ref())
    }

    /// The problem to answer when no series could be stored: the first refusal, else the first unreadable
    /// file, else "no images"; the detail lists up to five reasons.
    pub fn failure(&self) -> Problem {
        let mut reasons: Vec<(ErrorCode, String)> = self
            .series
            .iter()
            .filter_map(|s| s.error.as_ref())
            .map(|p| (p.code, p.detail.clone()))
            .collect();
        reasons.extend(
            self.rejected
                .iter()
                .map(|r| (r.error_code, r.detail.clone())),
        );
        let Some((code, _)) = reasons.first().cloned() else {
            return Problem::new(
                ErrorCode::DicomNoImages,
                "the upload contains no DICOM image",
            );
        };
        let more = reasons.len().saturating_sub(5);
        let mut detail = reasons
            .iter()
            .take(5)
            .map(|(_, d)| d.as_str())
            .collect::<Vec<_>>()
            .join("; ");
        if more > 0 {
            detail.push_str(&format!("; and {more} more"));
        }
        Problem::new(code, detail)
    }
}

/// The volumes of the ready series, synced in `tmp/` and not yet in place.
#[derive(Debug, Default)]
pub struct Staged(Vec<(SeriesId, TempBlob)>);

impl Staged {
    /// Move every volume to `series/<id>.npy`; call once the series rows are committed.
    pub async fn commit(self, store: &BlobStore) -> std::io::Result<()> {
        for (id, temp) in self.0 {
            store.commit_async(temp, store.series_path(id)).await?;
        }
        Ok(())
    }

    /// Take the staged volume of series `id` out (a series found stored already): it is not committed.
    pub fn take(&mut self, id: SeriesId) -> Option<TempBlob> {
        let at = self.0.iter().position(|(s, _)| *s == id)?;
        Some(self.0.remove(at).1)
    }

    /// Remove the staged volumes (the rows were not recorded).
    pub async fn discard(self) {
        for (_, temp) in self.0 {
            temp.discard().await;
        }
    }
}

fn storage_problem(e: std::io::Error) -> Problem {
    tracing::error!(error = %e, "DICOM ingestion storage failed");
    Problem::internal()
}

/// Unpack, decode, split and assemble `files` (on disk; they are read, never moved or removed); stage every
/// assembled series.
pub fn ingest(
    store: &BlobStore,
    upload_id: UploadId,
    files: Vec<UploadFile>,
    opts: &IngestOptions,
    ctl: Control<'_>,
) -> Result<(Ingested, Staged), Problem> {
    let scratch = store.scratch().map_err(storage_problem)?;
    let mut unpacked = Unpacked::default();
    for file in files {
        unpack_file(file, &opts.zip, scratch.path(), &mut unpacked)
            .map_err(|e| dicom_problem(&e))?;
    }
    let upload = read_upload_files(&unpacked.files, unpacked.rejected, &opts.read, ctl)
        .map_err(|e| dicom_problem(&e))?;
    drop(scratch);
    let rejected = upload
        .rejected
        .iter()
        .map(|r| {
            let p = dicom_problem(&r.error);
            RejectedFile {
                file: r.label.clone(),
                code: p.code.code().into(),
                detail: p.public_detail().into(),
                error_code: p.code,
            }
        })
        .collect();
    let assembly = AssemblyOptions {
        uneven: opts.uneven,
        max_voxels: opts.max_voxels,
        ..AssemblyOptions::default()
    };
    let mut series = Vec::new();
    let mut staged = Staged::default();
    for group in upload.series {
        let report = group.report();
        let first = group.instances.first();
        let identity = (
            first.and_then(|i| i.frame_of_reference_uid.clone()),
            first.and_then(|i| i.patient_name.clone()),
            first.and_then(|i| i.patient_id.clone()),
        );
        let (study_uid, modality) = (group.study_uid.clone(), group.modality.clone());
        let instances = group.instances.len();
        let assembled = match group.assemble(&assembly, true, ctl) {
            Ok(a) => a,
            Err(DicomError::Canceled) => return Err(Problem::internal()),
            Err(e) => {
                series.push(SeriesOutcome {
                    status: "refused",
                    report,
                    series: None,
                    error: Some(dicom_problem(&e)),
                });
                continue;
            }
        };
        let vol = &assembled.volume;
        let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for &v in vol.data.iter() {
            lo = lo.min(v);
            hi = hi.max(v);
        }
        let encoded = encode_f32(vol.data.view());
        let id = SeriesId::generate();
        let temp = store.write_temp(&encoded).map_err(storage_problem)?;
        staged.0.push((id, temp));
        let (nz, ny, nx) = vol.data.dim();
        let record = SeriesRecord {
            id,
            upload_id,
            series_uid: report.series_uid.clone(),
            study_uid,
            frame_of_reference_uid: identity.0,
            modality,
            description: report.description.clone(),
            patient_name: identity.1,
            patient_id: identity.2,
            instances,
            shape: [nz, ny, nx],
            frame: vol.frame,
            tilt_deg: assembled.tilt_deg,
            normal_spacing_mm: assembled.normal_spacing_mm,
            hu_min: if lo.is_finite() { lo } else { 0.0 },
            hu_max: if hi.is_finite() { hi } else { 0.0 },
            volume: FileInfo {
                bytes: encoded.len() as u64,
                sha256: hex(&Sha256::digest(&encoded)),
            },
            transfer_syntaxes: report.transfer_syntaxes.clone(),
            warnings: assembled.warnings.iter().map(Notice::from).collect(),
            created_us: now_us(),
        };
        tracing::info!(series_id = %id, series_uid = %record.series_uid, nz, ny, nx, "series assembled");
        series.push(SeriesOutcome {
            status: "ready",
            report,
            series: Some(record),
            error: None,
        });
    }
    Ok((Ingested { series, rejected }, staged))
}
