//! Forward and back projection of a subset of the views of a 2D geometry with the fast kernels of
//! [`super::joseph2_loops`] on padded line layouts ([`super::padded2`]).
//!
//! Forward: the image is copied once into the layouts its rays use (one for a parallel view); views run in parallel (each writes its own
//! data row), and the rays of a view too when the subset has fewer views than threads (single-view
//! SART). Back: one accumulator per layout the rays use, shared by all threads. Views go in chunks; for each chunk the
//! rays' segments are computed in parallel, then the lines of each layout are cut into bands and the
//! bands run in parallel, each adding the part of every ray of the chunk that lies on its lines (a ray
//! writes only the line of each of its samples), so no two threads write the same value and no
//! per-thread image is needed. The two accumulators are summed into the image at the end.
//!
//! Parallel views that [`LineView::plan`] takes (steps of 0.6–1.85 pixels between rays, on CPUs with
//! AVX2) run the line kernels of [`super::parallel2`] instead: forward per view on zero-margined line
//! copies of the image, back per image line over all such views, then added to the ray kernels' result.
//!
//! Layouts too large for the kernels ([`Kernel::fits`]) use the reference walks of
//! [`super::joseph2`].

use rayon::prelude::*;

use super::joseph2::{self, Walk2};
use super::joseph2_loops::{Kernel, Segment};
use super::padded2::{Layouts2, Lines, Needs};
use super::parallel2::{self, LineView, WideLines};
use super::{back_partitioned, forward_partitioned};
use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Source2, Views2};
use crate::recon::grid::ImageGrid;

/// Bytes of ray segments held per chunk of views during a back projection.
const CHUNK_BYTES: usize = 1 << 18;

/// Rays per parallel task when one view is split between threads.
const RAYS_PER_TASK: usize = 32;

/// Fewest lines per band of a back projection.
const MIN_BAND_LINES: usize = 8;

fn fits(grid: &ImageGrid) -> bool {
    Kernel::fits(grid.ny, grid.nx + 2) && Kernel::fits(grid.nx, grid.ny + 2)
}

/// The layouts the rays of `subset` use: the rays of a parallel view share its direction, so its
/// dominant axis (decided as [`Walk2::new`] decides it); a fan view may use both.
fn needs(views: &Views2, grid: &ImageGrid, subset: &[usize]) -> Needs {
    let mut n = Needs {
        rows: false,
        cols: false,
    };
    for &view in subset {
        match views.views[view].source {
            Source2::Parallel { direction } => {
                let (bx, by) = (direction[0] / grid.dx_mm, direction[1] / grid.dy_mm);
                if bx.abs() >= by.abs() {
                    n.cols = true;
                } else {
                    n.rows = true;
                }
            }
            Source2::Point { .. } => return Needs::BOTH,
        }
        if n == Needs::BOTH {
            break;
        }
    }
    n
}

/// The dot product of a ray (its walk) with the image held in `layouts`.
#[inline]
fn ray_dot(walk: Option<Walk2>, image: &[f32], layouts: &Layouts2, kernel: Kernel) -> f32 {
    match walk {
        Some(w) => {
            let l = layouts.lines(w.along_x);
            if l.is_used() {
                kernel.dot(&l.data, l.width, 0, &Segment::of(&w), w.start, w.end)
            } else {
                // Not reached: `needs` decides the dominant axis as the walk does.
                w.dot(image)
            }
        }
        None => 0.0,
    }
}

/// The walk of ray `k` of `view`: from `walks` (every ray of every view, view after view) when it is not
/// empty, else computed.
#[inline]
fn walk(
    views: &Views2,
    grid: &ImageGrid,
    walks: &[Option<Walk2>],
    view: usize,
    k: usize,
) -> Option<Walk2> {
    if walks.is_empty() {
        Walk2::new(&views.ray(&views.views[view], k), grid)
    } else {
        walks[view * views.detector.count + k]
    }
}

/// The walks of every ray of every view, view after view (what `walks` holds in [`forward`] and [`back`]).
pub fn all_walks(views: &Views2, grid: &ImageGrid) -> Vec<Option<Walk2>> {
    let m = views.detector.count;
    (0..views.views.len() * m)
        .into_par_iter()
        .map(|i| Walk2::new(&views.ray(&views.views[i / m], i % m), grid))
        .collect()
}

