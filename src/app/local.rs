//! Commands on local arrays, without a database, a data directory or an engine: what `ctrecon recon`,
//! `ctrecon phantom` and `ctrecon mesh` run. Admission is the HTTP submit's (`jobs::plan`): for a reconstruction the geometry,
//! the grid and its field of view, the algorithm's parameters against the views and the memory estimate
//! against the budget; for a simulation the phantom, its field of view, the noise and the size of the
//! projections. So what the command line accepts, the API accepts, and a refusal carries the same catalogue
//! code ([`Problem`]). The work runs on the caller's thread (its rayon pool), reporting to the caller's
//! [`Progress`] sink — the one the engine feeds for a job — and checking the caller's [`Cancel`] flag.

use ndarray::{ArrayD, ArrayViewD};

use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::{NoiseSpec, SimulationRequest};
use crate::jobs::plan::{check_reconstruction, recon_problem, reconstruction_bytes};
use crate::jobs::run::simulate;
use crate::mesh::{Mesh, MeshOptions, MeshStats};
use crate::recon::algorithm::{AlgorithmSpec, OutputGrid, reconstruct};
use crate::recon::control::{Cancel, Control, Progress};
use crate::recon::geometry::{Geometry, Views};
use crate::recon::grid::{ImageGrid, Limits, VolumeGrid};
use crate::recon::phantom::{MAX_BODIES, PhantomSpec};
use crate::volume::{Frame, Volume};

/// The memory budget of local work unless the caller sets one (bytes).
pub const DEFAULT_BUDGET_BYTES: u64 = 8 << 30;

/// Most point samples per pixel axis of a rasterised phantom.
pub const MAX_SUPERSAMPLE: usize = 16;

/// Local work under a memory budget: the limit of a reconstruction's estimate, and of the values an array
/// may hold (the budget in float32 values, as `app::limits::max_array_values` is for the service).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Local {
    budget_bytes: u64,
}

impl Default for Local {
    fn default() -> Self {
        Self::new(DEFAULT_BUDGET_BYTES)
    }
}

/// A reconstruction of projections acquired with `geometry` onto `grid` by `algorithm`.
#[derive(Debug, Clone, PartialEq)]
pub struct Reconstruction {
    pub geometry: Geometry,
    pub algorithm: AlgorithmSpec,
    pub grid: OutputGrid,
}

/// A reconstruction that passed admission, with its views and the bytes it is expected to need.
#[derive(Debug, Clone)]
pub struct Admitted {
    request: Reconstruction,
    views: Views,
    pub estimate_bytes: u64,
}

/// How a phantom is rasterised: a square image or a cubic volume of `size` samples per side, each the mean
/// of `supersample` point samples per axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Raster {
    pub size: usize,
    pub volume: bool,
    pub supersample: usize,
}

fn too_many_values(what: &str, values: u64, max: u64) -> Problem {
    Problem::new(
        ErrorCode::ArrayTooLarge,
        format!("the {what} would have {values} values, more than the limit of {max}"),
    )
}

impl Local {
    /// Local work under `budget_bytes`.
    pub fn new(budget_bytes: u64) -> Self {
        Self { budget_bytes }
    }

    /// Values an array may hold: the budget in float32 values.
    pub fn max_array_values(&self) -> u64 {
        self.budget_bytes / 4
    }

    /// The square image (2D geometries) or cube (cone beams) of `size` samples of `pixel_mm` centred on the
    /// isocentre; refused when the geometry is invalid.
    pub fn square_grid(
        &self,
        geometry: &Geometry,
        size: usize,
        pixel_mm: f64,
    ) -> Result<OutputGrid, Problem> {
        let views = geometry.to_views().map_err(|e| recon_problem(&e.into()))?;
        Ok(match views {
            Views::D2(_) => OutputGrid::Image(ImageGrid::square(size, pixel_mm)),
            Views::D3(_) | Views::Slices(_) => OutputGrid::Volume(VolumeGrid::cube(size, pixel_mm)),
        })
    }

    /// Admit `request` as a reconstruction job is admitted: geometry, grid, field of view, algorithm and the
    /// memory it needs, its input being the projections the geometry describes.
    pub fn admit_reconstruction(&self, request: Reconstruction) -> Result<Admitted, Problem> {
        let views = check_reconstruction(&request.geometry, &request.grid, &request.algorithm)?;
        let input = views
            .data_shape()
            .iter()
            .fold(1u64, |a, &n| a.saturating_mul(n as u64));
        let estimate_bytes = reconstruction_bytes(
            &request.algorithm,
            &views,
            &request.grid,
            input,
            false,
            self.budget_bytes,
        )?;
        Ok(Admitted {
            request,
            views,
            estimate_bytes,
        })
    }

