//! Service configuration: defaults, then a JSON file, then `CTRECON_*` environment variables, then the
//! command line (each overrides the one before).
//!
//! | field | env | default |
//! |---|---|---|
//! | `bind` | `CTRECON_BIND` | `127.0.0.1:8080` |
//! | `data_dir` | `CTRECON_DATA_DIR` | `./data` |
//! | `worker_threads` | `CTRECON_WORKER_THREADS` | 0 = one per CPU; threads of each running job's (and request computation's) pool |
//! | `max_concurrent_jobs` | `CTRECON_MAX_CONCURRENT_JOBS` | 2; 0 = API only (PostgreSQL and `ctrecon worker` processes) |
//! | `memory_budget_bytes` | `CTRECON_MEMORY_BUDGET_BYTES` | 4 GiB, shared by all running jobs |
//! | `max_upload_bytes` | `CTRECON_MAX_UPLOAD_BYTES` | 2 GiB per uploaded `.npy` |
//! | `max_json_bytes` | `CTRECON_MAX_JSON_BYTES` | 1 MiB per JSON body |
//! | `api_tokens` | `CTRECON_API_TOKENS` (comma-separated) | none; hashed at load, never stored in clear |
//! | `api_token_sha256` | `CTRECON_API_TOKEN_SHA256` (comma-separated hex) | none |
//! | `cors_origins` | `CTRECON_CORS_ORIGINS` (comma-separated) | none (no CORS headers) |
//! | `allow_insecure` | `CTRECON_ALLOW_INSECURE` | false: without tokens only loopback binds |
//! | `max_attempts` | `CTRECON_MAX_ATTEMPTS` | 3 starts per job before it fails |
//! | `mu_water_per_mm` | `CTRECON_MU_WATER_PER_MM` | 0.0192 (HU conversion of presets) |
//! | `request_timeout_secs` | `CTRECON_REQUEST_TIMEOUT_SECS` | 30 (uploads: `upload_timeout_secs`, 600) |
//! | `progress_interval_ms` | `CTRECON_PROGRESS_INTERVAL_MS` | 500: most one progress write per job per interval |
//! | `zip_max_member_bytes` | `CTRECON_ZIP_MAX_MEMBER_BYTES` | 1 GiB per inflated ZIP member (and at most the memory budget over the workers) |
//! | `zip_max_total_bytes` | `CTRECON_ZIP_MAX_TOTAL_BYTES` | 8 GiB inflated per upload |
//! | `zip_max_ratio` | `CTRECON_ZIP_MAX_RATIO` | 200: inflated/compressed of one member (members under 1 MiB exempt) |
//! | `drain_timeout_ms` | `CTRECON_DRAIN_TIMEOUT_MS` | 10000: after SIGTERM/Ctrl-C, open requests get this long, then close |
//! | `retain_finished_jobs_secs` | `CTRECON_RETAIN_FINISHED_JOBS_SECS` | 0 = forever; else jobs (and results) this long after they finished |
//! | `retain_datasets_secs` | `CTRECON_RETAIN_DATASETS_SECS` | 0 = forever; else datasets this long after creation, unless in use |
//! | `retain_series_secs` | `CTRECON_RETAIN_SERIES_SECS` | 0 = forever; else series this long after creation, unless in use |
//! | `retention_sweep_secs` | `CTRECON_RETENTION_SWEEP_SECS` | 3600: retention runs at start and this often |
//! | `dicom.port` | `CTRECON_DICOM_PORT` | none: no DICOM node; see [`dicom::NodeSettings`] |
//! | `dicom.ae_title` | `CTRECON_DICOM_AE_TITLE` | `CTRECON` |
//! | `dicom.host` | `CTRECON_DICOM_HOST` | `127.0.0.1` |
//! | `dicom.stable_age_secs` | `CTRECON_DICOM_STABLE_AGE_SECS` | 15: a series is complete after this long without an instance |
//! | `dicom.negotiation_timeout_secs` | — | 5: a connection that has not sent its whole A-ASSOCIATE-RQ this long after connecting is closed (at most `dicom.association_timeout_secs`, 30); until then it holds no association slot |
//! | `dicom.max_pending_per_address` | — | 8: connections from one address waiting for their A-ASSOCIATE-RQ; one more closes the oldest |
//! | `dicom.max_pending` | — | 0 = 4 × `dicom.max_associations` (16), at least 64: connections from all addresses waiting for their A-ASSOCIATE-RQ; one more closes the oldest |
//! | `dicom.rules` | — | processing rules (`POST /v1/rules` bodies) read at every start; read-only in the API |
//! | `dicom.delivery_retry_base_ms` | — | 5000: first wait before a delivery to an unreachable peer is tried again, doubled each time |
//! | `dicom.delivery_retry_max_ms` | — | 600000: longest wait between attempts of a delivery |
//! | `dicom.delivery_max_attempts` | — | 10: attempts before a delivery to an unreachable peer is `failed` |
//! | `dicom.web_peers` | `CTRECON_DICOM_WEB_PEERS` (a JSON array, replacing the file's) | none: DICOMweb destinations `{"name", "url", "bearer_token" \| "username" + "password", "timeout_secs": 600, "batch_instances": 200}`, sent to by STOW-RS; see [`dicom::WebPeer`] (needs the default `dicomweb-client` feature) |
//! | `database_url` | `CTRECON_DATABASE_URL` | none: SQLite in the data directory; `postgres://user@host:port/db` for a PostgreSQL job database shared by several processes |
//! | `lease_secs` | `CTRECON_LEASE_SECS` | 30: a running job whose worker sent no heartbeat for this long goes back to the queue |
//! | `render_max_side` | `CTRECON_RENDER_MAX_SIDE` | 2048: largest side (pixels) of a volume or surface rendering |
//! | `storage.url` | `CTRECON_STORAGE_URL` | none: blobs in the data directory only; `s3://bucket/prefix` keeps datasets, series and results in S3-compatible object storage (the data directory is then a cache) |
//! | `storage.endpoint` | `CTRECON_STORAGE_ENDPOINT` | none: AWS (or `AWS_ENDPOINT_URL`); `http://host:port` for a self-hosted server, addressed path-style |
//! | `storage.region` | `CTRECON_STORAGE_REGION` | none: `AWS_REGION` / `AWS_DEFAULT_REGION`, else `us-east-1` |
//! | `storage.access_key_id`, `storage.secret_access_key` | — | none: `AWS_ACCESS_KEY_ID` / `AWS_SECRET_ACCESS_KEY` (and, on AWS, the instance's role) |
//! | `header_read_timeout_ms` | `CTRECON_HEADER_READ_TIMEOUT_MS` | 10000: a connection whose first request head is not complete this long after it was accepted is closed |
//! | `idle_timeout_ms` | `CTRECON_IDLE_TIMEOUT_MS` | 60000: a connection with no request in flight since its last one, or whose client reads none of a response, for this long is closed |
//! | `max_connections` | `CTRECON_MAX_CONNECTIONS` | 2048 open HTTP connections (at most half the open-file limit less a reserve); more are answered 503 `too_many_connections` and closed |
//! | `max_connections_per_ip` | `CTRECON_MAX_CONNECTIONS_PER_IP` | 256 open connections per client address; 0 = no cap per address (behind a proxy) |
//! | `upload_min_bytes` | `CTRECON_UPLOAD_MIN_BYTES` | 16384: an upload body that delivers less in `upload_progress_window_secs` is answered 408 `upload_stalled`; 0 = off |
//! | `upload_progress_window_secs` | `CTRECON_UPLOAD_PROGRESS_WINDOW_SECS` | 30 |
//!
//! Every `ctrecon` command (and the examples and benchmarks) also reads `CTRECON_SIMD` at start-up
//! ([`limit_simd_from_env`]): `avx2` leaves AVX-512F unused, `scalar` every vector kernel.

