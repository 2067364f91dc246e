//! The work itself, run on the rayon pool (never on the async runtime): simulate a dataset, and execute a
//! reconstruction job — load the input, reconstruct, write the volume and the metrics atomically.

use ndarray::{Array3, ArrayD, ArrayView3, Axis, Ix3};
use sha2::{Digest, Sha256};

use super::model::{
    Dataset, FileInfo, ImageConvention, Job, JobRequest, JobResult, Quality, SimulationRequest,
    VolumeUnits, scan_derivation,
};
use super::plan::recon_problem;
use super::quality::quality;
use crate::error_code::{ErrorCode, Problem};
use crate::recon::algorithm::{OutputGrid, reconstruct};
use crate::recon::control::{Control, Progress};
use crate::recon::geometry::Views;
use crate::recon::grid::{Limits, VolumeGrid};
use crate::recon::phantom::poisson_noise;
use crate::recon::{ReconError, phantom::PhantomSpec};
use crate::storage::npy::{decode_f32, encode_f32, hex};
use crate::storage::{BlobStore, ResultName};
use crate::volume::{Frame, flip_rows};

/// How a job run ends when it does not succeed.
#[derive(Debug, Clone, PartialEq)]
pub enum RunError {
    Canceled,
    Failed(Problem),
}

impl From<ReconError> for RunError {
    fn from(e: ReconError) -> Self {
        match e {
            ReconError::Canceled => RunError::Canceled,
            other => RunError::Failed(recon_problem(&other)),
        }
    }
}

fn io_failure(what: &str, e: std::io::Error) -> RunError {
    tracing::error!(error = %e, "{what}");
    RunError::Failed(Problem::internal())
}

/// The exact projections of a simulation, with Poisson noise if asked.
pub fn simulate(req: &SimulationRequest, views: &Views) -> Result<ArrayD<f32>, Problem> {
    let mut data = match views {
        Views::D2(v) => req
            .phantom
            .phantom2()
            .map_err(|e| recon_problem(&e))?
            .project(v)
            .into_dyn(),
        Views::D3(v) => req
            .phantom
            .phantom3()
            .map_err(|e| recon_problem(&e))?
            .project(v)
            .into_dyn(),
        Views::Slices(v) => req
            .phantom
            .phantom3()
            .map_err(|e| recon_problem(&e))?
            .project_parallel(v)
            .into_dyn(),
    };
    if let Some(noise) = &req.noise {
        poisson_noise(data.view_mut(), noise.incident_photons, noise.seed)
            .map_err(|e| recon_problem(&e))?;
    }
    Ok(data)
}

/// Progress of the reconstruction mapped into `[lo, hi]` of the job.
struct Scaled<'a> {
    inner: &'a dyn Progress,
    lo: f64,
    hi: f64,
}

impl Progress for Scaled<'_> {
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>) {
        let f = self.lo + (self.hi - self.lo) * fraction.clamp(0.0, 1.0);
        self.inner.report(stage, f, iteration, residual);
    }
}

/// The volume grid of an output grid (a 2D image becomes one slice `dx_mm` thick).
pub fn volume_grid(grid: &OutputGrid) -> VolumeGrid {
    match grid {
        OutputGrid::Volume(g) => *g,
        OutputGrid::Image(g) => VolumeGrid {
            nx: g.nx,
            ny: g.ny,
            nz: 1,
            spacing_mm: [g.dx_mm, g.dy_mm, g.dx_mm],
            centre_mm: [g.centre_mm[0], g.centre_mm[1], 0.0],
        },
    }
}

/// The phantom on the output grid; a volume is rasterised slice by slice with cancel checks (seconds
/// for a few hundred slices at supersampling 2).
fn truth(
    phantom: &PhantomSpec,
    grid: &OutputGrid,
    s: usize,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    Ok(match grid {
        OutputGrid::Image(g) => phantom.phantom2()?.rasterize(g, s).insert_axis(Axis(0)),
        OutputGrid::Volume(g) => phantom.phantom3()?.rasterize_cancelable(g, s, ctl)?,
    })
}

