//! The instance index as application commands: keep and index the instances a DICOM node received, index
//! the DICOM results of volume jobs (a derived CT series of the job's volume, in the study of its source
//! series), answer queries over what is indexed, and pair instance folders with their rows.
//!
//! Files are named by generated ids ([`InstanceId`]), never by DICOM attributes. Every indexed attribute
//! is read from the file itself (`dicom::read_header`), so the index says what a C-MOVE sends.

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;

use ndarray::Ix3;

use super::query::{self, Found, Query};
use super::{App, AppResult};
use crate::dicom::{InstanceHeader, SeriesMeta, header_of, read_header, write_ct_series};
use crate::error_code::Problem;
use crate::jobs::repo::{IndexedInstance, NewInstance, StoredInstance};
use crate::jobs::{JobStatus, SeriesRecord};
use crate::storage::npy::decode_f32;
use crate::storage::{BlobStore, InstanceId, InstanceOwner, JobId, ResultName, SeriesId, UploadId};
use crate::volume::{Volume, mu_to_hu};

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

    /// Index the DICOM results of job `id` once it succeeded: the derived CT series of its volume, in the
    /// study and frame of reference of its source series. A job without a source series (no patient) is
    /// marked indexed with no instance. A job indexed before is left as it is. Returns the instances indexed.
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
        let written = self
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
            .await?;
        let owner = InstanceOwner::Job(id);
        let rows: Vec<NewInstance> = written.iter().map(|(r, _)| r.clone()).collect();
        self.db
            .node_tables()?
            .insert_instances(owner, &rows)
            .await?;
        for (row, temp) in written {
            self.store
                .commit_async(temp, self.store.instance_path(owner, row.id))
                .await
                .map_err(|e| storage("keeping a derived instance failed", e))?;
        }
        tracing::info!(job_id = %id, instances = rows.len(), "job results indexed");
        Ok(rows.len())
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
