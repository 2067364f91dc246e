//! STOW-RS (PS3.18 §10.5) as a front door of the same instance index as C-STORE: each part (already written
//! to a temporary file by the front door, within its size limits) is checked like a C-STORE data set (its
//! header read by the same reader, valid UIDs, a storable SOP class, the study of the request's path); the
//! accepted ones are kept under `instances/<upload>/` and indexed at once, so QIDO-RS, WADO-RS, C-FIND and
//! C-MOVE find them as soon as the answer is sent. An instance the index holds already, byte for byte, is
//! answered as stored and not kept again; one with other content replaces the earlier copy
//! ([`super::instances::resent`]). Their series are assembled, and the processing rules
//! fired, once no instance of the series arrived for the stable age ([`super::stow_series`]): a series sent
//! in several requests is assembled once, and the answer waits only for the instances to be stored. A
//! refused part is removed; nothing of it is kept.

use std::path::PathBuf;

use serde_json::json;

use super::instances::indexed;
use super::instances::resent::{Arrived, read_arrived_at};
use super::{App, AppError, AppResult};
use crate::dicom::STORABLE_SOP_CLASSES;
use crate::error_code::ErrorCode;
use crate::jobs::model::NewInstance;
use crate::storage::{InstanceId, InstanceOwner, UploadId};

/// PS3.18 / PS3.4 failure reasons (0008,1197) a STOW-RS answer gives.
pub mod reason {
    /// Processing failure (as Orthanc answers an instance of another study).
    pub const PROCESSING_FAILURE: u16 = 0x0110;
    /// SOP class not supported.
    pub const SOP_CLASS_NOT_SUPPORTED: u16 = 0x0122;
    /// Out of resources (a part over the size limit, or storage failed).
    pub const OUT_OF_RESOURCES: u16 = 0xA700;
    /// Cannot understand (not DICOM, or its header cannot be read).
    pub const CANNOT_UNDERSTAND: u16 = 0xC000;
}

/// One part of a STOW-RS body as the front door received it.
#[derive(Debug)]
pub enum StowPart {
    /// A DICOM part written whole to `path` (a temporary file the caller removes when it is still there).
    File { path: PathBuf, bytes: u64 },
    /// A part refused while it arrived (too large, another media type): reason and why.
    Refused { reason: u16, why: String },
}

/// What became of one part.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StowOutcome {
    pub sop_class_uid: Option<String>,
    pub sop_instance_uid: Option<String>,
    pub study_uid: Option<String>,
    pub series_uid: Option<String>,
    /// `None` when stored; the failure reason otherwise.
    pub failure: Option<u16>,
    pub why: String,
    /// The catalogue code of a part refused for what it holds (a malformed UID, an unreadable header).
    pub code: Option<&'static str>,
}

impl StowOutcome {
    fn failed(reason: u16, why: impl Into<String>) -> Self {
        StowOutcome {
            sop_class_uid: None,
            sop_instance_uid: None,
            study_uid: None,
            series_uid: None,
            failure: Some(reason),
            why: why.into(),
            code: None,
        }
    }
}

impl App {
    /// Store the parts of a STOW-RS request (to `study` when its path names one); one outcome per part, in
    /// order. The accepted instances are kept and indexed before this returns; their series are assembled
    /// once stable.
    pub async fn stow(
        &self,
        parts: Vec<StowPart>,
        study: Option<&str>,
    ) -> AppResult<Vec<StowOutcome>> {
        let max = self.max_received_bytes();
        let study = study.map(str::to_string);
        let checked = tokio::task::spawn_blocking(move || {
            parts
                .into_iter()
                .map(|p| check(p, study.as_deref(), max))
                .collect::<Vec<_>>()
        })
        .await
        .map_err(|e| AppError::Storage(std::io::Error::other(e)))?;
        let (mut outcomes, accepted): (Vec<StowOutcome>, Vec<Option<Arrived>>) =
            checked.into_iter().unzip();
        let parts: Vec<usize> = (0..accepted.len())
            .filter(|k| accepted[*k].is_some())
            .collect();
        let accepted: Vec<Arrived> = accepted.into_iter().flatten().collect();
        if accepted.is_empty() {
            return Ok(outcomes);
        }
        if let Err(e) = self.keep_stowed(accepted).await {
            tracing::error!(error = %e, "STOW-RS instances could not be stored");
            for k in parts {
                outcomes[k].failure = Some(reason::OUT_OF_RESOURCES);
                outcomes[k].why = "the instance could not be stored".into();
            }
        }
        Ok(outcomes)
    }

