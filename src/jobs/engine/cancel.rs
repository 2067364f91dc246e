//! Cancellation: a queued job ends at once; a running one is flagged (here, or through the database for
//! the process that runs it) and stops at its next check.

use super::{CancelError, Engine};
use crate::storage::JobId;

impl Engine {
    /// Cancel a job: a queued job is canceled at once; a running one is flagged and stops at its next
    /// check (within a second). Terminal jobs answer `job_already_finished`.
    pub async fn cancel(&self, id: JobId) -> Result<(), CancelError> {
        let db = &self.inner.db;
        if db.cancel_queued(id).await? {
            if let Some(job) = db.get_job(id).await? {
                self.publish(&job);
            }
            return Ok(());
        }
        let flag = self
            .inner
            .running
            .lock()
            .ok()
            .and_then(|r| r.get(&id).map(|x| x.cancel.clone()));
        if let Some(flag) = flag {
            db.request_cancel(id).await?;
            flag.cancel();
            return Ok(());
        }
        match db.get_job(id).await? {
            None => Err(CancelError::NotFound),
            Some(j) if j.status.is_terminal() => Err(CancelError::Finished(j.status)),
            // Running here (claimed between the two checks: the flag is registered before the claim) or in
            // another process, which learns of the request at its next heartbeat (within a second).
            Some(_) => {
                db.request_cancel(id).await?;
                let flag = self
                    .inner
                    .running
                    .lock()
                    .ok()
                    .and_then(|r| r.get(&id).map(|x| x.cancel.clone()));
                if let Some(flag) = flag {
                    flag.cancel();
                }
                Ok(())
            }
        }
    }
}
