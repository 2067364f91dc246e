//! The one place that names sqlx's two drivers: a pool, a transaction and a row of whichever database the
//! service was opened on, and a query written once that runs on either. Every statement of the adapter is a
//! [`Query`]: SQL text with `$n` parameters (PostgreSQL's; SQLite reads `$n` as the n-th argument too) and
//! its values, bound when it runs on the pool or transaction it is given.

use sqlx::postgres::{PgPool, PgRow};
use sqlx::sqlite::{SqlitePool, SqliteRow};
use sqlx::{AssertSqlSafe, Decode, Encode, Postgres, Row as _, Sqlite, Type};

use super::DbError;
use super::dialect::Dialect;
use crate::jobs::store::corrupt;

/// A pool of connections to the job database.
#[derive(Clone, Debug)]
pub(crate) enum Pool {
    Sqlite(SqlitePool),
    Postgres(PgPool),
}

impl Pool {
    pub(crate) fn dialect(&self) -> Dialect {
        match self {
            Pool::Sqlite(_) => Dialect::Sqlite,
            Pool::Postgres(_) => Dialect::Postgres,
        }
    }

    /// Begin a transaction that writes. On SQLite it takes the write lock at its start (`BEGIN
    /// IMMEDIATE`): a deferred transaction that reads and then writes fails at once with `SQLITE_BUSY` when
    /// another connection wrote in between (WAL cannot upgrade a stale read snapshot, and the busy timeout
    /// does not apply); an immediate one waits for the lock within the busy timeout instead.
    pub(crate) async fn begin(&self) -> Result<Tx, sqlx::Error> {
        Ok(match self {
            Pool::Sqlite(p) => Tx::Sqlite(p.begin_with("BEGIN IMMEDIATE").await?),
            Pool::Postgres(p) => Tx::Postgres(p.begin().await?),
        })
    }
}

/// A transaction on the job database (rolled back when dropped uncommitted).
pub(crate) enum Tx {
    Sqlite(sqlx::Transaction<'static, Sqlite>),
    Postgres(sqlx::Transaction<'static, Postgres>),
}

impl Tx {
    pub(crate) async fn commit(self) -> Result<(), sqlx::Error> {
        match self {
            Tx::Sqlite(t) => t.commit().await,
            Tx::Postgres(t) => t.commit().await,
        }
    }

    pub(crate) async fn rollback(self) -> Result<(), sqlx::Error> {
        match self {
            Tx::Sqlite(t) => t.rollback().await,
            Tx::Postgres(t) => t.rollback().await,
        }
    }

    pub(crate) fn dialect(&self) -> Dialect {
        match self {
            Tx::Sqlite(_) => Dialect::Sqlite,
            Tx::Postgres(_) => Dialect::Postgres,
        }
    }

    /// Hold the transaction-level lock `key` to the end of this transaction, so that transactions of
    /// several processes taking it run one after the other. PostgreSQL: an advisory lock; SQLite: nothing
    /// more than the write lock every transaction here already holds (see [`Pool::begin`]).
    pub(crate) async fn lock(&mut self, key: i64) -> Result<(), sqlx::Error> {
        if self.dialect() == Dialect::Postgres {
            query("SELECT pg_advisory_xact_lock($1)")
                .bind(key)
                .execute(&mut *self)
                .await?;
        }
        Ok(())
    }

    /// Announce `payload` on `channel` when this transaction commits (see [`notify`]).
    pub(crate) async fn notify(&mut self, channel: &str, payload: &str) -> Result<(), sqlx::Error> {
        notify(self, channel, payload).await
    }
}

/// Announce `payload` on `channel` to the processes listening on a shared database (PostgreSQL's `NOTIFY`;
/// inside a transaction it is delivered once, when the transaction commits). SQLite has one process, which
/// needs no announcement: nothing.
pub(crate) async fn notify<'a>(
    on: impl Into<Target<'a>>,
    channel: &str,
    payload: &str,
) -> Result<(), sqlx::Error> {
    let on = on.into();
    let dialect = match &on {
        Target::Pool(p) => p.dialect(),
        Target::Tx(t) => t.dialect(),
    };
    if dialect == Dialect::Postgres {
        query("SELECT pg_notify($1, $2)")
            .bind(channel)
            .bind(payload)
            .execute(on)
            .await?;
    }
    Ok(())
}

/// A row of either database; columns are read by name.
pub(crate) enum Row {
    Sqlite(SqliteRow),
    Postgres(PgRow),
}

/// A Rust type both drivers read from a column.
pub(crate) trait Column:
    for<'r> Decode<'r, Sqlite> + Type<Sqlite> + for<'r> Decode<'r, Postgres> + Type<Postgres>
{
}

impl<T> Column for T where
    T: for<'r> Decode<'r, Sqlite> + Type<Sqlite> + for<'r> Decode<'r, Postgres> + Type<Postgres>
{
}

impl Row {
    pub(crate) fn try_get<T: Column>(&self, column: &str) -> Result<T, sqlx::Error> {
        match self {
            Row::Sqlite(r) => r.try_get(column),
            Row::Postgres(r) => r.try_get(column),
        }
    }

