//! Volume jobs: image-domain processing of a CT series (HU) or of a reconstructed volume (μ), through the same
//! job API as reconstructions. A job applies `steps` (isotropic resampling, Gaussian or median smoothing) in
//! order, writes the processed volume, then makes `products`: projections (MIP/MinIP/average) along an axis,
//! MPR planes (axial, coronal, sagittal or oblique; thin or thick slabs; single or a series), curved MPR along
//! a polyline, a rotating projection, and iso-surface meshes.
//!
//! Everything a request asks for is planned first ([`plan`]): defaults resolved, parameters checked and the
//! memory estimated from the input's shape and frame alone, so a job that cannot run is refused at
//! submission. Execution ([`execute_volume`]) runs on the worker pool and checks the cancel flag between steps
//! and products.
use ndarray::Ix3;

use super::database::Database;
use super::model::*;
use super::model::{Job, JobResult, JobStatus, Notice, VolumeUnits, fill_value};
use super::run::RunError;
use super::store::DbError;
use super::views::volume_problem;
use crate::error_code::{ErrorCode, Problem};
use crate::recon::control::Control;
use crate::recon::grid::VolumeGrid;
use crate::storage::npy::{decode_f32, encode_f32};
use crate::storage::{AnyId, BlobStore, JobId, ResultName, SeriesId};
use crate::volume::{Volume, gaussian, median3, resample_isotropic};

mod plan;
mod products;

pub use plan::*;
use products::{Looks, file_info, io_failure, make_product};

/// The input of a volume job, resolved by the engine.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeInput {
    /// The `.npy` file of the volume (float32 `[z][y][x]`).
    pub path: std::path::PathBuf,
    pub shape: VolumeShape,
    pub units: VolumeUnits,
    pub source_series: Option<SeriesId>,
    pub warnings: Vec<Notice>,
    /// How the input volume was derived when it is not a DICOM series (a reconstruction of a scan).
    pub derivation: Option<String>,
}

/// Find the volume a job reads: a stored series, or the volume of a succeeded job.
pub async fn resolve_input(
    db: &Database,
    store: &BlobStore,
    id: AnyId,
) -> Result<VolumeInput, Problem> {
    let db_failure = |e: DbError| {
        tracing::error!(error = %e, "resolving a volume input failed");
        Problem::internal()
    };
    let text = id.to_string();
    if let Ok(sid) = SeriesId::parse(&text)
        && let Some(r) = db.get_series(sid).await.map_err(db_failure)?
    {
        return Ok(VolumeInput {
            path: store.series_path(sid),
            shape: VolumeShape {
                dim: (r.shape[0], r.shape[1], r.shape[2]),
                frame: r.frame,
                max_value: Some(r.hu_max),
            },
            units: VolumeUnits::Hu,
            source_series: Some(sid),
            warnings: r.warnings,
            derivation: None,
        });
    }
    let Ok(jid) = JobId::parse(&text) else {
        return Err(Problem::new(
            ErrorCode::SeriesNotFound,
            format!("no series or job {id}"),
        ));
    };
    match db.get_job(jid).await.map_err(db_failure)? {
        None => Err(Problem::new(
            ErrorCode::SeriesNotFound,
            format!("no series or job {id}"),
        )),
        Some(job) => match (job.status, job.result) {
            (JobStatus::Succeeded, Some(r)) => Ok(VolumeInput {
                path: store.result_path(jid, &ResultName::Volume),
                shape: VolumeShape {
                    dim: (r.shape[0], r.shape[1], r.shape[2]),
                    frame: r.frame(),
                    max_value: Some(r.max),
                },
                units: r.units,
                source_series: r.source_series,
                warnings: Vec::new(),
                derivation: r.derivation,
            }),
            (status, _) => Err(Problem::new(
                ErrorCode::JobNotSucceeded,
                format!(
                    "job {id} is {}: only a succeeded job's volume can be processed",
                    status.as_str()
                ),
            )),
        },
    }
}

/// The grid of a frame for [`JobResult::grid`]: sample counts, spacing and the centre of the box.
fn grid_of(shape: &VolumeShape) -> VolumeGrid {
    let (nz, ny, nx) = shape.dim;
    VolumeGrid {
        nx,
        ny,
        nz,
        spacing_mm: shape.frame.spacing_mm,
        centre_mm: shape.centre(),
    }
}

