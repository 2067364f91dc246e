//! Filtered backprojection of 2D sinograms: parallel beams, and fan beams on arc (equiangular) and flat
//! (equispaced) detectors with full scans, Parker short scans and Wang offset detectors.
//!
//! Parallel: f(x, y) = Σ_k Δθ_k Q_k(x cos θ_k + y sin θ_k), Q = τ·(p ⊛ h) (½ for a full turn).
//! Fan, arc: pre-weight D cos γ, filter with the equiangular kernel g, backproject Σ Δβ Q(γ′)/L².
//! The filtered arc views are resampled with Catmull–Rom cubic interpolation, 4 samples per element,
//! onto a uniform grid in tan γ with the factor 1/(1 + tan²γ) folded in, so that the backprojection needs one division per pixel and
//! no arctangent: L² = lc²(1 + tan²γ′) with lc the distance along the central ray.
//! Fan, flat: detector moved to the isocentre (s = u·D/DSD), pre-weight D/√(D² + s²), filter with h/2,
//! backproject Σ Δβ D²/lc² Q(u′).
//! Redundancy weights ([`Redundancy`]) multiply the pre-weights before filtering.

use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

use super::backproject::{PAD, RowLine, fan_row, parallel_row};
use super::filter::{Kernel, RowFilter};
use super::orbit::{Frame, fan_frames};
use super::progress::Ticker;
use super::weights::{Redundancy, extension, parallel_factor};
use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{DetectorShape, Source2, Views2, angular_steps};
use crate::recon::grid::ImageGrid;

/// Samples per detector element of the tan γ grid an arc view is resampled onto.
pub const ARC_OVERSAMPLING: usize = 4;

/// Filtered arc rows are computed at this many samples per detector element before they are resampled
/// (Catmull–Rom cubic) onto the tan γ grid. Parallel and flat fan beams interpolate linearly between
/// elements.
pub const ARC_UPSAMPLING: usize = 1;

/// Cap on the length of the tan γ grid, in multiples of `ARC_OVERSAMPLING` × elements (wide fans
/// stretch by 1/cos²γ; beyond ±69° the grid gets coarser than `ARC_OVERSAMPLING` per element at the edges).
const MAX_ARC_STRETCH: usize = 8;

/// Filtered views, one padded row each, and how to find a detector position in them.
struct Filtered {
    rows: Vec<f32>,
    width: usize,
}

impl Filtered {
    fn row(&self, k: usize) -> &[f32] {
        &self.rows[k * self.width..(k + 1) * self.width]
    }
}

pub(super) fn check_sinogram(views: &Views2, sino: &ArrayView2<'_, f32>) -> Result<(), ReconError> {
    let expected = views.shape();
    if sino.shape() != expected {
        return Err(ReconError::ShapeMismatch {
            expected: expected.to_vec(),
            got: sino.shape().to_vec(),
        });
    }
    if views.views.is_empty() {
        return Err(ReconError::param("geometry", "no views"));
    }
    Ok(())
}

/// True for a parallel-beam scan, false for a fan beam; a scan that mixes both, or has no view, is refused.
pub(super) fn parallel_beam(views: &Views2) -> Result<bool, ReconError> {
    let Some(first) = views.views.first() else {
        return Err(ReconError::param("geometry", "no views"));
    };
    let parallel = matches!(first.source, Source2::Parallel { .. });
    if views
        .views
        .iter()
        .any(|v| matches!(v.source, Source2::Parallel { .. }) != parallel)
    {
        return Err(ReconError::param(
            "geometry",
            "mixed parallel and fan views",
        ));
    }
    Ok(parallel)
}

