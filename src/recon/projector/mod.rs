//! Ray-driven forward projectors and their exact adjoints, for every canonical geometry.
//!
//! The forward projector is Joseph's method: along each ray (from [`Views2::ray`] / [`Views3::ray`], so
//! parallel, fan arc, fan flat and cone beams share one code path) it takes one sample per image line of
//! the ray's dominant axis, interpolates linearly (2D) or bilinearly (3D) between the nearest pixels of
//! that line, and weights the sample by the ray length between lines (mm). A projection value is
//! therefore a line integral in the units of the image times mm. Pixels outside the grid count zero.
//!
//! The back projector is the exact transpose: it enumerates the same (pixel, weight) pairs
//! ([`joseph2::Walk2::visit`], [`joseph3::Walk3::visit`]), so ⟨A x, y⟩ = ⟨x, Aᵀ y⟩ up to f32 rounding.
//! In 2D the whole-view passes run the kernels of [`joseph2_loops`] (AVX2 where the CPU has it), which
//! compute the pairs and weights of [`joseph2::Walk2`] bit for bit on padded line layouts
//! ([`padded2`]); see [`operator2`] for how they share the work between threads. Parallel-beam views
//! whose ray step along a line lies between 0.6 and 1.85 pixels run the line-driven kernels of
//! [`parallel2`] instead (8 or 16 rays or pixels per vector, windows instead of gathers), which
//! enumerate the same pairs in forward and back and differ from the walks by f32 rounding. In 3D the
//! whole-view passes run [`cone_columns`]: the walks' pairs organised by detector column (the rays of
//! a column of a panel whose v axis is z share their dominant axis and in-plane positions), as a blend
//! of two contiguous z lines and one linear interpolation per row and plane, with the transpose
//! accumulated into bands of planes that the threads own (no per-thread volumes, no write races).
//! Single rays (ART) use the walks. Arrays: images `[y][x]`, volumes `[z][y][x]`, sinograms
//! `[view][u]`, projections `[view][v][u]`.

pub mod cone_columns;
pub mod cone_lines;
pub mod cone_plans;
pub mod cone_stacks;
pub mod cone_steps;
pub mod footprint3;
pub mod joseph2;
#[cfg(target_arch = "x86_64")]
mod joseph2_avx2;
pub mod joseph2_loops;
pub mod joseph3;
pub mod operator2;
pub mod padded2;
pub mod parallel2;

use ndarray::{Array2, Array3, ArrayView2, ArrayView3};
use rayon::prelude::*;

use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Views2, Views3};
use crate::recon::grid::{ImageGrid, VolumeGrid};

