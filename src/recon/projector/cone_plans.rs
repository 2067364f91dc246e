//! The per-view plans of the column-ordered cone-beam pair ([`super::cone_columns`]): each detector
//! column's dominant axis, its in-plane line and row positions per plane, the planes it crosses and
//! its rows that are not steep, computed once per set of views and kept by [`PlanCache`] for every
//! pass of an iterative method.

use std::ops::Range;
use std::sync::{Arc, Mutex};

use rayon::prelude::*;

use super::cone_lines::{Form, PlaneStep, reaching};
use super::cone_stacks::Axis;
use super::footprint3::footprint;
use crate::recon::geometry::Views3;
use crate::recon::grid::VolumeGrid;

/// One detector column's rays in the layout of their dominant axis.
#[derive(Debug, Clone, Copy)]
pub(super) struct Column {
    pub(super) col: usize,
    pub(super) axis: Axis,
    /// Planes the column's rays cross inside the grid (a superset).
    pub(super) planes: (usize, usize),
    /// Rows `[lo, hi)` whose rays are not steep (every other row of the view is).
    pub(super) flat: (usize, usize),
    /// In-plane line coordinate at plane `k`: `c0 + k·dc` (voxel units).
    pub(super) c0: f32,
    pub(super) dc: f32,
    /// Position along z at plane `k`, row `r`: `a_e + (k − a_d)·(p + r·q)` (voxel units).
    pub(super) a_e: f64,
    pub(super) a_d: f64,
    pub(super) p: f64,
    pub(super) q: f64,
    /// Ray direction (unnormalised) without its z part, the z part at row 0 and per row, and the
    /// walk weight's factor `Δ_d/|d_d|`: a ray's weight is `|d|·Δ_d/|d_d|` (mm per plane).
    pub(super) dx: f64,
    pub(super) dy: f64,
    pub(super) dz0: f64,
    pub(super) dzr: f64,
    pub(super) scale: f64,
    /// `|d_z|/Δz` above this value makes a ray steep (its walk steps along z).
    pub(super) steep_above: f64,
}

