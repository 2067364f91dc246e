//! The `ctrecon` binary: parse the command line and hand over to the library.

use clap::Parser;
use ctrecon::cli::{Cli, Command};

fn main() -> std::process::ExitCode {
    ctrecon::config::limit_simd_from_env();
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Serve(args) => ctrecon::cli::serve::run(args),
        Command::Worker(args) => ctrecon::cli::serve::run_worker(args),
        Command::Phantom(args) => ctrecon::cli::phantom::run(args),
        Command::Recon(args) => ctrecon::cli::recon::run(args),
        Command::Mesh(args) => ctrecon::cli::mesh::run(args),
        Command::Geometry(args) => ctrecon::cli::geometry::run(args),
    };
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
