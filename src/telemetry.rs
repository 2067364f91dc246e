//! Logging, tracing and the Prometheus metrics recorder.
//!
//! Logs are structured `tracing` events (JSON with `CTRECON_LOG_FORMAT=json`, human-readable otherwise),
//! filtered by `RUST_LOG` (default `info`). HTTP requests log in a span carrying the request id, jobs in
//! a span carrying the job id.

use std::sync::OnceLock;

use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle};
use tracing_subscriber::EnvFilter;

/// Install the global tracing subscriber once; later calls (tests) do nothing.
pub fn init_logging(json: bool) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = if json {
        builder.json().flatten_event(true).try_init()
    } else {
        builder.try_init()
    };
}

/// The process-wide Prometheus recorder, installed on first use.
pub fn metrics_handle() -> PrometheusHandle {
    static HANDLE: OnceLock<PrometheusHandle> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let recorder = PrometheusBuilder::new().build_recorder();
            let handle = recorder.handle();
            // Fails only if another recorder was installed first; the handle then renders nothing.
            let _ = metrics::set_global_recorder(recorder);
            handle
        })
        .clone()
}

/// Names of the metrics the service records.
pub mod names {
    pub const HTTP_REQUESTS: &str = "ctrecon_http_requests_total";
    pub const HTTP_DURATION: &str = "ctrecon_http_request_duration_seconds";
    /// HTTP connections open now.
    pub const HTTP_CONNECTIONS: &str = "ctrecon_http_connections";
    /// HTTP connections answered 503 and closed at once, by the `cap` they were over (total, address).
    pub const HTTP_CONNECTIONS_REFUSED: &str = "ctrecon_http_connections_refused_total";
    /// HTTP connections closed by a timeout, by `timeout` (header, idle, send).
    pub const HTTP_CONNECTIONS_TIMED_OUT: &str = "ctrecon_http_connections_timed_out_total";
    pub const JOBS: &str = "ctrecon_jobs";
    pub const QUEUE_DEPTH: &str = "ctrecon_queue_depth";
    pub const JOBS_FINISHED: &str = "ctrecon_jobs_finished_total";
    pub const JOB_DURATION: &str = "ctrecon_job_duration_seconds";
    /// The latest residual an iterative job reported (relative, ‖Ax − b‖ / ‖b‖).
    pub const JOB_RESIDUAL: &str = "ctrecon_job_last_residual";
    /// Bytes the data directory holds, by `kind` (datasets, series, results, uploads).
    pub const STORAGE_BYTES: &str = "ctrecon_storage_bytes";
    /// Resources removed by retention, by `kind` (jobs, datasets, series, uploads).
    pub const RETENTION_REMOVED: &str = "ctrecon_retention_removed_total";
    /// Running jobs whose lease expired (their worker was lost), by `outcome` (requeued, failed).
    pub const LEASES_EXPIRED: &str = "ctrecon_lease_expiries_total";
    /// Jobs this process runs now (`ctrecon_jobs{status="running"}` counts those of every process);
    /// with `ctrecon_jobs_finished_total`, the per-worker figures of a scaled-out site.
    pub const RUNNING_HERE: &str = "ctrecon_jobs_running_here";
    /// Bytes of the memory budget that uploads being assembled hold now (beside the running jobs').
    pub const MEMORY_RESERVED: &str = "ctrecon_memory_reserved_bytes";
    /// DICOM series assembled from received or uploaded files, by `outcome`: `ready`, `refused`, or
    /// `refused_unread` (refused from their headers, before any pixel was decoded).
    pub const SERIES_INGESTED: &str = "ctrecon_series_ingested_total";
}
