//! Opening the job database: SQLite in the data directory or PostgreSQL at a URL, each with its own
//! migrations (`migrations/` and `migrations/postgres/`: the schemas differ in their types), and the typed
//! handles [`Db`] and [`PgDb`] — a [`Database`] known to be opened on one of them, for code and tests that
//! open one directly.

use std::marker::PhantomData;
use std::ops::Deref;
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use futures_util::future::BoxFuture;
use sqlx::Connection;
use sqlx::postgres::{PgConnection, PgPoolOptions};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};

use super::driver::Pool;
use super::{Database, DbError};
use crate::jobs::lifecycle::{JobState, Lease, Outcome};
use crate::jobs::model::{IdempotencyKey, Inserted, Job, JobFilter};
use crate::jobs::store::{Expired, JobStore, Renewed, StoreResult};
use crate::storage::JobId;

/// Connections each process keeps at most.
const MAX_CONNECTIONS: u32 = 8;

impl Database {
    /// Open the database `url` names (`postgres://…`), or SQLite at `sqlite_path` when there is none, and
    /// apply its migrations. A PostgreSQL server that cannot be reached fails within `connect_timeout`.
    pub async fn open(
        url: Option<&str>,
        sqlite_path: &Path,
        connect_timeout: Duration,
    ) -> Result<Self, DbError> {
        Ok(match url {
            Some(url) => PgDb::open(url, connect_timeout).await?.db,
            None => Db::open(sqlite_path).await?.db,
        })
    }
}

/// The SQLite dialect, as a type ([`Db`]).
#[derive(Clone, Copy, Debug)]
pub struct Sqlite;

/// The PostgreSQL dialect, as a type ([`PgDb`]).
#[derive(Clone, Copy, Debug)]
pub struct Postgres;

/// A [`Database`] opened on the database `D`; it is used as one (through `Deref`, the [`JobStore`] port and
/// `Database::from`).
#[derive(Clone, Debug)]
pub struct Opened<D> {
    db: Database,
    dialect: PhantomData<D>,
}

/// The job database on SQLite.
pub type Db = Opened<Sqlite>;

/// The job database on PostgreSQL.
pub type PgDb = Opened<Postgres>;

impl<D> Opened<D> {
    fn new(pool: Pool, url: Option<&str>) -> Self {
        Self {
            db: Database::new(pool, url),
            dialect: PhantomData,
        }
    }
}

impl Opened<Sqlite> {
    /// Open (creating if needed) the database file and apply the migrations.
    pub async fn open(path: &Path) -> Result<Self, DbError> {
        let options = SqliteConnectOptions::from_str("sqlite://")?
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(MAX_CONNECTIONS)
            .connect_with(options)
            .await?;
        sqlx::migrate!("./migrations").run(&pool).await?;
        Ok(Self::new(Pool::Sqlite(pool), None))
    }
}

impl Opened<Postgres> {
    /// Connect to the database at `url` (`postgres://…`) and apply the migrations (concurrent starts are
    /// serialised by sqlx's advisory lock). Fails within `connect_timeout` when the server cannot be
    /// reached.
    pub async fn open(url: &str, connect_timeout: Duration) -> Result<Self, DbError> {
        // One connection first, to say why the server cannot be reached (the pool only times out).
        let unreachable = |reason: String| DbError::Unreachable {
            target: redacted(url),
            reason,
        };
        match tokio::time::timeout(connect_timeout, PgConnection::connect(url)).await {
            Ok(Ok(c)) => {
                let _ = c.close().await;
            }
            Ok(Err(e)) => return Err(unreachable(e.to_string())),
            Err(_) => {
                return Err(unreachable(format!(
                    "no answer within {} s",
                    connect_timeout.as_secs()
                )));
            }
        }
        let pool = PgPoolOptions::new()
            .max_connections(MAX_CONNECTIONS)
            .acquire_timeout(connect_timeout)
            .connect(url)
            .await?;
        sqlx::migrate!("./migrations/postgres").run(&pool).await?;
        Ok(Self::new(Pool::Postgres(pool), Some(url)))
    }
}

