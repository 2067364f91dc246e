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

use ndarray::{Array3, Axis as NdAxis, Ix3};
use sha2::{Digest, Sha256};

use super::database::Database;
use super::model::{
    FileInfo, Job, JobResult, JobStatus, Notice, ProductResult, VolumeUnits, fill_value,
};
use super::render_products::{RenderSpec, make_render_product, plan_render};
use super::repo::DbError;
use super::run::RunError;
use super::views::volume_problem;
pub use super::volume_spec::*;
use crate::error_code::{ErrorCode, Problem};
use crate::mesh::{MeshOptions, extract};
use crate::recon::control::Control;
use crate::recon::grid::VolumeGrid;
use crate::storage::npy::{decode_f32, encode_f32, hex};
use crate::storage::{AnyId, BlobStore, JobId, ResultName, SeriesId};
use crate::volume::{
    Axis, DisplayGrid, Frame, ImagePlane, MAX_SIDE, Plane, ProjectionKind, ScreenSides, Slab,
    Volume, curved, direction_label, gaussian, isotropic_grid, median3, oriented_projection,
    reformat, resample_isotropic, rotating_axes, rotating_projection, series_count, slab_series,
    whole_ceil,
};

/// Shape and placement of a volume, known before any data is read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeShape {
    /// `[nz, ny, nx]`.
    pub dim: (usize, usize, usize),
    pub frame: Frame,
    /// No value of the volume exceeds this, when known (the stored maximum of a series or result; after a
    /// step, at least 0, which covers the fill of resampling and the borders of smoothing).
    pub max_value: Option<f32>,
}

impl VolumeShape {
    fn voxels(&self) -> u64 {
        (self.dim.0 as u64) * (self.dim.1 as u64) * (self.dim.2 as u64)
    }
    fn smallest_spacing(&self) -> f64 {
        self.frame
            .spacing_mm
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
    }
    /// Patient positions of the eight corner voxels.
    fn corners(&self) -> [[f64; 3]; 8] {
        self.frame.corners(self.dim)
    }
    fn centre(&self) -> [f64; 3] {
        let c = self.corners();
        std::array::from_fn(|a| c.iter().map(|p| p[a]).sum::<f64>() / 8.0)
    }
    /// Half the extent of the volume along unit vector `d`, seen from `centre`.
    fn half_extent(&self, centre: [f64; 3], d: [f64; 3]) -> f64 {
        self.corners()
            .iter()
            .map(|p| {
                ((p[0] - centre[0]) * d[0] + (p[1] - centre[1]) * d[1] + (p[2] - centre[2]) * d[2])
                    .abs()
            })
            .fold(0.0, f64::max)
    }
}

/// A product with its defaults resolved.
#[derive(Debug, Clone, PartialEq)]
enum Planned {
    Projection {
        axis: Axis,
        kind: ProjectionKind,
        slab: Option<std::ops::Range<usize>>,
    },
    Mpr {
        plane: Plane,
        slab: Option<Slab>,
        /// `(spacing, extent)` of a series.
        series: Option<(f64, f64)>,
    },
    Curved {
        points: Vec<[f64; 3]>,
        down: Option<[f64; 3]>,
        height: usize,
        pixel_mm: f64,
    },
    Rotating {
        angles: Vec<f64>,
        kind: ProjectionKind,
    },
    Mesh(MeshOptions),
    Render(RenderSpec),
}

/// A checked volume job: the shape after the steps, the products with defaults resolved, the memory needed.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumePlan {
    pub output: VolumeShape,
    products: Vec<Planned>,
    pub estimate_bytes: u64,
}

