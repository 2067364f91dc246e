//! Open uploads: one instance appended at a time, the completion that assembles them, and the deletion of
//! an upload that will not be completed.
//!
//! An instance is stored under its SHA-256 as it arrives (so re-sending one is harmless) and acknowledged
//! only once it is durable: in the data directory, and with object storage in the object of the same key
//! too, so that the upload can be completed through any API host, or after the host that received it was
//! restarted or lost. The completion takes what this host lacks from the object store; a completion that
//! fails (say, a missing slice) leaves the upload open, so the missing instance can still be sent. A
//! completed or deleted upload's instances are removed, here and in the object store.

use serde_json::{Value, json};

use super::{AppendAnswer, upload_json, upload_not_found};
use crate::app::error::refused;
use crate::app::idempotency::settle;
use crate::app::series::outcome_json;
use crate::app::{App, AppResult, Replay};
use crate::dicom::{ReadLimits, UploadFile, read_upload_file};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::dicom_problem;
use crate::jobs::{Appended, Completed, IdempotencyKey, SeriesRecord, UploadDeleted};
use crate::series::UnevenPolicy;
use crate::storage::{TempBlob, UploadId};

impl App {
    /// Append one instance (`body`: a temporary file of `bytes` bytes whose SHA-256 is `sha`, hex) to the open
    /// upload `existing`, or to a new one (under `key`, replayed when an identical request used it). The
    /// instance is decoded first, so that a broken file is refused at once and never reaches the upload.
    pub async fn append_instance(
        &self,
        existing: Option<UploadId>,
        key: Option<IdempotencyKey>,
        body: TempBlob,
        sha: &str,
        bytes: u64,
    ) -> AppResult<AppendAnswer> {
        match self.replayed_upload(key.as_ref()).await {
            Ok(None) => {}
            Ok(Some(u)) => {
                body.discard().await;
                return Ok(AppendAnswer::Replayed(u));
            }
            Err(e) => {
                body.discard().await;
                return Err(e);
            }
        }
        let (series_uid, name) = match self.decode_instance(&body).await {
            Ok(v) => v,
            Err(e) => {
                body.discard().await;
                return Err(e);
            }
        };
        let (id, opened) = match existing {
            Some(id) => (id, false),
            None => {
                let id = UploadId::generate();
                let inserted = self.db.insert_open_upload(id, key.as_ref()).await?;
                if let Replay::Existing(winner) = settle(inserted, key.as_ref())? {
                    // Lost a race with the same key: answer the winner.
                    return Ok(AppendAnswer::Replayed(self.recorded_upload(&winner).await?));
                }
                (id, true)
            }
        };
        // Temporary file → row → object and rename: a crash between the last two leaves a row without its
        // file, which the completion reports and which sending the instance again repairs.
        let path = self.store.upload_file(id, sha);
        let outcome = self
            .db
            .append_upload_file(
                id,
                sha,
                &name,
                bytes,
                &series_uid,
                self.settings.max_upload_bytes,
            )
            .await;
        let (instances, duplicate) = match outcome {
            Ok(Appended::Added(n)) => {
                body.sync().await?;
                self.store.commit_async(body, path).await?;
                (n, false)
            }
            Ok(Appended::Duplicate(n)) => {
                // Known, but its file may have been lost between its row and its rename: keep it again.
                if self.store.exists(&path).await.unwrap_or(true) {
                    body.discard().await;
                } else {
                    body.sync().await?;
                    self.store.commit_async(body, path).await?;
                }
                (n, true)
            }
            Ok(other) => {
                body.discard().await;
                return Err(match other {
                    Appended::Closed => refused(
                        ErrorCode::UploadClosed,
                        format!("upload {id} was completed meanwhile"),
                    ),
                    Appended::TooLarge(limit) => refused(
                        ErrorCode::BodyTooLarge,
                        format!("the upload would exceed its limit of {limit} bytes"),
                    ),
                    _ => upload_not_found(id),
                });
            }
            Err(e) => {
                body.discard().await;
                return Err(e.into());
            }
        };
        let Some(record) = self.db.get_upload(id).await? else {
            // Deleted while this instance was being stored: nothing may keep it.
            self.remove_instances_of(id).await;
            return Err(upload_not_found(id));
        };
        tracing::info!(upload_id = %id, instances, duplicate, "instance appended");
        let mut view = upload_json(&record);
        view["appended"] = json!({"file": name, "series_uid": series_uid, "duplicate": duplicate});
        Ok(AppendAnswer::Appended { id, view, opened })
    }