/// `out[s·m ..]` = A_view image for each `view = subset[s]` (m detector elements). `walks`: every ray's walk
/// ([`all_walks`]), or empty to compute them as needed.
pub fn forward(
    views: &Views2,
    grid: &ImageGrid,
    walks: &[Option<Walk2>],
    image: &[f32],
    subset: &[usize],
    out: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let m = views.detector.count;
    if !fits(grid) {
        return forward_partitioned(m, subset, out, cancel, |view, row| {
            joseph2::forward_view(views, view, grid, image, row)
        });
    }
    let plans = line_plans(views, grid, subset);
    let others: Vec<usize> = subset
        .iter()
        .zip(&plans)
        .filter(|(_, p)| p.is_none())
        .map(|(&v, _)| v)
        .collect();
    let layouts = Layouts2::from_image(image, grid.nx, grid.ny, needs(views, grid, &others));
    let wide = |along_x: bool| {
        plans
            .iter()
            .flatten()
            .any(|p| p.along_x == along_x)
            .then(|| WideLines::from_image(image, grid.nx, grid.ny, along_x))
    };
    let (wide_rows, wide_cols) = (wide(false), wide(true));
    let line_forward = |lv: &LineView, row: &mut [f32]| {
        let lines = if lv.along_x { &wide_cols } else { &wide_rows };
        if let Some(lines) = lines {
            parallel2::forward_view(lines, lv, row);
        }
    };
    let kernel = Kernel::detect();
    if subset.len() >= 2 * rayon::current_num_threads() {
        return out
            .par_chunks_mut(m)
            .zip(subset.par_iter().zip(plans.par_iter()))
            .try_for_each(|(row, (&view, plan))| {
                cancel.check()?;
                match plan {
                    Some(lv) => line_forward(lv, row),
                    None => {
                        for (k, o) in row.iter_mut().enumerate() {
                            *o =
                                ray_dot(walk(views, grid, walks, view, k), image, &layouts, kernel);
                        }
                    }
                }
                Ok(())
            });
    }
    for ((row, &view), plan) in out.chunks_mut(m).zip(subset).zip(&plans) {
        cancel.check()?;
        if let Some(lv) = plan {
            line_forward(lv, row);
            continue;
        }
        row.par_chunks_mut(RAYS_PER_TASK)
            .enumerate()
            .for_each(|(c, part)| {
                for (k, o) in part.iter_mut().enumerate() {
                    let w = walk(views, grid, walks, view, c * RAYS_PER_TASK + k);
                    *o = ray_dot(w, image, &layouts, kernel);
                }
            });
    }
    Ok(())
}

/// The line-kernel plan of every view, when the grid fits the padded layouts and every view has one
/// (see [`parallel2::LineView::plan`]).
pub fn every_line_plan(views: &Views2, grid: &ImageGrid) -> Option<Vec<LineView>> {
    if !fits(grid) || !parallel2::available() {
        return None;
    }
    (0..views.views.len())
        .into_par_iter()
        .map(|v| LineView::plan(views, v, grid))
        .collect()
}

/// The line-kernel plans of the views of `subset` (see [`parallel2`]); all `None` where the CPU
/// does not run the line kernels.
fn line_plans(views: &Views2, grid: &ImageGrid, subset: &[usize]) -> Vec<Option<LineView>> {
    if !parallel2::available() {
        return vec![None; subset.len()];
    }
    subset
        .par_iter()
        .map(|&v| LineView::plan(views, v, grid))
        .collect()
}

/// The rays of one view that carry data, by dominant axis, with their data values.
#[derive(Default)]
struct ViewRays {
    along_x: Vec<(f32, Segment)>,
    along_y: Vec<(f32, Segment)>,
}

impl ViewRays {
    fn new(
        views: &Views2,
        view: usize,
        grid: &ImageGrid,
        walks: &[Option<Walk2>],
        row: &[f32],
    ) -> Self {
        let mut out = Self::default();
        for (k, &r) in row.iter().enumerate() {
            if r == 0.0 {
                continue;
            }
            if let Some(w) = walk(views, grid, walks, view, k) {
                let list = if w.along_x {
                    &mut out.along_x
                } else {
                    &mut out.along_y
                };
                list.push((r, Segment::of(&w)));
            }
        }
        out
    }
}

/// The bands of `lines`: (dominant axis is x, first line, values), about `per_layout` of them.
fn bands(lines: &mut Lines, along_x: bool, per_layout: usize) -> Vec<(bool, usize, &mut [f32])> {
    let per_band = lines.count.div_ceil(per_layout.max(1)).max(MIN_BAND_LINES);
    let width = lines.width;
    lines
        .data
        .chunks_mut(per_band * width)
        .enumerate()
        .map(|(b, band)| (along_x, b * per_band, band))
        .collect()
}

