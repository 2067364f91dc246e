//! Job events across processes on a shared (PostgreSQL) database. Each process publishes what its engine
//! sees — status changes and progress of the jobs it runs, jobs submitted and deleted through it — on
//! [`EVENTS_CHANNEL`](crate::jobs::database::EVENTS_CHANNEL), and every process hears the others', so that an
//! event stream served by any process (`GET /v1/jobs/{id}/events`, `GET /v1/events`) follows a job run by
//! any other: an API process with `--workers 0` shows the progress of the workers' jobs.
//!
//! Notifications are best effort: one that is lost (a full queue, a listener reconnecting) costs a stream a
//! step of progress, never the job's truth, which the database holds. A lost connection is reported as
//! [`Remote::Lost`], so list readers reload, and the per-job stream re-reads the job now and then.

use serde::{Deserialize, Serialize};
use tokio::sync::mpsc;

use super::{Engine, JobEvent};
use crate::jobs::database::Database;
use crate::jobs::model::{Job, JobSummary};
use crate::storage::JobId;

/// Notifications queued for sending at most; beyond that they are dropped (counted in the log).
const QUEUE: usize = 1024;

/// What one process tells the others.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Relayed {
    /// A job's status, progress or stage changed where it runs.
    Job { event: JobEvent },
    /// A job was submitted through the sending process (its summary as queued).
    Created { summary: JobSummary },
    /// A job was deleted through the sending process.
    Deleted { id: JobId },
}

/// A notification as sent: the sending process's number and what happened.
#[derive(Debug, Serialize, Deserialize)]
struct Envelope {
    from: u64,
    #[serde(flatten)]
    item: Relayed,
}

/// What another process announced that is not a job event, for the list-wide feed.
#[derive(Debug, Clone, PartialEq)]
pub enum Remote {
    Created(JobSummary),
    Deleted(JobId),
    /// Notifications may have been lost (the listening connection was re-established).
    Lost,
}

/// The sending half kept by the engine (on a shared database only).
pub(super) struct Relay {
    /// This process's number: notifications carrying it are its own and are not heard again.
    pub(super) from: u64,
    queue: mpsc::Sender<String>,
}

impl Relay {
    /// A relay for `db` when it is shared, with its sending task; `None` otherwise.
    pub(super) fn start(db: &Database) -> Option<Self> {
        if !db.is_shared() {
            return None;
        }
        let (queue, mut rx) = mpsc::channel::<String>(QUEUE);
        let pg = db.clone();
        tokio::spawn(async move {
            while let Some(payload) = rx.recv().await {
                if let Err(e) = pg.notify_event(&payload).await {
                    tracing::debug!(error = %e, "a job event was not relayed");
                }
            }
        });
        Some(Relay {
            from: uuid::Uuid::new_v4().as_u64_pair().0,
            queue,
        })
    }

    /// Queue `item` for the other processes (never waits: called from the worker pool too).
    pub(super) fn send(&self, item: Relayed) {
        let envelope = Envelope {
            from: self.from,
            item,
        };
        match serde_json::to_string(&envelope) {
            Ok(payload) => {
                if self.queue.try_send(payload).is_err() {
                    tracing::debug!("the job event relay is full; an event was dropped");
                }
            }
            Err(e) => tracing::warn!(error = %e, "a job event could not be encoded"),
        }
    }
}

/// Decode a notification; `None` for one of this process (`own`) or one that is not an envelope.
pub(super) fn decode(payload: &str, own: u64) -> Option<Relayed> {
    let e: Envelope = serde_json::from_str(payload).ok()?;
    (e.from != own).then_some(e.item)
}

impl Engine {
    /// Tell the other processes about `item` (nothing on a database of one process).
    pub(super) fn relay(&self, item: Relayed) {
        if let Some(r) = &self.inner.relay {
            r.send(item);
        }
    }

    /// Tell subscribers here that `job` was queued, and the other processes' feeds that it was submitted.
    pub fn publish_created(&self, job: &Job) {
        let _ = self.inner.events.send(JobEvent::of(job));
        self.relay(Relayed::Created {
            summary: JobSummary::of(job),
        });
    }

    /// Announce a job deleted through this process to the others' feeds.
    pub fn announce_deleted(&self, id: JobId) {
        self.relay(Relayed::Deleted { id });
    }

    /// Subscribe to what other processes announce besides job events (submissions, deletions, loss).
    pub fn subscribe_remote(&self) -> tokio::sync::broadcast::Receiver<Remote> {
        self.inner.remote.subscribe()
    }

    /// Pass on what another process relayed: job events to this process's subscribers, the rest to the
    /// feed's.
    pub(super) fn heard(&self, payload: &str) {
        let Some(own) = self.inner.relay.as_ref().map(|r| r.from) else {
            return;
        };
        match decode(payload, own) {
            Some(Relayed::Job { event }) => {
                let _ = self.inner.events.send(event);
            }
            Some(Relayed::Created { summary }) => {
                let _ = self.inner.remote.send(Remote::Created(summary));
            }
            Some(Relayed::Deleted { id }) => {
                let _ = self.inner.remote.send(Remote::Deleted(id));
            }
            None => {}
        }
    }

    /// Notifications may have been lost: tell the feed's readers to reload.
    pub(super) fn notifications_lost(&self) {
        let _ = self.inner.remote.send(Remote::Lost);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::JobStatus;

    #[test]
    fn an_envelope_round_trips_and_a_process_does_not_hear_itself() {
        let id = JobId::generate();
        let event = JobEvent {
            id,
            status: JobStatus::Running,
            progress: 42,
            stage: "backprojecting".into(),
            iteration: Some(3),
            residual: Some(0.25),
        };
        let payload = serde_json::to_string(&Envelope {
            from: 7,
            item: Relayed::Job {
                event: event.clone(),
            },
        })
        .unwrap();
        assert_eq!(decode(&payload, 8), Some(Relayed::Job { event }));
        assert_eq!(decode(&payload, 7), None);
        let job = Job::queued(
            crate::jobs::JobSpec::Reconstruction(
                serde_json::from_value(serde_json::json!({
                    "input": JobId::generate().to_string(),
                    "algorithm": {"name": "fbp"},
                    "grid": {"nx": 4, "ny": 4, "dx_mm": 1, "dy_mm": 1}
                }))
                .unwrap(),
            ),
            1 << 20,
            123,
        );
        let summary = JobSummary::of(&job);
        let created = serde_json::to_string(&Envelope {
            from: 1,
            item: Relayed::Created {
                summary: summary.clone(),
            },
        })
        .unwrap();
        assert_eq!(decode(&created, 2), Some(Relayed::Created { summary }));
        assert_eq!(decode("not json", 2), None);
        assert_eq!(decode(&id.to_string(), 2), None);
    }
}