fn invalid(detail: impl Into<String>) -> Problem {
    Problem::new(ErrorCode::InvalidParameter, detail)
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

fn principal_normal(axis: Axis) -> [f64; 3] {
    match axis {
        Axis::Axial => [0.0, 0.0, 1.0],
        Axis::Coronal => [0.0, 1.0, 0.0],
        // Columns then run anterior → posterior (anterior on the left, as radiographers read sagittal images).
        Axis::Sagittal => [-1.0, 0.0, 0.0],
    }
}

fn plan_mpr(s: &MprSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let normal = match (s.plane, s.normal) {
        (Some(a), None) => principal_normal(a),
        (None, Some(n)) if finite3(&n) => n,
        (None, Some(_)) => return Err(invalid(format!("products[{i}]: `normal` must be finite"))),
        _ => {
            return Err(invalid(format!(
                "products[{i}]: give exactly one of `plane` (axial, coronal, sagittal) and `normal`"
            )));
        }
    };
    let centre = match s.centre_mm {
        Some(c) if finite3(&c) => c,
        Some(_) => {
            return Err(invalid(format!(
                "products[{i}]: `centre_mm` must be finite"
            )));
        }
        None => shape.centre(),
    };
    let pixel = s.pixel_mm.unwrap_or_else(|| shape.smallest_spacing());
    // Orientation first (a 1×1 plane), then the size that covers the volume.
    let probe = Plane::oblique(centre, normal, [1, 1], pixel)
        .map_err(|e| invalid(format!("products[{i}]: {e}")))?;
    let size = match s.size {
        Some(sz) => sz,
        None => {
            let side = |d: [f64; 3]| {
                let n = whole_ceil(2.0 * shape.half_extent(centre, d) / pixel) + 1.0;
                n.clamp(1.0, MAX_SIDE as f64) as usize
            };
            [side(probe.u), side(probe.v)]
        }
    };
    let plane = Plane { size, ..probe };
    plane
        .validate()
        .map_err(|e| invalid(format!("products[{i}]: {e}")))?;
    if let Some(slab) = s.slab
        && !(slab.thickness_mm.is_finite() && slab.thickness_mm >= 0.0)
    {
        return Err(invalid(format!(
            "products[{i}]: slab `thickness_mm` must be finite and non-negative"
        )));
    }
    let series = match (s.spacing_mm, s.extent_mm) {
        (None, None) => None,
        (None, Some(_)) => {
            return Err(invalid(format!(
                "products[{i}]: `extent_mm` needs `spacing_mm`"
            )));
        }
        (Some(sp), ext) => {
            let ext = ext.unwrap_or_else(|| shape.half_extent(centre, plane.normal()));
            if !(sp.is_finite() && sp > 0.0 && ext.is_finite() && ext >= 0.0) {
                return Err(invalid(format!(
                    "products[{i}]: `spacing_mm` must be positive and `extent_mm` non-negative"
                )));
            }
            if 2.0 * ext / sp + 1.0 > MAX_SIDE as f64 {
                return Err(invalid(format!("products[{i}]: too many planes")));
            }
            Some((sp, ext))
        }
    };
    let count = series.map_or(1, |(sp, ext)| series_count(sp, ext) as u64);
    let bytes = count * (size[0] as u64) * (size[1] as u64) * 4;
    Ok((
        Planned::Mpr {
            plane,
            slab: s.slab,
            series,
        },
        bytes,
    ))
}

fn plan_product(p: &ProductSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let (nz, ny, nx) = shape.dim;
    match p {
        ProductSpec::Projection(s) => {
            // Slabs count images of the display grid: the volume's own slices when it is axis-aligned.
            let grid = DisplayGrid::of(&shape.frame, shape.dim).map_err(|e| volume_problem(&e))?;
            let n = grid.len(s.axis);
            let (gz, gy, gx) = grid.dim;
            let slab = match s.slab {
                None => None,
                Some([a, b]) if a < b && b <= n => Some(a..b),
                Some([a, b]) => {
                    return Err(Problem::new(
                        ErrorCode::InvalidSlab,
                        format!("products[{i}]: slab {a}..{b} is empty or outside 0..{n}"),
                    ));
                }
            };
            let pixels = (gz * gy * gx / n.max(1)) as u64;
            Ok((
                Planned::Projection {
                    axis: s.axis,
                    kind: s.kind,
                    slab,
                },
                pixels * 4,
            ))
        }
        ProductSpec::Mpr(s) => plan_mpr(s, shape, i),
        ProductSpec::Curved(s) => {
            if s.points_mm.len() < 2 || s.points_mm.len() > MAX_CURVE_POINTS {
                return Err(invalid(format!(
                    "products[{i}]: a curve needs 2 to {MAX_CURVE_POINTS} points"
                )));
            }
            if !s.points_mm.iter().all(finite3) || s.down.is_some_and(|d| !finite3(&d)) {
                return Err(invalid(format!("products[{i}]: points must be finite")));
            }
            let pixel = s.pixel_mm.unwrap_or_else(|| shape.smallest_spacing());
            if !(pixel.is_finite() && pixel > 0.0) || s.height == 0 || s.height > MAX_SIDE {
                return Err(invalid(format!(
                    "products[{i}]: `pixel_mm` must be positive and `height` within 1..={MAX_SIDE}"
                )));
            }
            let length: f64 = s
                .points_mm
                .windows(2)
                .map(|w| {
                    (0..3)
                        .map(|c| (w[1][c] - w[0][c]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .sum();
            let cols = (length / pixel).floor() + 1.0;
            if cols > MAX_SIDE as f64 {
                return Err(invalid(format!(
                    "products[{i}]: the curve is longer than {MAX_SIDE} pixels"
                )));
            }
            Ok((
                Planned::Curved {
                    points: s.points_mm.clone(),
                    down: s.down,
                    height: s.height,
                    pixel_mm: pixel,
                },
                cols as u64 * s.height as u64 * 4,
            ))
        }
        ProductSpec::Rotating(s) => {
            if s.frames == 0 || s.frames > MAX_ROTATING_FRAMES {
                return Err(invalid(format!(
                    "products[{i}]: `frames` must be in 1..={MAX_ROTATING_FRAMES}"
                ))
                .at(format!("/products/{i}/frames")));
            }
            let angles = (0..s.frames)
                .map(|k| 360.0 * k as f64 / s.frames as f64)
                .collect();
            // Frames are about (volume diagonal in the axial plane) × (height) at the finest spacing.
            let px = shape.smallest_spacing().max(0.5);
            let sp = shape.frame.spacing_mm;
            let w = whole_ceil((nx as f64 * sp[0]).hypot(ny as f64 * sp[1]) / px) + 2.0;
            let h = whole_ceil(nz as f64 * sp[2] / px) + 1.0;
            Ok((
                Planned::Rotating {
                    angles,
                    kind: s.kind,
                },
                (s.frames as f64 * w.min(MAX_SIDE as f64) * h.min(MAX_SIDE as f64) * 4.0) as u64,
            ))
        }
        ProductSpec::Mesh(m) => {
            m.validate()
                .map_err(|e| Problem::new(ErrorCode::from(&e), format!("products[{i}]: {e}")))?;
            if let Some(max) = shape.max_value.filter(|&max| m.iso > max) {
                return Err(Problem::new(
                    ErrorCode::IsoOutOfRange,
                    format!(
                        "products[{i}]: {}",
                        super::iso_range::above_every_value("iso", m.iso, max)
                    ),
                )
                .at(format!("/products/{i}/iso")));
            }
            // Marching cubes keeps a vertex index over two slices plus the mesh; bound it by the volume.
            Ok((Planned::Mesh(m.clone()), shape.voxels() * 4))
        }
        ProductSpec::VolumeRender(s) => render_plan(RenderSpec::Volume(s.clone()), shape, i),
        ProductSpec::SurfaceRender(s) => render_plan(RenderSpec::Surface(s.clone()), shape, i),
    }
}

fn render_plan(spec: RenderSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let bytes = plan_render(&spec, shape.dim, &shape.frame, i)?;
    Ok((Planned::Render(spec), bytes))
}

/// Check a volume job against its input's shape and the memory budget.
pub fn plan(
    req: &VolumeJobRequest,
    input: VolumeShape,
    budget_bytes: u64,
) -> Result<VolumePlan, Problem> {
    if req.steps.len() > MAX_ITEMS || req.products.len() > MAX_ITEMS {
        let at = if req.steps.len() > MAX_ITEMS {
            "/steps"
        } else {
            "/products"
        };
        return Err(invalid(format!(
            "at most {MAX_ITEMS} steps and {MAX_ITEMS} products"
        ))
        .at(at));
    }
    let max_voxels = budget_bytes / 4;
    let mut shape = input;
    let mut peak = 2 * shape.voxels() * 4;
    for (i, step) in req.steps.iter().enumerate() {
        match *step {
            Step::Resample { spacing_mm } => {
                let (n, frame) = isotropic_grid(&shape.frame, shape.dim, spacing_mm, max_voxels)
                    .map_err(|e| {
                        invalid(format!("steps[{i}]: {e}")).at(format!("/steps/{i}/spacing_mm"))
                    })?;
                let before = shape.voxels();
                shape = VolumeShape {
                    dim: (n[2], n[1], n[0]),
                    frame,
                    max_value: shape.max_value,
                };
                peak = peak.max((before + shape.voxels()) * 4);
            }
            Step::Gaussian { sigma_mm } => {
                if !(sigma_mm.is_finite() && (0.0..=MAX_SIGMA_MM).contains(&sigma_mm)) {
                    return Err(invalid(format!(
                        "steps[{i}]: `sigma_mm` must be in [0, {MAX_SIGMA_MM}], got {sigma_mm}"
                    ))
                    .at(format!("/steps/{i}/sigma_mm")));
                }
                peak = peak.max(3 * shape.voxels() * 4);
            }
            Step::Median => peak = peak.max(2 * shape.voxels() * 4),
        }
        shape.max_value = shape.max_value.map(|m| m.max(0.0));
    }
    let mut products = Vec::with_capacity(req.products.len());
    let mut product_bytes = 0u64;
    for (i, p) in req.products.iter().enumerate() {
        // A product's problem names its field, or at least the product.
        let (planned, bytes) = plan_product(p, &shape, i).map_err(|e| {
            if e.errors.is_empty() {
                e.at(format!("/products/{i}"))
            } else {
                e
            }
        })?;
        products.push(planned);
        product_bytes = product_bytes.max(bytes);
    }
    let estimate = peak.max(shape.voxels() * 4 + 2 * product_bytes);
    if estimate > budget_bytes {
        return Err(Problem::new(
            ErrorCode::JobTooLarge,
            format!(
                "the job needs about {estimate} bytes, more than the whole memory budget of {budget_bytes} bytes"
            ),
        ));
    }
    Ok(VolumePlan {
        output: shape,
        products,
        estimate_bytes: estimate,
    })
}

/// The input of a volume job, resolved by the engine.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumeInput {
    /// The `.npy` file of the volume (float32 `[z][y][x]`).
    pub path: std::path::PathBuf,
    pub shape: VolumeShape,
    pub units: VolumeUnits,
    pub source_series: Option<SeriesId>,
    pub warnings: Vec<Notice>,
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

fn io_failure(what: &str, e: std::io::Error) -> RunError {
    tracing::error!(error = %e, "{what}");
    RunError::Failed(Problem::internal())
}

fn file_info(bytes: &[u8]) -> FileInfo {
    FileInfo {
        bytes: bytes.len() as u64,
        sha256: hex(&Sha256::digest(bytes)),
    }
}

fn stack(images: Vec<ndarray::Array2<f32>>) -> Result<Array3<f32>, RunError> {
    let views: Vec<_> = images.iter().map(|a| a.view()).collect();
    ndarray::stack(NdAxis(0), &views).map_err(|e| {
        tracing::error!(error = %e, "stacking product images failed");
        RunError::Failed(Problem::internal())
    })
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

fn product_kind(p: &ProductSpec) -> &'static str {
    match p {
        ProductSpec::Projection(_) => "projection",
        ProductSpec::Mpr(_) => "mpr",
        ProductSpec::Curved(_) => "curved",
        ProductSpec::Rotating(_) => "rotating",
        ProductSpec::Mesh(_) => "mesh",
        ProductSpec::VolumeRender(_) => "volume_render",
        ProductSpec::SurfaceRender(_) => "surface_render",
    }
}

/// How a volume's products look: the value outside the volume, and whether the volume is a patient's (patient
/// directions on screen) or a reconstruction's (its own axes).
#[derive(Debug, Clone, Copy)]
struct Looks {
    fill: f32,
    patient: bool,
    units: VolumeUnits,
    /// μ of water (/mm) for requests in HU on a μ volume (`mu_water_per_mm`).
    mu_water: f64,
}

fn make_product(
    store: &BlobStore,
    job: &Job,
    vol: &Volume,
    index: usize,
    planned: &Planned,
    spec: &ProductSpec,
    looks: Looks,
) -> Result<ProductResult, RunError> {
    let Looks {
        fill,
        patient,
        units,
        mu_water,
    } = looks;
    let fail = |e: crate::volume::VolumeError| RunError::Failed(volume_problem(&e));
    // The plane of the first frame and the step between frames, for planar products.
    let mut placed: Option<(ImagePlane, Option<f64>)> = None;
    // Screen sides of the first frame of non-planar products.
    let mut sides: Option<ScreenSides> = None;
    // Frames that face different ways (a rotating projection): each frame's sides.
    let mut frame_orientations: Vec<ScreenSides> = Vec::new();
    let (images, pixel_mm) = match planned {
        Planned::Render(spec) => {
            return make_render_product(store, job.id, vol, index, spec, units, mu_water, patient);
        }
        Planned::Mesh(opts) => {
            let (mesh, stats) = extract(vol, opts).map_err(|e| {
                RunError::Failed(Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))
            })?;
            let stl = mesh.to_stl_binary();
            let file = file_info(&stl);
            store
                .write_atomic(
                    &store.result_path(job.id, &ResultName::Product { index, ext: "stl" }),
                    &stl,
                )
                .map_err(|e| io_failure("writing a mesh", e))?;
            return Ok(ProductResult {
                index,
                kind: product_kind(spec).into(),
                shape: None,
                pixel_mm: None,
                mesh: Some(stats),
                orientation: None,
                plane: None,
                frame_spacing_mm: None,
                frame_orientations: Vec::new(),
                description: None,
                file,
            });
        }
        Planned::Projection { axis, kind, slab } => {
            // Display orientation whatever the acquisition: axial [y][x]; coronal [z↓][x]; sagittal [z↓][y]
            // on the volume's display grid (its own samples when axis-aligned).
            let grid = DisplayGrid::for_volume(vol, patient).map_err(fail)?;
            let (img, p) =
                oriented_projection(vol, &grid, *axis, *kind, slab.clone(), fill).map_err(fail)?;
            placed = Some((p, None));
            (vec![img], p.pixel_mm)
        }
        Planned::Mpr {
            plane,
            slab,
            series,
        } => {
            let (images, first_offset, step) = match series {
                None => (
                    vec![reformat(vol, plane, *slab, fill).map_err(fail)?],
                    0.0,
                    None,
                ),
                Some((spacing, extent)) => {
                    let slab = slab.unwrap_or(Slab {
                        thickness_mm: 0.0,
                        kind: ProjectionKind::Mean,
                    });
                    let images =
                        slab_series(vol, plane, slab, *spacing, *extent, fill).map_err(fail)?;
                    let first = -(images.len() as f64 - 1.0) / 2.0 * spacing;
                    (images, first, Some(*spacing))
                }
            };
            placed = Some((
                ImagePlane {
                    first_pixel_mm: plane.point(0, 0, first_offset),
                    row_direction: plane.u,
                    column_direction: plane.v,
                    pixel_mm: [plane.pixel_mm; 2],
                },
                step,
            ));
            (images, [plane.pixel_mm; 2])
        }
        Planned::Curved {
            points,
            down,
            height,
            pixel_mm,
        } => {
            // Columns follow the curve from its first point to its last; rows run `down`. Labels name unit
            // directions: a component counts when it is above a tenth of the whole.
            let (a, b) = (points[0], points[points.len() - 1]);
            let unit = |v: [f64; 3]| {
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if n > 0.0 && n.is_finite() {
                    v.map(|c| c / n)
                } else {
                    v
                }
            };
            let along = unit([b[0] - a[0], b[1] - a[1], b[2] - a[2]]);
            let down = unit(down.unwrap_or([0.0, 0.0, -1.0]));
            let neg = |v: [f64; 3]| v.map(|c| -c);
            sides = Some(if patient {
                ScreenSides {
                    left: direction_label(neg(along)),
                    right: direction_label(along),
                    top: direction_label(neg(down)),
                    bottom: direction_label(down),
                }
            } else {
                ImagePlane {
                    first_pixel_mm: a,
                    row_direction: along,
                    column_direction: down,
                    pixel_mm: [*pixel_mm; 2],
                }
                .axis_sides()
            });
            (
                vec![curved(vol, points, Some(down), *height, *pixel_mm, fill).map_err(fail)?],
                [*pixel_mm; 2],
            )
        }
        Planned::Rotating { angles, kind } => {
            // Frame k is seen from angles[k] about the superior axis, screen down inferior; the first looks
            // from anterior, as a coronal image.
            let seen_from = |angle: f64| {
                ImagePlane {
                    first_pixel_mm: [0.0; 3],
                    row_direction: rotating_axes(angle).1,
                    column_direction: [0.0, 0.0, -1.0],
                    pixel_mm: [1.0; 2],
                }
                .sides_for(patient)
            };
            sides = Some(seen_from(angles.first().copied().unwrap_or(0.0)));
            if angles.len() > 1 {
                frame_orientations = angles.iter().map(|&a| seen_from(a)).collect();
            }
            let px = vol
                .frame
                .spacing_mm
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min)
                .max(0.5);
            (
                rotating_projection(vol, angles, *kind, fill).map_err(fail)?,
                [px; 2],
            )
        }
    };
    let stacked = stack(images)?;
    let (n, h, w) = stacked.dim();
    let encoded = encode_f32(stacked.view());
    let file = file_info(&encoded);
    store
        .write_atomic(
            &store.result_path(job.id, &ResultName::Product { index, ext: "npy" }),
            &encoded,
        )
        .map_err(|e| io_failure("writing a product", e))?;
    Ok(ProductResult {
        index,
        kind: product_kind(spec).into(),
        shape: Some([n, h, w]),
        pixel_mm: Some(pixel_mm),
        mesh: None,
        orientation: placed.map(|(p, _)| p.sides_for(patient)).or(sides),
        plane: placed.map(|(p, _)| p),
        frame_spacing_mm: placed.and_then(|(_, step)| step),
        frame_orientations,
        description: None,
        file,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape() -> VolumeShape {
        VolumeShape {
            dim: (20, 40, 50),
            frame: Frame {
                spacing_mm: [0.5, 0.5, 2.0],
                origin_mm: [-12.25, -9.75, 100.0],
                direction: Frame::AXIS_ALIGNED,
            },
            max_value: None,
        }
    }

    fn request(json: &str) -> VolumeJobRequest {
        serde_json::from_str(json).unwrap()
    }

    #[test]
    fn requests_parse_with_tagged_steps_and_products_and_refuse_unknown_fields() {
        let r = request(
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
                "steps": [{"op": "resample", "spacing_mm": 1}, {"op": "gaussian", "sigma_mm": 1}, {"op": "median"}],
                "products": [{"type": "projection", "axis": "coronal", "kind": "minip"},
                             {"type": "mpr", "plane": "sagittal", "slab": {"thickness_mm": 3, "kind": "mip"}, "spacing_mm": 3},
                             {"type": "curved", "points_mm": [[0,0,0],[10,0,0]], "height": 8},
                             {"type": "rotating", "frames": 4},
                             {"type": "mesh", "iso": 300, "smoothing": 5}]}"#,
        );
        assert_eq!(r.steps.len(), 3);
        assert_eq!(r.products.len(), 5);
        assert!(
            matches!(&r.products[4], ProductSpec::Mesh(m) if m.iso == 300.0 && m.largest_component)
        );
        for bad in [
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "colour": 1}"#,
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "steps": [{"op": "blur"}]}"#,
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "products": [{"type": "mesh", "iso": 1, "x": 2}]}"#,
            r#"{"kind": "volume", "input": "../etc/passwd"}"#,
        ] {
            assert!(
                serde_json::from_str::<VolumeJobRequest>(bad).is_err(),
                "{bad}"
            );
        }
    }

    #[test]
    fn planning_follows_the_shape_through_resampling_and_sizes_default_planes_to_the_volume() {
        let r = request(
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
                "steps": [{"op": "resample"}],
                "products": [{"type": "mpr", "plane": "coronal"}, {"type": "mpr", "plane": "axial", "spacing_mm": 4}]}"#,
        );
        let p = plan(&r, shape(), 1 << 30).unwrap();
        // 50 × 0.5 = 24.5 mm span → 50 samples; 40 → 40; z: 19 × 2 mm = 38 mm → 77 samples of 0.5 mm.
        assert_eq!(p.output.dim, (77, 40, 50));
        match &p.products[0] {
            Planned::Mpr { plane, .. } => {
                assert_eq!(plane.size, [50, 77]);
                assert!((plane.u[0] - 1.0).abs() < 1e-12 && (plane.v[2] + 1.0).abs() < 1e-12);
            }
            other => panic!("{other:?}"),
        }
        match &p.products[1] {
            Planned::Mpr { series, .. } => assert_eq!(*series, Some((4.0, 19.0))),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn rounding_noise_in_the_frame_changes_no_default_size() {
        // The same patient read from another acquisition: its spacing and origin derived from slice
        // positions, a few ulps off.
        let exact = VolumeShape {
            dim: (10, 14, 18),
            frame: Frame {
                spacing_mm: [0.8, 1.0, 2.0],
                origin_mm: [-7.0, -5.0, 40.0],
                direction: Frame::AXIS_ALIGNED,
            },
            max_value: None,
        };
        let mut noisy = exact;
        noisy.frame.spacing_mm[0] = 0.7999999999999998;
        noisy.frame.origin_mm[0] = -6.999999999999999;
        let r = request(
            r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
                "products": [{"type": "mpr", "plane": "coronal", "centre_mm": [-4.6, -2, 44]},
                             {"type": "mpr", "plane": "sagittal", "centre_mm": [-0.6, 1, 50], "spacing_mm": 0.8}]}"#,
        );
        let (a, b) = (
            plan(&r, exact, 1 << 30).unwrap(),
            plan(&r, noisy, 1 << 30).unwrap(),
        );
        for (x, y) in a.products.iter().zip(&b.products) {
            match (x, y) {
                (
                    Planned::Mpr {
                        plane: p,
                        series: s,
                        ..
                    },
                    Planned::Mpr {
                        plane: q,
                        series: t,
                        ..
                    },
                ) => {
                    assert_eq!(p.size, q.size);
                    let count = |s: &Option<(f64, f64)>| s.map(|(sp, ext)| series_count(sp, ext));
                    assert_eq!(count(s), count(t));
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(whole_ceil(36.00000000000001), 36.0);
        assert_eq!(whole_ceil(36.01), 37.0);
        assert_eq!(series_count(0.8, 6.3999999999999995), 17);
    }

    #[test]
    fn bad_parameters_and_jobs_beyond_the_budget_are_refused_before_running() {
        let base = r#"{"kind": "volume", "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5", "#;
        for (body, code) in [
            (
                r#""steps": [{"op": "resample", "spacing_mm": 0}]}"#,
                "invalid_parameter",
            ),
            (
                r#""steps": [{"op": "resample", "spacing_mm": 0.001}]}"#,
                "invalid_parameter",
            ),
            (
                r#""steps": [{"op": "gaussian", "sigma_mm": -1}]}"#,
                "invalid_parameter",
            ),
            (r#""products": [{"type": "mpr"}]}"#, "invalid_parameter"),
            (
                r#""products": [{"type": "mpr", "plane": "axial", "normal": [0,0,1]}]}"#,
                "invalid_parameter",
            ),
            (
                r#""products": [{"type": "mpr", "normal": [0,0,0]}]}"#,
                "invalid_parameter",
            ),
            (
                r#""products": [{"type": "mpr", "plane": "axial", "size": [0, 10]}]}"#,
                "invalid_parameter",
            ),
            (
                r#""products": [{"type": "projection", "slab": [5, 5]}]}"#,
                "invalid_slab",
            ),
            (
                r#""products": [{"type": "curved", "points_mm": [[0,0,0]], "height": 4}]}"#,
                "invalid_parameter",
            ),
            (
                r#""products": [{"type": "rotating", "frames": 0}]}"#,
                "invalid_parameter",
            ),
            (
                r#""products": [{"type": "mesh", "iso": 1, "smoothing": 100000}]}"#,
                "invalid_mesh_options",
            ),
        ] {
            let r = request(&format!("{base}{body}"));
            let e = plan(&r, shape(), 1 << 30).unwrap_err();
            assert_eq!(e.code.code(), code, "{body}: {e}");
        }
        let r = request(&format!("{base}\"steps\": [{{\"op\": \"median\"}}]}}"));
        let e = plan(&r, shape(), 100_000).unwrap_err();
        assert_eq!(e.code, ErrorCode::JobTooLarge);
    }
}
