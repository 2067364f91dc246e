//! The HTTP layer: the only module that imports axum (router, extractors, errors, routes).
//!
//! [`Application::build`] opens the application ([`App::open`]: data directory, database, recovery,
//! engine) and binds the listener (port 0 picks a free port: tests run the real server);
//! [`Application::run_until`] serves (`serve`: connection caps and timeouts) until the shutdown signal, then
//! lets open requests finish for at most the drain timeout. Routes extract, call the application layer and
//! map its answers to responses.

pub mod activity;
pub mod auth;
pub mod connections;
pub mod drain;
pub mod extract;
pub mod files;
pub mod lists;
pub mod problem;
pub mod progress;
pub mod routes;
pub mod serve;
pub mod upload;
pub mod web;

pub use serve::shutdown_signal;

use std::future::Future;
use std::net::SocketAddr;
use std::ops::Deref;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::error_handling::HandleErrorLayer;
use axum::extract::{DefaultBodyLimit, MatchedPath, Request};
use axum::http::{HeaderName, HeaderValue, Method, header};
use axum::middleware::{self, Next};
use axum::response::Response;
use axum::routing::{get, post};
use axum::{BoxError, Router};
use futures_util::FutureExt;
use metrics_exporter_prometheus::PrometheusHandle;
use tokio::sync::{oneshot, watch};
use tokio_util::sync::CancellationToken;
use tower::ServiceBuilder;
use tower_http::catch_panic::CatchPanicLayer;
use tower_http::cors::{AllowOrigin, CorsLayer};
use tower_http::request_id::{MakeRequestUuid, PropagateRequestIdLayer, SetRequestIdLayer};
use tower_http::trace::TraceLayer;

use crate::app::{App, OpenError};
use crate::config::Settings;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::Engine;
use crate::telemetry::{metrics_handle, names};
use problem::{ApiError, api_error, problem_response};
use routes::{
    datasets, dicomweb, events, feed, health, jobs, limits, results, rules, scans, series, stow,
    uploads,
};

/// What every handler can reach: the application (and, through it, `db`, `store`, `engine`, `settings`)
/// and what only the HTTP layer needs.
pub struct Shared {
    pub app: App,
    pub metrics: PrometheusHandle,
    /// Turns true when the server shuts down (ends event streams).
    pub shutdown: watch::Receiver<bool>,
    /// Rendered job lists, reused until a job is written.
    pub lists: lists::ListCache,
}

/// Handler state; cheap to clone.
#[derive(Clone)]
pub struct AppState(Arc<Shared>);

impl Deref for AppState {
    type Target = Shared;
    fn deref(&self) -> &Shared {
        &self.0
    }
}

impl Deref for Shared {
    type Target = App;
    fn deref(&self) -> &App {
        &self.app
    }
}

/// Why the service could not start.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error(transparent)]
    App(#[from] OpenError),
    #[error("binding {addr}: {source}")]
    Bind {
        addr: SocketAddr,
        source: std::io::Error,
    },
}

/// The least time running jobs get to hand themselves back at shutdown (a job checks for cancellation
/// at least once a second).
pub const HAND_BACK_MIN: Duration = Duration::from_secs(3);

/// A built service, bound and ready to serve.
pub struct Application {
    app: App,
    listener: tokio::net::TcpListener,
    router: Router,
    shutdown: watch::Sender<bool>,
    addr: SocketAddr,
    drain_timeout: Duration,
    connections: serve::Options,
    engine: Engine,
}

async fn not_found() -> ApiError {
    api_error(ErrorCode::NotFound, "no such route; see /openapi.yaml")
}

async fn method_not_allowed() -> ApiError {
    api_error(
        ErrorCode::MethodNotAllowed,
        "this method is not allowed here; see /openapi.yaml",
    )
}

async fn timed_out(_: BoxError) -> ApiError {
    api_error(ErrorCode::RequestTimeout, "the request took too long")
}

