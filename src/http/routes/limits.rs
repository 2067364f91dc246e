//! `GET /v1/limits`: the bounds the API checks at submission (see `app::limits`); `GET /v1/protocols`: the
//! shipped volume protocols (see `app::protocols`). What clients build their forms and presets from.

use axum::extract::State;
use axum::response::{IntoResponse, Response};

use super::super::AppState;
use crate::app::limits::ApiLimits;
use crate::app::protocols;

pub async fn get_limits(State(st): State<AppState>) -> Response {
    axum::Json(ApiLimits::of(&st.settings)).into_response()
}

pub async fn get_protocols() -> Response {
    axum::Json(protocols::shipped()).into_response()
}