/// Run job `job` on `dataset`: every file is written atomically, and only after the reconstruction
/// succeeded, so a canceled, failed or killed run leaves no result behind.
pub fn execute(
    store: &BlobStore,
    job: &Job,
    req: &JobRequest,
    dataset: &Dataset,
    limits: &Limits,
    ctl: Control<'_>,
) -> Result<JobResult, RunError> {
    ctl.step("loading", 0.0);
    let bytes = store
        .local(&store.dataset_path(dataset.id))
        .and_then(std::fs::read)
        .map_err(|e| io_failure("reading the dataset", e))?;
    let data = decode_f32(&bytes)
        .map_err(|e| RunError::Failed(Problem::new(ErrorCode::MalformedNpy, e.to_string())))?;
    drop(bytes);
    ctl.check()?;
    let views = dataset.geometry.to_views().map_err(ReconError::from)?;
    let scaled = Scaled {
        inner: ctl.progress,
        lo: 0.02,
        hi: 0.9,
    };
    let out = reconstruct(
        &req.algorithm,
        &views,
        data.view(),
        &req.grid,
        limits,
        Control::new(ctl.cancel, &scaled),
    )?;
    drop(data);
    ctl.check()?;
    let vol: Array3<f32> = match out.ndim() {
        2 => out.insert_axis(Axis(0)),
        _ => out,
    }
    .into_dimensionality::<Ix3>()
    .map_err(|e| RunError::Failed(Problem::new(ErrorCode::Internal, e.to_string())))?;
    let metrics = match (&dataset.phantom, req.wants_metrics()) {
        (Some(phantom), true) => {
            ctl.step("metrics", 0.9);
            let s = if vol.len_of(Axis(0)) == 1 { 4 } else { 2 };
            let t = truth(phantom, &req.grid, s, ctl)?;
            Some(quality(vol.view(), t.view(), s, ctl)?)
        }
        _ => None,
    };
    ctl.check()?;
    ctl.step("writing", 0.95);
    let (vol, frame) = match req.image_convention {
        ImageConvention::Ctrecon => (vol, None),
        ImageConvention::Astra => {
            // Rows run from the largest y down; the frame says so, so positions stay exact.
            let g = volume_grid(&req.grid);
            let mut f = Frame::from_grid(&g);
            f.origin_mm[1] = g.y(g.ny - 1);
            f.direction[1] = [0.0, -1.0, 0.0];
            (flip_rows(vol), Some(f))
        }
    };
    let mut result = write_volume(store, job, vol.view(), &req.grid, metrics)?;
    result.frame = frame;
    result.derivation = dataset
        .scan
        .as_ref()
        .map(|scan| scan_derivation(req.algorithm.name(), scan));
    ctl.step("done", 1.0);
    Ok(result)
}

fn write_volume(
    store: &BlobStore,
    job: &Job,
    vol: ArrayView3<'_, f32>,
    grid: &OutputGrid,
    metrics: Option<Quality>,
) -> Result<JobResult, RunError> {
    let (mut min, mut max, mut sum) = (f32::INFINITY, f32::NEG_INFINITY, 0.0f64);
    for &v in vol.iter() {
        min = min.min(v);
        max = max.max(v);
        sum += v as f64;
    }
    let encoded = encode_f32(vol);
    let info = FileInfo {
        bytes: encoded.len() as u64,
        sha256: hex(&Sha256::digest(&encoded)),
    };
    if let Some(m) = &metrics {
        let text = serde_json::to_vec_pretty(m).unwrap_or_default();
        store
            .write_atomic(&store.result_path(job.id, &ResultName::Metrics), &text)
            .map_err(|e| io_failure("writing metrics", e))?;
    }
    store
        .write_atomic(&store.result_path(job.id, &ResultName::Volume), &encoded)
        .map_err(|e| io_failure("writing the volume", e))?;
    let (nz, ny, nx) = vol.dim();
    // JSON has no NaN or infinity: a statistic that is not finite is reported as 0.
    let finite = |v: f64| if v.is_finite() { v } else { 0.0 };
    Ok(JobResult {
        shape: [nz, ny, nx],
        grid: volume_grid(grid),
        volume: info,
        min: finite(min as f64) as f32,
        max: finite(max as f64) as f32,
        mean: finite(sum / vol.len().max(1) as f64),
        metrics,
        units: VolumeUnits::MuPerMm,
        frame: None,
        source_series: None,
        products: Vec::new(),
        warnings: Vec::new(),
        derivation: None,
    })
}
