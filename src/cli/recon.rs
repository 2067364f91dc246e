//! `ctrecon recon`: reconstruct a `.npy` sinogram or projection stack with its geometry JSON, or a scanner's
//! scan (`.xtekct`, Zeiss `.txrm`, NXtomo `.nx`, SkyScan `.log`, TIFF stack: geometry from its metadata, converted to line
//! integrals by `scans::line_integrals`), write the result as float32 `.npy` and optionally a PNG of one
//! slice with window/level. Admission, the reconstruction and its errors are the application's
//! (`app::local`), as for a job submitted to the API.

use std::path::{Path, PathBuf};

use clap::ValueEnum;
use ndarray::{ArrayD, ArrayView2, Axis, Ix2, Ix3};
use serde_json::{Map, Value};

use super::files::{CliResult, read_geometry, read_npy, sidecar, write_npy};
use super::progress::Bar;
use crate::app::local::{DEFAULT_BUDGET_BYTES, Local, Reconstruction};
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid, Window};
use crate::recon::control::Cancel;
use crate::recon::geometry::Geometry;
use crate::recon::prep::PrepPlan;
use crate::scans::calibrate::{CentrePolicy, calibrate};
use crate::scans::{self, Scan};

/// Ramp-filter windows (FBP and FDK).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum Filter {
    RamLak,
    SheppLogan,
    Cosine,
    Hamming,
    Hann,
}

impl From<Filter> for Window {
    fn from(f: Filter) -> Self {
        match f {
            Filter::RamLak => Window::RamLak,
            Filter::SheppLogan => Window::SheppLogan,
            Filter::Cosine => Window::Cosine,
            Filter::Hamming => Window::Hamming,
            Filter::Hann => Window::Hann,
        }
    }
}

/// Options of `ctrecon recon`.
#[derive(Debug, clap::Args)]
pub struct ReconArgs {
    /// Sinogram `[view][u]` or projections `[view][v][u]` (float32 or float64 `.npy`, line integrals), or a
    /// scan: `.xtekct` (Nikon), `.txrm`/`.xrm` (Zeiss Xradia), `.nx`/`.nxs`/`.h5`/`.hdf5` (NeXus NXtomo),
    /// `.log` (Bruker SkyScan), `.tif` stack, or a folder holding one.
    #[arg(long, visible_alias = "data")]
    pub input: PathBuf,
    /// Geometry JSON (default: the sidecar `<input>.json` written by `ctrecon phantom`, or the scan's own).
    #[arg(long)]
    pub geometry: Option<PathBuf>,
    /// `fbp` (2D parallel/fan) or `fdk` (cone); iterative: art, sart, os_sart, sirt, cgls, mlem, tv.
    #[arg(long, default_value = "fbp")]
    pub algorithm: String,
    /// Ramp-filter window (FBP/FDK).
    #[arg(long, value_enum)]
    pub filter: Option<Filter>,
    /// Frequency cut-off in (0, 1] as a fraction of Nyquist (FBP/FDK).
    #[arg(long)]
    pub cutoff: Option<f64>,
    /// More algorithm parameters as JSON, e.g. `{"iterations": 20}` or `{"filter": "hann"}`.
    #[arg(long)]
    pub params: Option<String>,
    /// Pixels (voxels) per side of the output grid.
    #[arg(long, default_value_t = 256)]
    pub size: usize,
    /// Pixel (voxel) size in mm.
    #[arg(long, default_value_t = 1.0)]
    pub pixel_mm: f64,
    /// An output grid JSON (`{"nx", "ny", "dx_mm", "dy_mm"}` or `{"nx", "ny", "nz", "spacing_mm"}`)
    /// instead of --size/--pixel-mm.
    #[arg(long, conflicts_with_all = ["size", "pixel_mm"])]
    pub grid: Option<PathBuf>,
    /// Most bytes the reconstruction may allocate.
    #[arg(long, default_value_t = DEFAULT_BUDGET_BYTES)]
    pub max_bytes: u64,
    /// Output `.npy` (float32, `[y][x]` or `[z][y][x]`).
    #[arg(long, visible_alias = "out")]
    pub output: PathBuf,
    /// Also write an 8-bit grey PNG of one slice.
    #[arg(long)]
    pub png: Option<PathBuf>,
    /// Centre of rotation of a scan: `auto` (found from the views unless the scan's metadata states a
    /// calibrated centre), `find`, `read` (as the metadata gives it), or a detector u offset in mm.
    #[arg(long, default_value = "auto")]
    pub centre: String,
    /// Preprocessing steps on the projections (`[view][v][u]`, a cone beam), as JSON with any of
    /// `angles` (`{"start", "step", "count"}`), `crop` (`{"u0", "v0", "nu", "nv"}`), `bin` (`{"u", "v"}`),
    /// `linearise` (`{"coefficients": [a0, a1, …]}`), `stripes` (`{"size": 21}`), applied in that order.
    #[arg(long)]
    pub preprocessing: Option<String>,
    /// Axial slice of a volume for the PNG (default: the middle one).
    #[arg(long)]
    pub slice: Option<usize>,
    /// Window width in the image's units (default: the slice's min..max).
    #[arg(long)]
    pub ww: Option<f64>,
    /// Window level (centre) in the image's units.
    #[arg(long)]
    pub wl: Option<f64>,
}

