//! Joseph's ray-driven projector on a 3D volume grid: one sample per voxel plane of the ray's dominant
//! axis, bilinearly interpolated in that plane and weighted by the ray length between planes.
//!
//! Forward and back projection enumerate exactly the same (voxel, weight) pairs through
//! [`Walk3::visit`], which makes the pair an exact adjoint (up to f32 rounding).

use super::footprint3::footprint;
use crate::recon::geometry::{Ray3, Views3};
use crate::recon::grid::VolumeGrid;

/// The samples of one ray through the volume, in voxel-index space: sample `i ∈ [start, end)` lies on
/// plane `i` of the dominant axis at fractional coordinates `(c0 + i·dc, e0 + i·de)` of the two others.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Walk3 {
    pub start: usize,
    pub end: usize,
    pub c0: f32,
    pub dc: f32,
    pub e0: f32,
    pub de: f32,
    pub weight: f32,
    pub stride_a: usize,
    pub stride_c: usize,
    pub stride_e: usize,
    pub n_c: usize,
    pub n_e: usize,
}

/// Index range `[lo, hi]` (within `[0, last]`) where `c0 + i·s` lies in (−1, n).
fn range(c0: f64, s: f64, n: usize, last: f64) -> Option<(f64, f64)> {
    if s.abs() < 1e-12 {
        return (c0 > -1.0 && c0 < n as f64).then_some((0.0, last));
    }
    let i1 = (-1.0 - c0) / s;
    let i2 = (n as f64 - c0) / s;
    Some((i1.min(i2).floor().max(0.0), i1.max(i2).ceil().min(last)))
}

impl Walk3 {
    /// The walk of `ray` through `grid` (volume `[z][y][x]`); `None` when the ray misses it.
    pub fn new(ray: &Ray3, grid: &VolumeGrid) -> Option<Self> {
        let lo = [grid.x(0), grid.y(0), grid.z(0)];
        let n = [grid.nx, grid.ny, grid.nz];
        let stride = [1, grid.nx, grid.nx * grid.ny];
        let mut a = [0.0; 3];
        let mut b = [0.0; 3];
        for k in 0..3 {
            a[k] = (ray.origin[k] - lo[k]) / grid.spacing_mm[k];
            b[k] = ray.direction[k] / grid.spacing_mm[k];
        }
        let d = if b[0].abs() >= b[1].abs() && b[0].abs() >= b[2].abs() {
            0
        } else if b[1].abs() >= b[2].abs() {
            1
        } else {
            2
        };
        let (c, e) = match d {
            0 => (1, 2),
            1 => (0, 2),
            _ => (0, 1),
        };
        if b[d] == 0.0 || !b[d].is_finite() {
            return None;
        }
        let sc = b[c] / b[d];
        let se = b[e] / b[d];
        let c0 = a[c] - a[d] * sc;
        let e0 = a[e] - a[d] * se;
        let last = n[d] as f64 - 1.0;
        let (l1, h1) = range(c0, sc, n[c], last)?;
        let (l2, h2) = range(e0, se, n[e], last)?;
        let (lo_i, hi_i) = (l1.max(l2), h1.min(h2));
        if lo_i.is_nan() || hi_i.is_nan() || lo_i > hi_i {
            return None;
        }
        Some(Self {
            start: lo_i as usize,
            end: hi_i as usize + 1,
            c0: c0 as f32,
            dc: sc as f32,
            e0: e0 as f32,
            de: se as f32,
            weight: (1.0 / b[d].abs()) as f32,
            stride_a: stride[d],
            stride_c: stride[c],
            stride_e: stride[e],
            n_c: n[c],
            n_e: n[e],
        })
    }

    /// Call `f(voxel index, weight)` for every voxel the ray touches (weights in mm).
    #[inline(always)]
    pub fn visit(&self, mut f: impl FnMut(usize, f32)) {
        let (n_c, n_e) = (self.n_c, self.n_e);
        let (sc, se) = (self.stride_c, self.stride_e);
        for i in self.start..self.end {
            let fi = i as f32;
            let tc = self.c0 + fi * self.dc + 1.0;
            let te = self.e0 + fi * self.de + 1.0;
            if tc <= 0.0 || te <= 0.0 {
                continue;
            }
            let jc = tc as usize;
            let je = te as usize;
            let wc1 = tc - jc as f32;
            let we1 = (te - je as f32) * self.weight;
            let we0 = self.weight - we1;
            let wc0 = 1.0 - wc1;
            let base = i * self.stride_a;
            if jc >= 1 && jc < n_c && je >= 1 && je < n_e {
                let p = base + (jc - 1) * sc + (je - 1) * se;
                f(p, wc0 * we0);
                f(p + sc, wc1 * we0);
                f(p + se, wc0 * we1);
                f(p + sc + se, wc1 * we1);
            } else {
                // Border: keep only the corners inside the grid (index jc−1 or jc, je−1 or je).
                for (oc, wc) in [(0usize, wc0), (1, wc1)] {
                    let kc = jc + oc;
                    if kc == 0 || kc > n_c {
                        continue;
                    }
                    for (oe, we) in [(0usize, we0), (1, we1)] {
                        let ke = je + oe;
                        if ke == 0 || ke > n_e {
                            continue;
                        }
                        f(base + (kc - 1) * sc + (ke - 1) * se, wc * we);
                    }
                }
            }
        }
    }

