//! Iterative reconstruction (ART, SART, OS-SART, SIRT, CGLS, MLEM/OSEM, TV) over the matched projector
//! pair of [`crate::recon::projector`].
//!
//! Every method works on flat `f32` buffers through the [`Operator`] trait, so 2D (parallel, fan arc,
//! fan flat) and cone-beam problems share one implementation. Parameters are checked before any work
//! ([`validate`]); [`estimate_bytes`] counts every work array so that [`Limits`] refuses a problem before
//! allocation. Progress is reported once per iteration (stage = the method's name, fraction k/n, the
//! iteration number and the data residual ‖Ax − b‖; see each method for exactly which residual), cancel
//! is checked between iterations and once per view inside projections.
//!
//! Initial images: zero, or the FBP/FDK image computed by the dispatcher ([`crate::recon::algorithm`]);
//! MLEM always starts from a uniform positive image.

mod art;
mod cgls;
#[cfg(test)]
mod counted;
mod mlem;
mod ops;
pub mod params;
mod sart;
mod sirt;
mod tv;
mod voxel;

use ndarray::{ArrayD, ArrayViewD, IxDyn};

pub use art::SHUFFLE_SEED;
pub use sart::MAX_STORED_WEIGHTS;
pub use tv::{AUTO_WEIGHT_FRACTION, Shape3, prox_tv};

use crate::recon::algorithm::{AlgorithmSpec, OutputGrid};
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::Views;
use crate::recon::grid::Limits;
use crate::recon::projector::{
    Operator, Projector2, Projector3, back_buffers, cone_columns, operator2,
};

/// Check the parameters of an iterative `spec` for a geometry of `views` views.
pub fn validate(spec: &AlgorithmSpec, views: usize) -> Result<(), ReconError> {
    match spec {
        AlgorithmSpec::Art(p) => p.validate(),
        AlgorithmSpec::Sart(p) => {
            params::check_iterations(p.iterations)?;
            params::check_relaxation(p.relaxation)?;
            params::check_tolerance(p.tolerance)?;
            params::check_upper(p.upper, p.nonnegative)
        }
        AlgorithmSpec::OsSart(p) => p.validate(views),
        AlgorithmSpec::Sirt(p) => p.validate(),
        AlgorithmSpec::Cgls(p) => p.validate(),
        AlgorithmSpec::Mlem(p) => p.validate(views),
        AlgorithmSpec::Tv(p) => p.validate(views),
        AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_) => Err(ReconError::param(
            "algorithm",
            format!("`{}` is not an iterative method", spec.name()),
        )),
    }
}

/// Whether `spec` asks for the voxel-driven back projector ([`params::BackProjector::Voxel`]).
fn voxel_back(spec: &AlgorithmSpec) -> bool {
    matches!(spec, AlgorithmSpec::Cgls(p) if p.back_projector == params::BackProjector::Voxel)
}

/// What `spec` needs of the views beyond [`validate`]: the ray-driven projectors of cone beams read flat
/// panels; the voxel-driven back projector is FDK's, so it takes the cone beams FDK takes.
pub fn check_views(spec: &AlgorithmSpec, views: &Views) -> Result<(), ReconError> {
    if let Views::D3(v) = views
        && v.detector.shape != crate::recon::geometry::PanelShape::Flat
    {
        return Err(ReconError::param(
            "geometry",
            "the iterative methods project onto flat panels; a cylindrical detector is reconstructed with              `fdk` (the helical filtered back projection)",
        ));
    }
    if !voxel_back(spec) {
        return Ok(());
    }
    if !matches!(views, Views::D3(_)) {
        return Err(ReconError::param(
            "back_projector",
            "`voxel` back-projects cone beams only; 2D and parallel3d geometries use `matched`",
        ));
    }
    crate::recon::analytic::check(views, &crate::recon::algorithm::FbpParams::default())
}

fn sizes(views: &Views, grid: &OutputGrid) -> (u64, u64, u64) {
    let n = match grid {
        OutputGrid::Image(g) => (g.nx as u64).saturating_mul(g.ny as u64),
        OutputGrid::Volume(g) => g.voxels(),
    };
    let shape = views.data_shape();
    let m = shape.iter().fold(1u64, |a, &k| a.saturating_mul(k as u64));
    (n, m, shape[0] as u64)
}