/// A linear projection operator A (image → data) with its exact adjoint Aᵀ, over flat `f32` buffers.
/// Data are laid out view after view, `view_len()` values per view. Subsets of views (lists of view
/// indices) select the rows of A that an ordered-subset method updates with.
pub trait Operator: Sync {
    /// Number of image values (pixels or voxels).
    fn image_len(&self) -> usize;
    /// Number of views.
    fn view_count(&self) -> usize;
    /// Data values per view (detector elements).
    fn view_len(&self) -> usize;
    /// `out[s·view_len ..]` = A_view x for each `view = subset[s]`. Checks `cancel` once per view.
    fn forward(
        &self,
        image: &[f32],
        subset: &[usize],
        out: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError>;
    /// `image` = Σ_s A_viewᵀ data[s·view_len ..] over `view = subset[s]` (overwrites `image`). Checks
    /// `cancel` once per view.
    fn back(
        &self,
        data: &[f32],
        subset: &[usize],
        image: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError>;
    /// a_i · x for the ray of element `element` of view `view`.
    fn ray_dot(&self, view: usize, element: usize, image: &[f32]) -> f32;
    /// x += alpha·a_i for that ray.
    fn ray_axpy(&self, view: usize, element: usize, alpha: f32, image: &mut [f32]);
    /// ‖a_i‖² for that ray.
    fn ray_norm2(&self, view: usize, element: usize) -> f32;
    /// The line-kernel plan of every view with the grid's `(nx, ny)`, when every view has one (2D
    /// parallel views that [`parallel2`] takes, on a CPU that runs it), for SART's single-view updates
    /// ([`parallel2::LineSweep`]). `None` by default.
    fn line_plans(&self) -> Option<(Vec<parallel2::LineView>, usize, usize)> {
        None
    }
}

/// Number of image-sized buffers a projection allocates at most: one volume per thread for a cone-beam
/// back projection; in 2D the two padded layouts of [`padded2::Layouts2`] (at most 3 images for grids
/// of 4 × 4 pixels or more) and a fixed 256 KiB of ray segments, or the two line layouts of
/// [`parallel2::WideLines`] (at most 3 images for grids of 100 × 100 pixels or more) and one image of
/// line sums. The line back projection's copy of the data is counted by the callers.
pub fn back_buffers() -> usize {
    rayon::current_num_threads().max(3)
}

/// Run `per_view(view, data row, acc)` over `subset` with one accumulator per thread, then sum the
/// accumulators into `image`.
fn back_partitioned(
    image_len: usize,
    view_len: usize,
    data: &[f32],
    subset: &[usize],
    image: &mut [f32],
    cancel: &Cancel,
    per_view: impl Fn(usize, &[f32], &mut [f32]) + Sync,
) -> Result<(), ReconError> {
    image.fill(0.0);
    if subset.is_empty() {
        return Ok(());
    }
    let parts = back_buffers().min(subset.len());
    let chunk = subset.len().div_ceil(parts);
    let pairs: Vec<(usize, &[f32])> = subset
        .iter()
        .copied()
        .zip(data.chunks_exact(view_len))
        .collect();
    let buffers: Vec<Result<Vec<f32>, ReconError>> = pairs
        .par_chunks(chunk)
        .map(|part| {
            let mut acc = vec![0.0f32; image_len];
            for &(view, row) in part {
                cancel.check()?;
                per_view(view, row, &mut acc);
            }
            Ok(acc)
        })
        .collect();
    let mut bufs = Vec::with_capacity(buffers.len());
    for b in buffers {
        bufs.push(b?);
    }
    const BLOCK: usize = 1 << 14;
    image
        .par_chunks_mut(BLOCK)
        .enumerate()
        .for_each(|(blk, out)| {
            let off = blk * BLOCK;
            let len = out.len();
            for b in &bufs {
                for (o, v) in out.iter_mut().zip(&b[off..off + len]) {
                    *o += *v;
                }
            }
        });
    Ok(())
}

fn forward_partitioned(
    view_len: usize,
    subset: &[usize],
    out: &mut [f32],
    cancel: &Cancel,
    per_view: impl Fn(usize, &mut [f32]) + Sync,
) -> Result<(), ReconError> {
    out.par_chunks_mut(view_len)
        .zip(subset.par_iter())
        .try_for_each(|(row, &view)| {
            cancel.check()?;
            per_view(view, row);
            Ok(())
        })
}

/// The Joseph projector pair of a 2D geometry on an image grid.
#[derive(Debug, Clone)]
pub struct Projector2<'a> {
    pub views: &'a Views2,
    pub grid: &'a ImageGrid,
    /// Every ray's walk, view after view ([`operator2::all_walks`]), or empty to compute walks as needed.
    /// Iterative methods apply the same operator many times and keep the table.
    pub walks: Vec<Option<joseph2::Walk2>>,
}

impl<'a> Projector2<'a> {
    /// Walks computed as needed (one application).
    pub fn new(views: &'a Views2, grid: &'a ImageGrid) -> Self {
        Self {
            views,
            grid,
            walks: Vec::new(),
        }
    }

    /// With the table of every ray's walk (for many applications; [`Projector2::table_bytes`] of memory).
    pub fn with_walk_table(views: &'a Views2, grid: &'a ImageGrid) -> Self {
        Self {
            views,
            grid,
            walks: operator2::all_walks(views, grid),
        }
    }