    /// The SeriesInstanceUID of the instance in `body` and its name in messages: its SOP Instance UID (a
    /// body has no file name).
    async fn decode_instance(&self, body: &TempBlob) -> AppResult<(String, String)> {
        let file = UploadFile {
            label: "the instance".to_string(),
            path: body.path().to_path_buf(),
        };
        let _held = self
            .reserve_decoding(file.path.clone(), &file.label, |_| 0)
            .await?;
        Ok(self
            .engine
            .compute(move || {
                read_upload_file(&file, &ReadLimits::default())
                    .map(|inst| {
                        let name = if inst.sop_instance_uid.is_empty() {
                            "an instance without a SOP Instance UID".to_string()
                        } else {
                            inst.sop_instance_uid
                        };
                        (inst.series_uid, name)
                    })
                    .map_err(|e| dicom_problem(&e))
            })
            .await?)
    }

    /// Complete the open upload `id`: assemble its instances (refused, the upload left open, when no series
    /// could be made), record its series, index its instances, fire the processing rules and remove the
    /// instances it kept. Instances received by another API host are fetched from the object store first.
    /// Returns the upload's outcome.
    pub async fn complete_upload(
        &self,
        id: UploadId,
        uneven: Option<UnevenPolicy>,
    ) -> AppResult<Value> {
        if !self.upload(id).await?.open {
            return Err(refused(
                ErrorCode::UploadClosed,
                format!("upload {id} is already completed"),
            ));
        }
        let listed = self.db.upload_files(id).await?;
        let instances = listed.len() as u32;
        let mut files = Vec::with_capacity(listed.len());
        let mut bytes = 0u64;
        for (sha, name) in listed {
            if sha.len() != 64 || !sha.bytes().all(|b| b.is_ascii_hexdigit()) {
                tracing::error!(upload_id = %id, "an upload file has a malformed hash");
                return Err(Problem::internal().into());
            }
            let path = self.store.fetch(&self.store.upload_file(id, &sha)).await?;
            bytes += tokio::fs::metadata(&path).await?.len();
            files.push(UploadFile { label: name, path });
        }
        let (mut ingested, mut staged) = self.ingest_files(id, files.clone(), uneven).await?;
        // A series stored already with the same content is answered as stored, not made again.
        let known = self.recognise_series(&mut ingested, &mut staged).await;
        let ready: Vec<SeriesRecord> = ingested.ready().cloned().collect();
        if ready.is_empty() {
            // The upload stays open: a missing instance can still be appended.
            staged.discard().await;
            return Err(ingested.failure().into());
        }
        let records: Vec<SeriesRecord> = ready
            .iter()
            .filter(|s| !known.contains(&s.id))
            .cloned()
            .collect();
        let view = outcome_json(id, instances, bytes, &ingested);
        let recorded = match self
            .db
            .complete_upload(id, instances, &view, &records)
            .await
        {
            Ok(Completed::Done) => Ok(None::<()>),
            Ok(Completed::Changed) => Err(refused(
                ErrorCode::UploadChanged,
                "instances arrived while the upload was being completed; complete it again",
            )),
            Ok(Completed::Closed) => Err(refused(
                ErrorCode::UploadClosed,
                format!("upload {id} was completed meanwhile"),
            )),
            Err(e) => Err(e.into()),
        };
        self.commit_series(staged, recorded).await?;
        if let Ok(kept) = self.stage_uploaded(&files, &ingested.rejected).await {
            self.index_upload(id, kept, &ready).await;
        }
        self.fire_rules(&ingested, None).await;
        self.remove_instances_of(id).await;
        tracing::info!(upload_id = %id, series = records.len(), "upload completed");
        Ok(view)
    }

    /// Delete the open upload `id` and the instances it holds, here and in the object store; refused for a
    /// completed upload (it goes with its series).
    pub async fn delete_upload(&self, id: UploadId) -> AppResult<()> {
        match self.db.delete_open_upload(id).await? {
            UploadDeleted::Done => {
                self.remove_instances_of(id).await;
                tracing::info!(upload_id = %id, "open upload deleted");
                Ok(())
            }
            UploadDeleted::Completed => Err(refused(
                ErrorCode::UploadClosed,
                format!("upload {id} is completed; it goes with its series"),
            )),
            UploadDeleted::NotFound => Err(upload_not_found(id)),
        }
    }

    /// Remove the instance files of upload `id` and their objects (a failure is logged: the start-up sweep
    /// removes a folder without an open upload).
    async fn remove_instances_of(&self, id: UploadId) {
        let store = self.store.clone();
        match tokio::task::spawn_blocking(move || store.remove_upload(id)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                tracing::warn!(error = %e, upload_id = %id, "removing an upload's instances failed")
            }
            Err(e) => {
                tracing::warn!(error = %e, upload_id = %id, "removing an upload's instances failed")
            }
        }
    }
}