    /// The text of `column` read by `parse` (an id's); a value it refuses makes this a corrupt row of
    /// `table`.
    pub(crate) fn parsed<T, E: ToString>(
        &self,
        column: &str,
        table: &'static str,
        parse: impl FnOnce(&str) -> Result<T, E>,
    ) -> Result<T, DbError> {
        let text: String = self.try_get(column)?;
        parse(&text).map_err(|e| corrupt(table, e))
    }
}

/// A value bound to a parameter.
#[derive(Debug, Clone)]
pub(crate) enum Value {
    Bool(bool),
    Int(Option<i64>),
    Text(Option<String>),
}

impl From<bool> for Value {
    fn from(v: bool) -> Self {
        Value::Bool(v)
    }
}

impl From<i64> for Value {
    fn from(v: i64) -> Self {
        Value::Int(Some(v))
    }
}

impl From<Option<i64>> for Value {
    fn from(v: Option<i64>) -> Self {
        Value::Int(v)
    }
}

impl From<String> for Value {
    fn from(v: String) -> Self {
        Value::Text(Some(v))
    }
}

impl From<&String> for Value {
    fn from(v: &String) -> Self {
        Value::Text(Some(v.clone()))
    }
}

impl From<&str> for Value {
    fn from(v: &str) -> Self {
        Value::Text(Some(v.to_string()))
    }
}

impl From<&Option<String>> for Value {
    fn from(v: &Option<String>) -> Self {
        Value::Text(v.clone())
    }
}

impl From<Option<String>> for Value {
    fn from(v: Option<String>) -> Self {
        Value::Text(v)
    }
}

impl From<Option<&String>> for Value {
    fn from(v: Option<&String>) -> Self {
        Value::Text(v.cloned())
    }
}

impl From<Option<&str>> for Value {
    fn from(v: Option<&str>) -> Self {
        Value::Text(v.map(str::to_string))
    }
}

/// Where a query runs: on a connection of the pool, or inside a transaction.
pub(crate) enum Target<'a> {
    Pool(&'a Pool),
    Tx(&'a mut Tx),
}

impl<'a> From<&'a Pool> for Target<'a> {
    fn from(p: &'a Pool) -> Self {
        Target::Pool(p)
    }
}

impl<'a> From<&'a mut Tx> for Target<'a> {
    fn from(t: &'a mut Tx) -> Self {
        Target::Tx(t)
    }
}

/// What a statement did.
pub(crate) struct Done(u64);

impl Done {
    pub(crate) fn rows_affected(&self) -> u64 {
        self.0
    }
}

/// A statement and the values of its `$n` parameters, in order.
pub(crate) struct Query {
    sql: Sql,
    values: Vec<Value>,
}

/// The text of a statement: fixed, or assembled from fixed fragments only (every value is bound).
enum Sql {
    Fixed(&'static str),
    Assembled(String),
}

/// A statement of fixed text.
pub(crate) fn query(sql: &'static str) -> Query {
    Query {
        sql: Sql::Fixed(sql),
        values: Vec::new(),
    }
}

/// A statement assembled from fixed fragments (a dialect's, a list of placeholders): no value is ever
/// part of `sql`.
pub(crate) fn assembled(sql: String) -> Query {
    Query {
        sql: Sql::Assembled(sql),
        values: Vec::new(),
    }
}

type SqliteQuery = sqlx::query::Query<'static, Sqlite, <Sqlite as sqlx::Database>::Arguments>;
type PgQuery = sqlx::query::Query<'static, Postgres, <Postgres as sqlx::Database>::Arguments>;

impl Query {
    pub(crate) fn bind(mut self, value: impl Into<Value>) -> Self {
        self.values.push(value.into());
        self
    }

