//! Joseph's ray-driven projector on a 2D image grid: one sample per image column (or row) along the
//! dominant axis of the ray, linearly interpolated between the two nearest pixels of the other axis and
//! weighted by the ray length between samples.
//!
//! Forward and back projection enumerate exactly the same (pixel, weight) pairs through [`Walk2::visit`],
//! which makes the pair an exact adjoint (up to f32 rounding).

use crate::recon::geometry::{Ray2, Views2};
use crate::recon::grid::ImageGrid;

/// The samples of one ray through the image, in pixel-index space.
///
/// Sample `i ∈ [start, end)` sits on line `i` of the dominant axis (pixel index `i·stride_a`) at
/// fractional coordinate `c0 + i·dc` of the other axis; it weighs `weight` mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Walk2 {
    pub start: usize,
    pub end: usize,
    pub c0: f32,
    pub dc: f32,
    pub weight: f32,
    pub stride_a: usize,
    pub stride_c: usize,
    pub n_c: usize,
    /// True when the dominant axis is x (samples on image columns, interpolation along y).
    pub along_x: bool,
}

impl Walk2 {
    /// The walk of `ray` through `grid`; `None` when the ray misses the grid.
    pub fn new(ray: &Ray2, grid: &ImageGrid) -> Option<Self> {
        let (x0, y0) = (grid.x(0), grid.y(0));
        let ax = (ray.origin[0] - x0) / grid.dx_mm;
        let bx = ray.direction[0] / grid.dx_mm;
        let ay = (ray.origin[1] - y0) / grid.dy_mm;
        let by = ray.direction[1] / grid.dy_mm;
        // Dominant axis: the one the ray crosses fastest in index space.
        let along_x = bx.abs() >= by.abs();
        let (a0, ba, c, bc, n_a, n_c, stride_a, stride_c) = if along_x {
            (ax, bx, ay, by, grid.nx, grid.ny, 1, grid.nx)
        } else {
            (ay, by, ax, bx, grid.ny, grid.nx, grid.nx, 1)
        };
        if ba == 0.0 || !ba.is_finite() {
            return None;
        }
        let s = bc / ba;
        let c0 = c - a0 * s;
        let last = n_a as f64 - 1.0;
        // Samples contribute while the interpolation coordinate lies in (−1, n_c).
        let (lo, hi) = if s.abs() < 1e-12 {
            if c0 > -1.0 && c0 < n_c as f64 {
                (0.0, last)
            } else {
                return None;
            }
        } else {
            let i1 = (-1.0 - c0) / s;
            let i2 = (n_c as f64 - c0) / s;
            (i1.min(i2).floor().max(0.0), i1.max(i2).ceil().min(last))
        };
        if lo.is_nan() || hi.is_nan() || lo > hi {
            return None;
        }
        Some(Self {
            start: lo as usize,
            end: hi as usize + 1,
            c0: c0 as f32,
            dc: s as f32,
            weight: (1.0 / ba.abs()) as f32,
            stride_a,
            stride_c,
            n_c,
            along_x,
        })
    }

    /// Call `f(pixel index, weight)` for every pixel the ray touches (weights in mm, positive). The same
    /// sequence drives forward and back projection.
    #[inline(always)]
    pub fn visit(&self, mut f: impl FnMut(usize, f32)) {
        let n_c = self.n_c;
        for i in self.start..self.end {
            // t = c + 1 > −0 on the sampled range; truncation equals floor for t ≥ 0.
            let t = self.c0 + i as f32 * self.dc + 1.0;
            if t <= 0.0 {
                continue;
            }
            let j1 = t as usize;
            let w1 = (t - j1 as f32) * self.weight;
            let w0 = self.weight - w1;
            let base = i * self.stride_a;
            if j1 >= 1 && j1 < n_c {
                f(base + (j1 - 1) * self.stride_c, w0);
                f(base + j1 * self.stride_c, w1);
            } else if j1 == n_c {
                f(base + (j1 - 1) * self.stride_c, w0);
            } else if j1 == 0 {
                f(base, w1);
            }
        }
    }

    /// Σ `image[p]·w` over the ray.
    #[inline]
    pub fn dot(&self, image: &[f32]) -> f32 {
        let mut acc = 0.0f32;
        self.visit(|p, w| acc += image[p] * w);
        acc
    }

    /// `image[p] += alpha·w` over the ray.
    #[inline]
    pub fn axpy(&self, alpha: f32, image: &mut [f32]) {
        self.visit(|p, w| image[p] += alpha * w);
    }
}

/// The walks of every element of one view (`None` for rays that miss the grid).
pub fn view_walks(views: &Views2, view: usize, grid: &ImageGrid) -> Vec<Option<Walk2>> {
    let v = &views.views[view];
    (0..views.detector.count)
        .map(|k| Walk2::new(&views.ray(v, k), grid))
        .collect()
}

/// Forward-project `image` (flat `[y][x]`) along every element of `view` into `out`.
pub fn forward_view(views: &Views2, view: usize, grid: &ImageGrid, image: &[f32], out: &mut [f32]) {
    let v = &views.views[view];
    for (k, o) in out.iter_mut().enumerate() {
        *o = match Walk2::new(&views.ray(v, k), grid) {
            Some(w) => w.dot(image),
            None => 0.0,
        };
    }
}

/// Add the back projection of one view's data `row` to `acc` (flat `[y][x]`).
pub fn back_view(views: &Views2, view: usize, grid: &ImageGrid, row: &[f32], acc: &mut [f32]) {
    let v = &views.views[view];
    for (k, &r) in row.iter().enumerate() {
        if r == 0.0 {
            continue;
        }
        if let Some(w) = Walk2::new(&views.ray(v, k), grid) {
            w.axpy(r, acc);
        }
    }
}