impl Column {
    fn d_z(&self, row: usize) -> f64 {
        self.dz0 + row as f64 * self.dzr
    }
    fn is_steep(&self, row: usize, dz_mm: f64) -> bool {
        self.d_z(row).abs() / dz_mm > self.steep_above
    }
    /// Walk weight of row `row`, one of [`Column::flat`] (`row as u32 as f64` is `row as f64` for
    /// rows far fewer than 2³², and converts eight lanes at once).
    #[inline(always)]
    fn weight(&self, row: usize) -> f32 {
        let dz = self.dz0 + row as u32 as f64 * self.dzr;
        ((self.dx * self.dx + self.dy * self.dy + dz * dz).sqrt() * self.scale) as f32
    }
    /// `out[i]` = the walk weight of row `flat.0 + i`, for every row of [`Column::flat`] (`out`
    /// holds at least that many); where `form` is AVX-512F, compiled with it, so that eight square
    /// roots go at once (the same values: the operations are the same, each rounded once).
    #[allow(unsafe_code)]
    pub(super) fn weights(&self, form: Form, out: &mut [f32]) {
        let out = &mut out[..self.flat.1 - self.flat.0];
        #[cfg(target_arch = "x86_64")]
        if form == Form::Avx512 {
            // SAFETY: `Form::Avx512` is only built where the CPU has AVX-512F.
            return unsafe { self.weights_avx512(out) };
        }
        let _ = form;
        self.weights_body(out);
    }
    #[inline(always)]
    fn weights_body(&self, out: &mut [f32]) {
        for (i, w) in out.iter_mut().enumerate() {
            *w = self.weight(self.flat.0 + i);
        }
    }
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn weights_avx512(&self, out: &mut [f32]) {
        self.weights_body(out);
    }
    /// The rows of `rows` that are not steep, found with [`Column::is_steep`] on a few rows: `|d_z|`
    /// falls and then rises with the row (`d_z` is monotone in f64 too), so those rows are one run
    /// around the rows where `d_z` changes sign, bounded by two binary searches.
    fn flat_rows(&self, rows: Range<usize>, dz_mm: f64) -> (usize, usize) {
        if rows.is_empty() {
            return (rows.start, rows.start);
        }
        let last = rows.end - 1;
        let centre = if self.dzr != 0.0 && (-self.dz0 / self.dzr).is_finite() {
            (-self.dz0 / self.dzr).clamp(rows.start as f64, last as f64) as usize
        } else {
            rows.start
        };
        let lowest = (centre.saturating_sub(1).max(rows.start)..=(centre + 2).min(last))
            .chain([rows.start, last])
            .min_by(|&a, &b| self.d_z(a).abs().total_cmp(&self.d_z(b).abs()))
            .unwrap_or(rows.start);
        if self.is_steep(lowest, dz_mm) {
            return (rows.start, rows.start);
        }
        // The first row of `lo..hi` for which `steep(row) != leftward`, by halving.
        let edge = |mut lo: usize, mut hi: usize, leftward: bool| {
            while lo < hi {
                let mid = lo + (hi - lo) / 2;
                if self.is_steep(mid, dz_mm) == leftward {
                    lo = mid + 1;
                } else {
                    hi = mid;
                }
            }
            lo
        };
        (
            edge(rows.start, lowest, true),
            edge(lowest + 1, rows.end, false),
        )
    }
    /// The step of plane `k`, its two line indices (padded), and the rows that reach the grid.
    #[inline(always)]
    pub(super) fn step(
        &self,
        k: usize,
        n_c: usize,
        n_e: usize,
        rows: &Range<usize>,
    ) -> (PlaneStep, usize, Range<usize>) {
        let (step, j, guess) = self.guess(k, n_c, n_e, rows);
        (step, j, reaching(&step, guess, rows.clone(), n_e + 3))
    }
    /// [`Column::step`] before its rows are refined: the rows are those whose position lies in
    /// (−1, n_e) in f64, which differ from the f32 ones by at most a row of rounding. Counts and
    /// indices convert through `u32` (every grid and panel here is far smaller), which gives the
    /// same values with cheaper conversions than `usize`.
    #[inline(always)]
    pub(super) fn guess(
        &self,
        k: usize,
        n_c: usize,
        n_e: usize,
        rows: &Range<usize>,
    ) -> (PlaneStep, usize, Range<usize>) {
        let t = (self.c0 + k as u32 as f32 * self.dc + 1.0)
            .max(0.0)
            .min(n_c as u32 as f32 + 1.0);
        let j = t as u32;
        let w1 = t - j as f32;
        let j = j as usize;
        let rel = k as u32 as f64 - self.a_d;
        let e0 = self.a_e + rel * self.p;
        let de = rel * self.q;
        let step = PlaneStep {
            w0: 1.0 - w1,
            w1,
            e0: e0 as f32,
            de: de as f32,
        };
        let guess = if de.abs() < 1e-12 {
            rows.clone()
        } else {
            let inv = 1.0 / de;
            let r1 = (-1.0 - e0) * inv;
            let r2 = (n_e as u32 as f64 - e0) * inv;
            let (start, end) = (rows.start as u32 as f64, rows.end as u32 as f64);
            let lo = (floor(r1.min(r2)) + 1.0).clamp(start, end);
            let hi = ceil(r1.max(r2)).clamp(lo, end);
            lo as u32 as usize..hi as u32 as usize
        };
        (step, j, guess)
    }
}

/// `x.floor()` without the library call that baseline x86-64 makes of it (no SSE4.1 rounding):
/// through an integer where that is exact, else the library's; +0 where the library gives −0.
#[inline(always)]
fn floor(x: f64) -> f64 {
    if x.abs() < 4.0e15 {
        let t = x as i64 as f64;
        if t > x { t - 1.0 } else { t }
    } else {
        x.floor()
    }
}

