//! FDK (Feldkamp–Davis–Kress) reconstruction of circular cone-beam projections on a flat panel, full scan,
//! Parker short scan or Wang offset (half-fan) detector.
//!
//! Virtual detector at the isocentre, coordinates (p, ζ) = (u, v)·D/DSD: pre-weight D/√(D² + p² + ζ²)
//! (times the redundancy weight of the in-plane fan angle), ramp along detector rows only (h/2, the ½ of
//! a full turn), backproject Σ Δβ D²/lc² Q(u′, v′) with lc the distance from the source along the central
//! ray. The volume is accumulated in batches of [`VIEWS_PER_THREAD`] projections per thread: filter the batch
//! (projections in parallel), backproject it into every slice (slices in parallel), drop it. Memory: the
//! volume plus a few filtered projections per thread; each pass reads and writes the volume once, so larger
//! batches mean fewer passes.

use ndarray::{Array3, ArrayView3, Axis};
use rayon::prelude::*;

use super::backproject::{PAD, Panel, RowLine, cone_row};
use super::fbp2d::fan_extent;
use super::filter::{Kernel, RowFilter, padded_len};
use super::orbit::{Frame, cone_frames};
use super::progress::Ticker;
use super::weights::{Redundancy, extension};
use crate::recon::algorithm::FbpParams;
use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::recon::geometry::{Views3, angular_steps};
use crate::recon::grid::VolumeGrid;

/// FDK; see the module docs.
pub fn fdk(
    views: &Views3,
    proj: ArrayView3<'_, f32>,
    grid: &VolumeGrid,
    params: &FbpParams,
    ctl: Control<'_>,
) -> Result<Array3<f32>, ReconError> {
    grid.validate()?;
    params.validate()?;
    let expected = views.shape();
    if proj.shape() != expected {
        return Err(ReconError::ShapeMismatch {
            expected: expected.to_vec(),
            got: proj.shape().to_vec(),
        });
    }
    if views.views.is_empty() {
        return Err(ReconError::param("geometry", "no views"));
    }
    let det = views.detector;
    let frames = cone_frames(views)?;
    let f0 = frames[0];
    let (nu, nv) = (det.nu, det.nv);
    let angles: Vec<f64> = frames.iter().map(|f| f.angle_rad).collect();
    let steps = angular_steps(&angles);
    let ends = (det.u(0) + f0.u0, det.u(nu - 1) + f0.u0);
    let (gmin, gmax, element) = fan_extent(ends, det.du_mm, Some(f0.dsd));
    let redundancy = Redundancy::classify(&angles, gmin, gmax, element)?;
    // Offset panels are filtered on rows extended with zeros on the short side.
    let (lo, hi) = extension(&redundancy, (ends.0 + ends.1) / det.du_mm);
    let full = redundancy.is_full();
    let ne = nu + lo + hi;
    let kernel = Kernel::Ramp {
        spacing: det.du_mm * f0.dso / f0.dsd,
    };
    let filter = RowFilter::new(ne, kernel, 0.5, params)?;
    let (width, rows) = (ne + 2 * PAD, nv + 2 * PAD);
    let batch = rayon::current_num_threads().max(1) * VIEWS_PER_THREAD;
    let mut volume = Array3::<f32>::zeros(grid.shape());
    let mut panels = vec![0.0f32; batch * width * rows];
    let ticker = Ticker::new(ctl, "fdk", views.views.len());
    let sampling = det_map(&det, lo);
    for first in (0..views.views.len()).step_by(batch) {
        let last = (first + batch).min(views.views.len());
        panels[..(last - first) * width * rows]
            .par_chunks_mut(width * rows)
            .enumerate()
            .try_for_each_init(
                || filter.scratch(),
                |scratch, (b, panel)| {
                    ctl.check()?;
                    let k = first + b;
                    let f = &frames[k];
                    let post = steps[k] * f.dso * f.dso;
                    for r in 0..nv {
                        let v = det.v(r) + f.v0;
                        let data = proj.slice(ndarray::s![k, r, ..]);
                        let input = scratch.input(ne);
                        for (i, o) in input.iter_mut().enumerate() {
                            *o = if i >= lo && i < lo + nu {
                                let u = det.u(0) + (i - lo) as f64 * det.du_mm + f.u0;
                                let pre = f.dsd / (f.dsd * f.dsd + u * u + v * v).sqrt();
                                let w = if full {
                                    1.0
                                } else {
                                    redundancy.weight(f.angle_rad, (u / f.dsd).atan())
                                };
                                data[i - lo] as f64 * pre * w
                            } else {
                                0.0
                            };
                        }
                        filter.run(scratch);
                        let start = (r + PAD) * width + PAD;
                        let out = &mut panel[start..start + ne];
                        for (o, q) in out.iter_mut().zip(scratch.output(ne).iter()) {
                            *o = (q * post) as f32;
                        }
                    }
                    Ok::<(), ReconError>(())
                },
            )?;
        ctl.check()?;
        let batch_frames = &frames[first..last];
        let maps: Vec<[f32; 4]> = batch_frames
            .iter()
            .map(|f| panel_map(f, &sampling))
            .collect();
        let panels = &panels;
        volume
            .axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(z, mut slice)| {
                let mut acc = vec![0.0f32; grid.nx];
                for y in 0..grid.ny {
                    acc.fill(0.0);
                    for (b, (f, map)) in batch_frames.iter().zip(&maps).enumerate() {
                        let panel = Panel {
                            q: &panels[b * width * rows..(b + 1) * width * rows],
                            width,
                            rows,
                        };
                        cone_row(&mut acc, panel, &volume_row(f, grid, y, z), *map);
                    }
                    for (o, a) in slice.row_mut(y).iter_mut().zip(&acc) {
                        *o += *a;
                    }
                }
            });
        ticker.add(last - first);
    }
    Ok(volume)
}

