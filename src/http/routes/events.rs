//! `GET /v1/jobs/{id}/events`: Server-Sent Events. The stream opens with a `progress` event holding the
//! job's current state, sends a `progress` event at each change of status, whole percent or stage, and
//! ends with one `final` event holding the whole job once it is terminal and, for a volume job, once its
//! DICOM results are indexed.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use tokio::sync::{broadcast, mpsc};

use super::super::AppState;
use super::super::extract::job_id;
use super::super::problem::{ApiResult, api_error};
use super::jobs::job_json;
use crate::error_code::ErrorCode;
use crate::jobs::model::KIND_VOLUME;
use crate::jobs::{Job, JobEvent, JobStatus};
use crate::storage::JobId;

/// How long a stream of a job on a shared database waits without an event before reading the job again.
const REREAD_AFTER: Duration = Duration::from_secs(3);

fn progress_event(e: &JobEvent) -> Event {
    Event::default()
        .event("progress")
        .json_data(e)
        .unwrap_or_default()
}

/// The job's `final` event, once everything it made is findable: a succeeded volume job's DICOM results
/// are indexed first (QIDO-RS and C-FIND answer them when a client acts on the event). Indexing is
/// idempotent and safe against the result indexer doing the same job at the same time.
async fn final_event_when_findable(st: &AppState, job: &Job) -> Event {
    if job.status == JobStatus::Succeeded
        && job.kind == KIND_VOLUME
        && let Err(e) = st.index_job(job.id).await
    {
        tracing::error!(job_id = %job.id, error = %e, "indexing job results before the final event failed");
    }
    final_event(job)
}

fn final_event(job: &Job) -> Event {
    Event::default()
        .event("final")
        .json_data(job_json(job))
        .unwrap_or_default()
}

fn snapshot(job: &Job) -> JobEvent {
    JobEvent::of(job)
}

pub async fn job_events(State(st): State<AppState>, Path(id): Path<String>) -> ApiResult<Response> {
    let id = job_id(&id)?;
    // Subscribe before reading the state, so that no change falls between the two.
    let sub = st.engine.subscribe();
    let job = st
        .db
        .get_job(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::JobNotFound, format!("no job {id}")))?;
    let (tx, rx) = mpsc::channel::<Event>(64);
    tokio::spawn(follow(st, id, job, sub, tx));
    let stream = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|e| (Ok::<_, Infallible>(e), rx))
    });
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}

async fn follow(
    st: AppState,
    id: JobId,
    job: Job,
    mut sub: broadcast::Receiver<JobEvent>,
    tx: mpsc::Sender<Event>,
) {
    if job.status.is_terminal() {
        let _ = tx.send(final_event_when_findable(&st, &job).await).await;
        return;
    }
    let mut last = snapshot(&job);
    if tx.send(progress_event(&last)).await.is_err() {
        return;
    }
    let mut shutdown = st.shutdown.clone();
    // On a shared database the job may run in another process, whose events come as notifications that
    // can be lost: the database is read again after a quiet spell, so the stream never waits forever.
    let shared = st.db.is_shared();
    let mut quiet = tokio::time::interval(REREAD_AFTER);
    quiet.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    quiet.reset();
    loop {
        let changed = tokio::select! {
            r = sub.recv() => Some(r),
            _ = quiet.tick(), if shared => None,
            _ = shutdown.changed() => return,
            _ = tx.closed() => return,
        };
        let reread = match changed {
            Some(Ok(e)) if e.id != id => continue,
            Some(Ok(e)) if !e.status.is_terminal() => {
                quiet.reset();
                if e != last {
                    last = e.clone();
                    if tx.send(progress_event(&e)).await.is_err() {
                        return;
                    }
                }
                continue;
            }
            // Terminal, missed events or a quiet spell: the database has the truth.
            Some(Ok(_)) | Some(Err(broadcast::error::RecvError::Lagged(_))) | None => true,
            Some(Err(broadcast::error::RecvError::Closed)) => return,
        };
        if reread {
            match st.db.get_job(id).await {
                Ok(Some(job)) if job.status.is_terminal() => {
                    let _ = tx.send(final_event_when_findable(&st, &job).await).await;
                    return;
                }
                Ok(Some(job)) => {
                    let now = snapshot(&job);
                    if now.status != last.status
                        || now.progress != last.progress
                        || now.stage != last.stage
                    {
                        last = now.clone();
                        if tx.send(progress_event(&now)).await.is_err() {
                            return;
                        }
                    }
                }
                _ => return,
            }
        }
    }
}