/// Count requests by route and status, and time them.
async fn track(req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str().to_owned())
        .unwrap_or_else(|| "unmatched".into());
    let method = req.method().to_string();
    let start = Instant::now();
    let resp = next.run(req).await;
    let status = resp.status().as_u16().to_string();
    metrics::counter!(names::HTTP_REQUESTS, "method" => method, "route" => route.clone(), "status" => status)
        .increment(1);
    metrics::histogram!(names::HTTP_DURATION, "route" => route)
        .record(start.elapsed().as_secs_f64());
    resp
}

fn cors(origins: &[String]) -> Option<CorsLayer> {
    if origins.is_empty() {
        return None;
    }
    let list: Vec<HeaderValue> = origins.iter().filter_map(|o| o.parse().ok()).collect();
    Some(
        CorsLayer::new()
            .allow_origin(AllowOrigin::list(list))
            .allow_methods([Method::GET, Method::POST, Method::DELETE])
            .allow_headers([
                header::AUTHORIZATION,
                header::CONTENT_TYPE,
                header::RANGE,
                header::IF_NONE_MATCH,
                HeaderName::from_static("idempotency-key"),
                HeaderName::from_static("x-ctrecon-geometry"),
                HeaderName::from_static("last-event-id"),
            ])
            .expose_headers([
                header::LOCATION,
                header::ETAG,
                header::CONTENT_RANGE,
                HeaderName::from_static("x-request-id"),
                HeaderName::from_static(routes::results::WARNINGS),
            ]),
    )
}

/// What a process serves on its HTTP port.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The API (and, unless `max_concurrent_jobs` is 0, the jobs): `ctrecon serve`.
    Api,
    /// Jobs only: `/healthz`, `/readyz` and `/metrics` on a small port, no API (`ctrecon worker`).
    Worker,
}

/// The routes of a `ctrecon worker`'s port: liveness, readiness and metrics, under the same tokens.
pub fn worker_router(state: AppState, tokens: auth::Tokens) -> Router {
    Router::new()
        .route("/healthz", get(health::healthz))
        .route("/readyz", get(health::readyz))
        .route("/metrics", get(health::metrics))
        .fallback(not_found)
        .with_state(state)
        .layer(middleware::from_fn(track))
        .layer(middleware::from_fn_with_state(tokens, auth::require_token))
        .layer(TraceLayer::new_for_http().make_span_with(|req: &Request| {
            tracing::info_span!("request", method = %req.method(), path = %req.uri().path())
        }))
}

/// The DICOMweb routes but STOW-RS (which is an upload).
fn dicomweb_routes() -> Router<AppState> {
    use dicomweb as d;
    Router::new()
        .route("/dicom-web/studies", get(d::search_studies))
        .route("/dicom-web/series", get(d::search_all_series))
        .route("/dicom-web/instances", get(d::search_all_instances))
        .route("/dicom-web/studies/{study}", get(d::retrieve_study))
        .route("/dicom-web/studies/{study}/metadata", get(d::study_metadata))
        .route("/dicom-web/studies/{study}/series", get(d::search_series))
        .route(
            "/dicom-web/studies/{study}/instances",
            get(d::search_study_instances),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}",
            get(d::retrieve_series),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/metadata",
            get(d::series_metadata),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/instances",
            get(d::search_instances),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/instances/{instance}",
            get(d::retrieve_instance),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/instances/{instance}/metadata",
            get(d::instance_metadata),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/instances/{instance}/rendered",
            get(d::instance_rendered),
        )
        .route(
            "/dicom-web/studies/{study}/series/{series}/instances/{instance}/frames/{frame}/rendered",
            get(d::frame_rendered),
        )
}