    /// Bytes of the walk table of `views`.
    pub fn table_bytes(views: &Views2) -> u64 {
        (views.views.len() as u64)
            .saturating_mul(views.detector.count as u64)
            .saturating_mul(std::mem::size_of::<Option<joseph2::Walk2>>() as u64)
    }
}

impl Operator for Projector2<'_> {
    fn image_len(&self) -> usize {
        self.grid.nx * self.grid.ny
    }
    fn view_count(&self) -> usize {
        self.views.views.len()
    }
    fn view_len(&self) -> usize {
        self.views.detector.count
    }
    fn forward(
        &self,
        image: &[f32],
        subset: &[usize],
        out: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        operator2::forward(
            self.views,
            self.grid,
            &self.walks,
            image,
            subset,
            out,
            cancel,
        )
    }
    fn back(
        &self,
        data: &[f32],
        subset: &[usize],
        image: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        operator2::back(
            self.views,
            self.grid,
            &self.walks,
            data,
            subset,
            image,
            cancel,
        )
    }
    fn ray_dot(&self, view: usize, element: usize, image: &[f32]) -> f32 {
        let ray = self.views.ray(&self.views.views[view], element);
        joseph2::Walk2::new(&ray, self.grid).map_or(0.0, |w| w.dot(image))
    }
    fn ray_axpy(&self, view: usize, element: usize, alpha: f32, image: &mut [f32]) {
        let ray = self.views.ray(&self.views.views[view], element);
        if let Some(w) = joseph2::Walk2::new(&ray, self.grid) {
            w.axpy(alpha, image);
        }
    }
    fn ray_norm2(&self, view: usize, element: usize) -> f32 {
        let ray = self.views.ray(&self.views.views[view], element);
        let mut s = 0.0f32;
        if let Some(w) = joseph2::Walk2::new(&ray, self.grid) {
            w.visit(|_, wt| s += wt * wt);
        }
        s
    }
    fn line_plans(&self) -> Option<(Vec<parallel2::LineView>, usize, usize)> {
        operator2::every_line_plan(self.views, self.grid).map(|p| (p, self.grid.nx, self.grid.ny))
    }
}

/// The Joseph projector pair of a cone-beam geometry on a volume grid, keeping the column plans of
/// the subsets it projects ([`cone_plans::PlanCache`]).
#[derive(Debug)]
pub struct Projector3<'a> {
    views: &'a Views3,
    grid: &'a VolumeGrid,
    plans: cone_plans::PlanCache,
}

impl<'a> Projector3<'a> {
    pub fn new(views: &'a Views3, grid: &'a VolumeGrid) -> Self {
        Projector3 {
            views,
            grid,
            plans: cone_plans::PlanCache::default(),
        }
    }
    fn walk(&self, view: usize, element: usize) -> Option<joseph3::Walk3> {
        let nu = self.views.detector.nu;
        let ray = self
            .views
            .ray(&self.views.views[view], element / nu, element % nu);
        joseph3::Walk3::new(&ray, self.grid)
    }
}

impl Operator for Projector3<'_> {
    fn image_len(&self) -> usize {
        self.grid.nx * self.grid.ny * self.grid.nz
    }
    fn view_count(&self) -> usize {
        self.views.views.len()
    }
    fn view_len(&self) -> usize {
        self.views.detector.nu * self.views.detector.nv
    }
    fn forward(
        &self,
        image: &[f32],
        subset: &[usize],
        out: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        let plans = self.plans.get(self.views, self.grid, subset);
        let form = cone_lines::Form::detect();
        cone_columns::forward_with(form, self.views, self.grid, &plans, image, out, cancel)
    }
    fn back(
        &self,
        data: &[f32],
        subset: &[usize],
        image: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        let plans = self.plans.get(self.views, self.grid, subset);
        let form = cone_lines::Form::detect();
        cone_columns::back_with(form, self.views, self.grid, &plans, data, image, cancel)
    }
    fn ray_dot(&self, view: usize, element: usize, image: &[f32]) -> f32 {
        self.walk(view, element).map_or(0.0, |w| w.dot(image))
    }
    fn ray_axpy(&self, view: usize, element: usize, alpha: f32, image: &mut [f32]) {
        if let Some(w) = self.walk(view, element) {
            w.axpy(alpha, image);
        }
    }
    fn ray_norm2(&self, view: usize, element: usize) -> f32 {
        let mut s = 0.0f32;
        if let Some(w) = self.walk(view, element) {
            w.visit(|_, wt| s += wt * wt);
        }
        s
    }
}

