//! `LISTEN/NOTIFY` wake-ups: a process learns at once that a job was queued (or re-queued) by any process,
//! and that a client asked, through any process, to cancel a job it runs — without polling.

use sqlx::postgres::PgListener;

use super::{CANCEL_CHANNEL, DbError, PgDb, QUEUED_CHANNEL};
use crate::storage::JobId;

/// What a notification announces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wakeup {
    /// A job was queued or re-queued: idle workers should look at the queue.
    Queued(JobId),
    /// A client asked to cancel this running job.
    Cancel(JobId),
}

/// A connection listening on the job channels.
pub struct Listener {
    inner: PgListener,
}

impl Listener {
    /// Connect and listen on the job channels.
    pub async fn connect(db: &PgDb) -> Result<Self, DbError> {
        let mut inner = PgListener::connect(db.url()).await?;
        inner.listen_all([QUEUED_CHANNEL, CANCEL_CHANNEL]).await?;
        Ok(Self { inner })
    }

    /// The next wake-up (notifications with a payload that is not a job id are skipped). A lost
    /// connection is re-established by the next call; notifications sent meanwhile are lost, so a caller
    /// must still look at the queue now and then.
    pub async fn next(&mut self) -> Result<Wakeup, DbError> {
        loop {
            let n = self.inner.recv().await?;
            let Ok(id) = JobId::parse(n.payload()) else {
                continue;
            };
            match n.channel() {
                QUEUED_CHANNEL => return Ok(Wakeup::Queued(id)),
                CANCEL_CHANNEL => return Ok(Wakeup::Cancel(id)),
                _ => continue,
            }
        }
    }
}
