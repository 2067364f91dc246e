//! DICOM ingestion, run on the worker pool in two steps. [`prepare`] unpacks the uploaded files (ZIP members
//! inflated one by one to a scratch directory, with limits), reads what each file's header declares
//! (`dicom::declared`: rows × columns × frames × samples, before anything is decoded) and groups the files by
//! the series their headers name, so that the caller knows what each series will hold in memory — and can
//! refuse or reserve it — before a byte of pixels is decoded. [`ingest_series`] then decodes one such
//! series, assembles it into an HU volume and stages it as a synced temporary file (written through a
//! buffer, never a second copy of the volume in memory).
//!
//! One series that cannot be assembled (a missing slice, a non-CT modality, …) does not stop the others: each
//! is reported as `ready` (with its new series id) or `refused` (with a problem), and every file or ZIP member
//! that could not be read is listed with its reason. Nothing is staged for refused series. The caller records
//! the series rows and then [`Staged::commit`]s the volumes to `series/<id>.npy` (temporary file → row →
//! rename), so a crash never leaves a volume without its row.

use serde::Serialize;

use super::model::{FileInfo, Notice, SeriesRecord, now_us};
use std::collections::BTreeMap;

use rayon::prelude::*;

use crate::dicom::{
    Declared, DicomError, ReadLimits, Rejected, SeriesReport, Unpacked, UploadFile, ZipLimits,
    declared, read_upload_files, unpack_file,
};
use crate::error_code::{ErrorCode, Problem};
use crate::recon::control::Control;
use crate::series::{AssemblyOptions, SeriesError, UnevenPolicy};
use crate::storage::npy::write_f32;
use crate::storage::{BlobStore, ScratchDir, SeriesId, TempBlob, UploadId};

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
    /// Add what another part of the same upload came to.
    pub fn append(&mut self, other: Ingested) {
        self.series.extend(other.series);
        self.rejected.extend(other.rejected);
    }

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
    /// Add the volumes `other` staged.
    pub fn append(&mut self, other: Staged) {
        self.0.extend(other.0);
    }

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

/// The files of one series, as their headers declare them (nothing decoded yet).
#[derive(Debug)]
pub struct DeclaredSeries {
    /// Series Instance UID the headers name (empty when they name none).
    pub series_uid: String,
    files: Vec<(UploadFile, Declared)>,
}

impl DeclaredSeries {
    pub fn instances(&self) -> usize {
        self.files.len()
    }

    /// Samples of every frame of every file.
    pub fn samples(&self) -> u64 {
        self.files.iter().map(|(_, d)| d.samples).sum()
    }

    /// The most bytes decoding the series on `threads` threads and assembling it hold at once: the stored
    /// values of every file (`f32` per sample), plus the larger of the buffers of the `threads` largest
    /// files being decoded and the `f32` volume assembled from the stored values. Written to disk through a
    /// buffer, the volume takes no second copy.
    pub fn memory_bytes(&self, threads: usize) -> u64 {
        let kept: u64 = self.files.iter().map(|(_, d)| d.kept_bytes()).sum();
        let mut decoding: Vec<u64> = self.files.iter().map(|(_, d)| d.decoding_bytes()).collect();
        decoding.sort_unstable_by(|a, b| b.cmp(a));
        let decoding: u64 = decoding.iter().take(threads.max(1)).sum();
        kept.saturating_add(decoding.max(kept))
    }