    /// Σ `volume[p]·w` over the ray.
    #[inline]
    pub fn dot(&self, volume: &[f32]) -> f32 {
        let mut acc = 0.0f32;
        self.visit(|p, w| acc += volume[p] * w);
        acc
    }

    /// `volume[p] += alpha·w` over the ray.
    #[inline]
    pub fn axpy(&self, alpha: f32, volume: &mut [f32]) {
        self.visit(|p, w| volume[p] += alpha * w);
    }
}

fn voxels(grid: &VolumeGrid) -> usize {
    grid.nx * grid.ny * grid.nz
}

/// Forward-project `volume` (flat `[z][y][x]`) along every element of `view` into `out` (`[v][u]`);
/// elements outside the grid's [`footprint`] get 0 without building their walk.
///
/// # Panics
/// If `volume` holds fewer than nx·ny·nz values.
pub fn forward_view(
    views: &Views3,
    view: usize,
    grid: &VolumeGrid,
    volume: &[f32],
    out: &mut [f32],
) {
    assert!(volume.len() >= voxels(grid), "volume smaller than its grid");
    let v = &views.views[view];
    let nu = views.detector.nu;
    let (rows, cols) = footprint(views, v, grid);
    out.fill(0.0);
    for r in rows {
        for c in cols.clone() {
            if let Some(w) = Walk3::new(&views.ray(v, r, c), grid) {
                out[r * nu + c] = w.dot(volume);
            }
        }
    }
}

/// Add the back projection of one view's data (`[v][u]`) to `acc` (flat `[z][y][x]`); elements
/// outside the grid's [`footprint`] are skipped.
///
/// # Panics
/// If `acc` holds fewer than nx·ny·nz values.
pub fn back_view(views: &Views3, view: usize, grid: &VolumeGrid, data: &[f32], acc: &mut [f32]) {
    assert!(acc.len() >= voxels(grid), "volume smaller than its grid");
    let v = &views.views[view];
    let nu = views.detector.nu;
    let (rows, cols) = footprint(views, v, grid);
    for row in rows {
        for c in cols.clone() {
            let r = data[row * nu + c];
            if r == 0.0 {
                continue;
            }
            if let Some(w) = Walk3::new(&views.ray(v, row, c), grid) {
                w.axpy(r, acc);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    //! The per-view loops skip only the rays that have no sample (the footprint).
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    #[test]
    fn the_footprint_skips_only_rays_without_samples() {
        use crate::recon::geometry::{Angles, ConeBeam, Panel};
        let grid = VolumeGrid {
            nx: 12,
            ny: 10,
            nz: 8,
            spacing_mm: [1.0, 1.2, 0.9],
            centre_mm: [1.5, -1.0, 0.5],
        };
        let views = ConeBeam {
            angles: Angles::uniform(16, 360.0),
            dso_mm: 40.0,
            dsd_mm: 70.0,
            detector: Panel {
                nu: 48,
                nv: 40,
                du_mm: 1.0,
                dv_mm: 0.8,
                offset_u_mm: 2.0,
                offset_v_mm: -1.5,
            },
        }
        .to_views()
        .unwrap();
        let mut rng = StdRng::seed_from_u64(4);
        let n = voxels(&grid);
        let volume: Vec<f32> = (0..n).map(|_| rng.random()).collect();
        let (nv, nu) = (views.detector.nv, views.detector.nu);
        let data: Vec<f32> = (0..nv * nu).map(|_| rng.random::<f32>() - 0.3).collect();
        let mut culled = 0;
        for view in 0..views.views.len() {
            let v = &views.views[view];
            let (rows, cols) = footprint(&views, v, &grid);
            culled += nv * nu - rows.len() * cols.len();
            let mut got = vec![f32::NAN; nv * nu];
            forward_view(&views, view, &grid, &volume, &mut got);
            let mut got_back = vec![0.0f32; n];
            back_view(&views, view, &grid, &data, &mut got_back);
            let mut want_back = vec![0.0f32; n];
            for r in 0..nv {
                for c in 0..nu {
                    let w = Walk3::new(&views.ray(v, r, c), &grid);
                    let want = w.map_or(0.0, |w| w.dot(&volume));
                    assert_eq!(got[r * nu + c], want, "view {view} [{r}][{c}]");
                    if !(rows.contains(&r) && cols.contains(&c)) {
                        assert_eq!(want, 0.0, "a skipped ray has samples");
                    }
                    if let Some(w) = w {
                        w.axpy(data[r * nu + c], &mut want_back);
                    }
                }
            }
            assert_eq!(got_back, want_back, "view {view}");
        }
        assert!(culled > 16 * nv * nu / 8, "only {culled} rays skipped");
    }
}
