//! DICOM uploads as application commands: a whole upload received in one request (files or ZIPs, already on
//! disk as temporary files), one instance appended to an open upload, the completion of an open upload, and
//! the upload's JSON representation.
//!
//! Received files are decoded on the worker pool, split by SeriesInstanceUID and assembled into HU volumes;
//! a file or member that cannot be read is listed as rejected with its reason and the others go on.
//! Volumes are renamed into place only after their rows are committed, and the instances of a recorded
//! upload are indexed. A series stored already with the same content is answered as that series, and an
//! instance the index holds already is not kept again ([`super::recognised`]). Open uploads (instances appended one by one, completed or deleted later) are in
//! [`open`].

mod open;

use serde_json::{Value, json};

use super::error::refused;
use super::idempotency::settle;
use super::instances::StagedInstances;
use super::series::outcome_json;
use super::{App, AppError, AppResult, Replay};
use crate::dicom::UploadFile;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::Staged;
use crate::jobs::model::rfc3339;
use crate::jobs::{IdempotencyKey, SeriesRecord, UploadRecord};
use crate::series::UnevenPolicy;
use crate::storage::{TempBlob, UploadId};

/// A file of an upload as received: streamed to a temporary file, with the name the client gave it (for
/// messages only; never a path).
#[derive(Debug)]
pub struct ReceivedFile {
    pub label: String,
    pub temp: TempBlob,
}

/// What a command that may create an upload answers.
#[derive(Debug)]
pub enum UploadAnswer {
    /// This request created upload `id`; `view` is its outcome (series made, files refused).
    Created { id: UploadId, view: Value },
    /// An earlier request with the same Idempotency-Key created this upload (or won a race for the key).
    Replayed(UploadRecord),
}

/// What appending an instance answers.
#[derive(Debug)]
pub enum AppendAnswer {
    /// Appended (or already there): the upload's view with `appended`, and whether this request opened it.
    Appended {
        id: UploadId,
        view: Value,
        opened: bool,
    },
    /// An earlier request with the same Idempotency-Key opened this upload (or won a race for the key).
    Replayed(UploadRecord),
}

/// The JSON document of an upload: its outcome once completed, else its state and links.
pub fn upload_json(u: &UploadRecord) -> Value {
    if let Some(outcome) = &u.outcome {
        return outcome.clone();
    }
    json!({
        "upload": {
            "id": u.id,
            "status": if u.open { "open" } else { "completed" },
            "instances": u.instances,
            "bytes": u.bytes,
            "created_at": rfc3339(u.created_us),
            "links": {
                "self": format!("/v1/uploads/{}", u.id),
                "append": format!("/v1/series?upload={}", u.id),
                "complete": format!("/v1/uploads/{}/complete", u.id),
            }
        }
    })
}

fn upload_not_found(id: UploadId) -> AppError {
    refused(ErrorCode::UploadNotFound, format!("no upload {id}"))
}

fn on_disk(files: &[ReceivedFile]) -> Vec<UploadFile> {
    files
        .iter()
        .map(|f| UploadFile {
            label: f.label.clone(),
            path: f.temp.path().to_path_buf(),
        })
        .collect()
}

async fn discard(files: Vec<ReceivedFile>) {
    for f in files {
        f.temp.discard().await;
    }
}

impl App {
    /// The upload `id`.
    pub async fn upload(&self, id: UploadId) -> AppResult<UploadRecord> {
        self.db
            .get_upload(id)
            .await?
            .ok_or_else(|| upload_not_found(id))
    }

    /// The upload recorded under the id a replayed key names.
    async fn recorded_upload(&self, id: &str) -> AppResult<UploadRecord> {
        let id = UploadId::parse(id).map_err(|e| refused(ErrorCode::InvalidId, e.to_string()))?;
        self.upload(id).await
    }

    /// The upload an earlier request with the same Idempotency-Key created; `None` when the key is new (or
    /// absent); refused when that request differed.
    async fn replayed_upload(
        &self,
        key: Option<&IdempotencyKey>,
    ) -> AppResult<Option<UploadRecord>> {
        match self.replay(key).await? {
            Replay::New => Ok(None),
            Replay::Existing(id) => self.recorded_upload(&id).await.map(Some),
        }
    }

    /// Refuse appending to upload `id` unless it exists and is open.
    pub async fn check_open_upload(&self, id: UploadId) -> AppResult<()> {
        match self.db.get_upload(id).await? {
            None => Err(upload_not_found(id)),
            Some(u) if !u.open => Err(refused(
                ErrorCode::UploadClosed,
                format!("upload {id} is completed; start a new one"),
            )),
            Some(_) => Ok(()),
        }
    }

