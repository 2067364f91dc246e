//! Job commands and queries: submit (admission, Idempotency-Key), fetch, list a page, cancel, delete.

use super::App;
use super::error::{AppError, AppResult, refused};
use super::hints::misplaced_fields;
use super::idempotency::{Replay, settle};
use crate::error_code::ErrorCode;
use crate::jobs::imaging::{VolumeShape, plan, resolve_input};
use crate::jobs::iso_range::refuse_surfaces_above;
use crate::jobs::model::VolumeJobRequest;
use crate::jobs::model::{KIND_RECONSTRUCTION, KIND_VOLUME, VolumeUnits, now_us};
use crate::jobs::model::{PacsSeries, VolumeSource};
use crate::jobs::plan::admit_job;
use crate::jobs::{CancelError, IdempotencyKey, Job, JobFilter, JobRequest, JobSpec, JobSummary};
use crate::storage::JobId;
use crate::volume::Frame;

/// The job a submission answers: the one it queued, or the one an identical earlier request queued.
#[derive(Debug, Clone)]
pub struct Submitted {
    pub job: Job,
    /// False when the Idempotency-Key replayed an earlier submission.
    pub created: bool,
}

/// One page of a job list, newest first, and the cursor of the next page.
#[derive(Debug, Clone)]
pub struct Page<T> {
    pub items: Vec<T>,
    /// Pass as [`JobFilter::before_id`] for the next page; `None` on the last page.
    pub next: Option<JobId>,
}

impl<T> Page<T> {
    /// The first `limit` of `rows` (fetched with `limit + 1`), with a cursor when there were more.
    fn of(mut rows: Vec<T>, limit: u32, id: impl Fn(&T) -> JobId) -> Self {
        let more = rows.len() > limit as usize;
        rows.truncate(limit as usize);
        let next = if more { rows.last().map(&id) } else { None };
        Page { items: rows, next }
    }
}

fn parse<T: serde::de::DeserializeOwned>(v: serde_json::Value) -> AppResult<T> {
    Ok(super::error::parse_body(v)?)
}

/// The volume a pulled series is planned against at submission, before it arrived: 512 × 512 slices of
/// 1 mm, as many as fit in a quarter of the memory budget (at most 512), so that its estimate reserves room
/// for a typical CT series.
fn nominal_pulled(budget_bytes: u64) -> VolumeShape {
    let slice_bytes = 512 * 512 * 4;
    let nz = (budget_bytes / 4 / slice_bytes).clamp(1, 512) as usize;
    VolumeShape {
        dim: (nz, 512, 512),
        frame: Frame {
            spacing_mm: [1.0, 1.0, 1.0],
            origin_mm: [0.0, 0.0, 0.0],
            direction: Frame::AXIS_ALIGNED,
        },
        max_value: None,
    }
}

fn job_not_found(id: JobId) -> AppError {
    refused(ErrorCode::JobNotFound, format!("no job {id}"))
}

impl App {
    /// Admit a request: a reconstruction (the default `kind`) of a dataset, or a volume job on a series or a
    /// succeeded job's volume. Returns the typed spec and its memory estimate.
    pub async fn admit(&self, body: serde_json::Value) -> AppResult<(JobSpec, u64)> {
        let kind = body
            .get("kind")
            .map(|k| k.as_str().unwrap_or("").to_string());
        let budget = self.settings.memory_budget_bytes;
        match kind.as_deref() {
            Some(KIND_VOLUME) => {
                misplaced_fields(&body, true)?;
                let req: VolumeJobRequest = parse(body)?;
                crate::jobs::render_products::check_render_sizes(
                    &req,
                    self.settings.render_max_side,
                )?;
                let (shape, units) = match &req.input {
                    VolumeSource::Stored(id) => {
                        let input = match resolve_input(&self.db, &self.store, *id).await {
                            Ok(input) => input,
                            Err(p) if p.code == ErrorCode::SeriesNotFound => {
                                return Err(self.volume_input_not_found(&id.to_string(), p).await);
                            }
                            Err(p) => return Err(p.into()),
                        };
                        (input.shape, input.units)
                    }
                    VolumeSource::Pacs(source) => {
                        self.check_pull(source)?;
                        // Planned against a nominal CT volume until the series has arrived; the job plans
                        // again on the series it pulled and fails if that does not fit.
                        (nominal_pulled(budget), VolumeUnits::Hu)
                    }
                };
                let planned = plan(&req, shape, budget)?;
                refuse_surfaces_above(
                    &req,
                    planned.output.max_value,
                    units,
                    self.settings.mu_water_per_mm,
                )?;
                Ok((JobSpec::Volume(req), planned.estimate_bytes))
            }
            None | Some(KIND_RECONSTRUCTION) => {
                let mut body = body;
                if let Some(m) = body.as_object_mut() {
                    m.remove("kind");
                }
                misplaced_fields(&body, false)?;
                let req: JobRequest = parse(body)?;
                let Some(dataset) = self.db.get_dataset(req.input).await? else {
                    return Err(self.dataset_not_found(req.input).await);
                };
                let estimate = admit_job(&req, &dataset, budget)?;
                Ok((JobSpec::Reconstruction(req), estimate))
            }
            Some(other) => Err(refused(
                ErrorCode::InvalidRequest,
                format!("unknown job kind `{other}`: `reconstruction` (default) or `volume`"),
            )),
        }
    }