pub mod dicom;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use serde::Deserialize;

/// Cap the reconstruction kernels as `CTRECON_SIMD` says (see [`crate::recon::cpu`]); call before any
/// reconstruction. Returns whether the cap took effect.
pub fn limit_simd_from_env() -> bool {
    let value = std::env::var("CTRECON_SIMD").ok();
    crate::recon::cpu::limit(crate::recon::cpu::Simd::parse(value.as_deref()))
}

/// `CTRECON_*` variables that are not settings but are read elsewhere: the log format (telemetry), the SIMD
/// cap (every command, [`limit_simd_from_env`]), the test-data and peer rules of the test suite, where the
/// viewer tests write their screenshots, and the cone case of the iterative benchmark. Setting them never
/// makes a command refuse to start.
pub const READ_ELSEWHERE: &[&str] = &[
    "CTRECON_LOG_FORMAT",
    "CTRECON_SIMD",
    "CTRECON_REQUIRE_TEST_DATA",
    "CTRECON_REQUIRE_PEERS",
    "CTRECON_SCREENSHOT_DIR",
    "CTRECON_BENCH_CONE",
];

/// Everything `ctrecon serve` can be told.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Settings {
    pub bind: SocketAddr,
    pub data_dir: PathBuf,
    pub worker_threads: usize,
    pub max_concurrent_jobs: usize,
    pub memory_budget_bytes: u64,
    pub max_upload_bytes: u64,
    pub max_json_bytes: usize,
    pub api_tokens: Vec<String>,
    pub api_token_sha256: Vec<String>,
    pub cors_origins: Vec<String>,
    pub allow_insecure: bool,
    pub max_attempts: u32,
    pub mu_water_per_mm: f64,
    pub request_timeout_secs: u64,
    pub upload_timeout_secs: u64,
    pub progress_interval_ms: u64,
    pub zip_max_member_bytes: u64,
    pub zip_max_total_bytes: u64,
    pub zip_max_ratio: u64,
    pub drain_timeout_ms: u64,
    pub retain_finished_jobs_secs: u64,
    pub retain_datasets_secs: u64,
    pub retain_series_secs: u64,
    pub retention_sweep_secs: u64,
    /// The DICOM node (off unless `dicom.port` is set).
    pub dicom: dicom::NodeSettings,
    pub render_max_side: usize,
    /// The job database: `None` is SQLite in the data directory; a `postgres://` URL selects PostgreSQL.
    pub database_url: Option<String>,
    /// Seconds a claim holds a running job without a heartbeat.
    pub lease_secs: u64,
    /// Object storage for datasets, series and results (off unless `storage.url` is set).
    pub storage: StorageSettings,
    /// Milliseconds from accepting a connection to its first complete request head.
    pub header_read_timeout_ms: u64,
    /// Milliseconds a connection may stay idle between requests, or blocked on a client that reads nothing.
    pub idle_timeout_ms: u64,
    /// Open HTTP connections at once (clamped below the open-file limit at start).
    pub max_connections: usize,
    /// Open HTTP connections of one client address at once; 0 = no cap per address.
    pub max_connections_per_ip: usize,
    /// Least bytes an upload body delivers in each progress window; 0 = no rule.
    pub upload_min_bytes: u64,
    pub upload_progress_window_secs: u64,
}

