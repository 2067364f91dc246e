//! `ctrecon phantom`: write an analytic phantom, or its exact projections, as float32 `.npy`. The
//! projections are admitted and computed as `POST /v1/simulations` does them (`app::local`).

use std::path::{Path, PathBuf};

use ndarray::{ArrayD, Ix3};

use clap::ValueEnum;

use super::files::{CliResult, read_geometry, sidecar, write_geometry, write_npy};
use crate::app::local::{Local, Raster};
use crate::jobs::model::NoiseSpec;
use crate::recon::geometry::Geometry;
use crate::recon::phantom::{PhantomSpec, TableName};

/// Built-in phantom tables.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Table {
    SheppLogan,
    ModifiedSheppLogan,
    /// 3D only.
    YuYeWang,
}

impl From<Table> for TableName {
    fn from(t: Table) -> Self {
        match t {
            Table::SheppLogan => TableName::SheppLogan,
            Table::ModifiedSheppLogan => TableName::ModifiedSheppLogan,
            Table::YuYeWang => TableName::YuYeWang,
        }
    }
}

/// Options of `ctrecon phantom`.
#[derive(Debug, clap::Args)]
pub struct PhantomArgs {
    /// Built-in table (ignored with --spec).
    #[arg(long, value_enum, default_value = "modified-shepp-logan")]
    pub table: Table,
    /// A phantom JSON (`{"table": …}` or `{"ellipses": […]}` / `{"ellipsoids": […]}`, with `scale_mm`).
    #[arg(long)]
    pub spec: Option<PathBuf>,
    /// Field of view (mm) spanned by the phantom's [−1, 1] (ignored with --spec).
    #[arg(long, default_value_t = 256.0)]
    pub fov_mm: f64,
    /// Write the exact projections for this geometry instead of an image: a geometry JSON file, or a
    /// built-in geometry by name (`parallel`, `fan_arc`, `cone`, `parallel3d`, `helical`: the files of docs/geometries/).
    #[arg(long)]
    pub geometry: Option<PathBuf>,
    /// Image side in pixels (image output).
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// 2 for an image, 3 for a volume (image output).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u8).range(2..=3))]
    pub dims: u8,
    /// Point samples per pixel axis (image output).
    #[arg(long, default_value_t = 1)]
    pub supersample: usize,
    /// Add Poisson noise for this many incident photons per ray (projection output).
    #[arg(long)]
    pub photons: Option<f64>,
    /// Seed of the noise generator.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Shift the rotation axis this many detector columns off the panel's centre (projections of a cone or
    /// 3D parallel beam; with a `.xtekct` or `.nx` output the shift is not written into the file, so that
    /// the import has to find it).
    #[arg(long, allow_hyphen_values = true)]
    pub axis_offset_px: Option<f64>,
    /// Output `.npy` (projections also get a geometry sidecar `<out>.json`); `<name>.xtekct`: the
    /// projections of a cone beam as a Nikon XT H scanner writes a scan (the `.xtekct` and 16-bit TIFFs
    /// beside it); `<name>.nx`: those of a 3D parallel beam as an NXtomo file (raw 16-bit frames with darks
    /// and flats), as a synchrotron beamline writes one.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: PhantomArgs) -> CliResult<()> {
    let spec = match &args.spec {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| format!("reading {}: {e}", path.display()))?;
            serde_json::from_str::<PhantomSpec>(&text)
                .map_err(|e| format!("phantom {}: {e}", path.display()))?
        }
        None => PhantomSpec {
            table: Some(args.table.into()),
            ellipses: None,
            ellipsoids: None,
            scale_mm: args.fov_mm / 2.0,
        },
    };
    let local = Local::default();
    let out = match &args.geometry {
        Some(path) => {
            let mut geometry = read_geometry(path)?;
            if let Some(px) = args.axis_offset_px {
                let panel = match &mut geometry {
                    Geometry::Cone(cone) => &mut cone.detector,
                    Geometry::Parallel3d(par) => &mut par.detector,
                    _ => {
                        return Err(
                            "--axis-offset-px shifts the panel of a cone or 3D parallel beam"
                                .into(),
                        );
                    }
                };
                panel.offset_u_mm += px * panel.du_mm;
            }
            let noise = args.photons.map(|incident_photons| NoiseSpec {
                incident_photons,
                seed: args.seed,
            });
            let data = super::on_pool(|| local.simulate(spec, geometry.clone(), noise))?;
            if is_xtekct(&args.out) || is_nx(&args.out) {
                return write_scan(&args.out, &geometry, &data, args.axis_offset_px);
            }
            write_geometry(&sidecar(&args.out), &geometry)?;
            data
        }
        None => local.rasterize(
            &spec,
            Raster {
                size: args.size,
                volume: args.dims == 3,
                supersample: args.supersample,
            },
        )?,
    };
    if is_xtekct(&args.out) {
        return Err("a .xtekct output holds projections: give --geometry (a cone beam)".into());
    }
    if is_nx(&args.out) {
        return Err("an .nx output holds projections: give --geometry (a parallel3d beam)".into());
    }
    write_npy(&args.out, &out)?;
    eprintln!("wrote {} {:?}", args.out.display(), out.shape());
    Ok(())
}

fn is_xtekct(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("xtekct"))
}

fn is_nx(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("nx"))
}

/// The projections as a Nikon XT H scan (`.xtekct`) or an NXtomo file (`.nx`), with the axis shift left
/// out of the file.
fn write_scan(
    out: &Path,
    geometry: &Geometry,
    data: &ArrayD<f32>,
    axis_offset_px: Option<f64>,
) -> CliResult<()> {
    let projections = data
        .view()
        .into_dimensionality::<Ix3>()
        .map_err(|e| format!("projections are [view][v][u]: {e}"))?;
    let mut written = geometry.clone();
    match (&mut written, axis_offset_px) {
        (Geometry::Cone(cone), Some(px)) => cone.detector.offset_u_mm -= px * cone.detector.du_mm,
        (Geometry::Parallel3d(par), Some(px)) => {
            par.detector.offset_u_mm -= px * par.detector.du_mm
        }
        _ => {}
    }
    let shifted = match axis_offset_px {
        Some(px) => format!(
            ", the rotation axis {px} columns off the panel's centre, not written in the file"
        ),
        None => String::new(),
    };
    if is_nx(out) {
        let w = crate::scans::simulated_nxtomo::write_nxtomo(out, &written, projections)?;
        eprintln!(
            "wrote {} (a simulated NXtomo scan of {} projections with darks and flats{shifted}; {} pixels \
             clipped to 16 bits)",
            w.file.display(),
            w.projections,
            w.clipped
        );
        return Ok(());
    }
    let w = crate::scans::simulated::write_nikon(out, &written, projections)?;
    eprintln!(
        "wrote {} and {} TIFFs beside it (a simulated Nikon XT H scan{shifted}; {} pixels clipped to 16 bits)",
        w.xtekct.display(),
        w.tiffs,
        w.clipped
    );
    Ok(())
}