    /// Keep the accepted instances of one request under a new upload and index them as pending assembly, by
    /// the rule of [`resent`](super::instances::resent): a copy the index holds already is answered as
    /// stored and kept no more; the others are moved first, then their rows written (replacing earlier
    /// copies; a row that a query answers always has its file), then their series start ageing. A request
    /// of copies only records nothing and assembles nothing.
    async fn keep_stowed(&self, accepted: Vec<Arrived>) -> AppResult<()> {
        let sorted = self.sort_arrived(accepted).await?;
        let (recognised, repeated) = (sorted.recognised.len(), sorted.repeated.len());
        let fresh = sorted.fresh;
        if fresh.is_empty() {
            tracing::info!(
                recognised,
                repeated,
                "STOW-RS instances were all stored already: nothing kept"
            );
            return Ok(());
        }
        let upload = UploadId::generate();
        let owner = InstanceOwner::Upload(upload);
        let rows: Vec<NewInstance> = fresh
            .iter()
            .map(|a| NewInstance {
                id: InstanceId::generate(),
                series_id: None,
                instance: a.instance.clone(),
                sha256: Some(a.sha256.clone()),
            })
            .collect();
        let store = self.store.clone();
        let moves: Vec<(PathBuf, PathBuf)> = fresh
            .iter()
            .zip(&rows)
            .map(|(a, r)| (a.path.clone(), store.instance_path(owner, r.id)))
            .collect();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            std::fs::create_dir_all(store.instance_dir(upload))?;
            for (from, to) in moves {
                std::fs::rename(from, to)?;
            }
            std::fs::File::open(store.instance_dir(upload))?.sync_all()
        })
        .await
        .map_err(|e| AppError::Storage(std::io::Error::other(e)))??;
        let bytes: u64 = fresh.iter().map(|a| a.instance.bytes).sum();
        let n = fresh.len() as u32;
        let view = json!({"upload": {
            "id": upload, "status": "completed", "instances": n, "bytes": bytes,
            "received_by": "STOW-RS", "series": "assembled once stable",
        }});
        let recorded = async {
            self.db
                .insert_completed_upload(upload, n, bytes, &view, &[], None)
                .await?;
            self.db.insert_received(upload, &rows, true).await
        }
        .await;
        let replaced = match recorded {
            Ok(r) => r,
            Err(e) => {
                let store = self.store.clone();
                let _ = tokio::task::spawn_blocking(move || store.remove_instances(upload)).await;
                return Err(e.into());
            }
        };
        let replaced_n = replaced.len();
        self.remove_replaced(replaced).await;
        self.stowed(fresh.iter().map(|a| &a.instance));
        tracing::info!(upload_id = %upload, instances = n, bytes, replaced = replaced_n, recognised, repeated, "STOW-RS instances stored and indexed");
        Ok(())
    }
}

/// Check one part: its header read (valid UIDs), a storable SOP class, the study of the path.
fn check(p: StowPart, study: Option<&str>, max: u64) -> (StowOutcome, Option<Arrived>) {
    let (path, bytes) = match p {
        StowPart::Refused { reason, why } => return (StowOutcome::failed(reason, why), None),
        StowPart::File { path, bytes } => (path, bytes),
    };
    let (h, sha256) = match read_arrived_at(&path, max) {
        Ok(v) => v,
        Err(e) => {
            let mut o = StowOutcome::failed(reason::CANNOT_UNDERSTAND, e.to_string());
            o.code = Some(ErrorCode::from(&e).code());
            return (o, None);
        }
    };
    let mut o = StowOutcome {
        sop_class_uid: Some(h.sop_class_uid.clone()),
        sop_instance_uid: Some(h.sop_instance_uid.clone()),
        study_uid: Some(h.study_uid.clone()),
        series_uid: Some(h.series_uid.clone()),
        failure: None,
        why: String::new(),
        code: None,
    };
    if !STORABLE_SOP_CLASSES.contains(&h.sop_class_uid.as_str()) {
        o.failure = Some(reason::SOP_CLASS_NOT_SUPPORTED);
        o.why = format!("SOP class {} is not stored here", h.sop_class_uid);
        return (o, None);
    }
    if let Some(s) = study
        && s != h.study_uid
    {
        o.failure = Some(reason::PROCESSING_FAILURE);
        o.why = format!("the instance belongs to study {}, not {s}", h.study_uid);
        return (o, None);
    }
    let instance = indexed(&h, bytes);
    (
        o,
        Some(Arrived {
            path,
            instance,
            sha256,
        }),
    )
}