    /// Reconstruct `data` (the projections, shaped as the geometry says) as `admitted` describes, reporting
    /// to `progress` and stopping when `cancel` is set.
    pub fn reconstruct(
        &self,
        admitted: &Admitted,
        data: ArrayViewD<'_, f32>,
        progress: &dyn Progress,
        cancel: &Cancel,
    ) -> Result<ArrayD<f32>, Problem> {
        let r = &admitted.request;
        reconstruct(
            &r.algorithm,
            &admitted.views,
            data,
            &r.grid,
            &Limits {
                max_bytes: self.budget_bytes,
            },
            Control::new(cancel, progress),
        )
        .map_err(|e| recon_problem(&e))
    }

    /// The exact projections of `phantom` for `geometry`, with Poisson noise when `noise` is given: admitted
    /// and computed as `POST /v1/simulations` does.
    pub fn simulate(
        &self,
        phantom: PhantomSpec,
        geometry: Geometry,
        noise: Option<NoiseSpec>,
    ) -> Result<ArrayD<f32>, Problem> {
        let request = SimulationRequest {
            phantom,
            geometry,
            noise,
        };
        let views = crate::jobs::plan::admit_simulation(&request, self.max_array_values())?;
        simulate(&request, &views)
    }

    /// `phantom` sampled on the grid `raster` describes, its field of view the phantom's `[−1, 1]`.
    pub fn rasterize(&self, phantom: &PhantomSpec, raster: Raster) -> Result<ArrayD<f32>, Problem> {
        let Raster {
            size,
            volume,
            supersample,
        } = raster;
        if supersample == 0 || supersample > MAX_SUPERSAMPLE {
            return Err(Problem::new(
                ErrorCode::InvalidParameter,
                format!("`supersample` must be in 1..={MAX_SUPERSAMPLE}, got {supersample}"),
            ));
        }
        let pixel = phantom.scale_mm * 2.0 / size as f64;
        let grid_problem = |e| Problem::new(ErrorCode::InvalidParameter, format!("grid: {e}"));
        let bodies = |n: usize| {
            if n > MAX_BODIES {
                Err(Problem::new(
                    ErrorCode::InvalidParameter,
                    format!("at most {MAX_BODIES} ellipses or ellipsoids"),
                ))
            } else {
                Ok(())
            }
        };
        let max = self.max_array_values();
        if volume {
            let grid = VolumeGrid::cube(size, pixel);
            grid.validate().map_err(grid_problem)?;
            let p = phantom.phantom3().map_err(|e| recon_problem(&e))?;
            bodies(p.ellipsoids.len())?;
            let values = grid.voxels();
            if values > max {
                return Err(too_many_values("volume", values, max));
            }
            Ok(p.rasterize(&grid, supersample).into_dyn())
        } else {
            let grid = ImageGrid::square(size, pixel);
            grid.validate().map_err(grid_problem)?;
            let p = phantom.phantom2().map_err(|e| recon_problem(&e))?;
            bodies(p.ellipses.len())?;
            let values = (grid.nx as u64).saturating_mul(grid.ny as u64);
            if values > max {
                return Err(too_many_values("image", values, max));
            }
            Ok(p.rasterize(&grid, supersample).into_dyn())
        }
    }

    /// The surface of a `[z][y][x]` volume of `voxel_mm` (x, y, z) voxels, voxel `[0][0][0]` at the origin,
    /// axes along x, y and z, through the surface pipeline of a volume job's mesh product (same options, same
    /// refusals).
    pub fn mesh(
        &self,
        volume: ArrayD<f32>,
        voxel_mm: [f64; 3],
        options: &MeshOptions,
    ) -> Result<(Mesh, MeshStats), Problem> {
        let invalid = |m: String| Problem::new(ErrorCode::InvalidParameter, m);
        if !voxel_mm.iter().all(|v| v.is_finite() && *v > 0.0) {
            return Err(invalid(format!(
                "voxel sizes must be positive and finite, got {voxel_mm:?}"
            )));
        }
        let data = volume
            .into_dimensionality::<ndarray::Ix3>()
            .map_err(|_| invalid("a volume is three-dimensional: [z][y][x]".into()))?;
        let values = data.len() as u64;
        if values > self.max_array_values() {
            return Err(too_many_values("volume", values, self.max_array_values()));
        }
        let vol = Volume {
            data,
            frame: Frame {
                spacing_mm: voxel_mm,
                origin_mm: [0.0; 3],
                direction: Frame::AXIS_ALIGNED,
            },
        };
        crate::mesh::extract(&vol, options)
            .map_err(|e| Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))
    }
}
