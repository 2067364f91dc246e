//! Wake-ups from other processes on a shared (PostgreSQL) database: a job queued anywhere starts an idle
//! worker here at once, a cancel posted to any process stops the job here at once (the heartbeat also
//! carries it, within a second, should a notification be lost), and the job events other processes relay
//! reach this process's event streams (`relay`).

use std::time::Duration;

use super::Engine;
use crate::jobs::database::listen::{Listener, Wakeup};

impl Engine {
    /// On a shared database: listen for wake-ups until the engine stops, reconnecting after a failure.
    pub(super) async fn listen_for_wakeups(self) {
        if !self.inner.db.is_shared() {
            return;
        }
        let db = self.inner.db.clone();
        while !self.is_stopping() {
            let mut listener = match Listener::connect(&db).await {
                Ok(Some(l)) => l,
                Ok(None) => return,
                Err(e) => {
                    tracing::warn!(error = %e, "listening for job notifications failed; retrying");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue;
                }
            };
            // Anything queued while nobody listened, and any event relayed meanwhile.
            self.wake();
            self.notifications_lost();
            while !self.is_stopping() {
                match listener.next().await {
                    Ok(Wakeup::Queued(_)) => self.wake(),
                    Ok(Wakeup::Relayed(payload)) => self.heard(&payload),
                    Ok(Wakeup::Cancel(id)) => {
                        if let Some(flag) = self.cancel_flag(id) {
                            tracing::info!(job_id = %id, "cancel requested through another process");
                            flag.cancel();
                        }
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "job notifications interrupted; reconnecting");
                        tokio::time::sleep(Duration::from_millis(200)).await;
                        break;
                    }
                }
            }
        }
    }
}
