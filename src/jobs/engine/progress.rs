//! Progress of a running job: the sink the core reports to (each change of whole percent, stage or
//! residual is broadcast at once) and its persistence at a bounded rate, for the attempt that runs it.

use std::sync::{Arc, Mutex};

use super::relay::Relayed;
use super::{Engine, JobEvent};
use crate::jobs::model::JobStatus;
use crate::jobs::store::JobStore;
use crate::recon::control::Progress;
use crate::storage::JobId;
use crate::telemetry::names;

/// Latest progress of a running job, written by the pool, read by the persisting task.
#[derive(Default)]
pub(super) struct Latest {
    pub(super) progress: u8,
    pub(super) stage: String,
    pub(super) iteration: Option<usize>,
    pub(super) dirty: bool,
}

/// The progress sink handed to a running job: publishes each change of whole percent or stage.
pub(super) struct Sink {
    pub(super) id: JobId,
    pub(super) latest: Arc<Mutex<Latest>>,
    /// Where the changes go: this process's subscribers and, on a shared database, the others.
    pub(super) engine: Engine,
}

impl Progress for Sink {
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>) {
        // Never 100 while running: 100 means succeeded.
        let pct = (fraction.clamp(0.0, 1.0) * 100.0).floor().min(99.0) as u8;
        let Ok(mut l) = self.latest.lock() else {
            return;
        };
        let new_residual = residual.is_some() && iteration != l.iteration;
        if l.progress == pct && l.stage == stage && !new_residual {
            return;
        }
        l.iteration = iteration;
        if let Some(r) = residual {
            metrics::gauge!(names::JOB_RESIDUAL).set(r);
        }
        l.progress = pct;
        if l.stage != stage {
            l.stage = stage.to_string();
        }
        l.dirty = true;
        let event = JobEvent {
            id: self.id,
            status: JobStatus::Running,
            progress: pct,
            stage: l.stage.clone(),
            iteration,
            residual,
        };
        drop(l);
        self.engine.relay(Relayed::Job {
            event: event.clone(),
        });
        let _ = self.engine.inner.events.send(event);
    }
}

impl Engine {
    pub(super) async fn persist_progress(&self, id: JobId, attempt: u32, latest: &Mutex<Latest>) {
        let snapshot = match latest.lock() {
            Ok(mut l) if l.dirty => {
                l.dirty = false;
                Some((l.progress, l.stage.clone()))
            }
            _ => None,
        };
        if let Some((p, stage)) = snapshot
            && let Err(e) = JobStore::set_progress(&self.inner.db, id, attempt, p, &stage).await
        {
            tracing::warn!(error = %e, "persisting progress failed");
        }
    }
}
