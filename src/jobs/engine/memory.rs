//! Memory held outside jobs, counted against the same budget as the jobs' estimates: a DICOM upload being
//! decoded and assembled holds its slices and its volume while it runs on the pool. A holder waits until the
//! budget has room (the jobs running and the other holders leave it), so uploads and reconstructions
//! together stay within `memory_budget_bytes`; jobs are dispatched only into what the holders leave.

use std::sync::atomic::Ordering;
use std::time::Duration;

use super::Engine;
use crate::telemetry::names;

/// Memory held by an ingest until dropped.
#[must_use = "the memory is released when the reservation is dropped"]
pub struct Reservation {
    engine: Engine,
    bytes: u64,
}

impl Drop for Reservation {
    fn drop(&mut self) {
        let now = self
            .engine
            .inner
            .reserved
            .fetch_sub(self.bytes, Ordering::SeqCst)
            - self.bytes;
        metrics::gauge!(names::MEMORY_RESERVED).set(now as f64);
        self.engine.inner.released.notify_waiters();
        self.engine.wake();
    }
}

impl Engine {
    /// Bytes the running jobs' estimates and the reservations hold now.
    pub(super) fn memory_in_use(&self, jobs: u64) -> u64 {
        jobs.saturating_add(self.inner.reserved.load(Ordering::SeqCst))
    }

    /// Hold `bytes` (at most the whole budget) of the memory budget, waiting while the running jobs and
    /// other reservations leave too little. A reservation is granted at once when nothing else holds memory,
    /// so one larger than what is free never waits forever.
    pub async fn reserve_memory(&self, bytes: u64) -> Reservation {
        let budget = self.inner.config.memory_budget_bytes;
        let bytes = bytes.min(budget);
        loop {
            let released = self.inner.released.notified();
            if let Ok(running) = self.inner.running.lock() {
                let jobs: u64 = running.values().map(|r| r.estimate).sum();
                let held = self.memory_in_use(jobs);
                if held == 0 || held.saturating_add(bytes) <= budget {
                    let now = self.inner.reserved.fetch_add(bytes, Ordering::SeqCst) + bytes;
                    metrics::gauge!(names::MEMORY_RESERVED).set(now as f64);
                    return Reservation {
                        engine: self.clone(),
                        bytes,
                    };
                }
            }
            // Woken when a job or a reservation lets go; the timeout covers a release between the check and
            // the wait.
            let _ = tokio::time::timeout(Duration::from_millis(500), released).await;
        }
    }
}
