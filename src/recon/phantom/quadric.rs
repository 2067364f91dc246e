//! The kernel shared by ellipses and ellipsoids: a filled body `{p : |M p − q0| ≤ 1}` (p in mm) with an
//! additive value, its exact chord along a line, and the interval of a line that lies inside it.
//!
//! For the line `s + λ d`, `q = M s − q0` and `r = M d`; the body holds the λ for which `|q + λ r|² ≤ 1`.
//! With `q⊥ = q − (q·r/|r|²) r` (the point of the mapped line nearest the origin) the inside interval is
//! `λ ∈ −q·r/|r|² ± √(1 − |q⊥|²)/|r|`, so the chord is `2√(1 − |q⊥|²)/|r|` in units of `|d|`. This is
//! DESIGN §3's `2√Δ/|r|²` with `Δ = (q·r)² − |r|²(|q|² − 1) = |r|²(1 − |q⊥|²)`, written so that no
//! large terms cancel when the source is far from the body.

/// Dot product of two N-vectors.
#[inline(always)]
pub(crate) fn dot<const N: usize>(a: &[f64; N], b: &[f64; N]) -> f64 {
    let mut s = 0.0;
    for k in 0..N {
        s += a[k] * b[k];
    }
    s
}

/// Matrix–vector product `m v`.
#[inline(always)]
pub(crate) fn mul<const N: usize>(m: &[[f64; N]; N], v: &[f64; N]) -> [f64; N] {
    let mut out = [0.0; N];
    for (o, row) in out.iter_mut().zip(m) {
        *o = dot(row, v);
    }
    out
}

/// A filled ellipse (N = 2) or ellipsoid (N = 3) in millimetres, ready for chords.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Quadric<const N: usize> {
    /// Maps a point (mm) into the body's unit-ball frame (together with `q0`).
    pub m: [[f64; N]; N],
    /// `M p − q0` is the point in the unit-ball frame.
    pub q0: [f64; N],
    /// `M⁻¹`: maps the unit-ball frame back to millimetres (used for bounding boxes).
    pub m_inv: [[f64; N]; N],
    /// Additive value (μ, 1/mm).
    pub value: f64,
}

/// Half-chord in the unit-ball frame for the mapped line `q + λ r`: `Some((λ_mid, half))` with the inside
/// interval `λ_mid ± half` (`half = 0` when the line touches the body), or `None` when it misses.
#[inline(always)]
pub(crate) fn mapped_interval<const N: usize>(q: &[f64; N], r: &[f64; N]) -> Option<(f64, f64)> {
    let rr = dot(r, r);
    if rr <= 0.0 || !rr.is_finite() {
        return None;
    }
    let mid = -dot(q, r) / rr;
    let mut perp2 = 0.0;
    for k in 0..N {
        let p = q[k] + mid * r[k];
        perp2 += p * p;
    }
    let h = 1.0 - perp2;
    if h >= 0.0 {
        Some((mid, (h / rr).sqrt()))
    } else {
        None
    }
}

impl<const N: usize> Quadric<N> {
    /// `M p − q0`: the point `p` (mm) in the unit-ball frame.
    #[inline(always)]
    pub fn unit_frame(&self, p: &[f64; N]) -> [f64; N] {
        let mut q = mul(&self.m, p);
        for (qk, ck) in q.iter_mut().zip(&self.q0) {
            *qk -= ck;
        }
        q
    }

    /// The λ interval `(λ1, λ2)` of the line `s + λ d` inside the body, if any.
    #[inline(always)]
    pub fn interval(&self, s: &[f64; N], d: &[f64; N]) -> Option<(f64, f64)> {
        let q = self.unit_frame(s);
        let r = mul(&self.m, d);
        mapped_interval(&q, &r).map(|(mid, half)| (mid - half, mid + half))
    }

    /// Exact line integral of the body along the line `s + λ d` (whole line), for a unit `d` in mm:
    /// value × chord length.
    #[inline(always)]
    pub fn line_integral(&self, s: &[f64; N], d: &[f64; N]) -> f64 {
        match self.interval(s, d) {
            Some((a, b)) => self.value * (b - a) * dot(d, d).sqrt(),
            None => 0.0,
        }
    }

    /// The 2^N corners (mm) of a box that contains the body: the image of the cube `[−1, 1]^N` of the
    /// unit-ball frame.
    pub fn box_corners(&self) -> Vec<[f64; N]> {
        (0..(1usize << N))
            .map(|bits| {
                let mut u = self.q0;
                for (k, uk) in u.iter_mut().enumerate() {
                    *uk += if bits >> k & 1 == 1 { 1.0 } else { -1.0 };
                }
                mul(&self.m_inv, &u)
            })
            .collect()
    }
}

/// Add `value` of every body to the samples of a row at `start + m·h·e0` (m = 0…len−1, e0 the unit x
/// axis) that lie inside it, where `start` is the position of sample 0 (mm).
pub(crate) fn fill_row<const N: usize>(
    bodies: &[Quadric<N>],
    start: &[f64; N],
    h: f64,
    row: &mut [f64],
) {
    let mut e0 = [0.0; N];
    e0[0] = 1.0;
    let last = row.len() as f64 - 1.0;
    for body in bodies {
        let Some((t1, t2)) = body.interval(start, &e0) else {
            continue;
        };
        let lo = (t1 / h).ceil().max(0.0);
        let hi = (t2 / h).floor().min(last);
        // Also skips NaN bounds, so the slice below is always in range.
        if lo.is_nan() || hi.is_nan() || lo > hi {
            continue;
        }
        // Both bounds are finite and within [0, len − 1] here.
        for v in &mut row[lo as usize..=hi as usize] {
            *v += body.value;
        }
    }
}