    fn sqlite(self) -> SqliteQuery {
        self.on()
    }

    fn postgres(self) -> PgQuery {
        self.on()
    }

    /// The statement with its values bound, for the driver of `DB`.
    fn on<DB>(self) -> sqlx::query::Query<'static, DB, DB::Arguments>
    where
        DB: sqlx::Database,
        for<'q> bool: Encode<'q, DB> + Type<DB>,
        for<'q> Option<i64>: Encode<'q, DB> + Type<DB>,
        for<'q> Option<String>: Encode<'q, DB> + Type<DB>,
    {
        let mut q = match self.sql {
            Sql::Fixed(s) => sqlx::query(s),
            Sql::Assembled(s) => sqlx::query(AssertSqlSafe(s)),
        };
        for v in self.values {
            q = match v {
                Value::Bool(b) => q.bind(b),
                Value::Int(i) => q.bind(i),
                Value::Text(t) => q.bind(t),
            };
        }
        q
    }

    pub(crate) async fn execute<'a>(self, on: impl Into<Target<'a>>) -> Result<Done, sqlx::Error> {
        let affected = match on.into() {
            Target::Pool(Pool::Sqlite(p)) => self.sqlite().execute(p).await?.rows_affected(),
            Target::Pool(Pool::Postgres(p)) => self.postgres().execute(p).await?.rows_affected(),
            Target::Tx(Tx::Sqlite(t)) => self.sqlite().execute(&mut **t).await?.rows_affected(),
            Target::Tx(Tx::Postgres(t)) => self.postgres().execute(&mut **t).await?.rows_affected(),
        };
        Ok(Done(affected))
    }

    pub(crate) async fn fetch_all<'a>(
        self,
        on: impl Into<Target<'a>>,
    ) -> Result<Vec<Row>, sqlx::Error> {
        Ok(match on.into() {
            Target::Pool(Pool::Sqlite(p)) => sqlite_rows(self.sqlite().fetch_all(p).await?),
            Target::Pool(Pool::Postgres(p)) => pg_rows(self.postgres().fetch_all(p).await?),
            Target::Tx(Tx::Sqlite(t)) => sqlite_rows(self.sqlite().fetch_all(&mut **t).await?),
            Target::Tx(Tx::Postgres(t)) => pg_rows(self.postgres().fetch_all(&mut **t).await?),
        })
    }

    pub(crate) async fn fetch_optional<'a>(
        self,
        on: impl Into<Target<'a>>,
    ) -> Result<Option<Row>, sqlx::Error> {
        Ok(match on.into() {
            Target::Pool(Pool::Sqlite(p)) => {
                self.sqlite().fetch_optional(p).await?.map(Row::Sqlite)
            }
            Target::Pool(Pool::Postgres(p)) => {
                self.postgres().fetch_optional(p).await?.map(Row::Postgres)
            }
            Target::Tx(Tx::Sqlite(t)) => self
                .sqlite()
                .fetch_optional(&mut **t)
                .await?
                .map(Row::Sqlite),
            Target::Tx(Tx::Postgres(t)) => self
                .postgres()
                .fetch_optional(&mut **t)
                .await?
                .map(Row::Postgres),
        })
    }

    pub(crate) async fn fetch_one<'a>(self, on: impl Into<Target<'a>>) -> Result<Row, sqlx::Error> {
        self.fetch_optional(on)
            .await?
            .ok_or(sqlx::Error::RowNotFound)
    }
}

fn sqlite_rows(rows: Vec<SqliteRow>) -> Vec<Row> {
    rows.into_iter().map(Row::Sqlite).collect()
}

fn pg_rows(rows: Vec<PgRow>) -> Vec<Row> {
    rows.into_iter().map(Row::Postgres).collect()
}
