//! The detector u offset of any circular cone-beam scan covering at least π + fan angle (short scans, full
//! turns), from the consistency of conjugate rays in the mid-plane.
//!
//! In the plane of the orbit the ray of view β at fan angle γ (positive toward the panel's u axis) is
//! measured again, reversed, by the view at `β + π − 2γ` at fan angle `−γ`. On a flat panel whose
//! centre-of-rotation foot lies at `ũ = a` (`ũ = (c − (nu−1)/2)·du`, `a = −offset_u_mm`), column `c` has
//! `γ = atan((ũ_c − a)/DSD)` and its conjugate column is `2m − c`, `m` the axis column. For each candidate
//! `a` the mismatch is the mean squared difference between the mid-plane sinogram and its conjugate
//! (sampled bilinearly in angle and column); it is minimised over a coarse grid of whole columns on a
//! sparse set of rays, then over tenths of a column on all rays, and the minimum refined by a parabola.
//! The mid-plane row (v = 0) is interpolated between the two nearest rows.

use ndarray::Array2;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::centre::{CentreEstimate, CentreMethod};
use super::views::ViewSource;
use crate::recon::error::ReconError;
use crate::recon::geometry::Views3;

fn quarter() -> f64 {
    0.25
}
fn d360() -> usize {
    360
}

/// Options of [`find_centre_conjugate`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConjugateOptions {
    /// Half-width of the search around the panel's centre, as a fraction of its width (default 0.25).
    #[serde(default = "quarter")]
    pub search_fraction: f64,
    /// Most views whose rays are compared in the fine search (default 360); every view is read.
    #[serde(default = "d360")]
    pub max_views: usize,
}

impl Default for ConjugateOptions {
    fn default() -> Self {
        Self {
            search_fraction: quarter(),
            max_views: d360(),
        }
    }
}

/// The mid-plane sinogram and where its views lie in angle.
struct Sino {
    data: Array2<f32>,
    /// View angles measured from the first view in the scan's sense of rotation (increasing, radians).
    turn: Vec<f64>,
    sense: f64,
}

impl Sino {
    /// Fractional view index at angle `t` (from the first view, in the scan's sense), if inside the scan.
    fn view_at(&self, t: f64) -> Option<f64> {
        let t = t.rem_euclid(std::f64::consts::TAU);
        let last = *self.turn.last()?;
        if t > last {
            return None;
        }
        let k = self
            .turn
            .partition_point(|&x| x <= t)
            .clamp(1, self.turn.len() - 1);
        let (a, b) = (self.turn[k - 1], self.turn[k]);
        Some(k as f64 - 1.0 + (t - a) / (b - a))
    }
}

/// Mean squared conjugate mismatch of axis column `m` over views `0, vs, 2vs, …` and columns
/// `0, cs, 2cs, …`.
fn mismatch(s: &Sino, views: &Views3, dsd: f64, m: f64, vs: usize, cs: usize) -> f64 {
    let (n, nu) = s.data.dim();
    let du = views.detector.du_mm;
    let (sum, count) = (0..n)
        .into_par_iter()
        .step_by(vs)
        .map(|k| {
            let beta = views.views[k].angle_rad;
            let (mut sum, mut count) = (0.0f64, 0usize);
            for c in (0..nu).step_by(cs) {
                let cc = 2.0 * m - c as f64;
                if cc < 0.0 || cc > (nu - 1) as f64 {
                    continue;
                }
                let gamma = ((c as f64 - m) * du / dsd).atan();
                let other = beta + std::f64::consts::PI - 2.0 * gamma;
                let Some(kv) = s.view_at((other - views.views[0].angle_rad) * s.sense) else {
                    continue;
                };
                let (k0, c0) = (
                    (kv.floor() as usize).min(n - 2),
                    (cc.floor() as usize).min(nu - 2),
                );
                let (fk, fc) = (kv - k0 as f64, cc - c0 as f64);
                let at = |i: usize, j: usize| s.data[[i, j]] as f64;
                let top = at(k0, c0) + fc * (at(k0, c0 + 1) - at(k0, c0));
                let bot = at(k0 + 1, c0) + fc * (at(k0 + 1, c0 + 1) - at(k0 + 1, c0));
                let d = at(k, c) - (top + fk * (bot - top));
                sum += d * d;
                count += 1;
            }
            (sum, count)
        })
        .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    if count < nu / 4 {
        f64::INFINITY
    } else {
        sum / count as f64
    }
}

