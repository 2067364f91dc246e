//! The DICOM results of volume jobs in the index: a derived CT series of the job's volume, in the study of
//! its source series, and its products as exported for delivery (derived CT stacks, Secondary Capture MIPs,
//! reformats and renderings, Encapsulated STL — the same files and UIDs a delivery sends); indexed as each
//! job succeeds, and at start for those missed while the service was down.

use std::path::PathBuf;

use ndarray::Ix3;

use super::{DERIVED_SERIES_NUMBER, indexed, storage};
use crate::app::{App, AppResult};
use crate::dicom::{SeriesMeta, header_of, read_header, write_ct_series};
use crate::error_code::Problem;
use crate::jobs::JobStatus;
use crate::jobs::export::export_dir;
use crate::jobs::model::{NewInstance, now_us};
use crate::storage::npy::decode_f32;
use crate::storage::{InstanceId, InstanceOwner, JobId, ResultName};
use crate::volume::{Volume, mu_to_hu};

/// How often a process on a shared database indexes the results of jobs other processes finished.
pub const SHARED_CATCH_UP: std::time::Duration = std::time::Duration::from_secs(5);

/// How long after a job finished a process on a shared database leaves its indexing to the process that
/// ran it (a worker process indexes nothing; a job of a lost process is indexed by another after this).
pub const SHARED_GRACE: std::time::Duration = std::time::Duration::from_secs(60);

