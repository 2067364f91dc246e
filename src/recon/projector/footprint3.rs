//! The footprint of a volume grid on a cone-beam detector: the detector rows and columns whose rays
//! can touch the grid. Rays outside it are skipped by both projectors without building their walk
//! (most of the cost of a ray that misses), which changes no value: such a ray has no sample.
//!
//! The grid's box, widened by [`MARGIN_VOXELS`] voxels on every side (Joseph samples reach one voxel
//! beyond the grid; the rest absorbs rounding), is projected from the source onto the detector plane:
//! its image is the convex hull of its 8 projected corners, inside their bounding rectangle, widened by
//! one more element on each side. Where a corner is not in front of the source (towards the detector),
//! the whole detector is kept.

use std::ops::Range;

use crate::recon::geometry::vectors::{add3, cross3, dot3, scale3, sub3};
use crate::recon::geometry::{View3, Views3};
use crate::recon::grid::VolumeGrid;

/// Voxels added to every side of the grid's box.
pub const MARGIN_VOXELS: f64 = 3.0;

/// Detector `(rows, columns)` of `view` whose rays can touch `grid` (half-open index ranges).
pub fn footprint(views: &Views3, view: &View3, grid: &VolumeGrid) -> (Range<usize>, Range<usize>) {
    let det = &views.detector;
    let full = (0..det.nv, 0..det.nu);
    let normal = cross3(view.det_u, view.det_v);
    let to_plane = dot3(sub3(view.det_centre, view.source), normal);
    let n = [grid.nx, grid.ny, grid.nz];
    let first = [grid.x(0), grid.y(0), grid.z(0)];
    let (mut u_lo, mut u_hi, mut v_lo, mut v_hi) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for corner in 0..8 {
        let mut p = [0.0; 3];
        for k in 0..3 {
            let m = MARGIN_VOXELS * grid.spacing_mm[k];
            p[k] = if corner >> k & 1 == 0 {
                first[k] - m
            } else {
                first[k] + (n[k] as f64 - 1.0) * grid.spacing_mm[k] + m
            };
        }
        let ray = sub3(p, view.source);
        let t = to_plane / dot3(ray, normal);
        if !(t.is_finite() && t > 0.0) {
            return full;
        }
        let rel = sub3(add3(view.source, scale3(ray, t)), view.det_centre);
        let (u, v) = (dot3(rel, view.det_u), dot3(rel, view.det_v));
        if !(u.is_finite() && v.is_finite()) {
            return full;
        }
        (u_lo, u_hi) = (u_lo.min(u), u_hi.max(u));
        (v_lo, v_hi) = (v_lo.min(v), v_hi.max(v));
    }
    let span = |a: f64, b: f64, count: usize| {
        let (lo, hi) = (a.min(b), a.max(b));
        let start = (lo.floor() - 1.0).clamp(0.0, count as f64) as usize;
        let end = (hi.ceil() + 2.0).clamp(0.0, count as f64) as usize;
        start..end.max(start)
    };
    (
        span(det.row_of(v_lo), det.row_of(v_hi), det.nv),
        span(det.col_of(u_lo), det.col_of(u_hi), det.nu),
    )
}