/// Best of `cands` axis columns, refined by a parabola through its neighbours (equal spacing `step`).
fn best(cands: &[f64], costs: &[f64], step: f64) -> Option<(f64, f64)> {
    let i = (0..costs.len())
        .filter(|&i| costs[i].is_finite())
        .min_by(|&i, &j| costs[i].total_cmp(&costs[j]))?;
    let mut m = cands[i];
    if i > 0 && i + 1 < costs.len() && costs[i - 1].is_finite() && costs[i + 1].is_finite() {
        let (l, c, r) = (costs[i - 1], costs[i], costs[i + 1]);
        let den = l - 2.0 * c + r;
        if den > 0.0 {
            m += step * (0.5 * (l - r) / den).clamp(-0.5, 0.5);
        }
    }
    Some((m, costs[i]))
}

/// Find the u offset of a circular cone-beam scan from conjugate rays in the mid-plane; see the module
/// docs. `dsd_mm` is the source-to-detector distance; the views' angles must be monotonic.
pub fn find_centre_conjugate(
    views: &Views3,
    dsd_mm: f64,
    source: &dyn ViewSource,
    opts: &ConjugateOptions,
) -> Result<CentreEstimate, ReconError> {
    let det = views.detector;
    let (n, nu, nv) = (views.views.len(), det.nu, det.nv);
    if source.view_count() != n {
        return Err(ReconError::ShapeMismatch {
            expected: vec![n],
            got: vec![source.view_count()],
        });
    }
    if n < 3 || nu < 8 || nv < 2 {
        return Err(ReconError::param(
            "projections",
            "at least 3 views of 8 columns and 2 rows are needed",
        ));
    }
    if !(dsd_mm.is_finite() && dsd_mm > 0.0) {
        return Err(ReconError::param("dsd_mm", "must be positive"));
    }
    if !(opts.search_fraction > 0.0 && opts.search_fraction <= 0.5) {
        return Err(ReconError::param("search_fraction", "must be in (0, 0.5]"));
    }
    let first = views.views[0].angle_rad;
    let sense = if views.views[n - 1].angle_rad >= first {
        1.0
    } else {
        -1.0
    };
    let turn: Vec<f64> = views
        .views
        .iter()
        .map(|v| (v.angle_rad - first) * sense)
        .collect();
    if turn.windows(2).any(|w| w[1] <= w[0]) || turn[n - 1] >= std::f64::consts::TAU {
        return Err(ReconError::param(
            "angles",
            "must be strictly monotonic within one turn",
        ));
    }
    // The mid-plane row, v = 0, between rows r and r + 1.
    let r = det.row_of(0.0).clamp(0.0, (nv - 1) as f64);
    let r0 = (r.floor() as usize).min(nv.saturating_sub(2));
    let f = (r - r0 as f64) as f32;
    let mut data = Array2::<f32>::zeros((n, nu));
    data.outer_iter_mut()
        .into_par_iter()
        .enumerate()
        .try_for_each_init(
            || Array2::<f32>::zeros((2, nu)),
            |buf, (k, mut row)| {
                source.read_rows(k, r0, nv, buf.view_mut())?;
                for c in 0..nu {
                    row[c] = buf[[0, c]] * (1.0 - f) + buf[[1, c]] * f;
                }
                if row.iter().any(|x| !x.is_finite()) {
                    return Err(ReconError::param(
                        "projections",
                        format!("view {k} has a non-finite value"),
                    ));
                }
                Ok(())
            },
        )?;
    let s = Sino { data, turn, sense };
    let mid = (nu as f64 - 1.0) / 2.0;
    let half = (opts.search_fraction * nu as f64).max(2.0);
    let vs_coarse = n.div_ceil(90).max(1);
    let cs_coarse = nu.div_ceil(256).max(1);
    let coarse: Vec<f64> = (-(half as isize)..=half as isize)
        .map(|k| mid + k as f64)
        .collect();
    let costs: Vec<f64> = coarse
        .iter()
        .map(|&m| mismatch(&s, views, dsd_mm, m, vs_coarse, cs_coarse))
        .collect();
    let (m0, _) = best(&coarse, &costs, 1.0)
        .ok_or_else(|| ReconError::param("angles", "the scan has too few conjugate rays"))?;
    let vs = n.div_ceil(opts.max_views.max(1));
    let fine: Vec<f64> = (-20..=20).map(|k| m0.round() + k as f64 * 0.1).collect();
    let costs: Vec<f64> = fine
        .iter()
        .map(|&m| mismatch(&s, views, dsd_mm, m, vs, 1))
        .collect();
    let (m, cost) = best(&fine, &costs, 0.1)
        .ok_or_else(|| ReconError::param("angles", "the scan has too few conjugate rays"))?;
    let power = s.data.iter().map(|&x| (x as f64) * (x as f64)).sum::<f64>() / (n * nu) as f64;
    let a = (m - mid) * det.du_mm;
    Ok(CentreEstimate {
        offset_u_px: -(m - mid),
        offset_u_mm: -a,
        tilt_deg: None,
        residual: (cost / power.max(1e-30)).sqrt(),
        method: CentreMethod::ConjugateRays,
        views_used: n.div_ceil(vs),
    })
}
