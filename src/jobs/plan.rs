//! Admission: everything about a job or a simulation that can be checked before it is accepted — the
//! geometry, the grid, the algorithm's parameters, the requested outputs and the memory it will need. A job
//! that can never fit the memory budget is refused here, not failed later.

use crate::error_code::{ErrorCode, Problem};
use crate::recon::ReconError;
use crate::recon::algorithm::{AlgorithmSpec, FbpParams, OutputGrid, check_grid, estimate_bytes};
use crate::recon::geometry::Views;
use crate::recon::grid::Limits;
use crate::recon::iterative::params::InitialImage;
use crate::recon::phantom::MAX_BODIES;

use super::model::{Dataset, DatasetKind, JobRequest, SimulationRequest};

/// The catalogue problem of a reconstruction-core error.
pub fn recon_problem(e: &ReconError) -> Problem {
    let code = match e {
        ReconError::Geometry(_) => ErrorCode::InvalidGeometry,
        ReconError::ShapeMismatch { .. } => ErrorCode::ShapeMismatch,
        ReconError::NonFinite { .. } => ErrorCode::NonFiniteData,
        ReconError::InvalidParameter { .. } => ErrorCode::InvalidParameter,
        ReconError::TooLarge { .. } => ErrorCode::JobTooLarge,
        ReconError::Canceled => ErrorCode::ReconstructionFailed,
    };
    Problem::new(code, e.to_string())
}

fn count_of_views(views: &Views) -> usize {
    views.data_shape().first().copied().unwrap_or(0)
}

/// Check an algorithm's parameters against the data it will run on.
pub fn check_algorithm(spec: &AlgorithmSpec, views: &Views) -> Result<(), ReconError> {
    let n_views = count_of_views(views);
    match spec {
        // The analytic family: everything FBP/FDK refuse about the orbit and the filtered row length.
        AlgorithmSpec::Fbp(p) | AlgorithmSpec::Fdk(p) => crate::recon::analytic::check(views, p)?,
        // The iterative family: the core's own checks (ranges, subsets against the views, box bounds), and
        // those of the FBP that starts it when asked to.
        _ => {
            crate::recon::iterative::validate(spec, n_views)?;
            if starts_from_fbp(spec) {
                crate::recon::analytic::check(views, &FbpParams::default())?;
            }
        }
    }
    Ok(())
}

fn starts_from_fbp(spec: &AlgorithmSpec) -> bool {
    let initial = match spec {
        AlgorithmSpec::Art(p) => p.initial,
        AlgorithmSpec::Sart(p) | AlgorithmSpec::OsSart(p) => p.initial,
        AlgorithmSpec::Sirt(p) => p.initial,
        AlgorithmSpec::Cgls(p) => p.initial,
        AlgorithmSpec::Tv(p) => p.initial,
        AlgorithmSpec::Mlem(_) | AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_) => return false,
    };
    initial == InitialImage::Fbp
}

fn grid_voxels(grid: &OutputGrid) -> u64 {
    match grid {
        OutputGrid::Image(g) => (g.nx as u64).saturating_mul(g.ny as u64),
        OutputGrid::Volume(g) => g.voxels(),
    }
}

/// Radius (mm) of the circle around the isocentre that holds the grid.
fn grid_radius_mm(grid: &OutputGrid) -> f64 {
    match grid {
        OutputGrid::Image(g) => g.enclosing_radius_mm(),
        OutputGrid::Volume(g) => g.slice_grid().enclosing_radius_mm(),
    }
}

/// Check a job against its input and the memory budget; returns the bytes it will need.
pub fn admit_job(req: &JobRequest, dataset: &Dataset, budget_bytes: u64) -> Result<u64, Problem> {
    let views = dataset
        .geometry
        .to_views()
        .map_err(|e| recon_problem(&e.into()))?;
    check_grid(&views, &req.grid)
        .map_err(|e| Problem::new(ErrorCode::InvalidParameter, format!("grid: {e}")))?;
    dataset
        .geometry
        .check_fov(grid_radius_mm(&req.grid))
        .map_err(|e| recon_problem(&e.into()))?;
    check_algorithm(&req.algorithm, &views).map_err(|e| recon_problem(&e))?;
    if req.wants_metrics() && dataset.kind != DatasetKind::Simulation {
        return Err(Problem::new(
            ErrorCode::InvalidParameter,
            "`metrics` needs a simulated input (POST /v1/simulations): uploads have no truth",
        ));
    }
    let input = Limits::f32_bytes(dataset.shape.iter().product::<usize>() as u64);
    let voxels = Limits::f32_bytes(grid_voxels(&req.grid));
    let truth = if req.wants_metrics() { voxels } else { 0 };
    let need = estimate_bytes(&req.algorithm, &views, &req.grid)
        .saturating_add(input)
        .saturating_add(voxels)
        .saturating_add(truth);
    if need > budget_bytes {
        return Err(Problem::new(
            ErrorCode::JobTooLarge,
            format!(
                "the job needs about {need} bytes, more than the whole memory budget of {budget_bytes} bytes"
            ),
        ));
    }
    Ok(need)
}

/// Check a simulation request; returns its views.
pub fn admit_simulation(req: &SimulationRequest, max_elements: u64) -> Result<Views, Problem> {
    let views = req
        .geometry
        .to_views()
        .map_err(|e| recon_problem(&e.into()))?;
    let bodies = match &views {
        Views::D2(_) => req.phantom.phantom2().map(|p| p.ellipses.len()),
        Views::D3(_) => req.phantom.phantom3().map(|p| p.ellipsoids.len()),
    }
    .map_err(|e| recon_problem(&e))?;
    if bodies > MAX_BODIES {
        return Err(Problem::new(
            ErrorCode::InvalidParameter,
            format!("at most {MAX_BODIES} ellipses or ellipsoids"),
        ));
    }
    req.geometry
        .check_fov(req.phantom.scale_mm)
        .map_err(|e| recon_problem(&e.into()))?;
    if let Some(noise) = &req.noise {
        let i0 = noise.incident_photons;
        if !(i0.is_finite() && i0 > 0.0 && i0 <= 1e15) {
            return Err(Problem::new(
                ErrorCode::InvalidParameter,
                format!("`noise.incident_photons` must be in (0, 1e15], got {i0}"),
            ));
        }
    }
    let elements = views
        .data_shape()
        .iter()
        .fold(1u64, |a, &n| a.saturating_mul(n as u64));
    if elements > max_elements {
        return Err(Problem::new(
            ErrorCode::ArrayTooLarge,
            format!(
                "the projections would have {elements} values, more than the limit of {max_elements}"
            ),
        ));
    }
    Ok(views)
}
