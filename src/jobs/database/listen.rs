//! `LISTEN/NOTIFY` wake-ups: a process learns at once that a job was queued (or re-queued) by any process,
//! that a client asked, through any process, to cancel a job it runs, and what the other processes' engines
//! relay of their jobs — without polling.

use sqlx::postgres::PgListener;

use super::{CANCEL_CHANNEL, Database, DbError, EVENTS_CHANNEL, QUEUED_CHANNEL};
use crate::storage::JobId;

/// What a notification announces.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Wakeup {
    /// A job was queued or re-queued: idle workers should look at the queue.
    Queued(JobId),
    /// A client asked to cancel this running job.
    Cancel(JobId),
    /// A process relayed a job event (the notification's payload, undecoded).
    Relayed(String),
}

/// A connection listening on the job channels.
pub struct Listener {
    inner: PgListener,
}

impl Listener {
    /// Connect and listen on the job channels of a shared database; `None` on a database no other process
    /// uses (nothing is announced there).
    pub async fn connect(db: &Database) -> Result<Option<Self>, DbError> {
        let Some(url) = db.url.as_deref() else {
            return Ok(None);
        };
        let mut inner = PgListener::connect(url).await?;
        inner
            .listen_all([QUEUED_CHANNEL, CANCEL_CHANNEL, EVENTS_CHANNEL])
            .await?;
        Ok(Some(Self { inner }))
    }

    /// The next wake-up (queue and cancel notifications with a payload that is not a job id are skipped). A lost
    /// connection is re-established by the next call; notifications sent meanwhile are lost, so a caller
    /// must still look at the queue now and then.
    pub async fn next(&mut self) -> Result<Wakeup, DbError> {
        loop {
            let n = self.inner.recv().await?;
            if n.channel() == EVENTS_CHANNEL {
                return Ok(Wakeup::Relayed(n.payload().to_string()));
            }
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