/// The algorithm spec from `--algorithm`, `--params`, `--filter` and `--cutoff`.
pub fn algorithm_spec(args: &ReconArgs) -> CliResult<AlgorithmSpec> {
    let mut fields = match &args.params {
        Some(text) => {
            match serde_json::from_str::<Value>(text).map_err(|e| format!("--params: {e}"))? {
                Value::Object(m) => m,
                _ => return Err("--params must be a JSON object".into()),
            }
        }
        None => Map::new(),
    };
    fields.insert("name".into(), Value::String(args.algorithm.clone()));
    if let Some(f) = args.filter {
        fields.insert("filter".into(), serde_json::to_value(Window::from(f))?);
    }
    if let Some(c) = args.cutoff {
        fields.insert("cutoff".into(), serde_json::to_value(c)?);
    }
    serde_json::from_value(Value::Object(fields))
        .map_err(|e| format!("algorithm `{}`: {e}", args.algorithm).into())
}

fn output_grid(args: &ReconArgs, local: &Local, geometry: &Geometry) -> CliResult<OutputGrid> {
    if let Some(path) = &args.grid {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("reading {}: {e}", path.display()))?;
        return Ok(
            serde_json::from_str(&text).map_err(|e| format!("grid {}: {e}", path.display()))?
        );
    }
    Ok(local.square_grid(geometry, args.size, args.pixel_mm)?)
}

/// Whether `--input` names a scanner's scan (`.xtekct`, Zeiss `.txrm`/`.xrm`, NXtomo `.nx`/`.nxs`/`.h5`/
/// `.hdf5`, SkyScan `.log`, `.tif`/`.tiff`, or a folder) rather than a `.npy`.
fn is_scan(input: &Path) -> bool {
    input.is_dir() || scans::detect::is_scan_file(input)
}

/// Open a scan and say what was read from where.
fn open_scan(input: &Path) -> CliResult<Scan> {
    let scan = scans::open(input)?;
    let (nv, nu) = scan.views.shape();
    eprintln!(
        "scan {}: {} views of {nu} × {nv} ({})",
        scan.format,
        scan.views.view_count(),
        input.display()
    );
    for p in &scan.provenance {
        eprintln!("  {} = {} ({})", p.key, p.value, p.origin);
    }
    for n in &scan.notes {
        eprintln!("  note: {n}");
    }
    Ok(scan)
}

/// The projections of a scan as line integrals (the minimal conversion of `scans::convert`).
/// `data` (`[view][v][u]`) put through `plan`: the kept views cropped, binned and linearised, then the
/// stripe filter on every detector row's sinogram.
fn preprocess(data: ArrayD<f32>, plan: &PrepPlan) -> CliResult<ArrayD<f32>> {
    let data = data
        .into_dimensionality::<Ix3>()
        .map_err(|_| "--preprocessing works on projections [view][v][u]")?;
    let (n, nv, nu) = data.dim();
    let bad = |e: crate::recon::ReconError| format!("--preprocessing: {e}");
    plan.check(n, nv, nu).map_err(bad)?;
    let kept = plan.kept_views(n).map_err(bad)?;
    let (pv, pu) = plan.view_shape(nv, nu).map_err(bad)?;
    let mut out = ndarray::Array3::<f32>::zeros((kept.len(), pv, pu));
    for (o, &k) in kept.iter().enumerate() {
        let view = plan.apply_view(data.index_axis(Axis(0), k)).map_err(bad)?;
        out.index_axis_mut(Axis(0), o).assign(&view);
    }
    plan.apply_stripes(out.view_mut()).map_err(bad)?;
    eprintln!(
        "preprocessing: {}",
        serde_json::Value::Array(plan.steps(n, kept.len()))
    );
    Ok(out.into_dyn())
}

fn scan_data(scan: &mut Scan, max_bytes: u64) -> CliResult<ArrayD<f32>> {
    let li = scans::line_integrals(scan, max_bytes)?;
    eprintln!(
        "line integrals: {} pixels clamped at transmission {}",
        li.clamped,
        scans::TRANSMISSION_FLOOR
    );
    if li.shifted_views > 0 {
        eprintln!(
            "  {} views moved by the scanner's alignment shifts",
            li.shifted_views
        );
    }
    Ok(li.projections.into_dyn())
}

/// `--centre`: `auto` (found from the views unless the scan states a calibrated centre, or `--geometry`
/// gives one), `find`, `read`, or a u offset in mm.
fn centre_policy(args: &ReconArgs) -> CliResult<CentrePolicy> {
    match CentrePolicy::parse(&args.centre) {
        Some(CentrePolicy::Auto) if args.geometry.is_some() => Ok(CentrePolicy::Read),
        Some(policy) => Ok(policy),
        None => Err(format!(
            "--centre {:?}: give auto, find, read or a detector u offset in mm",
            args.centre
        )
        .into()),
    }
}