/// The router with every route and layer.
pub fn router(state: AppState, tokens: auth::Tokens) -> Router {
    let s = &state.settings;
    let request_timeout = Duration::from_secs(s.request_timeout_secs);
    let upload_timeout = Duration::from_secs(s.upload_timeout_secs);
    let timeout = |d: Duration| {
        ServiceBuilder::new()
            .layer(HandleErrorLayer::new(timed_out))
            .layer(tower::timeout::TimeoutLayer::new(d))
    };
    let api = Router::new()
        .route("/healthz", get(health::healthz))
        .route("/readyz", get(health::readyz))
        .route("/metrics", get(health::metrics))
        .route("/openapi.yaml", get(health::openapi))
        .route(
            "/v1/datasets/{id}",
            get(datasets::get_dataset).delete(datasets::delete_dataset),
        )
        .route("/v1/limits", get(limits::get_limits))
        .route("/v1/protocols", get(limits::get_protocols))
        .route("/v1/jobs", post(jobs::post_job).get(jobs::list_jobs))
        .route("/v1/jobs/{id}", get(jobs::get_job).delete(jobs::delete_job))
        .route("/v1/jobs/{id}/cancel", post(jobs::cancel_job))
        .route("/v1/jobs/{id}/result/volume.npy", get(results::volume))
        .route("/v1/jobs/{id}/result/slice", get(results::slice))
        .route("/v1/jobs/{id}/result/projection", get(results::projection))
        .route("/v1/jobs/{id}/result/mesh.stl", get(results::mesh))
        .route("/v1/jobs/{id}/result/series.zip", get(results::series_zip))
        .route(
            "/v1/jobs/{id}/result/products/{index}",
            get(results::product),
        )
        .route(
            "/v1/uploads/{id}",
            get(uploads::get_upload).delete(uploads::delete_upload),
        )
        .route(
            "/v1/series/{id}",
            get(series::get_series).delete(series::delete_series),
        )
        .route("/v1/series/{id}/volume.npy", get(series::series_volume))
        .route("/v1/jobs/{id}/result/metrics", get(results::metrics))
        .route("/v1/rules", post(rules::post_rule).get(rules::list_rules))
        .route(
            "/v1/rules/{name}",
            get(rules::get_rule)
                .put(rules::put_rule)
                .delete(rules::delete_rule),
        )
        .route(
            "/v1/deliveries",
            get(rules::list_deliveries).post(rules::post_delivery),
        )
        .route("/v1/deliveries/{id}", get(rules::get_delivery))
        .route("/v1/deliveries/{id}/retry", post(rules::retry_delivery))
        .route("/v1/peers", get(rules::list_peers))
        .route("/v1/peers/{ae_title}/echo", post(rules::echo_peer))
        .merge(dicomweb_routes())
        .layer(DefaultBodyLimit::max(s.max_json_bytes))
        .layer(timeout(request_timeout));
    let simulations = Router::new()
        .route("/v1/simulations", post(datasets::post_simulation))
        .layer(DefaultBodyLimit::max(s.max_json_bytes))
        .layer(timeout(upload_timeout));
    let uploads = Router::new()
        .route("/v1/sinograms", post(datasets::post_sinogram))
        .route("/v1/scans", post(scans::post_scan))
        .route("/v1/series", post(uploads::post_series))
        .route("/v1/uploads/{id}/complete", post(uploads::complete_upload))
        .route("/dicom-web/studies", post(stow::store_instances))
        .route(
            "/dicom-web/studies/{study}",
            post(stow::store_study_instances),
        )
        .layer(DefaultBodyLimit::disable())
        .layer(middleware::from_fn_with_state(
            progress::ProgressRule::from_settings(s),
            progress::require_progress,
        ))
        .layer(timeout(upload_timeout));
    let streams = Router::new()
        .route("/v1/jobs/{id}/events", get(events::job_events))
        .route("/v1/events", get(feed::all_events));
    let cors = cors(&s.cors_origins);
    let app = api
        .merge(simulations)
        .merge(uploads)
        .merge(streams)
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .with_state(state)
        .layer(middleware::from_fn(track))
        .layer(middleware::from_fn_with_state(tokens, auth::require_token))
        .merge(web::router())
        .layer(CatchPanicLayer::custom(|_| {
            tracing::error!("a request handler panicked");
            problem_response(&Problem::internal())
        }))
        .layer(
            TraceLayer::new_for_http().make_span_with(|req: &Request| {
                let id = req
                    .headers()
                    .get("x-request-id")
                    .and_then(|v| v.to_str().ok())
                    .unwrap_or("");
                tracing::info_span!("request", method = %req.method(), path = %req.uri().path(), request_id = %id)
            }),
        )
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(SetRequestIdLayer::x_request_id(MakeRequestUuid));
    match cors {
        Some(c) => app.layer(c),
        None => app,
    }
}

