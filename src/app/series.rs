//! DICOM series commands: decode and assemble files on disk into series (on the worker pool), record a
//! whole set of received instances as one completed upload — what an HTTP upload and the DICOM node share —
//! and fetch or delete a stored series.

use std::sync::Arc;

use serde_json::{Value, json};

use super::error::refused;
use super::{App, AppError, AppResult};
use crate::dicom::{ReadLimits, UploadFile, ZipLimits};
use crate::error_code::ErrorCode;
use crate::jobs::SeriesRecord;
use crate::jobs::ingest::{IngestOptions, Ingested, Staged, ingest_series, prepare};
use crate::jobs::model::rfc3339;
use crate::jobs::store::Deleted;
use crate::recon::control::{Cancel, Control, NoProgress};
use crate::series::UnevenPolicy;
use crate::storage::sweep::BlobKind;
use crate::storage::{SeriesId, UploadId};
use crate::telemetry::names;

/// The JSON document of a stored series (also part of an upload's outcome).
pub fn series_json(r: &SeriesRecord) -> Value {
    let mut v = serde_json::to_value(r).unwrap_or_default();
    if let Some(m) = v.as_object_mut() {
        m.insert("created_at".into(), rfc3339(r.created_us).into());
        m.insert(
            "links".into(),
            json!({
                "self": format!("/v1/series/{}", r.id),
                "volume": format!("/v1/series/{}/volume.npy", r.id),
                "upload": format!("/v1/uploads/{}", r.upload_id),
            }),
        );
    }
    v
}

/// The outcome document of a completed upload: the upload, each series (with links when stored) and the
/// refused files.
pub fn outcome_json(id: UploadId, instances: u32, bytes: u64, ingested: &Ingested) -> Value {
    let series: Vec<Value> = ingested
        .series
        .iter()
        .map(|s| {
            let mut v = json!({ "status": s.status, "report": s.report });
            if let Some(r) = &s.series {
                v["series"] = series_json(r);
            }
            if let Some(e) = &s.error {
                v["error"] = json!(e);
            }
            v
        })
        .collect();
    json!({
        "upload": {"id": id, "status": "completed", "instances": instances, "bytes": bytes,
                   "links": {"self": format!("/v1/uploads/{id}")}},
        "series": series,
        "rejected": ingested.rejected,
    })
}

/// A stored series and whether its volume is still there (the start-up sweep marks a lost one).
#[derive(Debug, Clone)]
pub struct StoredSeries {
    pub record: SeriesRecord,
    pub available: bool,
}

fn series_not_found(id: SeriesId) -> AppError {
    refused(ErrorCode::SeriesNotFound, format!("no series {id}"))
}

/// A set of instances received whole (by the DICOM node) and what became of it.
#[derive(Debug)]
pub struct Received {
    pub upload_id: UploadId,
    pub ingested: Ingested,
}

impl App {
    /// How files become series under this application's limits.
    pub fn ingest_options(&self, uneven: Option<UnevenPolicy>) -> IngestOptions {
        let s = &self.settings;
        let budget = s.memory_budget_bytes;
        // Each worker holds one file's bytes while decoding it: a member is capped by its share of the budget.
        let share = budget / s.resolved_worker_threads().max(1) as u64;
        IngestOptions {
            uneven: uneven.unwrap_or_default(),
            read: ReadLimits::default(),
            zip: ZipLimits {
                max_total_bytes: s.zip_max_total_bytes,
                max_ratio: s.zip_max_ratio,
                max_member_bytes: s.zip_max_member_bytes.min(share),
                ..ZipLimits::default()
            },
            // Stored slices and the f32 volume both live in memory while assembling.
            max_voxels: usize::try_from(budget / 8).unwrap_or(usize::MAX),
        }
    }

    /// Decode and assemble `files` (on disk; read, never moved) on the pool, one series at a time; the
    /// volumes are staged, not yet in place.
    ///
    /// What a series holds in memory is known from its files' headers before anything is decoded
    /// ([`crate::jobs::ingest::DeclaredSeries::memory_bytes`]): a series that could never fit the memory budget is refused
    /// (`series_too_large`) unread, and every other one is decoded only once that much of the budget is
    /// reserved — whichever door the files came through (uploads, the DICOM node, STOW-RS), and however
    /// small they are on disk.
    pub async fn ingest_files(
        &self,
        id: UploadId,
        files: Vec<UploadFile>,
        uneven: Option<UnevenPolicy>,
    ) -> AppResult<(Ingested, Staged)> {
        let store = self.store.clone();
        let opts = self.ingest_options(uneven);
        let prepared = self
            .engine
            .compute(move || {
                let cancel = Cancel::new();
                prepare(&store, files, &opts, Control::new(&cancel, &NoProgress))
            })
            .await?;
        let budget = self.settings.memory_budget_bytes;
        let threads = self.settings.resolved_worker_threads();
        let mut ingested = Ingested {
            series: Vec::new(),
            rejected: prepared.rejected.clone(),
        };
        let mut staged = Staged::default();
        let prepared = Arc::new(prepared);
        for i in 0..prepared.series.len() {
            let series = &prepared.series[i];
            if let Some(refused) = series.refusal(opts.max_voxels, budget, threads) {
                tracing::warn!(series_uid = %series.series_uid, instances = series.instances(), "series refused from its headers");
                metrics::counter!(names::SERIES_INGESTED, "outcome" => "refused_unread")
                    .increment(1);
                ingested.series.push(refused);
                continue;
            }
            let _held = self
                .engine
                .reserve_memory(series.memory_bytes(threads))
                .await;
            let (store, prepared) = (self.store.clone(), prepared.clone());
            let done = self
                .engine
                .compute(move || {
                    let cancel = Cancel::new();
                    let ctl = Control::new(&cancel, &NoProgress);
                    ingest_series(&store, id, &prepared.series[i], &opts, ctl)
                })
                .await;
            match done {
                Ok((more, more_staged)) => {
                    for s in &more.series {
                        metrics::counter!(names::SERIES_INGESTED, "outcome" => s.status)
                            .increment(1);
                    }
                    ingested.append(more);
                    staged.append(more_staged);
                }
                Err(e) => {
                    staged.discard().await;
                    return Err(e.into());
                }
            }
        }
        Ok((ingested, staged))
    }