/// Filtered projections held per worker thread: each pass over the volume adds this many views per thread,
/// so the volume is read and written once per `threads × VIEWS_PER_THREAD` views.
pub const VIEWS_PER_THREAD: usize = 4;

/// Detector sampling (du, dv, offset_u, offset_v, base_u, base_v): stored column =
/// (u − offset_u)/du + (nu − 1)/2 + PAD + lo, with `lo` zero columns added on the left.
fn det_map(det: &crate::recon::geometry::Detector2, lo: usize) -> [f64; 6] {
    [
        det.du_mm,
        det.dv_mm,
        det.offset_u_mm,
        det.offset_v_mm,
        (det.nu as f64 - 1.0) / 2.0 + (PAD + lo) as f64,
        (det.nv as f64 - 1.0) / 2.0 + PAD as f64,
    ]
}

/// [au, bu, av, bv] with stored column = au·lat/lc + bu and stored row = av·latv/lc + bv.
fn panel_map(f: &Frame, m: &[f64; 6]) -> [f32; 4] {
    let [du, dv, ou, ov, cu, cv] = *m;
    [
        (f.dsd / du) as f32,
        (cu - (f.u0 + ou) / du) as f32,
        (f.dsd / dv) as f32,
        (cv - (f.v0 + ov) / dv) as f32,
    ]
}

fn volume_row(f: &Frame, grid: &VolumeGrid, y: usize, z: usize) -> RowLine {
    let [lc0, lat0, latv0] = f.local([grid.x(0), grid.y(y), grid.z(z)]);
    let dx = grid.spacing_mm[0];
    RowLine {
        lc0: lc0 as f32,
        dlc: (dx * f.dir[0]) as f32,
        lat0: lat0 as f32,
        dlat: (dx * f.e_u[0]) as f32,
        latv0: latv0 as f32,
        dlatv: (dx * f.e_v[0]) as f32,
    }
}

/// Bytes FDK allocates: the volume, [`VIEWS_PER_THREAD`] filtered projections per thread and per-thread
/// filter buffers.
pub fn estimate_bytes(views: &Views3, grid: &VolumeGrid, params: &FbpParams) -> u64 {
    let d = views.detector;
    // Offset panels are extended up to twice their width before filtering.
    let panel = ((2 * d.nu + 2 * PAD) as u64)
        .saturating_mul((d.nv + 2 * PAD) as u64)
        .saturating_mul(4);
    let padded = padded_len(d.nu, params.padded_len)
        .map(|p| p as u64)
        .unwrap_or(0);
    let threads = rayon::current_num_threads() as u64;
    let per_thread = panel
        .saturating_mul(VIEWS_PER_THREAD as u64)
        .saturating_add(padded.saturating_mul(8 * 4))
        .saturating_add((grid.nx as u64) * 4);
    grid.voxels()
        .saturating_mul(4)
        .saturating_add(threads.saturating_mul(per_thread))
}
