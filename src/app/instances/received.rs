//! Received instances kept and indexed: what a DICOM node, STOW-RS or an HTTP upload (`POST /v1/series`)
//! received is moved under `instances/<upload>/` after its rows are written; an HTTP upload's files (ZIP
//! members unpacked) are staged aside first, since the upload's own files go before it is recorded.

use std::collections::HashMap;
use std::path::PathBuf;

use super::resent::Sorted;
use super::storage;
use crate::app::{App, AppResult};
use crate::dicom::{Unpacked, UploadFile, unpack_file};
use crate::jobs::SeriesRecord;
use crate::jobs::model::NewInstance;
use crate::storage::{InstanceId, InstanceOwner, ScratchDir, SeriesId, UploadId};

/// Instances of an HTTP upload copied aside until the upload is recorded (the scratch folder goes with it).
#[derive(Debug, Default)]
pub struct StagedInstances {
    files: Vec<PathBuf>,
    scratch: Option<ScratchDir>,
}

impl StagedInstances {
    /// Files staged (ZIP members unpacked).
    pub fn len(&self) -> usize {
        self.files.len()
    }

    pub fn is_empty(&self) -> bool {
        self.files.is_empty()
    }
}

impl App {
    /// Keep the received instances `files` of upload `upload` and index them (each with its assembled series
    /// among `series`, when it has one), by the rule of [`resent`](super::resent): a copy the index holds
    /// already is not kept again (its row is linked to its series, when one was made now); the others get
    /// their rows first, replacing earlier copies, then are moved under `instances/<upload>/`. A file whose
    /// header cannot be read is left where it is. Returns the count of instances kept.
    pub async fn index_received(
        &self,
        upload: UploadId,
        files: Vec<PathBuf>,
        series: &[SeriesRecord],
    ) -> AppResult<usize> {
        let arrived = self.read_arrived(files).await?;
        let sorted = self.sort_arrived(arrived).await?;
        self.index_sorted(upload, sorted, series).await
    }

    /// [`index_received`](Self::index_received) of instances already read and sorted.
    pub(crate) async fn index_sorted(
        &self,
        upload: UploadId,
        sorted: Sorted,
        series: &[SeriesRecord],
    ) -> AppResult<usize> {
        let by_uid: HashMap<String, SeriesId> = series
            .iter()
            .map(|s| (s.series_uid.clone(), s.id))
            .collect();
        let mut relink: HashMap<SeriesId, Vec<InstanceId>> = HashMap::new();
        for (a, row) in &sorted.recognised {
            if let Some(&s) = by_uid.get(&a.instance.series_uid)
                && row.series_id != Some(s)
            {
                relink.entry(s).or_default().push(row.id);
            }
        }
        for (s, ids) in relink {
            self.db.settle_instances(&ids, Some(s)).await?;
        }
        let (recognised, repeated) = (sorted.recognised.len(), sorted.repeated.len());
        let read = sorted.fresh;
        let owner = InstanceOwner::Upload(upload);
        let rows: Vec<NewInstance> = read
            .iter()
            .map(|a| NewInstance {
                id: InstanceId::generate(),
                series_id: by_uid.get(&a.instance.series_uid).copied(),
                instance: a.instance.clone(),
                sha256: Some(a.sha256.clone()),
            })
            .collect();
        if rows.is_empty() {
            tracing::info!(upload_id = %upload, recognised, repeated, "received instances were all indexed already");
            return Ok(0);
        }
        let replaced = self.db.insert_received(upload, &rows, false).await?;
        let store = self.store.clone();
        let moves: Vec<(PathBuf, PathBuf)> = read
            .into_iter()
            .zip(&rows)
            .map(|(a, r)| (a.path, store.instance_path(owner, r.id)))
            .collect();
        let n = moves.len();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            std::fs::create_dir_all(store.instance_dir(upload))?;
            for (from, to) in moves {
                std::fs::rename(from, to)?;
            }
            if let Ok(d) = std::fs::File::open(store.instance_dir(upload)) {
                let _ = d.sync_all();
            }
            Ok(())
        })
        .await
        .map_err(|e| {
            storage(
                "keeping received instances failed",
                std::io::Error::other(e),
            )
        })?
        .map_err(|e| storage("keeping received instances failed", e))?;
        let replaced_n = replaced.len();
        self.remove_replaced(replaced).await;
        tracing::info!(upload_id = %upload, instances = n, replaced = replaced_n, recognised, repeated, "received instances indexed");
        Ok(n)
    }

    /// Copy the instances of an HTTP upload (single files, and the members of ZIP archives under the
    /// upload limits) into a scratch folder, before the upload's own files go; [`index_staged`] indexes
    /// them once the upload is recorded.
    ///
    /// [`index_staged`]: App::index_staged
    pub async fn stage_uploaded(
        &self,
        files: &[UploadFile],
        rejected: &[crate::jobs::ingest::RejectedFile],
    ) -> AppResult<StagedInstances> {
        let store = self.store.clone();
        let limits = self.ingest_options(None).zip;
        let files = files.to_vec();
        // What the ingest refused is not an instance: it is neither read again nor indexed (a refused file may
        // be as large as the upload limit).
        let refused: std::collections::HashSet<String> =
            rejected.iter().map(|r| r.file.clone()).collect();
        let staged = tokio::task::spawn_blocking(move || -> std::io::Result<StagedInstances> {
            let scratch = store.scratch()?;
            let mut unpacked = Unpacked::default();
            for (k, f) in files.into_iter().enumerate() {
                if refused.contains(&f.label) {
                    continue;
                }
                let copy = scratch.path().join(format!("part-{k:06}"));
                if std::fs::hard_link(&f.path, &copy).is_err() {
                    std::fs::copy(&f.path, &copy)?;
                }
                let file = UploadFile {
                    label: f.label,
                    path: copy,
                };
                // A member that cannot be unpacked was refused by the ingest already.
                if let Err(e) = unpack_file(file, &limits, scratch.path(), &mut unpacked) {
                    tracing::debug!(error = %e, "an uploaded file is not indexed");
                }
            }
            Ok(StagedInstances {
                files: unpacked
                    .files
                    .into_iter()
                    .filter(|f| !refused.contains(&f.label))
                    .map(|f| f.path)
                    .collect(),
                scratch: Some(scratch),
            })
        })
        .await
        .map_err(|e| {
            storage(
                "staging uploaded instances failed",
                std::io::Error::other(e),
            )
        })?
        .map_err(|e| storage("staging uploaded instances failed", e))?;
        Ok(staged)
    }

    /// Index the instances of recorded upload `upload` staged by [`stage_uploaded`](App::stage_uploaded),
    /// each with its assembled series among `series`; returns the count.
    pub async fn index_staged(
        &self,
        upload: UploadId,
        mut staged: StagedInstances,
        series: &[SeriesRecord],
    ) -> AppResult<usize> {
        let files = std::mem::take(&mut staged.files);
        let n = self.index_received(upload, files, series).await?;
        if let Some(scratch) = staged.scratch.take() {
            let _ = tokio::task::spawn_blocking(move || drop(scratch)).await;
        }
        Ok(n)
    }
}