impl App {
    /// Index the DICOM results of job `id` once it succeeded: its products as exported for delivery, and
    /// the derived CT series of its volume (unless the export holds it already), in the study and frame of
    /// reference of its source series. A job without a source series (no patient) is marked indexed with
    /// no instance. A job indexed before is left as it is. Returns the instances indexed.
    pub async fn index_job(&self, id: JobId) -> AppResult<usize> {
        if self.db.job_indexed(id).await? {
            return Ok(0);
        }
        let Some(job) = self.db.get_job(id).await? else {
            return Ok(0);
        };
        if job.status != JobStatus::Succeeded {
            return Ok(0);
        }
        let Some(result) = job.result.filter(|r| r.source_series.is_some()) else {
            self.db.mark_job_indexed(id).await?;
            return Ok(0);
        };
        let exported = self.exported_instances(id).await;
        let volume_exported = exported
            .iter()
            .any(|(_, r)| r.instance.series_number == Some(DERIVED_SERIES_NUMBER.into()));
        let written = if volume_exported {
            Vec::new()
        } else {
            self.write_volume_series(id, result).await?
        };
        let owner = InstanceOwner::Job(id);
        let rows: Vec<NewInstance> = written
            .iter()
            .map(|(r, _)| r.clone())
            .chain(exported.iter().map(|(_, r)| r.clone()))
            .collect();
        // Files first, rows second: a row is what QIDO-RS and C-FIND answer, so its file must already be
        // there when a client asks for it. The files live under the job's results folder, so a crash in
        // between leaves nothing the job's deletion does not remove.
        for (row, temp) in written {
            self.store
                .commit_async(temp, self.store.instance_path(owner, row.id))
                .await
                .map_err(|e| storage("keeping a derived instance failed", e))?;
        }
        let store = self.store.clone();
        let links: Vec<(PathBuf, PathBuf)> = exported
            .into_iter()
            .map(|(from, r)| (from, store.instance_path(owner, r.id)))
            .collect();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            for (from, to) in links {
                if let Some(dir) = to.parent() {
                    std::fs::create_dir_all(dir)?;
                }
                // The exported file is never written again: a hard link shares it.
                if std::fs::hard_link(&from, &to).is_err() {
                    std::fs::copy(&from, &to)?;
                }
            }
            Ok(())
        })
        .await
        .map_err(|e| storage("indexing exported results failed", std::io::Error::other(e)))?
        .map_err(|e| storage("indexing exported results failed", e))?;
        if !self.db.insert_instances(owner, &rows).await? {
            // Indexed meanwhile by another process (or task): its rows name its own files, not these.
            for r in &rows {
                let path = self.store.instance_path(owner, r.id);
                if let Err(e) = self.store.remove_blob_async(&path).await {
                    tracing::warn!(error = %e, "removing a file indexed twice failed");
                }
            }
            tracing::info!(job_id = %id, "job results were indexed elsewhere first");
            return Ok(0);
        }
        tracing::info!(job_id = %id, instances = rows.len(), "job results indexed");
        Ok(rows.len())
    }

    /// The job's exported DICOM results with their index rows; none (logged) when they cannot be exported,
    /// so that the volume is indexed all the same.
    async fn exported_instances(&self, id: JobId) -> Vec<(PathBuf, NewInstance)> {
        let files = match self.export_results(id).await {
            Ok(f) => f,
            Err(p) => {
                tracing::warn!(job_id = %id, code = p.code.code(), detail = %p.detail, "the job's products are not indexed");
                return Vec::new();
            }
        };
        let dir = export_dir(&self.store, id);
        let max = self
            .settings
            .dicom
            .max_instance_bytes
            .saturating_add(64 << 10);
        tokio::task::spawn_blocking(move || {
            files
                .into_iter()
                .filter_map(|f| {
                    let path = dir.join(&f.file);
                    let bytes = std::fs::metadata(&path).ok()?.len();
                    match read_header(&path, max) {
                        Ok(h) => Some((
                            path,
                            NewInstance {
                                id: InstanceId::generate(),
                                series_id: None,
                                instance: indexed(&h, bytes),
                                sha256: None,
                            },
                        )),
                        Err(e) => {
                            tracing::warn!(error = %e, "an exported instance is not indexed");
                            None
                        }
                    }
                })
                .collect()
        })
        .await
        .unwrap_or_default()
    }

    /// Write the derived CT series of job `id`'s volume as temporary files with their index rows.
    async fn write_volume_series(
        &self,
        id: JobId,
        result: crate::jobs::model::JobResult,
    ) -> AppResult<Vec<(NewInstance, crate::storage::TempBlob)>> {
        let source = match result.source_series {
            Some(s) => self.db.get_series(s).await?,
            None => None,
        };
        let meta = SeriesMeta {
            study_uid: source.as_ref().and_then(|s| s.study_uid.clone()),
            frame_of_reference_uid: source
                .as_ref()
                .and_then(|s| s.frame_of_reference_uid.clone()),
            patient_name: source.as_ref().and_then(|s| s.patient_name.clone()),
            patient_id: source.as_ref().and_then(|s| s.patient_id.clone()),
            series_description: format!(
                "ctrecon {}",
                source
                    .as_ref()
                    .and_then(|s| s.description.as_deref())
                    .unwrap_or("derived")
            )
            .chars()
            .take(64)
            .collect(),
            series_number: DERIVED_SERIES_NUMBER,
            source_series_uid: source.as_ref().map(|s| s.series_uid.clone()),
            derivation_description: Some(match (&source, &result.derivation) {
                (None, Some(d)) => d.clone(),
                _ => "Volume reconstructed by ctrecon from the referenced series".into(),
            }),
        };
        let (store, mu_water) = (self.store.clone(), self.settings.mu_water_per_mm);
        let volume_path = store.result_path(id, &ResultName::Volume);
        Ok(self
            .engine
            .compute(move || {
                let bytes = store
                    .local(&volume_path)
                    .and_then(std::fs::read)
                    .map_err(|e| storage("reading a job's volume failed", e))?;
                let data = decode_f32(&bytes)
                    .ok()
                    .and_then(|a| a.into_dimensionality::<Ix3>().ok())
                    .ok_or_else(Problem::internal)?;
                let data = match result.units {
                    crate::jobs::model::VolumeUnits::Hu => data,
                    crate::jobs::model::VolumeUnits::MuPerMm => {
                        data.mapv(|v| mu_to_hu(v, mu_water))
                    }
                };
                let vol = Volume {
                    data,
                    frame: result.frame(),
                };
                let series = write_ct_series(&vol, &meta)
                    .map_err(|e| crate::jobs::ingest::dicom_problem(&e))?;
                let mut out = Vec::with_capacity(series.files.len());
                for (name, bytes) in &series.files {
                    let h = header_of(name, bytes)
                        .map_err(|e| crate::jobs::ingest::dicom_problem(&e))?;
                    let temp = store
                        .write_temp(bytes)
                        .map_err(|e| storage("writing a derived instance failed", e))?;
                    let row = NewInstance {
                        id: InstanceId::generate(),
                        series_id: None,
                        instance: indexed(&h, bytes.len() as u64),
                        sha256: None,
                    };
                    out.push((row, temp));
                }
                Ok(out)
            })
            .await?)
    }

    /// Index the results of every succeeded volume job not indexed yet (after a restart).
    pub async fn index_pending_jobs(&self) -> AppResult<usize> {
        self.index_jobs_finished_before(i64::MAX).await
    }

    /// Index the results of the succeeded volume jobs not indexed yet that finished before `before_us`.
    async fn index_jobs_finished_before(&self, before_us: i64) -> AppResult<usize> {
        let mut n = 0;
        for id in self.db.jobs_to_index().await? {
            let finished = self.db.get_job(id).await?.and_then(|j| j.finished_us);
            if finished.is_some_and(|t| t < before_us) {
                n += self.index_job(id).await?;
            }
        }
        Ok(n)
    }

    /// Index each volume job's results as it succeeds, and those missed while the service was down; runs
    /// as long as the runtime. On a shared database the jobs other processes ran (a `ctrecon worker` runs no
    /// indexer) are caught up every [`SHARED_CATCH_UP`], [`SHARED_GRACE`] after they finished; a job is
    /// indexed once whoever gets there first.
    pub fn spawn_result_indexer(&self) {
        let app = self.clone();
        let mut events = self.engine.subscribe();
        tokio::spawn(async move {
            if let Err(e) = app.index_pending_jobs().await {
                tracing::error!(error = %e, "indexing job results at start failed");
            }
            let mut catch_up = tokio::time::interval(SHARED_CATCH_UP);
            catch_up.tick().await;
            loop {
                let event = tokio::select! {
                    ev = events.recv() => ev,
                    _ = catch_up.tick(), if app.db.is_shared() => {
                        // Jobs that finished just now are being indexed by the process that ran them.
                        let before = now_us().saturating_sub(SHARED_GRACE.as_micros() as i64);
                        if let Err(e) = app.index_jobs_finished_before(before).await {
                            tracing::error!(error = %e, "indexing job results failed");
                        }
                        continue;
                    }
                };
                match event {
                    Ok(ev) if ev.status == JobStatus::Succeeded => {
                        let kind = match app.db.get_job(ev.id).await {
                            Ok(Some(j)) => j.kind,
                            _ => continue,
                        };
                        if kind == crate::jobs::model::KIND_VOLUME
                            && let Err(e) = app.index_job(ev.id).await
                        {
                            tracing::error!(job_id = %ev.id, error = %e, "indexing job results failed");
                        }
                    }
                    Ok(_) => {}
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                        if let Err(e) = app.index_pending_jobs().await {
                            tracing::error!(error = %e, "indexing job results failed");
                        }
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
                }
            }
        });
    }
}