/// Run a planned volume job: load the input, apply the steps, write the volume and every product atomically.
/// Renderings of a μ volume take their HU values through `mu_water` (/mm).
pub fn execute_volume(
    store: &BlobStore,
    job: &Job,
    req: &VolumeJobRequest,
    input: &VolumeInput,
    budget_bytes: u64,
    mu_water: f64,
    ctl: Control<'_>,
) -> Result<JobResult, RunError> {
    ctl.step("loading", 0.0);
    let plan = plan(req, input.shape, budget_bytes).map_err(RunError::Failed)?;
    let bytes = store
        .local(&input.path)
        .and_then(std::fs::read)
        .map_err(|e| io_failure("reading the input volume", e))?;
    let data = decode_f32(&bytes)
        .ok()
        .and_then(|a| a.into_dimensionality::<Ix3>().ok())
        .ok_or_else(|| {
            tracing::error!("the input volume is not a 3D float32 array");
            RunError::Failed(Problem::internal())
        })?;
    drop(bytes);
    let fill = fill_value(input.units);
    let mut vol = Volume {
        data,
        frame: input.shape.frame,
    };
    let total = (req.steps.len() + plan.products.len() + 1) as f64;
    for (i, step) in req.steps.iter().enumerate() {
        ctl.check()?;
        ctl.step(step_name(step), 0.02 + 0.9 * i as f64 / total);
        vol = match *step {
            Step::Resample { spacing_mm } => {
                resample_isotropic(&vol, spacing_mm, fill, budget_bytes / 4)
                    .map_err(|e| RunError::Failed(volume_problem(&e)))?
            }
            Step::Gaussian { sigma_mm } => Volume {
                data: gaussian(vol.data.view(), vol.frame.spacing_mm, sigma_mm)
                    .map_err(|e| RunError::Failed(volume_problem(&e)))?,
                frame: vol.frame,
            },
            Step::Median => Volume {
                data: median3(vol.data.view()),
                frame: vol.frame,
            },
        };
    }
    ctl.check()?;
    let (mut min, mut max, mut sum) = (f32::INFINITY, f32::NEG_INFINITY, 0.0f64);
    for &v in vol.data.iter() {
        min = min.min(v);
        max = max.max(v);
        sum += v as f64;
    }
    // Shaded surfaces that the steps (or a series known only once pulled) left above every value.
    let surface_warnings = super::iso_range::warn_surfaces_above(req, max, input.units, mu_water);
    let mut products = Vec::with_capacity(plan.products.len());
    for (index, p) in plan.products.iter().enumerate() {
        ctl.check()?;
        ctl.step(
            "products",
            0.02 + 0.9 * (req.steps.len() + index) as f64 / total,
        );
        products.push(make_product(
            store,
            job,
            &vol,
            index,
            p,
            &req.products[index],
            Looks {
                fill,
                patient: input.source_series.is_some(),
                units: input.units,
                mu_water,
            },
        )?);
    }
    ctl.check()?;
    ctl.step("writing", 0.95);
    let encoded = encode_f32(vol.data.view());
    let volume = file_info(&encoded);
    store
        .write_atomic(&store.result_path(job.id, &ResultName::Volume), &encoded)
        .map_err(|e| io_failure("writing the volume", e))?;
    let finite = |v: f64| if v.is_finite() { v } else { 0.0 };
    let (nz, ny, nx) = vol.data.dim();
    ctl.step("done", 1.0);
    Ok(JobResult {
        shape: [nz, ny, nx],
        grid: grid_of(&plan.output),
        volume,
        min: finite(min as f64) as f32,
        max: finite(max as f64) as f32,
        mean: finite(sum / vol.data.len().max(1) as f64),
        metrics: None,
        units: input.units,
        frame: Some(vol.frame),
        source_series: input.source_series,
        derivation: input.derivation.clone(),
        products,
        // An isotropic resample makes the grid orthogonal: warnings about the input grid no longer apply.
        warnings: input
            .warnings
            .iter()
            .filter(|w| {
                !(req.steps.iter().any(|s| matches!(s, Step::Resample { .. }))
                    && crate::series::stale_after_resample(&w.code))
            })
            .cloned()
            .chain(surface_warnings)
            .collect(),
    })
}

fn step_name(s: &Step) -> &'static str {
    match s {
        Step::Resample { .. } => "resample",
        Step::Gaussian { .. } => "gaussian",
        Step::Median => "median",
    }
}

#[cfg(test)]
mod tests;