    /// Refuse a body sent as `application/zip` that is not a ZIP archive (415, naming what it starts like
    /// and how to send that), rather than reading it as one DICOM file named `upload.zip`.
    pub async fn check_zip(&self, path: &std::path::Path) -> AppResult<()> {
        let path = path.to_path_buf();
        let (zip, head) =
            tokio::task::spawn_blocking(move || -> std::io::Result<(bool, Vec<u8>)> {
                use std::io::Read;
                let mut head = Vec::new();
                std::fs::File::open(&path)?
                    .take(132)
                    .read_to_end(&mut head)?;
                Ok((crate::dicom::is_zip(&path)?, head))
            })
            .await
            .map_err(|_| Problem::internal())??;
        if zip {
            return Ok(());
        }
        let what = crate::dicom::starts_like(&head).unwrap_or("not a ZIP archive");
        let how = if what == "a DICOM file" {
            "send one instance as application/dicom, or several as multipart/form-data"
        } else {
            "send DICOM files as a ZIP (application/zip), as multipart/form-data parts, or one instance as \
             application/dicom"
        };
        Err(refused(
            ErrorCode::UnsupportedMediaType,
            format!("the body was sent as application/zip but is {what}: {how}"),
        ))
    }

    /// Ingest `files` (`bytes` in all) as one upload completed at once: replayed when `key` was used by an
    /// identical request; refused when no series could be assembled; otherwise recorded with its series
    /// (rows, then volumes in place), its instances indexed and the processing rules fired. The received
    /// files are removed whatever the answer.
    pub async fn upload_files(
        &self,
        files: Vec<ReceivedFile>,
        bytes: u64,
        uneven: Option<UnevenPolicy>,
        key: Option<IdempotencyKey>,
    ) -> AppResult<UploadAnswer> {
        let id = UploadId::generate();
        let on_disk = on_disk(&files);
        let outcome = match self.replayed_upload(key.as_ref()).await {
            Ok(None) => self.ingest_files(id, on_disk.clone(), uneven).await.map(Ok),
            Ok(Some(u)) => Ok(Err(u)),
            Err(e) => Err(e),
        };
        // Kept aside for the instance index before the received files go; indexed once the upload is recorded.
        let kept = match &outcome {
            Ok(Ok((ingested, _))) if ingested.ready().next().is_some() => {
                self.stage_uploaded(&on_disk, &ingested.rejected).await.ok()
            }
            _ => None,
        };
        discard(files).await;
        let (mut ingested, mut staged) = match outcome? {
            Ok(done) => done,
            Err(replayed) => return Ok(UploadAnswer::Replayed(replayed)),
        };
        // A series stored already with the same content is answered as stored, not made again.
        let known = self.recognise_series(&mut ingested, &mut staged).await;
        // Instances (ZIP entries included), not request parts.
        let instances = ingested.files() as u32;
        let ready: Vec<SeriesRecord> = ingested.ready().cloned().collect();
        if ready.is_empty() {
            staged.discard().await;
            return Err(ingested.failure().into());
        }
        let records: Vec<SeriesRecord> = ready
            .iter()
            .filter(|s| !known.contains(&s.id))
            .cloned()
            .collect();
        let view = outcome_json(id, instances, bytes, &ingested);
        let recorded = self
            .record_upload(id, (instances, bytes), &view, &records, key.as_ref())
            .await;
        if let Some(winner) = self.commit_series(staged, recorded).await? {
            return Ok(UploadAnswer::Replayed(winner));
        }
        if let Some(kept) = kept {
            self.index_upload(id, kept, &ready).await;
        }
        self.fire_rules(&ingested, None).await;
        tracing::info!(upload_id = %id, series = records.len(), stored_already = known.len(), rejected = ingested.rejected.len(), "upload completed");
        Ok(UploadAnswer::Created { id, view })
    }

    /// Record an upload completed in one request with its series: `None` when recorded, or the upload of
    /// the request that won a race for the same Idempotency-Key.
    async fn record_upload(
        &self,
        id: UploadId,
        (instances, bytes): (u32, u64),
        view: &Value,
        records: &[SeriesRecord],
        key: Option<&IdempotencyKey>,
    ) -> AppResult<Option<UploadRecord>> {
        let inserted = self
            .db
            .insert_completed_upload(id, instances, bytes, view, records, key)
            .await?;
        match settle(inserted, key)? {
            Replay::New => Ok(None),
            Replay::Existing(id) => self.recorded_upload(&id).await.map(Some),
        }
    }

    /// After the series rows were recorded (`Ok(None)`), move their volumes into place; otherwise (the
    /// winner of a race, or an error) remove them, so that nothing is left behind.
    async fn commit_series<T>(
        &self,
        staged: Staged,
        recorded: AppResult<Option<T>>,
    ) -> AppResult<Option<T>> {
        match recorded {
            Ok(None) => {
                staged.commit(&self.store).await?;
                Ok(None)
            }
            other => {
                staged.discard().await;
                other
            }
        }
    }

    /// Index the instances of recorded upload `id` (the upload stands whether or not they could be indexed).
    async fn index_upload(&self, id: UploadId, kept: StagedInstances, records: &[SeriesRecord]) {
        if let Err(e) = self.index_staged(id, kept, records).await {
            tracing::warn!(upload_id = %id, error = %e, "the upload's instances are not indexed");
        }
    }
}