/// Parallel or fan-beam FBP; see the module docs.
pub fn fbp_2d(
    views: &Views2,
    sino: ArrayView2<'_, f32>,
    grid: &ImageGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array2<f32>, ReconError> {
    grid.validate()?;
    params.validate()?;
    check_sinogram(views, &sino)?;
    if parallel_beam(views)? {
        parallel_fbp(views, sino, grid, params, ctl)
    } else {
        fan_fbp(views, sino, grid, params, ctl)
    }
}

/// Filter every view: `prepare(k, input)` writes the weighted row `k` into `input`, `store(k, filtered,
/// out)` writes the stored (padded) row.
fn filter_views(
    count: usize,
    filter: &RowFilter,
    width: usize,
    ctl: Control<'_>,
    prepare: impl Fn(usize, &mut [f64]) + Sync,
    store: impl Fn(usize, &[f64], &mut [f32]) + Sync,
) -> Result<Filtered, ReconError> {
    let n = filter.len();
    let mut rows = vec![0.0f32; count * width];
    let ticker = Ticker::new(ctl, "filter", count);
    rows.par_chunks_mut(width).enumerate().try_for_each_init(
        || filter.scratch(),
        |scratch, (k, out)| {
            ctl.check()?;
            prepare(k, scratch.input(n));
            filter.run(scratch);
            store(k, scratch.output(n * filter.up()), out);
            ticker.tick();
            Ok::<(), ReconError>(())
        },
    )?;
    Ok(Filtered { rows, width })
}

/// Image rows backprojected together: each filtered view is read once per block from memory.
const ROW_BLOCK: usize = 8;

/// Backproject: `add_view(j, k, acc)` adds view `k` to image row `j`; blocks of rows run in parallel.
fn backproject_rows(
    grid: &ImageGrid,
    count: usize,
    ctl: Control<'_>,
    add_view: impl Fn(usize, usize, &mut [f32]) + Sync,
) -> Result<Array2<f32>, ReconError> {
    let nx = grid.nx;
    let mut image = Array2::<f32>::zeros(grid.shape());
    let ticker = Ticker::new(ctl, "backproject", grid.ny);
    let Some(flat) = image.as_slice_mut() else {
        return Err(ReconError::param("grid", "image is not contiguous"));
    };
    flat.par_chunks_mut(ROW_BLOCK * nx)
        .enumerate()
        .try_for_each(|(block, rows)| {
            ctl.check()?;
            let first = block * ROW_BLOCK;
            for k in 0..count {
                for (r, acc) in rows.chunks_mut(nx).enumerate() {
                    add_view(first + r, k, acc);
                }
            }
            ticker.add(rows.len() / nx);
            Ok::<(), ReconError>(())
        })?;
    Ok(image)
}

fn parallel_fbp(
    views: &Views2,
    sino: ArrayView2<'_, f32>,
    grid: &ImageGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array2<f32>, ReconError> {
    let det = views.detector;
    let angles: Vec<f64> = views.views.iter().map(|v| v.angle_rad).collect();
    let factor = parallel_factor(&angles)?;
    let steps = angular_steps(&angles);
    let n = det.count;
    let up = 1;
    let kernel = Kernel::Ramp {
        spacing: det.spacing,
    };
    let filter = RowFilter::upsampled(n, kernel, 1.0, params, up)?;
    let filtered = filter_views(
        views.views.len(),
        &filter,
        up * n + 2 * PAD,
        ctl,
        |k, input| {
            for (i, v) in input.iter_mut().zip(sino.row(k)) {
                *i = *v as f64;
            }
        },
        |k, row, out| {
            let w = steps[k] * factor;
            for (o, v) in out[PAD..PAD + up * n].iter_mut().zip(row) {
                *o = (v * w) as f32;
            }
        },
    )?;
    // Stored position of t: ((t − offset)/spacing + (n − 1)/2)·up + PAD.
    let sp = det.spacing / up as f64;
    let base = (n as f64 - 1.0) / 2.0 * up as f64 + PAD as f64 - det.offset / sp;
    let x0 = grid.x(0);
    backproject_rows(grid, views.views.len(), ctl, |j, k, acc| {
        let v = &views.views[k];
        let (cx, cy) = (x0 - v.det_centre[0], grid.y(j) - v.det_centre[1]);
        let pos0 = (cx * v.det_u[0] + cy * v.det_u[1]) / sp + base;
        let dpos = grid.dx_mm * v.det_u[0] / sp;
        parallel_row(acc, filtered.row(k), pos0 as f32, dpos as f32);
    })
}

/// Fan angles (relative to the central ray) of the outer edges of the detector, and of one element.
pub(super) fn fan_extent(
    coords: (f64, f64),
    spacing: f64,
    flat_dsd: Option<f64>,
) -> (f64, f64, f64) {
    let (lo, hi) = (coords.0 - spacing / 2.0, coords.1 + spacing / 2.0);
    match flat_dsd {
        Some(dsd) => ((lo / dsd).atan(), (hi / dsd).atan(), (spacing / dsd).atan()),
        None => (lo, hi, spacing),
    }
}

fn row_line(f: &Frame, grid: &ImageGrid, j: usize) -> RowLine {
    let [lc0, lat0, _] = f.local([grid.x(0), grid.y(j), 0.0]);
    RowLine {
        lc0: lc0 as f32,
        dlc: (grid.dx_mm * f.dir[0]) as f32,
        lat0: lat0 as f32,
        dlat: (grid.dx_mm * f.e_u[0]) as f32,
        latv0: 0.0,
        dlatv: 0.0,
    }
}

/// Catmull–Rom interpolation at one position of a row: four neighbouring samples and their weights
/// (zero for samples outside the row, whose indices are clamped into it).
#[derive(Debug, Clone, Copy)]
struct Taps {
    index: [u32; 4],
    weight: [f64; 4],
}

impl Taps {
    /// The taps at sample position `p` of a row of `len` samples (zero outside), times `scale`.
    fn catmull_rom(p: f64, len: usize, scale: f64) -> Self {
        let mut taps = Taps {
            index: [0; 4],
            weight: [0.0; 4],
        };
        if !(p > -2.0 && p < len as f64 + 1.0) || len == 0 {
            return taps;
        }
        let i = p.floor();
        let t = p - i;
        let (t2, t3) = (t * t, t * t * t);
        let w = [
            0.5 * (-t + 2.0 * t2 - t3),
            0.5 * (2.0 - 5.0 * t2 + 3.0 * t3),
            0.5 * (t + 4.0 * t2 - 3.0 * t3),
            0.5 * (t3 - t2),
        ];
        for (r, wr) in w.iter().enumerate() {
            let at = i as i64 - 1 + r as i64;
            if at >= 0 && (at as usize) < len {
                taps.index[r] = at as u32;
                taps.weight[r] = wr * scale;
            }
        }
        taps
    }

    /// The interpolated value; `row` must hold the `len` samples the taps were made for.
    fn apply(&self, row: &[f64]) -> f64 {
        self.index
            .iter()
            .zip(&self.weight)
            .map(|(&i, &w)| row.get(i as usize).map_or(0.0, |v| v * w))
            .sum()
    }
}

fn fan_fbp(
    views: &Views2,
    sino: ArrayView2<'_, f32>,
    grid: &ImageGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array2<f32>, ReconError> {
    let det = views.detector;
    let frames = fan_frames(views)?;
    let f0 = frames[0];
    let n = det.count;
    let angles: Vec<f64> = frames.iter().map(|f| f.angle_rad).collect();
    let steps = angular_steps(&angles);
    let ends = (det.coord(0) + f0.u0, det.coord(n - 1) + f0.u0);
    let flat = det.shape == DetectorShape::Flat;
    let (gmin, gmax, element) = fan_extent(ends, det.spacing, flat.then_some(f0.dsd));
    let redundancy = Redundancy::classify(&angles, gmin, gmax, element)?;
    let count = views.views.len();
    // Offset detectors are filtered on a row extended with zeros on the short side.
    let (lo, hi) = extension(&redundancy, (ends.0 + ends.1) / det.spacing);
    let ne = n + lo + hi;
    // Stored sample i (before PAD) is detector element i − lo.
    let sample = |i: usize, row: ndarray::ArrayView1<'_, f32>| -> f64 {
        if i >= lo && i < lo + n {
            row[i - lo] as f64
        } else {
            0.0
        }
    };
    let coord = |i: usize| det.coord(0) + (i as f64 - lo as f64) * det.spacing;
    if flat {
        let magnification = f0.dsd / f0.dso;
        let kernel = Kernel::Ramp {
            spacing: det.spacing / magnification,
        };
        let up = 1;
        let filter = RowFilter::upsampled(ne, kernel, 0.5, params, up)?;
        let filtered = filter_views(
            count,
            &filter,
            up * ne + 2 * PAD,
            ctl,
            |k, input| {
                let f = &frames[k];
                let measured = sino.row(k);
                for (i, o) in input.iter_mut().enumerate() {
                    let u = coord(i) + f.u0;
                    let pre = f.dsd / f.dsd.hypot(u);
                    let w = redundancy.weight(f.angle_rad, (u / f.dsd).atan());
                    *o = sample(i, measured) * pre * w;
                }
            },
            |k, row, out| {
                let w = steps[k] * frames[k].dso * frames[k].dso;
                for (o, v) in out[PAD..PAD + up * ne].iter_mut().zip(row) {
                    *o = (v * w) as f32;
                }
            },
        )?;
        backproject_rows(grid, count, ctl, |j, k, acc| {
            let f = &frames[k];
            let sp = det.spacing / up as f64;
            let a = f.dsd / sp;
            let b = ((n as f64 - 1.0) / 2.0 + lo as f64) * up as f64 + PAD as f64
                - (f.u0 + det.offset) / sp;
            fan_row(
                acc,
                filtered.row(k),
                &row_line(f, grid, j),
                a as f32,
                b as f32,
            );
        })
    } else {
        let kernel = Kernel::Equiangular {
            spacing: det.spacing,
        };
        let up = ARC_UPSAMPLING;
        let filter = RowFilter::upsampled(ne, kernel, 1.0, params, up)?;
        let nf = up * ne;
        // The tan γ grid: one element beyond each end, ARC_OVERSAMPLING samples per element.
        let (t_lo, t_hi) = (
            (coord(0) + f0.u0 - det.spacing).tan(),
            (coord(ne - 1) + f0.u0 + det.spacing).tan(),
        );
        let fine = ((t_hi - t_lo) / det.spacing * ARC_OVERSAMPLING as f64).ceil() as usize;
        let m = fine.min(MAX_ARC_STRETCH * ARC_OVERSAMPLING * ne) + 1;
        let dt = (t_hi - t_lo) / (m - 1) as f64;
        // Element position of tan-grid sample j, and the factor 1/(1 + t²).
        let position = |j: usize, u0: f64| {
            let t = t_lo + j as f64 * dt;
            (t.atan() - u0 - coord(0)) / det.spacing
        };
        let stretch: Vec<f64> = (0..m)
            .map(|j| {
                let t = t_lo + j as f64 * dt;
                1.0 / (1.0 + t * t)
            })
            .collect();
        // Views whose central ray meets the detector where the first view's does (the usual case) share
        // one table of interpolation taps, with the stretch factor folded in.
        let shared: Vec<Taps> = (0..m)
            .map(|j| Taps::catmull_rom(position(j, f0.u0) * up as f64, nf, stretch[j]))
            .collect();
        // cos γ of each element for the same views.
        let cosines: Vec<f64> = (0..ne).map(|i| (coord(i) + f0.u0).cos()).collect();
        let filtered = filter_views(
            count,
            &filter,
            m + 2 * PAD,
            ctl,
            |k, input| {
                let f = &frames[k];
                let same = (f.u0 - f0.u0).abs() <= 1e-12;
                let measured = sino.row(k);
                for (i, o) in input.iter_mut().enumerate() {
                    let g = coord(i) + f.u0;
                    let cos = if same { cosines[i] } else { g.cos() };
                    *o = sample(i, measured) * f.dso * cos * redundancy.weight(f.angle_rad, g);
                }
            },
            |k, row, out| {
                let f = &frames[k];
                let same = (f.u0 - f0.u0).abs() <= 1e-12;
                let out = &mut out[PAD..PAD + m];
                if same {
                    for (o, taps) in out.iter_mut().zip(&shared) {
                        *o = (taps.apply(row) * steps[k]) as f32;
                    }
                } else {
                    for (j, o) in out.iter_mut().enumerate() {
                        let taps = Taps::catmull_rom(position(j, f.u0) * up as f64, nf, stretch[j]);
                        *o = (taps.apply(row) * steps[k]) as f32;
                    }
                }
            },
        )?;
        backproject_rows(grid, count, ctl, |j, k, acc| {
            let a = 1.0 / dt;
            let b = PAD as f64 - t_lo / dt;
            fan_row(
                acc,
                filtered.row(k),
                &row_line(&frames[k], grid, j),
                a as f32,
                b as f32,
            );
        })
    }
}

/// Bytes a 2D FBP allocates: the image, the filtered views and per-thread filter buffers.
pub fn estimate_bytes(views: &Views2, grid: &ImageGrid, params: &FbpParams) -> u64 {
    // Offset detectors are extended up to twice their length before filtering.
    let n = (views.detector.count as u64).saturating_mul(2);
    let width = match (views.detector.shape, views.views.first().map(|v| v.source)) {
        (DetectorShape::Arc, Some(Source2::Point { .. })) => {
            n.saturating_mul((ARC_OVERSAMPLING * MAX_ARC_STRETCH) as u64)
        }
        _ => n,
    }
    .saturating_add(2 * PAD as u64 + 2);
    let filtered = (views.views.len() as u64)
        .saturating_mul(width)
        .saturating_mul(4);
    let image = (grid.nx as u64)
        .saturating_mul(grid.ny as u64)
        .saturating_mul(4);
    let padded = super::filter::padded_len(views.detector.count, params.padded_len)
        .map(|p| p as u64)
        .unwrap_or(0);
    let threads = rayon::current_num_threads() as u64;
    let per_thread = padded
        .saturating_mul(8 * 4 * ARC_UPSAMPLING as u64)
        .saturating_add((grid.nx as u64) * 4);
    image
        .saturating_add(filtered)
        .saturating_add(threads.saturating_mul(per_thread))
}
