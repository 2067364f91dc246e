//! `ctrecon serve`: the HTTP service. Settings come from defaults, `--config` (JSON), `CTRECON_*`
//! environment variables and these flags, in that order of precedence (flags win).

use std::net::SocketAddr;
use std::path::PathBuf;

use crate::config::Settings;
use crate::http::{Application, shutdown_signal};

/// Options of `ctrecon serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {
    /// JSON configuration file (fields as in the README's table).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Address to listen on (port 0 picks a free port).
    #[arg(long)]
    pub bind: Option<SocketAddr>,
    /// Directory of the database and the files.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    /// Threads of the reconstruction pool (default: one per CPU).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Jobs running at once.
    #[arg(long)]
    pub max_concurrent_jobs: Option<usize>,
    /// Allow a non-loopback bind without API tokens.
    #[arg(long)]
    pub allow_insecure: bool,
    /// Log as JSON lines.
    #[arg(long)]
    pub log_json: bool,
}

/// Run the service until Ctrl-C or SIGTERM.
pub fn run(args: ServeArgs) -> Result<(), Box<dyn std::error::Error>> {
    let mut settings = Settings::load(args.config.as_deref(), std::env::vars())?;
    if let Some(b) = args.bind {
        settings.bind = b;
    }
    if let Some(d) = args.data_dir {
        settings.data_dir = d;
    }
    if let Some(w) = args.workers {
        settings.worker_threads = w;
    }
    if let Some(m) = args.max_concurrent_jobs {
        settings.max_concurrent_jobs = m;
    }
    settings.allow_insecure |= args.allow_insecure;
    crate::telemetry::init_logging(
        args.log_json || std::env::var("CTRECON_LOG_FORMAT").is_ok_and(|v| v == "json"),
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("ctrecon-http")
        .build()?;
    runtime.block_on(async move {
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