impl<D> Deref for Opened<D> {
    type Target = Database;

    fn deref(&self) -> &Database {
        &self.db
    }
}

impl<D> From<Opened<D>> for Database {
    fn from(opened: Opened<D>) -> Self {
        opened.db
    }
}

/// The port of the database it holds.
impl<D: Send + Sync> JobStore for Opened<D> {
    fn insert<'a>(
        &'a self,
        job: &'a Job,
        key: Option<&'a IdempotencyKey>,
    ) -> BoxFuture<'a, StoreResult<Inserted>> {
        JobStore::insert(&self.db, job, key)
    }

    fn get(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<Job>>> {
        JobStore::get(&self.db, id)
    }

    fn state(&self, id: JobId) -> BoxFuture<'_, StoreResult<Option<JobState>>> {
        JobStore::state(&self.db, id)
    }

    fn list<'a>(&'a self, filter: &'a JobFilter) -> BoxFuture<'a, StoreResult<Vec<Job>>> {
        JobStore::list(&self.db, filter)
    }

    fn queued(&self, limit: u32) -> BoxFuture<'_, StoreResult<Vec<(JobId, u64)>>> {
        JobStore::queued(&self.db, limit)
    }

    fn claim(&self, id: JobId, lease: Lease) -> BoxFuture<'_, StoreResult<u32>> {
        JobStore::claim(&self.db, id, lease)
    }

    fn heartbeat(
        &self,
        id: JobId,
        attempt: u32,
        lease: Lease,
    ) -> BoxFuture<'_, StoreResult<Renewed>> {
        JobStore::heartbeat(&self.db, id, attempt, lease)
    }

    fn set_progress<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        progress: u8,
        stage: &'a str,
    ) -> BoxFuture<'a, StoreResult<()>> {
        JobStore::set_progress(&self.db, id, attempt, progress, stage)
    }

    fn hand_back(&self, id: JobId, attempt: u32) -> BoxFuture<'_, StoreResult<()>> {
        JobStore::hand_back(&self.db, id, attempt)
    }

    fn expire_leases(&self, now_us: i64, max_attempts: u32) -> BoxFuture<'_, StoreResult<Expired>> {
        JobStore::expire_leases(&self.db, now_us, max_attempts)
    }

    fn finish<'a>(
        &'a self,
        id: JobId,
        attempt: u32,
        outcome: &'a Outcome,
    ) -> BoxFuture<'a, StoreResult<()>> {
        JobStore::finish(&self.db, id, attempt, outcome)
    }

    fn cancel_queued(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        JobStore::cancel_queued(&self.db, id)
    }

    fn request_cancel(&self, id: JobId) -> BoxFuture<'_, StoreResult<()>> {
        JobStore::request_cancel(&self.db, id)
    }

    fn delete_finished(&self, id: JobId) -> BoxFuture<'_, StoreResult<bool>> {
        JobStore::delete_finished(&self.db, id)
    }
}

/// `url` without its password, for messages.
fn redacted(url: &str) -> String {
    let Some(scheme_end) = url.find("://").map(|i| i + 3) else {
        return "the configured database_url".into();
    };
    let rest = &url[scheme_end..];
    match (rest.find('@'), rest.find(':')) {
        (Some(at), Some(colon)) if colon < at => {
            format!(
                "{}{}:***{}",
                &url[..scheme_end],
                &rest[..colon],
                &rest[at..]
            )
        }
        _ => url.to_string(),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_password_never_reaches_a_message() {
        assert_eq!(
            super::redacted("postgres://ctrecon:s3cret@db:5432/ctrecon"),
            "postgres://ctrecon:***@db:5432/ctrecon"
        );
        assert_eq!(
            super::redacted("postgres://ctrecon@db/ctrecon"),
            "postgres://ctrecon@db/ctrecon"
        );
    }
}
