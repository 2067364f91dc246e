//! `ctrecon serve` (the HTTP service) and `ctrecon worker` (jobs only, beside API processes on a shared job
//! database). Settings come from defaults, `--config` (JSON), `CTRECON_*` environment variables and these
//! flags, in that order of precedence (flags win).

use std::net::SocketAddr;
use std::path::PathBuf;

use crate::config::Settings;
use crate::http::{Application, Role, shutdown_signal};

/// Options of `ctrecon serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Address to listen on (port 0 picks a free port).
    #[arg(long)]
    pub bind: Option<SocketAddr>,
    /// Allow a non-loopback bind without API tokens.
    #[arg(long)]
    pub allow_insecure: bool,
}

/// Options of `ctrecon worker`.
#[derive(Debug, clap::Args)]
pub struct WorkerArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Address of the worker's `/healthz`, `/readyz` and `/metrics` (port 0 picks a free port).
    #[arg(long, default_value = "127.0.0.1:8081")]
    pub health_bind: SocketAddr,
}

/// Options both roles take.
#[derive(Debug, clap::Args)]
pub struct CommonArgs {
    /// JSON configuration file (fields as in the README's table).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Directory of the database and the files (shared by every process of one job database).
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Jobs this process runs at once; 0 = none (an API process beside `ctrecon worker` processes on
    /// PostgreSQL).
    #[arg(long, visible_alias = "max-concurrent-jobs")]
    pub workers: Option<usize>,
    /// Threads of the reconstruction pool (default: one per CPU).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Log as JSON lines.
    #[arg(long)]
    pub log_json: bool,
}

impl CommonArgs {
    fn settings(&self) -> Result<Settings, Box<dyn std::error::Error>> {
        let mut settings = Settings::load(self.config.as_deref(), std::env::vars())?;
        if let Some(d) = &self.data_dir {
            settings.data_dir = d.clone();
        }
        if let Some(w) = self.workers {
            settings.max_concurrent_jobs = w;
        }
        if let Some(t) = self.threads {
            settings.worker_threads = t;
        }
        crate::telemetry::init_logging(
            self.log_json || std::env::var("CTRECON_LOG_FORMAT").is_ok_and(|v| v == "json"),
        );
        Ok(settings)
    }
}

fn runtime() -> std::io::Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("ctrecon-http")
        .build()
}

/// Run the service until Ctrl-C or SIGTERM.
pub fn run(args: ServeArgs) -> Result<(), Box<dyn std::error::Error>> {
    let mut settings = args.common.settings()?;
    if let Some(b) = args.bind {
        settings.bind = b;
    }
    settings.allow_insecure |= args.allow_insecure;
    runtime()?.block_on(async move {
        let app = Application::build(settings).await?;
        // The one line scripts and tests wait for.
        println!("ctrecon listening on http://{}", app.local_addr());
        tracing::info!(addr = %app.local_addr(), "listening");
        if let Some(dicom) = crate::dimse::serve_node(app.app().clone()).await? {
            println!(
                "ctrecon DICOM node {} on {dicom}",
                app.app().settings.dicom.ae_title
            );
        }
        app.run_until(shutdown_signal()).await?;
        Ok::<(), Box<dyn std::error::Error>>(())
    })
}

/// Run jobs from a shared job database until Ctrl-C or SIGTERM, then hand back or finish the running ones.
pub fn run_worker(args: WorkerArgs) -> Result<(), Box<dyn std::error::Error>> {
    let mut settings = args.common.settings()?;
    if settings.database_url.is_none() {
        return Err("ctrecon worker needs a shared job database: set database_url (or \
                    CTRECON_DATABASE_URL) to a postgres:// URL; with SQLite, `ctrecon serve` runs the jobs"
            .into());
    }
    if settings.max_concurrent_jobs == 0 {
        return Err("a worker that runs no jobs (--workers 0) has nothing to do".into());
    }
    settings.bind = args.health_bind;
    runtime()?.block_on(async move {
        let app = Application::build_as(settings, Role::Worker).await?;
        // The one line scripts and tests wait for.
        println!("ctrecon worker health on http://{}", app.local_addr());
        tracing::info!(addr = %app.local_addr(), "worker started");
        app.run_until(shutdown_signal()).await?;
        Ok::<(), Box<dyn std::error::Error>>(())
    })
}