/// `image` = Σ_s A_viewᵀ data[s·m ..] over `view = subset[s]` (overwrites `image`).
pub fn back(
    views: &Views2,
    grid: &ImageGrid,
    walks: &[Option<Walk2>],
    data: &[f32],
    subset: &[usize],
    image: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let m = views.detector.count;
    if !fits(grid) {
        return back_partitioned(
            image.len(),
            m,
            data,
            subset,
            image,
            cancel,
            |view, row, acc| joseph2::back_view(views, view, grid, row, acc),
        );
    }
    let plans = line_plans(views, grid, subset);
    let mut rest = Vec::new();
    let (mut rows, mut cols) = (Vec::new(), Vec::new());
    for ((&view, row), plan) in subset.iter().zip(data.chunks_exact(m)).zip(&plans) {
        match plan {
            Some(lv) if lv.along_x => cols.push((lv, row)),
            Some(lv) => rows.push((lv, row)),
            None => rest.push((view, row)),
        }
    }
    back_rays(views, grid, walks, &rest, image, cancel)?;
    if !rows.is_empty() {
        parallel2::back_lines(&rows, grid.ny, grid.nx, image, cancel)?;
    }
    if !cols.is_empty() {
        let mut lines = vec![0.0f32; image.len()];
        parallel2::back_lines(&cols, grid.nx, grid.ny, &mut lines, cancel)?;
        add_transposed(&lines, grid.nx, grid.ny, image);
    }
    Ok(())
}

/// `image[y][x] += lines[x][y]` (`nx` lines of `ny` values).
fn add_transposed(lines: &[f32], nx: usize, ny: usize, image: &mut [f32]) {
    const ROWS_PER_TASK: usize = 16;
    image
        .par_chunks_mut(nx * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, block)| {
            let y0 = task * ROWS_PER_TASK;
            for x in 0..nx {
                let col = &lines[x * ny + y0..];
                for (k, row) in block.chunks_exact_mut(nx).enumerate() {
                    row[x] += col[k];
                }
            }
        });
}

/// `image` = Σ A_viewᵀ row over `pairs` (view, data row) with the ray-driven kernels (overwrites
/// `image`).
fn back_rays(
    views: &Views2,
    grid: &ImageGrid,
    walks: &[Option<Walk2>],
    pairs: &[(usize, &[f32])],
    image: &mut [f32],
    cancel: &Cancel,
) -> Result<(), ReconError> {
    let m = views.detector.count;
    let kernel = Kernel::detect();
    let none = Needs {
        rows: false,
        cols: false,
    };
    // Each layout is allocated when a ray first needs it.
    let mut acc = Layouts2::zeros(grid.nx, grid.ny, none);
    let per_layout = 2 * rayon::current_num_threads();
    let chunk = (CHUNK_BYTES / (m.max(1) * std::mem::size_of::<(f32, Segment)>())).max(1);
    for part in pairs.chunks(chunk) {
        let rays: Vec<ViewRays> = part
            .par_iter()
            .map(|&(view, row)| {
                cancel.check()?;
                Ok(ViewRays::new(views, view, grid, walks, row))
            })
            .collect::<Result<_, ReconError>>()?;
        if !acc.cols.is_used() && rays.iter().any(|r| !r.along_x.is_empty()) {
            acc.cols = Lines::zeros(grid.nx, grid.ny, true);
        }
        if !acc.rows.is_used() && rays.iter().any(|r| !r.along_y.is_empty()) {
            acc.rows = Lines::zeros(grid.ny, grid.nx, true);
        }
        let mut tasks = bands(&mut acc.cols, true, per_layout);
        tasks.extend(bands(&mut acc.rows, false, per_layout));
        tasks.into_par_iter().for_each(|(along_x, first, band)| {
            let width = if along_x { grid.ny + 2 } else { grid.nx + 2 };
            let last = first + band.len() / width;
            for vr in &rays {
                let list = if along_x { &vr.along_x } else { &vr.along_y };
                for (alpha, seg) in list {
                    let lo = (seg.start as usize).max(first);
                    let hi = (seg.end as usize).min(last);
                    kernel.axpy(band, width, first, seg, lo, hi, *alpha);
                }
            }
        });
    }
    acc.sum_into(image);
    Ok(())
}

#[cfg(test)]
mod tests {
    //! The whole-subset passes against the reference walks of `joseph2` (sums in another order, so
    //! within 1e-5 of the largest value), on parallel (views at 0°, 45°, 90°, 135° among them), fan arc
    //! and fan flat geometries, with all views, single views (rays split between threads) and data
    //! with zeros (skipped rays).
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::recon::geometry::{Angles, FanBeam, FanDetector, ParallelBeam};