/// True when every view of this 2D geometry runs on the line kernels on this CPU: SART with one view
/// per subset then runs the fused updates of [`crate::recon::projector::parallel2::LineSweep`], which
/// keep no per-view weights, and no whole-view pass walks a ray.
fn all_line_kernels(views: &Views, grid: &OutputGrid) -> bool {
    match (views, grid) {
        (Views::D2(v), OutputGrid::Image(g)) => operator2::every_line_plan(v, g).is_some(),
        _ => false,
    }
}

/// Whether a 2D run keeps the table of every ray's walk: where some view lacks a line-kernel plan
/// (its whole-view passes then walk the rays) or the method updates ray by ray (ART). With every
/// view on the line kernels, the other methods never walk a ray.
fn keeps_walk_table(spec: &AlgorithmSpec, views: &Views, grid: &OutputGrid) -> bool {
    matches!(spec, AlgorithmSpec::Art(_)) || !all_line_kernels(views, grid)
}

/// Bytes an iterative run allocates besides its input: image-sized and data-sized work arrays, one
/// back-projection buffer per thread, stored per-subset weights (none for SART's fused updates), and the
/// initial image. A 3D parallel beam is run and counted slice by slice by the dispatcher
/// ([`crate::recon::algorithm::estimate_bytes`]); here it counts only its image- and data-sized arrays.
pub fn estimate_bytes(spec: &AlgorithmSpec, views: &Views, grid: &OutputGrid) -> u64 {
    let (n, m, nv) = sizes(views, grid);
    let stored = |s: u64| {
        if s.saturating_mul(n) <= MAX_STORED_WEIGHTS {
            s.saturating_mul(n)
        } else {
            n
        }
    };
    // (image-sized arrays, stored per-subset weights in values, data-sized arrays) besides the
    // back-projection buffers, the output and its initial copy.
    let (images, weights, data): (u64, u64, u64) = match spec {
        AlgorithmSpec::Sirt(_) | AlgorithmSpec::Cgls(_) => (3, 0, 2),
        AlgorithmSpec::Art(_) => (1, 0, 3),
        AlgorithmSpec::Sart(_) if all_line_kernels(views, grid) => (2, 0, 2),
        AlgorithmSpec::Sart(_) => (2, stored(nv), 2),
        AlgorithmSpec::OsSart(p) if p.subsets as u64 >= nv && all_line_kernels(views, grid) => {
            (2, 0, 2)
        }
        AlgorithmSpec::OsSart(p) => (2, stored(p.subsets as u64), 2),
        AlgorithmSpec::Mlem(p) => (3, stored(p.subsets as u64), 3),
        AlgorithmSpec::Tv(p) => (11, stored((p.subsets as u64).min(nv)), 2),
        AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_) => (0, 0, 0),
    };
    let buffers = back_buffers() as u64 + 2;
    // 2D operators keep the walk of every ray where they walk rays, and their line kernels (parallel
    // views) copy the data of a back projection in ray order (one more data-sized array, plus a few
    // values per view); the cone-beam pair keeps two padded copies of the volume and a weighted copy
    // of the data.
    let (table, data) = match (views, grid) {
        (Views::D2(v), _) if keeps_walk_table(spec, views, grid) => {
            (Projector2::table_bytes(v), data + 1)
        }
        (Views::D2(_), _) => (0, data + 1),
        (Views::D3(v), OutputGrid::Volume(g)) if voxel_back(spec) => (
            cone_columns::work_bytes(v, g)
                .saturating_add(crate::recon::analytic::back_project_voxels_bytes(v, g)),
            data,
        ),
        (Views::D3(v), OutputGrid::Volume(g)) => (cone_columns::work_bytes(v, g), data),
        (Views::D3(_), _) => (0, data),
        (Views::Slices(_), _) => (0, data),
    };
    Limits::f32_bytes(
        (images + buffers)
            .saturating_mul(n)
            .saturating_add(weights)
            .saturating_add(data.saturating_mul(m)),
    )
    .saturating_add(table)
}

