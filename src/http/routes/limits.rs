//! `GET /v1/limits`: the bounds the API checks at submission (see `app::limits`).

use axum::extract::State;
use axum::response::{IntoResponse, Response};

use super::super::AppState;
use crate::app::limits::ApiLimits;

pub async fn get_limits(State(st): State<AppState>) -> Response {
    axum::Json(ApiLimits::of(&st.settings)).into_response()
}
