//! The instance index as application commands: keep and index the instances a DICOM node, STOW-RS or an
//! HTTP upload (`POST /v1/series`) received, index the DICOM results of volume jobs (a derived CT series
//! of the job's volume, in the study of its source series, and its products as exported for delivery:
//! derived CT stacks, Secondary Capture MIPs, reformats and renderings, Encapsulated STL — the same files
//! and UIDs a delivery sends), answer queries over what is indexed, and pair instance folders with their
//! rows. Indexing runs whether or not the DICOM node listens.
//!
//! Files are named by generated ids ([`InstanceId`]), never by DICOM attributes. Every indexed attribute
//! is read from the file itself (`dicom::read_header`), so the index says what a C-MOVE sends.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;

use ndarray::Ix3;

use super::query::{self, Found, Query};
use super::{App, AppResult};
use crate::dicom::{
    InstanceHeader, SeriesMeta, Unpacked, UploadFile, header_of, read_header, unpack_file,
    write_ct_series,
};
use crate::error_code::Problem;
use crate::jobs::export::export_dir;
use crate::jobs::repo::{IndexedInstance, NewInstance, StoredInstance};
use crate::jobs::{JobStatus, SeriesRecord};
use crate::storage::npy::decode_f32;
use crate::storage::{
    BlobStore, InstanceId, InstanceOwner, JobId, ResultName, ScratchDir, SeriesId, UploadId,
};
use crate::volume::{Volume, mu_to_hu};

/// The series number of derived series (as on the results' DICOM downloads).
pub const DERIVED_SERIES_NUMBER: i32 = 900;

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

    /// Keep the received instances `files` of upload `upload` and index them (each with its assembled series
    /// among `series`, when it has one): rows first, then the files are moved under
    /// `instances/<upload>/`. A file whose header cannot be read is left where it is. Returns the count.
    pub async fn index_received(
        &self,
        upload: UploadId,
        files: Vec<PathBuf>,
        series: &[SeriesRecord],
    ) -> AppResult<usize> {
        let max = self
            .settings
            .dicom
            .max_instance_bytes
            .saturating_add(64 << 10);
        let by_uid: HashMap<String, SeriesId> = series
            .iter()
            .map(|s| (s.series_uid.clone(), s.id))
            .collect();
        let read = tokio::task::spawn_blocking(move || {
            files
                .into_iter()
                .filter_map(|f| {
                    let bytes = std::fs::metadata(&f).ok()?.len();
                    match read_header(&f, max) {
                        Ok(h) => Some((f, indexed(&h, bytes))),
                        Err(e) => {
                            tracing::warn!(error = %e, "a received instance is not indexed");
                            None
                        }
                    }
                })
                .collect::<Vec<_>>()
        })
        .await
        .map_err(|e| storage("reading received headers failed", std::io::Error::other(e)))?;
        let owner = InstanceOwner::Upload(upload);
        let rows: Vec<NewInstance> = read
            .iter()
            .map(|(_, i)| NewInstance {
                id: InstanceId::generate(),
                series_id: by_uid.get(&i.series_uid).copied(),
                instance: i.clone(),
            })
            .collect();
        self.db
            .node_tables()?
            .insert_instances(owner, &rows)
            .await?;
        let store = self.store.clone();
        let moves: Vec<(PathBuf, PathBuf)> = read
            .into_iter()
            .zip(&rows)
            .map(|((from, _), r)| (from, store.instance_path(owner, r.id)))
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
        tracing::info!(upload_id = %upload, instances = n, "received instances indexed");
        Ok(n)
    }

    /// Answer a query over the index (grouped and matched off the async threads).
    pub async fn find_instances(&self, q: &Query) -> AppResult<Vec<Found>> {
        let rows = self.db.node_tables()?.indexed_instances(&q.scope()).await?;
        let q = q.clone();
        tokio::task::spawn_blocking(move || query::run(rows, &q))
            .await
            .map_err(|e| storage("a query failed", std::io::Error::other(e)).into())
    }

    /// Index the DICOM results of job `id` once it succeeded: its products as exported for delivery, and
    /// the derived CT series of its volume (unless the export holds it already), in the study and frame of
    /// reference of its source series. A job without a source series (no patient) is marked indexed with
    /// no instance. A job indexed before is left as it is. Returns the instances indexed.
    pub async fn index_job(&self, id: JobId) -> AppResult<usize> {
        if self.db.node_tables()?.job_indexed(id).await? {
            return Ok(0);
        }
        let Some(job) = self.db.get_job(id).await? else {
            return Ok(0);
        };
        if job.status != JobStatus::Succeeded {
            return Ok(0);
        }
        let Some(result) = job.result.filter(|r| r.source_series.is_some()) else {
            self.db.node_tables()?.mark_job_indexed(id).await?;
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
        self.db
            .node_tables()?
            .insert_instances(owner, &rows)
            .await?;
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
            derivation_description: Some(
                "Volume reconstructed by ctrecon from the referenced series".into(),
            ),
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
                    };
                    out.push((row, temp));
                }
                Ok(out)
            })
            .await?)
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

    /// Index the results of every succeeded volume job not indexed yet (after a restart).
    pub async fn index_pending_jobs(&self) -> AppResult<usize> {
        let mut n = 0;
        for id in self.db.node_tables()?.jobs_to_index().await? {
            n += self.index_job(id).await?;
        }
        Ok(n)
    }

    /// Index each volume job's results as it succeeds, and those missed while the service was down; runs
    /// as long as the runtime.
    pub fn spawn_result_indexer(&self) {
        if let Err(e) = self.db.node_tables() {
            // The index has no PostgreSQL twin yet: nothing to index into, and no export to make for it.
            tracing::info!(reason = %e, "derived results are not indexed");
            return;
        }
        let app = self.clone();
        let mut events = self.engine.subscribe();
        tokio::spawn(async move {
            if let Err(e) = app.index_pending_jobs().await {
                tracing::error!(error = %e, "indexing job results at start failed");
            }
            loop {
                match events.recv().await {
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

    /// Remove `instances/<upload>/` folders whose upload has no indexed instance any more (its series or
    /// upload was deleted); returns how many were removed.
    pub async fn sweep_instances(&self) -> AppResult<usize> {
        let keep: HashSet<String> = self
            .db
            .node_tables()?
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
                if let Ok(u) = UploadId::parse(&name)
                    && !keep.contains(&name)
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
