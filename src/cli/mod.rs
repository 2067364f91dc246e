//! The `ctrecon` command line: `serve` runs the HTTP service, `worker` runs jobs beside it, `phantom`, `recon`, `mesh` and `geometry` work on local files.

use clap::{Parser, Subcommand};

/// CT reconstruction service and tools.
#[derive(Debug, Parser)]
#[command(name = "ctrecon", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run the HTTP service (SQLite and a local data directory by default).
    Serve(serve::ServeArgs),
    /// Run jobs from a shared PostgreSQL job database, without the API (health and metrics on a small port).
    Worker(serve::WorkerArgs),
    /// Write an analytic phantom, or its exact projections for a geometry, as float32 `.npy`.
    Phantom(phantom::PhantomArgs),
    /// Reconstruct a `.npy` sinogram or projection stack (FBP, FDK or an iterative method).
    Recon(recon::ReconArgs),
    /// Write the iso-surface of a `.npy` volume as a binary STL.
    Mesh(mesh::MeshArgs),
    /// Convert a geometry between ctrecon JSON, per-view vectors, RTK geometry XML and ASTRA vector arrays.
    Geometry(geometry::GeometryArgs),
}

pub mod files;
pub mod geometry;
pub mod mesh;
pub mod phantom;
pub mod progress;
pub mod recon;
pub mod serve;

/// Runs `f` on a thread of rayon's global pool, as a job of the service runs on its pool: the kernels'
/// parallel loops then start on a pool thread, instead of each loop being handed over from the main
/// thread, which then sleeps until it is done (a wake-up and a sleep per loop, more than a small loop
/// costs; SART runs thousands of them).
pub(crate) fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}
