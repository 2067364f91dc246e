//! The instance index as application commands: keep and index the instances a DICOM node, STOW-RS or an
//! HTTP upload (`POST /v1/series`) received, index the DICOM results of volume jobs (a derived CT series
//! of the job's volume, in the study of its source series, and its products as exported for delivery:
//! derived CT stacks, Secondary Capture MIPs, reformats and renderings, Encapsulated STL — the same files
//! and UIDs a delivery sends), answer queries over what is indexed, and pair instance folders with their
//! rows. Indexing runs whether or not the DICOM node listens.
//!
//! Files are named by generated ids ([`InstanceId`]), never by DICOM attributes. Every indexed attribute
//! is read from the file itself (`dicom::read_header`), so the index says what a C-MOVE sends.
//!
//! `received` keeps and indexes what was received (one copy per SOP Instance UID: `resent` says what
//! becomes of an instance sent again), `results` indexes the DICOM results of volume jobs;
//! this file holds the index row of an instance and the queries and sweep over the index.

mod received;
pub mod resent;
mod results;

use std::collections::HashSet;
use std::path::PathBuf;

use super::query::{self, Found, Query};
use super::{App, AppResult};
use crate::dicom::InstanceHeader;
use crate::error_code::Problem;
use crate::jobs::model::{IndexedInstance, StoredInstance};
use crate::storage::{BlobStore, UploadId};

pub use received::StagedInstances;

/// The series number of derived series (as on the results' DICOM downloads).
pub const DERIVED_SERIES_NUMBER: i32 = 900;

/// The index row of an instance whose header is `h` and whose file has `bytes` bytes.
pub fn indexed(h: &InstanceHeader, bytes: u64) -> IndexedInstance {
    IndexedInstance {
        sop_class_uid: h.sop_class_uid.clone(),
        sop_instance_uid: h.sop_instance_uid.clone(),
        transfer_syntax: h.transfer_syntax.clone(),
        study_uid: h.study_uid.clone(),
        series_uid: h.series_uid.clone(),
        patient_id: h.patient_id.clone(),
        patient_name: h.patient_name.clone(),
        patient_birth_date: h.patient_birth_date.clone(),
        patient_sex: h.patient_sex.clone(),
        study_date: h.study_date.clone(),
        study_time: h.study_time.clone(),
        accession_number: h.accession_number.clone(),
        study_description: h.study_description.clone(),
        referring_physician: h.referring_physician.clone(),
        study_id: h.study_id.clone(),
        modality: h.modality.clone(),
        series_number: h.series_number,
        series_description: h.series_description.clone(),
        body_part: h.body_part.clone(),
        instance_number: h.instance_number,
        bytes,
    }
}

fn storage(what: &str, e: std::io::Error) -> Problem {
    tracing::error!(error = %e, "{what}");
    Problem::internal()
}

impl App {
    /// The file of an indexed instance.
    pub fn instance_file(&self, i: &StoredInstance) -> PathBuf {
        self.store.instance_path(i.owner, i.id)
    }

    /// Answer a query over the index (grouped and matched off the async threads).
    pub async fn find_instances(&self, q: &Query) -> AppResult<Vec<Found>> {
        let rows = self.db.indexed_instances(&q.scope()).await?;
        let q = q.clone();
        tokio::task::spawn_blocking(move || query::run(rows, &q))
            .await
            .map_err(|e| storage("a query failed", std::io::Error::other(e)).into())
    }

    /// Remove `instances/<upload>/` folders whose upload has no indexed instance any more (its series or
    /// upload was deleted); returns how many were removed. On a shared database only folders untouched for
    /// [`SHARED_IDLE`](crate::storage::SHARED_IDLE) go: another process may be storing instances whose rows
    /// it has not written yet.
    pub async fn sweep_instances(&self) -> AppResult<usize> {
        let idle = self.db.is_shared().then_some(crate::storage::SHARED_IDLE);
        let keep: HashSet<String> = self
            .db
            .uploads_with_instances()
            .await?
            .into_iter()
            .map(|u| u.to_string())
            .collect();
        let store: BlobStore = self.store.clone();
        let removed = tokio::task::spawn_blocking(move || -> std::io::Result<usize> {
            let mut n = 0;
            for entry in std::fs::read_dir(store.root().join("instances"))? {
                let entry = entry?;
                let name = entry.file_name().to_string_lossy().into_owned();
                let quiet = idle.is_none_or(|idle| {
                    entry
                        .metadata()
                        .and_then(|m| m.modified())
                        .is_ok_and(|t| t.elapsed().is_ok_and(|age| age >= idle))
                });
                if let Ok(u) = UploadId::parse(&name)
                    && !keep.contains(&name)
                    && quiet
                {
                    store.remove_instances(u)?;
                    n += 1;
                }
            }
            Ok(n)
        })
        .await
        .map_err(|e| storage("sweeping instance folders failed", std::io::Error::other(e)))?
        .map_err(|e| storage("sweeping instance folders failed", e))?;
        Ok(removed)
    }
}
