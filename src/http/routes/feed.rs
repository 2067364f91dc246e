//! `GET /v1/events`: Server-Sent Events of every job, on one connection.
//!
//! Events: `created` (the job's summary, as `GET /v1/jobs` lists it), `status` and `progress` (the job's
//! id, status, progress and stage, as the per-job stream sends them), `deleted` (`{"id"}`), and `resync`
//! (events were lost: reload the list, then keep reading). A new connection first gets `ready`; a client
//! that opens the stream, waits for `ready` and then loads the list misses nothing. Every event but
//! `resync` carries an id; reconnecting with `Last-Event-ID` resumes after it while the server still holds
//! it (the newest `FEED_CAPACITY` events of this process), and gets `resync` otherwise. A comment line is
//! sent every [`HEARTBEAT`] so that proxies keep the connection open. Each connection holds a cursor into
//! the shared ring and a channel of [`QUEUE`] events: a slow client costs no more memory, and one that
//! falls behind the ring gets `resync`. `?seconds=N` ends the stream after N seconds (for scripts that watch
//! for a while and move on; `0` sends `ready` alone); without it the stream stays open.

use std::convert::Infallible;
use std::time::Duration;

use axum::extract::State;
use axum::http::HeaderMap;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::json;
use tokio::sync::mpsc;

use super::super::AppState;
use super::super::extract::ApiQuery;
use super::super::problem::{ApiResult, api_error};
use super::jobs::summary_json;
use crate::app::feed::{Feed, FeedItem, Since};
use crate::error_code::ErrorCode;

/// Time between heartbeat comments.
pub const HEARTBEAT: Duration = Duration::from_secs(15);
/// Events queued per connection before the reader waits for the client.
const QUEUE: usize = 32;
/// Events read from the ring at a time.
const BATCH: usize = 64;
/// The longest `?seconds=` a stream may be asked to last (a day).
pub const MAX_SECONDS: u32 = 86_400;

/// The query of `GET /v1/events`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EventsQuery {
    /// End the stream after this many seconds (0 to [`MAX_SECONDS`]; the first event is always sent);
    /// without it the stream stays open.
    seconds: Option<u32>,
}

fn event(feed: &Feed, seq: u64, item: &FeedItem) -> Event {
    let (name, data) = match item {
        FeedItem::Created(s) => ("created", summary_json(s)),
        FeedItem::Status(e) => ("status", serde_json::to_value(e).unwrap_or_default()),
        FeedItem::Progress(e) => ("progress", serde_json::to_value(e).unwrap_or_default()),
        FeedItem::Deleted(id) => ("deleted", json!({ "id": id })),
        FeedItem::Resync => ("resync", json!({ "reason": "events were lost" })),
    };
    let e = Event::default()
        .event(name)
        .json_data(data)
        .unwrap_or_default();
    if matches!(item, FeedItem::Resync) {
        e
    } else {
        e.id(feed.event_id(seq))
    }
}

pub async fn all_events(
    State(st): State<AppState>,
    ApiQuery(q): ApiQuery<EventsQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let deadline = match q.seconds {
        None => None,
        Some(s @ 0..=MAX_SECONDS) => {
            Some(tokio::time::Instant::now() + Duration::from_secs(u64::from(s)))
        }
        Some(s) => {
            return Err(api_error(
                ErrorCode::InvalidQuery,
                format!("seconds must be 0 to {MAX_SECONDS} (a day), not {s}"),
            ));
        }
    };
    let feed = st.feed.clone();
    let last = headers
        .get("last-event-id")
        .and_then(|v| v.to_str().ok())
        .map(|id| feed.seq_of(id));
    let (tx, rx) = mpsc::channel::<Event>(QUEUE);
    tokio::spawn(follow(st, feed, last, deadline, tx));
    let stream = futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|e| (Ok::<_, Infallible>(e), rx))
    });
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(HEARTBEAT).text("heartbeat"))
        .into_response())
}

/// Send the feed from `last` (`None`: a new connection; `Some(None)`: an id this process does not know)
/// until `deadline`, if any; returning drops the sender, which ends the stream.
async fn follow(
    st: AppState,
    feed: Feed,
    last: Option<Option<u64>>,
    deadline: Option<tokio::time::Instant>,
    tx: mpsc::Sender<Event>,
) {
    // Watch before reading the position, so that no event falls between the two.
    let mut changed = feed.watch();
    let mut cursor = feed.latest();
    let first = match last {
        None => Event::default()
            .event("ready")
            .id(feed.event_id(cursor))
            .json_data(json!({ "latest": feed.event_id(cursor) }))
            .unwrap_or_default(),
        Some(Some(seq)) => {
            cursor = seq;
            Event::default().comment("resuming")
        }
        Some(None) => event(&feed, cursor, &FeedItem::Resync),
    };
    if tx.send(first).await.is_err() {
        return;
    }
    let mut shutdown = st.shutdown.clone();
    let past =
        |d: Option<tokio::time::Instant>| d.is_some_and(|d| tokio::time::Instant::now() >= d);
    let until = async {
        match deadline {
            Some(d) => tokio::time::sleep_until(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::pin!(until);
    loop {
        if past(deadline) {
            return;
        }
        match feed.since(cursor, BATCH) {
            Since::Gone => {
                cursor = feed.latest();
                if tx
                    .send(event(&feed, cursor, &FeedItem::Resync))
                    .await
                    .is_err()
                {
                    return;
                }
            }
            Since::Items(items) if items.is_empty() => {
                tokio::select! {
                    r = changed.changed() => if r.is_err() { return },
                    _ = shutdown.changed() => return,
                    _ = tx.closed() => return,
                    _ = &mut until => return,
                }
            }
            Since::Items(items) => {
                for (seq, item) in &items {
                    if tx.send(event(&feed, *seq, item)).await.is_err() {
                        return;
                    }
                    cursor = *seq;
                }
            }
        }
    }
}
