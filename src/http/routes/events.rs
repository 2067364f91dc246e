//! `GET /v1/jobs/{id}/events`: Server-Sent Events. The stream opens with a `progress` event holding the
//! job's current state, sends a `progress` event at each change of status, whole percent or stage, and
//! ends with one `final` event holding the whole job once it is terminal.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use tokio::sync::{broadcast, mpsc};

use super::super::AppState;
use super::super::extract::job_id;
use super::super::problem::{ApiResult, api_error};
use super::jobs::job_view;
use crate::error_code::ErrorCode;
use crate::jobs::{Job, JobEvent};
use crate::storage::JobId;

fn progress_event(e: &JobEvent) -> Event {
    Event::default()
        .event("progress")
        .json_data(e)
        .unwrap_or_default()
}

fn final_event(job: &Job) -> Event {
    Event::default()
        .event("final")
        .json_data(job_view(job))
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
        let _ = tx.send(final_event(&job)).await;
        return;
    }
    if tx.send(progress_event(&snapshot(&job))).await.is_err() {
        return;
    }
    let mut shutdown = st.shutdown.clone();
    loop {
        let changed = tokio::select! {
            r = sub.recv() => r,
            _ = shutdown.changed() => return,
            _ = tx.closed() => return,
        };
        let reread = match changed {
            Ok(e) if e.id != id => continue,
            Ok(e) if !e.status.is_terminal() => {
                if tx.send(progress_event(&e)).await.is_err() {
                    return;
                }
                continue;
            }
            // Terminal, or missed events: the database has the truth.
            Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => true,
            Err(broadcast::error::RecvError::Closed) => return,
        };
        if reread {
            match st.db.get_job(id).await {
                Ok(Some(job)) if job.status.is_terminal() => {
                    let _ = tx.send(final_event(&job)).await;
                    return;
                }
                Ok(Some(job)) => {
                    if tx.send(progress_event(&snapshot(&job))).await.is_err() {
                        return;
                    }
                }
                _ => return,
            }
        }
    }
}