/// Run the iterative algorithm of `spec` on `data`, starting from `initial` (or zero).
///
/// `data` is `[view][u]` (2D) or `[view][v][u]` (cone), already checked by the dispatcher against the
/// geometry; `initial`, when given, has the shape of `grid`. Parameters are validated and the memory
/// estimate checked against `limits` before any work.
pub fn solve(
    spec: &AlgorithmSpec,
    views: &Views,
    data: ArrayViewD<'_, f32>,
    grid: &OutputGrid,
    initial: Option<ArrayViewD<'_, f32>>,
    limits: &Limits,
    ctl: Control<'_>,
) -> Result<ArrayD<f32>, ReconError> {
    let nviews = views.data_shape()[0];
    validate(spec, nviews)?;
    let expected = views.data_shape();
    if data.shape() != expected.as_slice() {
        return Err(ReconError::ShapeMismatch {
            expected,
            got: data.shape().to_vec(),
        });
    }
    limits.check(estimate_bytes(spec, views, grid))?;
    check_views(spec, views)?;
    let (op, out_shape, shape3): (Box<dyn Operator + '_>, Vec<usize>, Shape3) = match (views, grid)
    {
        (Views::D2(v), OutputGrid::Image(g)) => {
            g.validate()?;
            (
                Box::new(if keeps_walk_table(spec, views, grid) {
                    Projector2::with_walk_table(v, g)
                } else {
                    Projector2::new(v, g)
                }),
                g.shape().to_vec(),
                Shape3 {
                    nz: 1,
                    ny: g.ny,
                    nx: g.nx,
                },
            )
        }
        (Views::D3(v), OutputGrid::Volume(g)) => {
            g.validate()?;
            let op: Box<dyn Operator + '_> = if voxel_back(spec) {
                Box::new(voxel::VoxelBack3::new(v, g))
            } else {
                Box::new(Projector3::new(v, g))
            };
            (
                op,
                g.shape().to_vec(),
                Shape3 {
                    nz: g.nz,
                    ny: g.ny,
                    nx: g.nx,
                },
            )
        }
        (Views::Slices(_), _) => {
            return Err(ReconError::param(
                "geometry",
                "a 3D parallel beam is reconstructed slice by slice (recon::algorithm::reconstruct)",
            ));
        }
        _ => {
            return Err(ReconError::param(
                "grid",
                "grid and geometry dimensionality differ",
            ));
        }
    };
    let b: Vec<f32> = data.iter().copied().collect();
    let mut x = match initial {
        Some(init) => {
            if init.shape() != out_shape.as_slice() {
                return Err(ReconError::ShapeMismatch {
                    expected: out_shape,
                    got: init.shape().to_vec(),
                });
            }
            init.iter().copied().collect()
        }
        None => vec![0.0f32; op.image_len()],
    };
    run(spec, op.as_ref(), &b, &mut x, shape3, &ctl)?;
    ArrayD::from_shape_vec(IxDyn(&out_shape), x)
        .map_err(|e| ReconError::param("grid", e.to_string()))
}

/// Run `spec` on flat buffers: `b` the data (view after view), `x` the start, overwritten with the result.
/// Parameters must have been validated ([`validate`]).
pub fn run(
    spec: &AlgorithmSpec,
    op: &dyn Operator,
    b: &[f32],
    x: &mut [f32],
    shape: Shape3,
    ctl: &Control<'_>,
) -> Result<(), ReconError> {
    validate(spec, op.view_count())?;
    match spec {
        AlgorithmSpec::Art(p) => art::art(op, b, x, p, ctl),
        AlgorithmSpec::Sart(p) => sart::sart(op, b, x, p, op.view_count(), "sart", ctl),
        AlgorithmSpec::OsSart(p) => sart::sart(op, b, x, p, p.subsets, "os_sart", ctl),
        AlgorithmSpec::Sirt(p) => sirt::sirt(op, b, x, p, ctl),
        AlgorithmSpec::Cgls(p) => cgls::cgls(op, b, x, p, ctl),
        AlgorithmSpec::Mlem(p) => mlem::mlem(op, b, x, p, ctl),
        AlgorithmSpec::Tv(p) => {
            let mut p = *p;
            p.subsets = p.subsets.min(op.view_count());
            tv::tv(op, b, x, &p, shape, ctl)
        }
        AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_) => validate(spec, op.view_count()),
    }
}
