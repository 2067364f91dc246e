//! Admission: everything about a job or a simulation that can be checked before it is accepted — the
//! geometry, the grid, the algorithm's parameters, the requested outputs and the memory it will need. A job
//! that can never fit the memory budget is refused here, not failed later.

use crate::error_code::{ErrorCode, Problem, field_pointer};
use crate::recon::algorithm::{AlgorithmSpec, FbpParams, OutputGrid, check_grid, estimate_bytes};
use crate::recon::geometry::{Geometry, Views};
use crate::recon::grid::Limits;
use crate::recon::iterative::params::InitialImage;
use crate::recon::phantom::{MAX_BODIES, MAX_INCIDENT_PHOTONS};
use crate::recon::{GeometryError, ReconError};

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

/// The problem of a core error about the part of the request body at `base` (a JSON Pointer), naming the
/// field it is about in `errors`.
pub fn recon_problem_at(e: &ReconError, base: &str) -> Problem {
    let p = recon_problem(e);
    match e {
        ReconError::Geometry(g) => p.at(geometry_pointer(g, base)),
        ReconError::InvalidParameter { name, .. } if base.ends_with(&format!("/{name}")) => {
            p.at(base)
        }
        ReconError::InvalidParameter { name, .. } if is_field_path(name) => {
            p.at(field_pointer(base, name))
        }
        _ => p.at(base),
    }
}

/// Whether a core field name is a path into the request (`detector.nu`, `centre_mm[0]`), not a phrase.
fn is_field_path(name: &str) -> bool {
    !name.is_empty()
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'_' | b'.' | b'[' | b']'))
}

/// The pointer of the geometry field (under `base`, the geometry's own pointer) a geometry error is about.
fn geometry_pointer(g: &GeometryError, base: &str) -> String {
    use GeometryError as G;
    match g {
        G::NonFinite { field, .. }
        | G::NonPositive { field, .. }
        | G::Zero { field }
        | G::TooMany { field, .. }
            if is_field_path(field) =>
        {
            field_pointer(base, field)
        }
        G::DetectorInsideOrbit { .. } => field_pointer(base, "dsd_mm"),
        G::SourceInsideFov { .. } => field_pointer(base, "dso_mm"),
        G::FanTooWide { .. } => field_pointer(base, "detector"),
        G::ShortScanTooShort { .. } => field_pointer(base, "angles"),
        G::AnglesNotMonotonic { index } => field_pointer(base, &format!("angles.degrees[{index}]")),
        _ => base.to_string(),
    }
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
            crate::recon::iterative::check_views(spec, views)?;
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
    let views = check_reconstruction(&dataset.geometry, &req.grid, &req.algorithm)?;
    if req.wants_metrics() && dataset.kind != DatasetKind::Simulation {
        return Err(Problem::new(
            ErrorCode::InvalidParameter,
            "`metrics` needs a simulated input (POST /v1/simulations): uploads have no truth",
        )
        .at("/outputs"));
    }
    let input = dataset.shape.iter().product::<usize>() as u64;
    reconstruction_bytes(
        &req.algorithm,
        &views,
        &req.grid,
        input,
        req.wants_metrics(),
        budget_bytes,
    )
}

/// Check a reconstruction of data acquired with `geometry` onto `grid` by `algorithm`: the geometry, the grid
/// and its field of view, the algorithm's parameters against the views. Returns the views. Problems about the
/// geometry point at `/input` (a job's geometry is its dataset's), the others at `/grid` or `/algorithm`.
pub fn check_reconstruction(
    geometry: &Geometry,
    grid: &OutputGrid,
    algorithm: &AlgorithmSpec,
) -> Result<Views, Problem> {
    let views = geometry
        .to_views()
        .map_err(|e| recon_problem(&e.into()).at("/input"))?;
    check_grid(&views, grid).map_err(|e| {
        let pointer = recon_problem_at(&e, "/grid")
            .errors
            .pop()
            .map_or_else(|| "/grid".to_string(), |f| f.pointer);
        Problem::new(ErrorCode::InvalidParameter, format!("grid: {e}")).at(pointer)
    })?;
    geometry
        .check_fov(grid_radius_mm(grid))
        .map_err(|e| recon_problem(&e.into()).at("/grid"))?;
    check_algorithm(algorithm, &views).map_err(|e| match &e {
        ReconError::Geometry(_) => recon_problem(&e).at("/input"),
        ReconError::InvalidParameter { name, .. } if *name == "geometry" => {
            recon_problem(&e).at("/input")
        }
        _ => recon_problem_at(&e, "/algorithm"),
    })?;
    Ok(views)
}

/// The bytes a reconstruction needs (the algorithm's working memory, its input of `input_elements` values,
/// the output grid and, `with_truth`, the phantom rasterised for metrics); refused (`job_too_large`) above the
/// whole `budget_bytes`.
pub fn reconstruction_bytes(
    algorithm: &AlgorithmSpec,
    views: &Views,
    grid: &OutputGrid,
    input_elements: u64,
    with_truth: bool,
    budget_bytes: u64,
) -> Result<u64, Problem> {
    let input = Limits::f32_bytes(input_elements);
    let voxels = Limits::f32_bytes(grid_voxels(grid));
    let truth = if with_truth { voxels } else { 0 };
    let need = estimate_bytes(algorithm, views, grid)
        .saturating_add(input)
        .saturating_add(voxels)
        .saturating_add(truth);
    if need > budget_bytes {
        return Err(Problem::new(
            ErrorCode::JobTooLarge,
            format!(
                "the job needs about {need} bytes, more than the whole memory budget of {budget_bytes} bytes: \
                 reconstruct onto a smaller grid (or from fewer views), or raise the service's memory_budget_bytes"
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
        .map_err(|e| recon_problem_at(&e.into(), "/geometry"))?;
    let bodies = match &views {
        Views::D2(_) => req.phantom.phantom2().map(|p| p.ellipses.len()),
        Views::D3(_) | Views::Slices(_) => req.phantom.phantom3().map(|p| p.ellipsoids.len()),
    }
    .map_err(|e| recon_problem_at(&e, "/phantom"))?;
    if bodies > MAX_BODIES {
        return Err(Problem::new(
            ErrorCode::InvalidParameter,
            format!("at most {MAX_BODIES} ellipses or ellipsoids"),
        )
        .at("/phantom"));
    }
    req.geometry
        .check_fov(req.phantom.scale_mm)
        .map_err(|e| recon_problem(&e.into()).at("/phantom/scale_mm"))?;
    if let Some(noise) = &req.noise {
        let i0 = noise.incident_photons;
        if !(i0.is_finite() && i0 > 0.0 && i0 <= MAX_INCIDENT_PHOTONS) {
            return Err(Problem::new(
                ErrorCode::InvalidParameter,
                format!(
                    "`noise.incident_photons` must be in (0, {MAX_INCIDENT_PHOTONS:e}], got {i0}"
                ),
            )
            .at("/noise/incident_photons"));
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
        )
        .at("/geometry"));
    }
    Ok(views)
}