/// `x.ceil()` as [`floor`] does `x.floor()`.
#[inline(always)]
fn ceil(x: f64) -> f64 {
    if x.abs() < 4.0e15 {
        let t = x as i64 as f64;
        if t < x { t + 1.0 } else { t }
    } else {
        x.ceil()
    }
}

/// One view's columns, or `None` when its panel is tilted (the walks handle it whole).
pub(super) struct ViewPlan {
    pub(super) rows: Range<usize>,
    pub(super) columns: Vec<Column>,
    /// Steep rays `(row, col)`.
    pub(super) steep: Vec<(usize, usize)>,
}

pub(super) fn plan(views: &Views3, view: usize, grid: &VolumeGrid) -> Option<ViewPlan> {
    let v = &views.views[view];
    if v.det_v[0] != 0.0 || v.det_v[1] != 0.0 || v.det_v[2] == 0.0 {
        return None;
    }
    let det = &views.detector;
    let (rows, cols) = footprint(views, v, grid);
    let s = grid.spacing_mm;
    let lo = [grid.x(0), grid.y(0), grid.z(0)];
    let a: [f64; 3] = std::array::from_fn(|k| (v.source[k] - lo[k]) / s[k]);
    let mut columns = Vec::with_capacity(cols.len());
    let mut steep = Vec::new();
    let n = [grid.nx, grid.ny];
    for col in cols {
        let u = det.u(col);
        let p0: [f64; 3] =
            std::array::from_fn(|k| v.det_centre[k] + u * v.det_u[k] + det.v(0) * v.det_v[k]);
        let d = [
            p0[0] - v.source[0],
            p0[1] - v.source[1],
            p0[2] - v.source[2],
        ];
        let dzr = det.dv_mm * v.det_v[2];
        let b = [d[0] / s[0], d[1] / s[1]];
        let (axis, di, ci) = if b[0].abs() >= b[1].abs() {
            (Axis::X, 0, 1)
        } else {
            (Axis::Y, 1, 0)
        };
        let mut column = Column {
            col,
            axis,
            planes: (0, 0),
            flat: (0, 0),
            c0: 0.0,
            dc: 0.0,
            a_e: a[2],
            a_d: a[di],
            p: 0.0,
            q: 0.0,
            dx: d[0],
            dy: d[1],
            dz0: d[2],
            dzr,
            scale: 0.0,
            steep_above: b[0].abs().max(b[1].abs()),
        };
        if b[di] != 0.0 && b[di].is_finite() {
            let sc = b[ci] / b[di];
            let c0 = a[ci] - a[di] * sc;
            let m = s[di] / (s[2] * d[di]);
            column.c0 = c0 as f32;
            column.dc = sc as f32;
            column.p = d[2] * m;
            column.q = dzr * m;
            column.scale = s[di] / d[di].abs();
            column.planes = planes(c0, sc, n[ci], n[di]);
            column.flat = column.flat_rows(rows.clone(), s[2]);
        }
        let flat = column.flat.0..column.flat.1;
        steep.extend(rows.clone().filter(|r| !flat.contains(r)).map(|r| (r, col)));
        columns.push(column);
    }
    Some(ViewPlan {
        rows,
        columns,
        steep,
    })
}

/// Planes `[lo, hi)` of `count` where `c0 + k·s` lies in (−1, n) (a superset, as the walks compute it).
fn planes(c0: f64, s: f64, n: usize, count: usize) -> (usize, usize) {
    if s.abs() < 1e-12 {
        return if c0 > -1.0 && c0 < n as f64 {
            (0, count)
        } else {
            (0, 0)
        };
    }
    let k1 = (-1.0 - c0) / s;
    let k2 = (n as f64 - c0) / s;
    let lo = k1.min(k2).floor().max(0.0);
    let hi = (k1.max(k2).ceil() + 1.0).min(count as f64);
    if lo.is_nan() || hi.is_nan() || hi <= lo {
        (0, 0)
    } else {
        (lo as usize, hi as usize)
    }
}