/// Where datasets, series and results live durably besides the data directory.
#[derive(Clone, Default, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StorageSettings {
    /// `s3://bucket[/prefix]`; `None` keeps everything in the data directory.
    pub url: Option<String>,
    /// A self-hosted server (`http://127.0.0.1:9000`), addressed path-style.
    pub endpoint: Option<String>,
    pub region: Option<String>,
    pub access_key_id: Option<String>,
    pub secret_access_key: Option<String>,
}

impl std::fmt::Debug for StorageSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StorageSettings")
            .field("url", &self.url)
            .field("endpoint", &self.endpoint)
            .field("region", &self.region)
            .field("access_key_id", &self.access_key_id)
            .field(
                "secret_access_key",
                &self.secret_access_key.as_ref().map(|_| "<redacted>"),
            )
            .finish()
    }
}

impl Default for Settings {
    fn default() -> Self {
        Self {
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            data_dir: PathBuf::from("data"),
            worker_threads: 0,
            max_concurrent_jobs: 2,
            memory_budget_bytes: 4 << 30,
            max_upload_bytes: 2 << 30,
            max_json_bytes: 1 << 20,
            api_tokens: Vec::new(),
            api_token_sha256: Vec::new(),
            cors_origins: Vec::new(),
            allow_insecure: false,
            max_attempts: 3,
            mu_water_per_mm: 0.0192,
            request_timeout_secs: 30,
            upload_timeout_secs: 600,
            progress_interval_ms: 500,
            zip_max_member_bytes: 1 << 30,
            zip_max_total_bytes: 8 << 30,
            zip_max_ratio: 200,
            drain_timeout_ms: 10_000,
            retain_finished_jobs_secs: 0,
            retain_datasets_secs: 0,
            retain_series_secs: 0,
            retention_sweep_secs: 3600,
            dicom: dicom::NodeSettings::default(),
            render_max_side: 2048,
            database_url: None,
            lease_secs: 30,
            storage: StorageSettings::default(),
            header_read_timeout_ms: 10_000,
            idle_timeout_ms: 60_000,
            max_connections: 2048,
            max_connections_per_ip: 256,
            upload_min_bytes: 16 << 10,
            upload_progress_window_secs: 30,
        }
    }
}