fn all_views(n: usize) -> Vec<usize> {
    (0..n).collect()
}

fn contiguous<'a, D: ndarray::Dimension>(
    a: &'a ndarray::ArrayView<'a, f32, D>,
) -> std::borrow::Cow<'a, [f32]> {
    match a.as_slice() {
        Some(s) => std::borrow::Cow::Borrowed(s),
        None => std::borrow::Cow::Owned(a.iter().copied().collect()),
    }
}

fn never() -> Cancel {
    Cancel::new()
}

/// Which side of the operator pair to apply.
#[derive(Clone, Copy)]
enum Direction {
    Forward,
    Back,
}

/// Apply `op` (or its adjoint) over every view to `input`, into the fresh zeroed array `out`; never canceled.
fn apply_all<D: ndarray::Dimension>(
    op: &impl Operator,
    direction: Direction,
    input: &[f32],
    mut out: ndarray::Array<f32, D>,
) -> ndarray::Array<f32, D> {
    let subset = all_views(op.view_count());
    let slice = out.as_slice_mut().expect("fresh array is contiguous");
    let r = match direction {
        Direction::Forward => op.forward(input, &subset, slice, &never()),
        Direction::Back => op.back(input, &subset, slice, &never()),
    };
    debug_assert!(r.is_ok());
    out
}

/// Joseph forward projection of `image` (`[y][x]` on `grid`, μ in 1/mm) for every view: the sinogram
/// `[view][u]` of line integrals. Parallel, fan arc and fan flat geometries alike.
///
/// # Panics
/// If `image` does not have the shape of `grid` (a programming error; the dispatcher checks shapes).
pub fn forward_2d(views: &Views2, image: ArrayView2<'_, f32>, grid: &ImageGrid) -> Array2<f32> {
    assert_eq!(image.shape(), grid.shape(), "image shape must match grid");
    apply_all(
        &Projector2::new(views, grid),
        Direction::Forward,
        &contiguous(&image),
        Array2::<f32>::zeros(views.shape()),
    )
}

/// The exact adjoint of [`forward_2d`]: back projection of `sinogram` (`[view][u]`) onto `grid`.
///
/// # Panics
/// If `sinogram` does not have the shape of `views`.
pub fn back_2d(views: &Views2, sinogram: ArrayView2<'_, f32>, grid: &ImageGrid) -> Array2<f32> {
    assert_eq!(
        sinogram.shape(),
        views.shape(),
        "sinogram shape must match views"
    );
    apply_all(
        &Projector2::new(views, grid),
        Direction::Back,
        &contiguous(&sinogram),
        Array2::<f32>::zeros(grid.shape()),
    )
}

/// Joseph forward projection of `volume` (`[z][y][x]` on `grid`) for every cone-beam view: projections
/// `[view][v][u]`.
///
/// # Panics
/// If `volume` does not have the shape of `grid`.
pub fn forward_3d(views: &Views3, volume: ArrayView3<'_, f32>, grid: &VolumeGrid) -> Array3<f32> {
    assert_eq!(volume.shape(), grid.shape(), "volume shape must match grid");
    apply_all(
        &Projector3::new(views, grid),
        Direction::Forward,
        &contiguous(&volume),
        Array3::<f32>::zeros(views.shape()),
    )
}

/// The exact adjoint of [`forward_3d`]: back projection of `projections` (`[view][v][u]`) onto `grid`.
///
/// # Panics
/// If `projections` does not have the shape of `views`.
pub fn back_3d(views: &Views3, projections: ArrayView3<'_, f32>, grid: &VolumeGrid) -> Array3<f32> {
    assert_eq!(
        projections.shape(),
        views.shape(),
        "projections shape must match views"
    );
    apply_all(
        &Projector3::new(views, grid),
        Direction::Back,
        &contiguous(&projections),
        Array3::<f32>::zeros(grid.shape()),
    )
}