impl Application {
    /// Open the application (settings, storage, database, recovery, engine), then bind.
    pub async fn build(settings: Settings) -> Result<Self, BuildError> {
        Self::build_as(settings, Role::Api).await
    }

    /// [`Application::build`] for `role`: a worker binds `settings.bind` for its health routes only and
    /// leaves retention to the API processes.
    pub async fn build_as(settings: Settings, role: Role) -> Result<Self, BuildError> {
        let app = App::open(settings).await?;
        let metrics = metrics_handle();
        let settings = &app.settings;
        let listener = tokio::net::TcpListener::bind(settings.bind)
            .await
            .map_err(|source| BuildError::Bind {
                addr: settings.bind,
                source,
            })?;
        let addr = listener.local_addr().map_err(|source| BuildError::Bind {
            addr: settings.bind,
            source,
        })?;
        let (shutdown, shutdown_rx) = watch::channel(false);
        if role == Role::Api {
            app.spawn_retention(shutdown_rx.clone());
        }
        let drain_timeout = Duration::from_millis(settings.drain_timeout_ms);
        let connections = serve::Options::from_settings(settings);
        let tokens = auth::Tokens::from_settings(settings);
        let engine = app.engine.clone();
        let state = AppState(Arc::new(Shared {
            app,
            metrics,
            shutdown: shutdown_rx,
            lists: Default::default(),
        }));
        Ok(Self {
            app: state.app.clone(),
            listener,
            router: match role {
                Role::Api => router(state, tokens),
                Role::Worker => worker_router(state, tokens),
            },
            shutdown,
            addr,
            drain_timeout,
            connections,
            engine,
        })
    }

    /// The bound address (with the real port when the settings asked for port 0).
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The application behind the routes (for the other front doors started beside them).
    pub fn app(&self) -> &App {
        &self.app
    }

    /// Serve until `signal` completes, then stop accepting, end event streams and let open requests
    /// finish; connections still open after the drain timeout are closed (a client reading a large body
    /// slowly cannot hold the shutdown up). At the signal the engine starts no more jobs and asks the running
    /// ones to stop; those that stop in time (the drain timeout, at least [`HAND_BACK_MIN`]) go back to the
    /// queue without spending an attempt.
    pub async fn run_until(
        self,
        signal: impl Future<Output = ()> + Send + 'static,
    ) -> std::io::Result<()> {
        let shutdown = self.shutdown;
        let drain = self.drain_timeout;
        let engine = self.engine;
        let stopping = engine.clone();
        let cut = CancellationToken::new();
        let (began, signalled) = oneshot::channel::<tokio::time::Instant>();
        let signalled = signalled.shared();
        let serve = serve::serve(
            self.listener,
            self.router,
            self.connections,
            cut.clone(),
            async move {
                signal.await;
                tracing::info!(drain_ms = drain.as_millis() as u64, "shutting down");
                let _ = shutdown.send(true);
                stopping.begin_stop();
                let _ = began.send(tokio::time::Instant::now());
            },
        );
        let deadline = async {
            if signalled.clone().await.is_err() {
                // The server ended without a signal (it failed): nothing to bound.
                return std::future::pending::<()>().await;
            }
            tokio::time::sleep(drain).await;
            tracing::warn!("drain timeout: closing the connections still open");
            cut.cancel();
            // Every cut connection fails at its next poll; this only bounds one that is never polled.
            tokio::time::sleep(Duration::from_secs(1)).await;
        };
        let served = tokio::select! {
            r = serve => r,
            _ = deadline => Ok(()),
        };
        // Running jobs stop at their next check; wait for their hand-back, bounded from the signal.
        engine.begin_stop();
        let since = signalled
            .await
            .unwrap_or_else(|_| tokio::time::Instant::now());
        let left = engine.stopped(since + drain.max(HAND_BACK_MIN)).await;
        if left > 0 {
            tracing::warn!(
                left,
                "jobs still running at exit: the next start recovers them"
            );
        }
        served
    }
}