/// The plans of the views of one subset, in subset order (`None` where a panel is tilted).
pub struct Plans {
    subset: Vec<usize>,
    pub(super) views: Vec<Option<ViewPlan>>,
    /// The back projection's weighted copy of the data, one buffer per view, kept between passes so
    /// that each pass writes it in place instead of allocating (and faulting in) it afresh; shared
    /// by every set of plans of one [`PlanCache`], so that a projector holds one copy at most.
    pub(super) weighted: Weighted,
}

/// Buffers for the back projection's weighted copy of the data (see [`Plans`]).
pub(super) type Weighted = Arc<Mutex<Vec<Vec<f32>>>>;

impl Plans {
    pub fn new(views: &Views3, grid: &VolumeGrid, subset: &[usize]) -> Self {
        Self::sharing(views, grid, subset, Weighted::default())
    }
    fn sharing(views: &Views3, grid: &VolumeGrid, subset: &[usize], weighted: Weighted) -> Self {
        Plans {
            subset: subset.to_vec(),
            views: subset.par_iter().map(|&v| plan(views, v, grid)).collect(),
            weighted,
        }
    }
    pub fn subset(&self) -> &[usize] {
        &self.subset
    }
    /// Bytes the plans hold.
    fn bytes(&self) -> u64 {
        let per_view = |p: &ViewPlan| {
            p.columns.len() * std::mem::size_of::<Column>()
                + p.steep.len() * std::mem::size_of::<(usize, usize)>()
        };
        self.views.iter().flatten().map(per_view).sum::<usize>() as u64
    }
}

/// The plans a [`PlanCache`] keeps at most, as a multiple of the columns of every view: every subset of
/// a fixed partition fits (the columns of 360 views of 256 columns take at most 13 MB). Steep rays
/// (steeper than 45° against the planes, rare) count against the same bound, so plans with many
/// are planned afresh for each pass.
const CACHED_VIEWS_PER_VIEW: usize = 2;

/// Bytes a [`PlanCache`] holds at most for `views`: the columns of every view, twice over.
pub fn cached_bytes(views: &Views3) -> u64 {
    (views.detector.nu as u64)
        .saturating_mul(std::mem::size_of::<Column>() as u64)
        .saturating_mul(views.views.len() as u64)
        .saturating_mul(CACHED_VIEWS_PER_VIEW as u64)
}

/// The plans of the subsets one projector has projected, for one geometry and grid: an iterative
/// method projects the same subsets every iteration. Subsets past the cache's bound are planned
/// afresh each time.
#[derive(Default)]
pub struct PlanCache {
    cached: Mutex<Vec<Arc<Plans>>>,
    weighted: Weighted,
}

impl PlanCache {
    /// The plans of `subset` (of `views` on `grid`, which must be the same for every call).
    pub fn get(&self, views: &Views3, grid: &VolumeGrid, subset: &[usize]) -> Arc<Plans> {
        let mut cached = self
            .cached
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        if let Some(p) = cached.iter().find(|p| p.subset == subset) {
            return Arc::clone(p);
        }
        let weighted = Arc::clone(&self.weighted);
        let plans = Arc::new(Plans::sharing(views, grid, subset, weighted));
        let held: u64 = cached.iter().map(|p| p.bytes()).sum();
        if held.saturating_add(plans.bytes()) <= cached_bytes(views) {
            cached.push(Arc::clone(&plans));
        }
        plans
    }
}

impl std::fmt::Debug for PlanCache {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("PlanCache")
    }
}

#[cfg(test)]
mod tests {
    //! The rows not steep against [`Column::is_steep`] row by row, and the rounding helpers against
    //! the library's.
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::recon::projector::cone_columns::tests::{cone, grid};

