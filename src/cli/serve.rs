//! `ctrecon serve`.

/// Options of `ctrecon serve`.
#[derive(Debug, clap::Args)]
pub struct ServeArgs {}

/// Run the service until shutdown.
pub fn run(_args: ServeArgs) -> Result<(), Box<dyn std::error::Error>> {
    Err("the service is not built yet".into())
}