    /// The refusal of a series that could never be assembled within `max_voxels` or the memory `budget`
    /// (on `threads` decoding threads), as its outcome: decided from the headers alone.
    pub fn refusal(&self, max_voxels: usize, budget: u64, threads: usize) -> Option<SeriesOutcome> {
        let samples = self.samples();
        let source = if samples > max_voxels as u64 {
            SeriesError::TooLarge {
                voxels: usize::try_from(samples).unwrap_or(usize::MAX),
                limit: max_voxels,
            }
        } else {
            let bytes = self.memory_bytes(threads);
            if bytes <= budget {
                return None;
            }
            SeriesError::OverBudget {
                samples,
                bytes,
                budget,
            }
        };
        let error = DicomError::Series {
            series_uid: self.series_uid.clone(),
            source,
        };
        Some(SeriesOutcome {
            status: "refused",
            report: SeriesReport {
                series_uid: self.series_uid.clone(),
                instances: self.files.len(),
                size_bytes: self
                    .files
                    .iter()
                    .map(|(_, d)| usize::try_from(d.file_bytes).unwrap_or(usize::MAX))
                    .fold(0, usize::saturating_add),
                ..SeriesReport::default()
            },
            series: None,
            error: Some(dicom_problem(&error)),
        })
    }
}

/// An upload unpacked and read as far as its headers.
pub struct Prepared {
    /// Holds the inflated ZIP members until the series are ingested.
    _scratch: ScratchDir,
    pub series: Vec<DeclaredSeries>,
    /// Files refused while unpacking or reading their headers.
    pub rejected: Vec<RejectedFile>,
}

fn rejected_file(r: &Rejected) -> RejectedFile {
    let p = dicom_problem(&r.error);
    RejectedFile {
        file: r.label.clone(),
        code: p.code.code().into(),
        detail: p.public_detail().into(),
        error_code: p.code,
    }
}

/// Unpack `files` (on disk; read, never moved or removed) and read what each declares, in parallel; group
/// them by the series their headers name.
pub fn prepare(
    store: &BlobStore,
    files: Vec<UploadFile>,
    opts: &IngestOptions,
    ctl: Control<'_>,
) -> Result<Prepared, Problem> {
    let scratch = store.scratch().map_err(storage_problem)?;
    let mut unpacked = Unpacked::default();
    for file in files {
        unpack_file(file, &opts.zip, scratch.path(), &mut unpacked)
            .map_err(|e| dicom_problem(&e))?;
    }
    let read: Vec<Result<Declared, DicomError>> = unpacked
        .files
        .par_iter()
        .map(|f| declared(&f.path, &f.label, &opts.read))
        .collect();
    if ctl.cancel.is_canceled() {
        return Err(Problem::internal());
    }
    let mut rejected = unpacked.rejected;
    let mut by_uid: BTreeMap<String, DeclaredSeries> = BTreeMap::new();
    for (file, r) in unpacked.files.into_iter().zip(read) {
        match r {
            Ok(d) => {
                let uid = d.series_uid.clone().unwrap_or_default();
                by_uid
                    .entry(uid.clone())
                    .or_insert_with(|| DeclaredSeries {
                        series_uid: uid,
                        files: Vec::new(),
                    })
                    .files
                    .push((file, d));
            }
            Err(e) if !e.is_client_error() => return Err(dicom_problem(&e)),
            Err(error) => rejected.push(Rejected {
                label: file.label,
                error,
            }),
        }
    }
    Ok(Prepared {
        _scratch: scratch,
        series: by_uid.into_values().collect(),
        rejected: rejected.iter().map(rejected_file).collect(),
    })
}

/// Decode, assemble and stage one declared series (normally one series; files whose decoded headers differ
/// from what was declared are grouped as they decode).
pub fn ingest_series(
    store: &BlobStore,
    upload_id: UploadId,
    declared: &DeclaredSeries,
    opts: &IngestOptions,
    ctl: Control<'_>,
) -> Result<(Ingested, Staged), Problem> {
    let files: Vec<UploadFile> = declared.files.iter().map(|(f, _)| f.clone()).collect();
    let upload =
        read_upload_files(&files, Vec::new(), &opts.read, ctl).map_err(|e| dicom_problem(&e))?;
    let rejected = upload.rejected.iter().map(rejected_file).collect();
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
        let id = SeriesId::generate();
        let (temp, (bytes, sha256)) = store
            .write_temp_with(|w| write_f32(vol.data.view(), w))
            .map_err(storage_problem)?;
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
            volume: FileInfo { bytes, sha256 },
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