    fn geometries() -> Vec<Views2> {
        let parallel = ParallelBeam {
            angles: Angles::uniform(8, 180.0),
            det_count: 61,
            det_spacing_mm: 0.9,
            det_offset_mm: 0.3,
        };
        let fan = |detector| FanBeam {
            angles: Angles::uniform(13, 360.0),
            dso_mm: 90.0,
            dsd_mm: 150.0,
            detector,
            centre_mm: [1.0, -0.5],
        };
        // Detector elements of 0.6 mm (two rays per pixel on some lines) and of 1.6 mm (the
        // steepest views left to the ray kernels) for the line kernels of `parallel2`.
        let spaced = |spacing_mm| ParallelBeam {
            det_spacing_mm: spacing_mm,
            ..parallel.clone()
        };
        vec![
            spaced(0.6).to_views().unwrap(),
            spaced(1.6).to_views().unwrap(),
            parallel.to_views().unwrap(),
            fan(FanDetector::Arc {
                count: 71,
                spacing_deg: 0.4,
                offset_deg: 0.1,
            })
            .to_views()
            .unwrap(),
            fan(FanDetector::Flat {
                count: 67,
                spacing_mm: 1.1,
                offset_mm: -0.4,
            })
            .to_views()
            .unwrap(),
        ]
    }

    fn close(a: &[f32], b: &[f32]) {
        let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(1e-30);
        for (k, (x, y)) in a.iter().zip(b).enumerate() {
            assert!((x - y).abs() <= 1e-5 * scale, "{k}: {x} vs {y}");
        }
    }

    #[test]
    fn subset_passes_match_the_reference_walks() {
        let grid = ImageGrid {
            nx: 41,
            ny: 29,
            dx_mm: 1.0,
            dy_mm: 1.2,
            centre_mm: [0.5, 0.25],
        };
        let mut rng = StdRng::seed_from_u64(5);
        let image: Vec<f32> = (0..grid.nx * grid.ny).map(|_| rng.random()).collect();
        let cancel = Cancel::new();
        // Both spaced geometries mix views of the line kernels and of the ray kernels.
        for views in &geometries()[..2] {
            let all: Vec<usize> = (0..views.views.len()).collect();
            let planned = line_plans(views, &grid, &all).iter().flatten().count();
            assert!(!parallel2::available() || (0 < planned && planned < all.len()));
        }
        for views in geometries() {
            let (nv, m) = (views.views.len(), views.detector.count);
            let mut subsets: Vec<Vec<usize>> = vec![(0..nv).collect(), vec![nv / 2]];
            subsets.extend((0..nv).map(|v| vec![v]));
            // Walks computed as needed, and taken from the table of every ray.
            let table = all_walks(&views, &grid);
            let modes: [&[Option<Walk2>]; 2] = [&[], &table];
            for (walks, subset) in modes
                .iter()
                .flat_map(|&w| subsets.iter().map(move |s| (w, s.clone())))
            {
                let mut got = vec![0.0f32; subset.len() * m];
                forward(&views, &grid, walks, &image, &subset, &mut got, &cancel).unwrap();
                let mut want = vec![0.0f32; subset.len() * m];
                for (row, &v) in want.chunks_mut(m).zip(&subset) {
                    joseph2::forward_view(&views, v, &grid, &image, row);
                }
                close(&got, &want);

                let data: Vec<f32> = (0..subset.len() * m)
                    .map(|_| {
                        if rng.random::<f32>() < 0.2 {
                            0.0
                        } else {
                            rng.random::<f32>() - 0.3
                        }
                    })
                    .collect();
                let mut got = vec![f32::NAN; image.len()];
                back(&views, &grid, walks, &data, &subset, &mut got, &cancel).unwrap();
                let mut want = vec![0.0f32; image.len()];
                for (row, &v) in data.chunks(m).zip(&subset) {
                    joseph2::back_view(&views, v, &grid, row, &mut want);
                }
                close(&got, &want);
            }
        }
    }

    #[test]
    fn an_empty_subset_back_projects_to_zero() {
        let grid = ImageGrid::square(8, 1.0);
        let views = &geometries()[0];
        let mut image = vec![1.0f32; 64];
        back(views, &grid, &[], &[], &[], &mut image, &Cancel::new()).unwrap();
        assert!(image.iter().all(|&v| v == 0.0));
    }
}