    /// Check that `source` can be pulled: a configured peer allowed to retrieve and to store (the moved
    /// instances come back by C-STORE from it), a valid series UID, and a DICOM node listening here.
    fn check_pull(&self, source: &PacsSeries) -> AppResult<()> {
        let dicom = &self.settings.dicom;
        let peer = dicom.peer(&source.pacs).ok_or_else(|| {
            refused(
                ErrorCode::UnknownPeer,
                format!(
                    "`{}` is not a configured DICOM peer (dicom.peers)",
                    source.pacs
                ),
            )
        })?;
        if !(peer.retrieve && peer.store) {
            return Err(refused(
                ErrorCode::PeerNotPermitted,
                format!(
                    "peer `{}` needs `retrieve` and `store` set in dicom.peers to be pulled from (its \
                     instances arrive by C-STORE)",
                    peer.ae_title
                ),
            ));
        }
        if !crate::dicom::is_valid_uid(&source.series_instance_uid) {
            return Err(refused(
                ErrorCode::InvalidParameter,
                "`series_instance_uid` is not a valid UID (digits and dots, at most 64 characters)",
            ));
        }
        if !self.engine.can_pull() {
            return Err(refused(
                ErrorCode::DicomNodeOff,
                "the DICOM node is off (set dicom.port): a series cannot be pulled from a PACS",
            ));
        }
        Ok(())
    }

    /// Submit a job (a JSON request as `POST /v1/jobs` takes it) under an optional Idempotency-Key: it is
    /// persisted as `queued` before this returns, and the engine is woken.
    pub async fn submit_job(
        &self,
        body: serde_json::Value,
        key: Option<IdempotencyKey>,
    ) -> AppResult<Submitted> {
        if let Replay::Existing(id) = self.replay(key.as_ref()).await? {
            return self.replayed_job(&id).await;
        }
        let (spec, estimate) = self.admit(body).await?;
        let job = Job::queued(spec, estimate, now_us());
        let inserted = self.db.insert_job(&job, key.as_ref()).await?;
        match settle(inserted, key.as_ref())? {
            Replay::New => {
                let what = match &job.request {
                    JobSpec::Reconstruction(r) => r.algorithm.name(),
                    JobSpec::Volume(_) => KIND_VOLUME,
                };
                tracing::info!(job_id = %job.id, kind = %job.kind, what, "job queued");
                self.feed.created(&job);
                self.engine.publish_created(&job);
                self.engine.wake();
                Ok(Submitted { job, created: true })
            }
            Replay::Existing(id) => self.replayed_job(&id).await,
        }
    }

    async fn replayed_job(&self, id: &str) -> AppResult<Submitted> {
        let id = JobId::parse(id).map_err(|e| {
            AppError::Db(crate::jobs::DbError::Corrupt {
                table: "idempotency_keys",
                reason: e.to_string(),
            })
        })?;
        Ok(Submitted {
            job: self.get_job(id).await?,
            created: false,
        })
    }

    /// A job by id.
    pub async fn get_job(&self, id: JobId) -> AppResult<Job> {
        match self.db.get_job(id).await? {
            Some(job) => Ok(job),
            None => Err(self
                .not_found(
                    ErrorCode::JobNotFound,
                    format!("no job {id}"),
                    &id.to_string(),
                )
                .await),
        }
    }

    /// The summaries of the jobs matching `filter` (its `limit`: the page size), newest first.
    pub async fn list_job_summaries(&self, filter: &JobFilter) -> AppResult<Page<JobSummary>> {
        let limit = filter.limit;
        let f = JobFilter {
            limit: limit.saturating_add(1),
            ..filter.clone()
        };
        let rows = self.db.list_job_summaries(&f).await?;
        Ok(Page::of(rows, limit, |j| j.id))
    }

    /// The whole jobs matching `filter` (its `limit`: the page size), newest first.
    pub async fn list_jobs(&self, filter: &JobFilter) -> AppResult<Page<Job>> {
        let limit = filter.limit;
        let f = JobFilter {
            limit: limit.saturating_add(1),
            ..filter.clone()
        };
        let rows = self.db.list_jobs(&f).await?;
        Ok(Page::of(rows, limit, |j| j.id))
    }

    /// Cancel a job: a queued job ends `canceled` at once, a running one stops at its next check. Answers
    /// the job as it is now.
    pub async fn cancel_job(&self, id: JobId) -> AppResult<Job> {
        match self.engine.cancel(id).await {
            Ok(()) => self.get_job(id).await,
            Err(CancelError::NotFound) => Err(job_not_found(id)),
            Err(CancelError::Finished(s)) => Err(refused(
                ErrorCode::JobAlreadyFinished,
                format!("the job has already {}; it cannot be canceled", s.as_str()),
            )),
            Err(CancelError::Db(e)) => Err(e.into()),
        }
    }

    /// Delete a finished job and its results.
    pub async fn delete_job(&self, id: JobId) -> AppResult<()> {
        let job = self.get_job(id).await?;
        if !job.status.is_terminal() || !self.db.delete_finished(id).await? {
            return Err(refused(
                ErrorCode::JobActive,
                "cancel the job and wait for it to finish before deleting it",
            ));
        }
        self.feed.deleted(id);
        self.engine.announce_deleted(id);
        let store = self.store.clone();
        tokio::task::spawn_blocking(move || store.delete_results(id))
            .await
            .map_err(std::io::Error::other)??;
        tracing::info!(job_id = %id, "job deleted");
        Ok(())
    }
}