/// A configuration that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("reading {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config file {path}: {source}")]
    Parse {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("environment variable {name}: {reason}")]
    Env { name: String, reason: String },
    #[error("invalid setting `{name}`: {reason}")]
    Invalid { name: &'static str, reason: String },
}

fn list(value: &str) -> Vec<String> {
    value
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect()
}

fn parsed<T: std::str::FromStr>(name: &str, value: &str) -> Result<T, ConfigError>
where
    T::Err: std::fmt::Display,
{
    value.trim().parse().map_err(|e: T::Err| ConfigError::Env {
        name: name.to_string(),
        reason: e.to_string(),
    })
}

impl Settings {
    /// Defaults, overridden by the JSON file at `path` (if any), then by `CTRECON_*` variables in `env`.
    pub fn load(
        path: Option<&Path>,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> Result<Self, ConfigError> {
        let mut s = match path {
            Some(p) => {
                let text = std::fs::read_to_string(p).map_err(|source| ConfigError::Read {
                    path: p.to_path_buf(),
                    source,
                })?;
                serde_json::from_str(&text).map_err(|source| ConfigError::Parse {
                    path: p.to_path_buf(),
                    source,
                })?
            }
            None => Settings::default(),
        };
        for (name, value) in env {
            s.apply_env(&name, &value)?;
        }
        Ok(s)
    }

    fn apply_env(&mut self, name: &str, v: &str) -> Result<(), ConfigError> {
        match name {
            "CTRECON_BIND" => self.bind = parsed(name, v)?,
            "CTRECON_DATA_DIR" => self.data_dir = PathBuf::from(v),
            "CTRECON_WORKER_THREADS" => self.worker_threads = parsed(name, v)?,
            "CTRECON_MAX_CONCURRENT_JOBS" => self.max_concurrent_jobs = parsed(name, v)?,
            "CTRECON_MEMORY_BUDGET_BYTES" => self.memory_budget_bytes = parsed(name, v)?,
            "CTRECON_MAX_UPLOAD_BYTES" => self.max_upload_bytes = parsed(name, v)?,
            "CTRECON_MAX_JSON_BYTES" => self.max_json_bytes = parsed(name, v)?,
            "CTRECON_API_TOKENS" => self.api_tokens = list(v),
            "CTRECON_API_TOKEN_SHA256" => self.api_token_sha256 = list(v),
            "CTRECON_CORS_ORIGINS" => self.cors_origins = list(v),
            "CTRECON_ALLOW_INSECURE" => self.allow_insecure = parsed(name, v)?,
            "CTRECON_MAX_ATTEMPTS" => self.max_attempts = parsed(name, v)?,
            "CTRECON_MU_WATER_PER_MM" => self.mu_water_per_mm = parsed(name, v)?,
            "CTRECON_REQUEST_TIMEOUT_SECS" => self.request_timeout_secs = parsed(name, v)?,
            "CTRECON_UPLOAD_TIMEOUT_SECS" => self.upload_timeout_secs = parsed(name, v)?,
            "CTRECON_PROGRESS_INTERVAL_MS" => self.progress_interval_ms = parsed(name, v)?,
            "CTRECON_ZIP_MAX_MEMBER_BYTES" => self.zip_max_member_bytes = parsed(name, v)?,
            "CTRECON_ZIP_MAX_TOTAL_BYTES" => self.zip_max_total_bytes = parsed(name, v)?,
            "CTRECON_ZIP_MAX_RATIO" => self.zip_max_ratio = parsed(name, v)?,
            "CTRECON_DRAIN_TIMEOUT_MS" => self.drain_timeout_ms = parsed(name, v)?,
            "CTRECON_RETAIN_FINISHED_JOBS_SECS" => {
                self.retain_finished_jobs_secs = parsed(name, v)?
            }
            "CTRECON_RETAIN_DATASETS_SECS" => self.retain_datasets_secs = parsed(name, v)?,
            "CTRECON_RETAIN_SERIES_SECS" => self.retain_series_secs = parsed(name, v)?,
            "CTRECON_RETENTION_SWEEP_SECS" => self.retention_sweep_secs = parsed(name, v)?,
            "CTRECON_DICOM_PORT" => self.dicom.port = Some(parsed(name, v)?),
            "CTRECON_DICOM_AE_TITLE" => self.dicom.ae_title = v.trim().to_string(),
            "CTRECON_DICOM_HOST" => self.dicom.host = parsed(name, v)?,
            "CTRECON_DICOM_STABLE_AGE_SECS" => self.dicom.stable_age_secs = parsed(name, v)?,
            "CTRECON_DICOM_WEB_PEERS" => {
                self.dicom.web_peers = if v.trim().is_empty() {
                    Vec::new()
                } else {
                    serde_json::from_str(v).map_err(|e| ConfigError::Env {
                        name: name.to_string(),
                        reason: format!("not a JSON array of web peers: {e}"),
                    })?
                }
            }
            "CTRECON_RENDER_MAX_SIDE" => self.render_max_side = parsed(name, v)?,
            "CTRECON_DATABASE_URL" => {
                self.database_url = Some(v.trim().to_string()).filter(|u| !u.is_empty())
            }
            "CTRECON_LEASE_SECS" => self.lease_secs = parsed(name, v)?,
            "CTRECON_STORAGE_URL" => {
                self.storage.url = Some(v.trim().to_string()).filter(|u| !u.is_empty())
            }
            "CTRECON_STORAGE_ENDPOINT" => {
                self.storage.endpoint = Some(v.trim().to_string()).filter(|u| !u.is_empty())
            }
            "CTRECON_STORAGE_REGION" => {
                self.storage.region = Some(v.trim().to_string()).filter(|u| !u.is_empty())
            }
            "CTRECON_HEADER_READ_TIMEOUT_MS" => self.header_read_timeout_ms = parsed(name, v)?,
            "CTRECON_IDLE_TIMEOUT_MS" => self.idle_timeout_ms = parsed(name, v)?,
            "CTRECON_MAX_CONNECTIONS" => self.max_connections = parsed(name, v)?,
            "CTRECON_MAX_CONNECTIONS_PER_IP" => self.max_connections_per_ip = parsed(name, v)?,
            "CTRECON_UPLOAD_MIN_BYTES" => self.upload_min_bytes = parsed(name, v)?,
            "CTRECON_UPLOAD_PROGRESS_WINDOW_SECS" => {
                self.upload_progress_window_secs = parsed(name, v)?
            }
            other if READ_ELSEWHERE.contains(&other) => {}
            other if other.starts_with("CTRECON_") => {
                return Err(ConfigError::Env {
                    name: other.to_string(),
                    reason: "unknown setting".into(),
                });
            }
            _ => {}
        }
        Ok(())
    }

    /// Check ranges and the security rule: without API tokens the service binds only to a loopback
    /// address, unless `allow_insecure` is set.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |name, reason: &str| {
            Err(ConfigError::Invalid {
                name,
                reason: reason.to_string(),
            })
        };
        if self.max_concurrent_jobs == 0 && self.database_url.is_none() {
            return invalid(
                "max_concurrent_jobs",
                "0 (an API process that runs no jobs) needs a shared job database (database_url = \
                 postgres://…) and `ctrecon worker` processes on it; with SQLite at least 1",
            );
        }
        if self.memory_budget_bytes == 0 || self.max_upload_bytes == 0 || self.max_json_bytes == 0 {
            return invalid("limits", "memory and size limits must be positive");
        }
        if self.zip_max_member_bytes == 0
            || self.zip_max_total_bytes == 0
            || self.zip_max_ratio == 0
        {
            return invalid("zip limits", "must be positive");
        }
        if self.max_attempts == 0 {
            return invalid("max_attempts", "must be at least 1");
        }
        if !(self.mu_water_per_mm.is_finite() && self.mu_water_per_mm > 0.0) {
            return invalid("mu_water_per_mm", "must be positive and finite");
        }
        if self.render_max_side == 0 || self.render_max_side > crate::render::DEFAULT_MAX_SIDE {
            return invalid("render_max_side", "must be within 1..=4096");
        }
        if self.retention_sweep_secs == 0 {
            return invalid("retention_sweep_secs", "must be at least 1");
        }
        if self.lease_secs == 0 {
            return invalid("lease_secs", "must be at least 1");
        }
        if let Some(url) = &self.database_url
            && !(url.starts_with("postgres://") || url.starts_with("postgresql://"))
        {
            return invalid(
                "database_url",
                "must be a postgres:// URL (leave it out for SQLite in the data directory)",
            );
        }
        if let Some(url) = &self.storage.url
            && !url.starts_with("s3://")
        {
            return invalid(
                "storage.url",
                "must be an s3://bucket/prefix URL (leave it out to keep blobs in the data directory)",
            );
        }
        if let Some(e) = &self.storage.endpoint
            && !(e.starts_with("http://") || e.starts_with("https://"))
        {
            return invalid("storage.endpoint", "must be an http:// or https:// URL");
        }
        if self.request_timeout_secs == 0 || self.upload_timeout_secs == 0 {
            return invalid("timeouts", "must be positive");
        }
        if self.header_read_timeout_ms == 0
            || self.idle_timeout_ms == 0
            || self.upload_progress_window_secs == 0
        {
            return invalid("connection timeouts", "must be positive");
        }
        if self.max_connections == 0 {
            return invalid("max_connections", "must be at least 1");
        }
        for h in &self.api_token_sha256 {
            if h.len() != 64 || !h.bytes().all(|b| b.is_ascii_hexdigit()) {
                return invalid("api_token_sha256", "each entry is 64 hexadecimal digits");
            }
        }
        if self.api_tokens.iter().any(|t| t.len() < 16) {
            return invalid("api_tokens", "each token needs at least 16 characters");
        }
        let authenticated = !self.api_tokens.is_empty() || !self.api_token_sha256.is_empty();
        if !authenticated && !self.bind.ip().is_loopback() && !self.allow_insecure {
            return invalid(
                "bind",
                "refusing to listen on a non-loopback address without API tokens \
                 (configure api_tokens, or pass --allow-insecure)",
            );
        }
        if let Some(reason) = self.dicom.problem() {
            return Err(ConfigError::Invalid {
                name: "dicom",
                reason,
            });
        }
        Ok(())
    }

    /// Worker threads of the reconstruction pool (0 resolves to the number of CPUs).
    pub fn resolved_worker_threads(&self) -> usize {
        if self.worker_threads > 0 {
            self.worker_threads
        } else {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        }
    }
}

#[cfg(test)]
mod tests;
