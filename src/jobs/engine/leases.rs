//! Leases of running jobs: the heartbeat that renews the lease of each job this engine runs (and learns
//! whether a client asked to cancel it, possibly through another process), and the periodic expiry that
//! returns the jobs of lost workers to the queue (`attempts` kept) or fails those out of attempts.

use std::time::Duration;

use super::Engine;
use crate::jobs::lifecycle::Lease;
use crate::jobs::model::now_us;
use crate::jobs::store::{JobStore, StoreError};
use crate::recon::control::Cancel;
use crate::storage::JobId;
use crate::telemetry::names;

/// The default time a claim holds a job without a heartbeat.
pub const LEASE: Duration = Duration::from_secs(30);

/// How often a running job's lease is renewed: a third of the lease, and at least once a second so that a
/// cancel posted to another process reaches the job within about a second.
pub fn heartbeat_interval(lease: Duration) -> Duration {
    (lease / 3).clamp(Duration::from_millis(20), Duration::from_secs(1))
}

/// How often the engine looks for expired leases: a third of the lease.
pub fn expiry_interval(lease: Duration) -> Duration {
    (lease / 3).max(Duration::from_millis(20))
}

impl Engine {
    pub(super) fn lease_from_now(&self) -> Lease {
        Lease {
            expires_us: now_us() + self.inner.config.lease.as_micros() as i64,
        }
    }

    /// Renew the lease of a running job; a job whose lease was lost (another worker took it over) or that
    /// a client asked to cancel stops at its next check.
    pub(super) async fn renew(&self, id: JobId, attempt: u32, cancel: &Cancel) {
        match JobStore::heartbeat(&self.inner.db, id, attempt, self.lease_from_now()).await {
            Ok(r) if r.cancel_requested => {
                if !cancel.is_canceled() {
                    tracing::info!("cancel requested: stopping the job");
                }
                cancel.cancel();
            }
            Ok(_) => {}
            Err(StoreError::LeaseLost | StoreError::Illegal(_)) => {
                tracing::warn!("the job's lease was lost: stopping it");
                cancel.cancel();
            }
            Err(StoreError::Backend(e)) => tracing::warn!(error = %e, "renewing a lease failed"),
        }
    }

    /// Every [`expiry_interval`] until the engine stops: re-queue (or fail) the jobs whose lease expired.
    pub(super) async fn expire_leases_periodically(self) {
        let mut tick = tokio::time::interval(expiry_interval(self.inner.config.lease));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        while !self.is_stopping() {
            tick.tick().await;
            self.expire_leases_once().await;
        }
    }

    /// Re-queue the jobs whose lease expired before now (failing those claimed `max_attempts` times) and
    /// publish their new state; returns how many moved.
    pub async fn expire_leases_once(&self) -> usize {
        let db = &self.inner.db;
        let e = match JobStore::expire_leases(db, now_us(), self.inner.config.max_attempts).await {
            Ok(e) => e,
            Err(e) => {
                tracing::warn!(error = %e, "expiring leases failed");
                return 0;
            }
        };
        for (ids, outcome) in [(&e.requeued, "requeued"), (&e.failed, "failed")] {
            if ids.is_empty() {
                continue;
            }
            tracing::warn!(jobs = ?ids, outcome, "leases expired: their workers were lost");
            metrics::counter!(names::LEASES_EXPIRED, "outcome" => outcome)
                .increment(ids.len() as u64);
            for id in ids {
                if let Ok(Some(job)) = db.get_job(*id).await {
                    self.publish(&job);
                }
            }
        }
        let n = e.requeued.len() + e.failed.len();
        if !e.requeued.is_empty() {
            self.wake();
        }
        n
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn heartbeats_come_at_least_every_second_and_three_times_per_lease() {
        assert_eq!(heartbeat_interval(LEASE), Duration::from_secs(1));
        assert_eq!(
            heartbeat_interval(Duration::from_millis(900)),
            Duration::from_millis(300)
        );
        assert_eq!(expiry_interval(LEASE), Duration::from_secs(10));
    }
}
