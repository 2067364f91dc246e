//! The minimum-progress rule of upload bodies (`POST /v1/series`, `/v1/sinograms`, STOW-RS): a body must
//! deliver at least `upload_min_bytes` in every `upload_progress_window_secs` (each window starts when the
//! previous one's bytes have arrived). A body that falls short is abandoned: the handler sees its stream
//! fail, removes what it spooled as it does for any broken body, and the answer becomes 408
//! `upload_stalled` with `Connection: close`, so that a stalled client holds neither its connection nor a
//! partial file for the whole `upload_timeout_secs` (nginx closes after `client_body_timeout` between two
//! reads; this rule also stops a client trickling a few bytes per window).

use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, BodyDataStream, Bytes};
use axum::extract::{Request, State};
use axum::http::{HeaderValue, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use futures_util::Stream;
use tokio::time::{Instant, Sleep};

use super::problem::api_error;
use crate::error_code::ErrorCode;

/// At least `min_bytes` in every `window`; `min_bytes` 0 is no rule.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ProgressRule {
    pub min_bytes: u64,
    pub window: Duration,
}

impl ProgressRule {
    pub fn from_settings(s: &crate::config::Settings) -> Self {
        Self {
            min_bytes: s.upload_min_bytes,
            window: Duration::from_secs(s.upload_progress_window_secs),
        }
    }
}

/// Why a paced body failed (the stream error the handler sees).
#[derive(Debug, thiserror::Error)]
#[error("the upload delivered fewer than {min_bytes} bytes in {window_secs} s")]
pub struct Stalled {
    min_bytes: u64,
    window_secs: u64,
}

/// A request body held to a [`ProgressRule`].
struct Paced {
    inner: BodyDataStream,
    rule: ProgressRule,
    window_end: Pin<Box<Sleep>>,
    got: u64,
    stalled: Arc<AtomicBool>,
    done: bool,
}

impl Stream for Paced {
    type Item = Result<Bytes, axum::Error>;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        let this = &mut *self;
        if this.done {
            return Poll::Ready(None);
        }
        match Pin::new(&mut this.inner).poll_next(cx) {
            Poll::Ready(Some(Ok(chunk))) => {
                this.got = this.got.saturating_add(chunk.len() as u64);
                if this.got >= this.rule.min_bytes {
                    this.got = 0;
                    let next = Instant::now() + this.rule.window;
                    this.window_end.as_mut().reset(next);
                }
                return Poll::Ready(Some(Ok(chunk)));
            }
            Poll::Ready(other) => {
                this.done = other.is_none();
                return Poll::Ready(other);
            }
            Poll::Pending => {}
        }
        if this.window_end.as_mut().poll(cx).is_ready() {
            this.done = true;
            this.stalled.store(true, Ordering::Release);
            return Poll::Ready(Some(Err(axum::Error::new(Stalled {
                min_bytes: this.rule.min_bytes,
                window_secs: this.rule.window.as_secs(),
            }))));
        }
        Poll::Pending
    }
}

/// Middleware of the upload routes: hold the body to the rule, and answer 408 `upload_stalled` (closing the
/// connection) when it fell short, whatever the handler made of the failed stream.
pub async fn require_progress(
    State(rule): State<ProgressRule>,
    req: Request,
    next: Next,
) -> Response {
    if rule.min_bytes == 0 {
        return next.run(req).await;
    }
    let stalled = Arc::new(AtomicBool::new(false));
    let (parts, body) = req.into_parts();
    let paced = Paced {
        inner: body.into_data_stream(),
        rule,
        window_end: Box::pin(tokio::time::sleep(rule.window)),
        got: 0,
        stalled: stalled.clone(),
        done: false,
    };
    let response = next
        .run(Request::from_parts(parts, Body::from_stream(paced)))
        .await;
    if !stalled.load(Ordering::Acquire) {
        return response;
    }
    let detail = format!(
        "the upload delivered fewer than {} bytes in {} s; it was abandoned",
        rule.min_bytes,
        rule.window.as_secs()
    );
    let mut r = api_error(ErrorCode::UploadStalled, detail).into_response();
    r.headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}