    /// Assemble a complete set of received instances and record it as one completed upload, its series
    /// stored like uploaded ones (rows first, then the volumes in place; a series stored already with the
    /// same content is answered as stored, [`App::recognise_series`]). An upload none of whose series
    /// could be assembled is recorded too, so `GET /v1/uploads/{id}` says why.
    pub async fn ingest_received(&self, files: Vec<UploadFile>, bytes: u64) -> AppResult<Received> {
        self.ingest_received_from(files, bytes, None).await
    }

    /// [`ingest_received`](Self::ingest_received) of instances sent by `calling_ae`, then the processing
    /// rules fire on the series stored.
    pub async fn ingest_received_from(
        &self,
        files: Vec<UploadFile>,
        bytes: u64,
        calling_ae: Option<&str>,
    ) -> AppResult<Received> {
        let received = self.record_received(files, bytes).await?;
        self.fire_rules(&received.ingested, calling_ae.filter(|a| !a.is_empty()))
            .await;
        Ok(received)
    }

    /// [`ingest_received`](Self::ingest_received) without processing rules: a series pulled from a PACS as
    /// a job's input is that job's, not an arrival that rules act on.
    pub async fn record_received(&self, files: Vec<UploadFile>, bytes: u64) -> AppResult<Received> {
        let id = UploadId::generate();
        let (mut ingested, mut staged) = self.ingest_files(id, files, None).await?;
        // A series stored already with the same content is answered as stored, not made again.
        let known = self.recognise_series(&mut ingested, &mut staged).await;
        let instances = ingested.files() as u32;
        let records: Vec<SeriesRecord> = ingested
            .ready()
            .filter(|s| !known.contains(&s.id))
            .cloned()
            .collect();
        let view = outcome_json(id, instances, bytes, &ingested);
        match self
            .db
            .insert_completed_upload(id, instances, bytes, &view, &records, None)
            .await
        {
            Ok(_) => staged.commit(&self.store).await?,
            Err(e) => {
                staged.discard().await;
                return Err(e.into());
            }
        }
        Ok(Received {
            upload_id: id,
            ingested,
        })
    }

    /// The series `id` and whether its volume is available.
    pub async fn get_series(&self, id: SeriesId) -> AppResult<StoredSeries> {
        let Some(record) = self.db.get_series(id).await? else {
            let detail = format!("no series {id}");
            return Err(self
                .not_found(ErrorCode::SeriesNotFound, detail, &id.to_string())
                .await);
        };
        let missing = self
            .db
            .blob_missing(BlobKind::Series, &record.id.to_string())
            .await?;
        Ok(StoredSeries {
            record,
            available: !missing,
        })
    }

    /// The series `id` whose volume is to be read: refused (`file_missing`) when the start-up sweep found the
    /// volume missing.
    pub async fn series_with_volume(&self, id: SeriesId) -> AppResult<SeriesRecord> {
        let record = self
            .db
            .get_series(id)
            .await?
            .ok_or_else(|| series_not_found(id))?;
        if self
            .db
            .blob_missing(BlobKind::Series, &record.id.to_string())
            .await?
        {
            return Err(refused(
                ErrorCode::FileMissing,
                format!(
                    "the volume of series {} was lost; upload the series again",
                    record.id
                ),
            ));
        }
        Ok(record)
    }

    /// Delete the series `id`: the row, then its volume and the folder of its indexed instances; refused
    /// while a queued or running job reads it.
    pub async fn delete_series(&self, id: SeriesId) -> AppResult<()> {
        match self.db.delete_series(id).await? {
            Deleted::Done => {
                // A crash before this removal leaves an orphan file, which the start-up sweep removes.
                if let Err(e) = self
                    .store
                    .remove_blob_async(&self.store.series_path(id))
                    .await
                {
                    tracing::warn!(error = %e, series_id = %id, "removing a deleted series' volume failed");
                }
                // Its indexed instances went with its row; their folder goes once no row names it.
                if let Err(e) = self.sweep_instances().await {
                    tracing::warn!(error = %e, series_id = %id, "removing a deleted series' instances failed");
                }
                tracing::info!(series_id = %id, "series deleted");
                Ok(())
            }
            Deleted::InUse => Err(refused(
                ErrorCode::ResourceInUse,
                format!("series {id} is the input of a queued or running job; cancel it or wait"),
            )),
            Deleted::NotFound => Err(series_not_found(id)),
        }
    }
}
