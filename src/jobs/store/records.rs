//! What both job database adapters answer besides jobs: their error, the outcomes of upload and deletion
//! commands, and the row helpers they share.

/// A database failure (logged; answered as a 500 without detail).
#[derive(Debug, thiserror::Error)]
pub enum DbError {
    #[error(transparent)]
    Sql(#[from] sqlx::Error),
    #[error(transparent)]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("corrupt row in {table}: {reason}")]
    Corrupt { table: &'static str, reason: String },
    /// The database server could not be reached at start (`target`: the URL without its password).
    #[error("cannot connect to {target}: {reason}")]
    Unreachable { target: String, reason: String },
}

/// Outcome of appending an instance to an open upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Appended {
    /// Added; the upload now holds this many instances.
    Added(u32),
    /// The same bytes were already appended (nothing changed).
    Duplicate(u32),
    /// The upload is completed.
    Closed,
    NotFound,
    /// The upload would exceed this many bytes.
    TooLarge(u64),
}

/// Outcome of deleting an open upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UploadDeleted {
    /// The upload and its instance rows are gone.
    Done,
    /// The upload is completed: it goes with its series, not by itself.
    Completed,
    NotFound,
}

/// Outcome of completing an upload.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Completed {
    Done,
    /// Completed by someone else, or unknown.
    Closed,
    /// Instances were appended while the series were assembled.
    Changed,
}

/// Outcome of deleting a series or a dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Deleted {
    Done,
    /// A queued or running job reads it.
    InUse,
    NotFound,
}

/// A job summary's product indexes, as both backends aggregate them: comma-separated, in product order.
pub(crate) fn product_indexes(list: Option<&str>) -> Result<Vec<usize>, DbError> {
    list.iter()
        .flat_map(|p| p.split(','))
        .map(|i| {
            i.trim()
                .parse::<usize>()
                .map_err(|e| corrupt("jobs", format!("product index {i}: {e}")))
        })
        .collect()
}

pub(crate) fn corrupt(table: &'static str, reason: impl ToString) -> DbError {
    DbError::Corrupt {
        table,
        reason: reason.to_string(),
    }
}

pub(crate) fn to_json<T: serde::Serialize>(v: &T) -> String {
    serde_json::to_string(v).unwrap_or_else(|_| "null".into())
}
