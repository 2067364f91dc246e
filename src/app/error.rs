//! Errors of the application layer: a refusal with a catalogue code (the client's input, or a state that
//! does not allow the command), or a failure of a port (database, storage), which front doors answer as an
//! internal error after logging it once.

use crate::error_code::{ErrorCode, Problem, json_pointer};
use crate::jobs::DbError;

/// Why a command or query did not succeed.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// Refused, with a stable catalogue code (4xx, or a job's own recorded problem).
    #[error(transparent)]
    Refused(Problem),
    /// The job database failed.
    #[error("database: {0}")]
    Db(#[from] DbError),
    /// The blob store failed.
    #[error("storage: {0}")]
    Storage(#[from] std::io::Error),
}

pub type AppResult<T> = Result<T, AppError>;

impl From<Problem> for AppError {
    fn from(p: Problem) -> Self {
        AppError::Refused(p)
    }
}

/// Shorthand for a refusal with `code` and `detail`.
pub fn refused(code: ErrorCode, detail: impl Into<String>) -> AppError {
    AppError::Refused(Problem::new(code, detail))
}

impl AppError {
    /// The problem a client sees: refusals as they are; port failures logged here (once) and answered as
    /// `internal`, without their detail.
    pub fn into_problem(self) -> Problem {
        match self {
            AppError::Refused(p) => p,
            AppError::Db(e) => {
                tracing::error!(error = %e, "database error");
                Problem::internal()
            }
            AppError::Storage(e) => {
                tracing::error!(error = %e, "storage error");
                Problem::internal()
            }
        }
    }
}

/// Deserialise a request body into `T`; a mismatch is `invalid_request` naming the field (a JSON Pointer
/// into the body: the field itself for a wrong value, the object for a missing or unknown field).
pub fn parse_body<T: serde::de::DeserializeOwned>(v: serde_json::Value) -> Result<T, Problem> {
    serde_path_to_error::deserialize(v).map_err(|e| {
        use serde_path_to_error::Segment;
        let mut segments: Vec<String> = Vec::new();
        for s in e.path().iter() {
            match s {
                Segment::Seq { index } => segments.push(index.to_string()),
                Segment::Map { key } => segments.push(key.clone()),
                Segment::Enum { .. } => {}
                Segment::Unknown => break,
            }
        }
        let pointer = json_pointer("", segments.iter().map(String::as_str));
        Problem::new(ErrorCode::InvalidRequest, e.into_inner().to_string()).at(pointer)
    })
}