    #[test]
    fn flat_rows_are_the_rows_not_steep() {
        // Every column of the steep cone, whose tallest rays are steep at both ends of the panel.
        let grid = grid();
        let views = cone(true);
        let mut seen = [0usize; 2];
        for p in (0..views.views.len()).filter_map(|v| plan(&views, v, &grid)) {
            for c in &p.columns {
                let want: Vec<usize> = p.rows.clone().filter(|&r| !c.is_steep(r, 1.3)).collect();
                let got: Vec<usize> = (c.flat.0..c.flat.1).collect();
                assert_eq!(got, want, "column {}", c.col);
                seen[usize::from(got.len() < p.rows.len())] += 1;
            }
        }
        assert!(seen[0] > 0 && seen[1] > 0, "{seen:?}");
        // Columns of every kind: slopes of either sign or none, sign changes inside, before and after
        // the rows, thresholds that keep no row, every row or a few, and empty row ranges.
        let mut rng = StdRng::seed_from_u64(12);
        let base = cone(false);
        let column = plan(&base, 0, &grid).unwrap().columns[7];
        for _ in 0..4000 {
            let c = Column {
                dz0: rng.random_range(-80.0..80.0),
                dzr: [
                    0.0,
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-0.01..0.01),
                ][rng.random_range(0..3)],
                steep_above: rng.random_range(0.0..40.0),
                ..column
            };
            let start = rng.random_range(0..30);
            let rows = start..start + rng.random_range(0..90);
            let want: Vec<usize> = rows.clone().filter(|&r| !c.is_steep(r, 1.3)).collect();
            let (lo, hi) = c.flat_rows(rows.clone(), 1.3);
            assert_eq!((lo..hi).collect::<Vec<_>>(), want, "{c:?} {rows:?}");
        }
    }

    #[test]
    fn floor_and_ceil_match_the_library() {
        let mut rng = StdRng::seed_from_u64(11);
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            2.5,
            -2.5,
            1e-300,
            -1e-300,
            4.0e15 - 0.5,
            -(4.0e15 - 0.5),
            4.0e15,
            9.3e18,
            -9.3e18,
            1e300,
            -1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MAX,
            f64::MIN,
        ];
        values.extend((0..10_000).map(|_| rng.random_range(-1e6..1e6)));
        values.extend((0..1000).map(|_| rng.random_range(-3.0..3.0)));
        for x in values {
            // The same values, and the same bits except +0 for the library's −0.
            for (got, want) in [(floor(x), x.floor()), (ceil(x), x.ceil())] {
                assert!(
                    got == want && (got.to_bits() == want.to_bits() || got == 0.0),
                    "{x}"
                );
            }
        }
        assert!(floor(f64::NAN).is_nan() && ceil(f64::NAN).is_nan());
    }

    #[test]
    fn the_cache_keeps_each_subset_once_within_its_bound() {
        let (grid, views) = (grid(), cone(false));
        let n = views.views.len();
        let cache = PlanCache::default();
        let all: Vec<usize> = (0..n).collect();
        let first = cache.get(&views, &grid, &all);
        assert!(Arc::ptr_eq(&first, &cache.get(&views, &grid, &all)));
        assert_eq!(first.subset(), all.as_slice());
        let fresh = Plans::new(&views, &grid, &all);
        for (a, b) in first.views.iter().zip(&fresh.views) {
            let (a, b) = (a.as_ref().unwrap(), b.as_ref().unwrap());
            assert_eq!((a.rows.clone(), &a.steep), (b.rows.clone(), &b.steep));
            assert_eq!(a.columns.len(), b.columns.len());
        }
        // A second subset of every view fills the bound (twice the views); a third is planned
        // but not kept.
        let reversed: Vec<usize> = (0..n).rev().collect();
        let kept = cache.get(&views, &grid, &reversed);
        assert!(Arc::ptr_eq(&kept, &cache.get(&views, &grid, &reversed)));
        assert_eq!(kept.subset()[0], n - 1);
        let odd = [1, 3];
        let once = cache.get(&views, &grid, &odd);
        assert!(!Arc::ptr_eq(&once, &cache.get(&views, &grid, &odd)));
        assert_eq!(once.views.len(), 2);
    }
}
