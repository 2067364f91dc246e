//! `ctrecon mesh`: the iso-surface of a `.npy` volume as a binary STL, through the surface pipeline of a volume
//! job's mesh product (`app::local`): marching cubes, the largest connected piece, Taubin smoothing and
//! decimation, with the same options and refusals.

use std::path::PathBuf;

use super::files::{CliResult, read_npy};
use crate::app::local::Local;
use crate::mesh::MeshOptions;

/// Options of `ctrecon mesh`.
#[derive(Debug, clap::Args)]
pub struct MeshArgs {
    /// Volume `[z][y][x]` (float32 or float64 `.npy`), e.g. from `ctrecon recon` or `ctrecon phantom --dims 3`.
    #[arg(long)]
    pub input: PathBuf,
    /// Iso-value in the volume's units: inside is at or above it.
    #[arg(long, allow_hyphen_values = true)]
    pub iso: f32,
    /// Voxel size in mm along x, y and z.
    #[arg(long, num_args = 3, value_names = ["X", "Y", "Z"], default_values_t = [1.0, 1.0, 1.0])]
    pub voxel_mm: Vec<f64>,
    /// Keep every connected piece (default: only the one with the most triangles).
    #[arg(long)]
    pub all_components: bool,
    /// Taubin λ|μ smoothing iterations.
    #[arg(long, default_value_t = 0)]
    pub smoothing: usize,
    /// Decimate to at most this many triangles.
    #[arg(long)]
    pub target_triangles: Option<usize>,
    /// Output binary STL (millimetres, voxel `[0][0][0]` at the origin).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: MeshArgs) -> CliResult<()> {
    let [x, y, z] = args.voxel_mm[..] else {
        return Err("--voxel-mm takes three sizes".into());
    };
    let volume = read_npy(&args.input)?;
    let options = MeshOptions {
        iso: args.iso,
        largest_component: !args.all_components,
        smoothing: args.smoothing,
        target_triangles: args.target_triangles,
        clip: Default::default(),
    };
    let (mesh, stats) = super::on_pool(|| Local::default().mesh(volume, [x, y, z], &options))?;
    std::fs::write(&args.out, mesh.to_stl_binary())
        .map_err(|e| format!("writing {}: {e}", args.out.display()))?;
    for w in &stats.warnings {
        eprintln!("warning: {}: {}", w.code, w.message);
    }
    eprintln!(
        "wrote {}: {} triangles, {} vertices, closed {}, manifold {}",
        args.out.display(),
        stats.triangles,
        stats.vertices,
        stats.closed,
        stats.manifold
    );
    Ok(())
}
