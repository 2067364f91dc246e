//! The claim of a delivery being sent: taken for [`DELIVERY_CLAIM`] and renewed every quarter of it while
//! the attempt runs, so that on a shared database another process queues the delivery again only when its
//! sender was lost (see `jobs::database::node`).

use std::time::Duration;

use crate::app::App;
use crate::app::error::AppResult;
use crate::jobs::deliveries::Delivery;
use crate::jobs::model::now_us;

/// How long a claimed delivery stays this process's without a renewal; renewed every quarter of it while
/// it is sent, so on a shared database another process queues it again only when its sender was lost.
pub const DELIVERY_CLAIM: Duration = Duration::from_secs(60);

impl App {
    /// One attempt of a claimed (`sending`) delivery, its claim renewed while it runs.
    pub(super) async fn attempt(&self, d: Delivery) -> AppResult<()> {
        let renew = self.renew_claim(d.id.clone(), d.attempts);
        tokio::select! {
            r = self.attempt_claimed(d) => r,
            never = renew => match never {},
        }
    }

    /// Renew the claim of attempt `attempts` of delivery `id` every quarter of [`DELIVERY_CLAIM`]; runs
    /// until dropped (a lost claim is logged: the attempt's end will not be recorded).
    async fn renew_claim(&self, id: String, attempts: u32) -> std::convert::Infallible {
        let mut tick = tokio::time::interval(DELIVERY_CLAIM / 4);
        tick.tick().await;
        let mut lost = false;
        loop {
            tick.tick().await;
            if lost {
                continue;
            }
            let until = now_us().saturating_add(DELIVERY_CLAIM.as_micros() as i64);
            match self.db.renew_delivery_claim(&id, attempts, until).await {
                Ok(true) => {}
                Ok(false) => {
                    lost = true;
                    tracing::warn!(
                        "the delivery's claim was lost; this attempt's end will not be recorded"
                    );
                }
                Err(e) => tracing::warn!(error = %e, "renewing a delivery's claim failed"),
            }
        }
    }
}
