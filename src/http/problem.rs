//! API errors: every failure becomes an RFC 9457 `application/problem+json` response with a catalogue code.

use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use crate::app::AppError;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::DbError;

/// An error answered as a problem response.
#[derive(Debug)]
pub struct ApiError(pub Problem);

pub type ApiResult<T> = Result<T, ApiError>;

/// Shorthand for an [`ApiError`] with `code` and `detail`.
pub fn api_error(code: ErrorCode, detail: impl Into<String>) -> ApiError {
    ApiError(Problem::new(code, detail))
}

impl From<Problem> for ApiError {
    fn from(p: Problem) -> Self {
        ApiError(p)
    }
}

impl From<AppError> for ApiError {
    fn from(e: AppError) -> Self {
        ApiError(e.into_problem())
    }
}

impl From<DbError> for ApiError {
    fn from(e: DbError) -> Self {
        ApiError(crate::app::AppError::Db(e).into_problem())
    }
}

impl From<std::io::Error> for ApiError {
    fn from(e: std::io::Error) -> Self {
        tracing::error!(error = %e, "storage error");
        ApiError(Problem::internal())
    }
}

/// The response of a problem.
pub fn problem_response(p: &Problem) -> Response {
    let status = StatusCode::from_u16(p.code.status()).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
    let body = serde_json::to_vec(p).unwrap_or_default();
    let mut r = (status, body).into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/problem+json"),
    );
    r
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.0.code.status();
        if status >= 500 && !self.0.detail.is_empty() {
            tracing::error!(detail = %self.0.detail, code = self.0.code.code(), "server error");
        } else if status < 500 {
            tracing::info!(status, code = self.0.code.code(), detail = %self.0.detail, "request refused");
        }
        problem_response(&self.0)
    }
}