pub fn run(args: ReconArgs) -> CliResult<()> {
    let mut scan = if is_scan(&args.input) {
        Some(open_scan(&args.input)?)
    } else {
        None
    };
    let mut geometry = match (&args.geometry, &scan) {
        (Some(path), _) => read_geometry(path)?,
        (None, Some(scan)) => scan.geometry.clone(),
        (None, None) => read_geometry(&sidecar(&args.input))?,
    };
    let plan: PrepPlan = match &args.preprocessing {
        Some(text) => serde_json::from_str(text).map_err(|e| format!("--preprocessing: {e}"))?,
        None => PrepPlan::default(),
    };
    if !plan.is_empty() {
        geometry = plan
            .geometry(&geometry)
            .map_err(|e| format!("--preprocessing: {e}"))?;
    }
    let policy = centre_policy(&args)?;
    let local = Local::new(args.max_bytes);
    let grid = output_grid(&args, &local, &geometry)?;
    let algorithm = algorithm_spec(&args)?;
    // What cannot fit is refused before anything is read.
    let mut admitted = local.admit_reconstruction(Reconstruction {
        geometry: geometry.clone(),
        algorithm: algorithm.clone(),
        grid,
    })?;
    let data = match &mut scan {
        Some(scan) => scan_data(scan, args.max_bytes)?,
        None => read_npy(&args.input)?,
    };
    let data = if plan.is_empty() {
        data
    } else {
        preprocess(data, &plan)?
    };
    if let Some(scan) = &scan {
        let projections = data
            .view()
            .into_dimensionality::<Ix3>()
            .map_err(|e| format!("a scan's projections are [view][v][u]: {e}"))?;
        let c = calibrate(&mut geometry, &projections, &scan.provenance, policy)?;
        match &c.estimate {
            Some(e) => eprintln!(
                "centre of rotation: found, detector offset_u_mm = {:.4} ({:.2} px, {:?}, {} views, residual {:.2e})",
                c.offset_u_mm, e.offset_u_px, e.method, e.views_used, e.residual
            ),
            None => eprintln!(
                "centre of rotation: {}, detector offset_u_mm = {:.4}",
                c.centre, c.offset_u_mm
            ),
        }
        admitted = local.admit_reconstruction(Reconstruction {
            geometry,
            algorithm,
            grid,
        })?;
    }
    let cancel = Cancel::new();
    let bar = Bar::new();
    let out = super::on_pool(|| local.reconstruct(&admitted, data.view(), &bar, &cancel));
    bar.finish();
    let out = out?;
    write_npy(&args.output, &out)?;
    eprintln!("wrote {} {:?}", args.output.display(), out.shape());
    if let Some(png) = &args.png {
        let slice = match out.ndim() {
            3 => {
                let nz = out.shape()[0];
                let k = args.slice.unwrap_or(nz / 2);
                if k >= nz {
                    return Err(format!("--slice {k} is outside 0..{nz}").into());
                }
                out.index_axis(Axis(0), k)
                    .into_dimensionality::<Ix2>()
                    .map_err(|e| e.to_string())?
            }
            _ => out
                .view()
                .into_dimensionality::<Ix2>()
                .map_err(|e| e.to_string())?,
        };
        write_png(png, slice, args.ww, args.wl)?;
        eprintln!("wrote {}", png.display());
    }
    Ok(())
}

/// Map `value` through the window [level − width/2, level + width/2] to 0..=255.
pub fn window_level(slice: ArrayView2<'_, f32>, ww: Option<f64>, wl: Option<f64>) -> Vec<u8> {
    let (lo, hi) = slice.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &v| {
        (lo.min(v as f64), hi.max(v as f64))
    });
    let width = ww.unwrap_or(hi - lo);
    let level = wl.unwrap_or((lo + hi) / 2.0);
    let bottom = level - width / 2.0;
    slice
        .iter()
        .map(|&v| {
            let t = if width > 0.0 {
                (v as f64 - bottom) / width
            } else {
                0.0
            };
            (t.clamp(0.0, 1.0) * 255.0).round() as u8
        })
        .collect()
}

fn write_png(
    path: &Path,
    slice: ArrayView2<'_, f32>,
    ww: Option<f64>,
    wl: Option<f64>,
) -> CliResult<()> {
    if let Some(w) = ww
        && !(w.is_finite() && w > 0.0)
    {
        return Err(format!("--ww must be positive, got {w}").into());
    }
    let (h, w) = slice.dim();
    let pixels = window_level(slice, ww, wl);
    let file =
        std::fs::File::create(path).map_err(|e| format!("writing {}: {e}", path.display()))?;
    let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), w as u32, h as u32);
    encoder.set_color(png::ColorType::Grayscale);
    encoder.set_depth(png::BitDepth::Eight);
    // A reconstruction has no patient: the screen sides are the image axes ([y][x], row 0 at the smallest y).
    encoder.add_text_chunk(
        "Orientation".into(),
        r#"{"left":"-x","right":"+x","top":"-y","bottom":"+y"}"#.into(),
    )?;
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&pixels)?;
    writer.finish()?;
    Ok(())
}
