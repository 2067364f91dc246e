//! Ramp filtering of detector rows: the Kak–Slaney spatial kernels (flat and equiangular), apodisation
//! windows with a frequency cut-off, zero padding, FFT convolution in f64 (realfft).
//!
//! The kernel is sampled on the detector grid and its FFT is used as the transfer function (not a sampled
//! |ω|, which biases the DC term). Rows are zero-padded to `padded_len` ≥ 2N − 1 samples, so the linear
//! convolution never wraps around; the default is the power of two ≥ max(64, 2N).

use std::f64::consts::PI;
use std::sync::Arc;

use realfft::num_complex::Complex;
use realfft::{ComplexToReal, RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner};

use crate::recon::algorithm::{FbpParams, Window};
use crate::recon::error::ReconError;

/// Longest padded row accepted.
pub const MAX_PADDED_LEN: usize = 1 << 20;

/// The spatial ramp kernel, sampled with the detector spacing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Kernel {
    /// Flat (equispaced) samples `τ` apart: h(0) = 1/(4τ²), h(n) = 0 for even n, −1/(n²π²τ²) for odd n.
    Ramp { spacing: f64 },
    /// Equiangular samples `α` radians apart (fan beam on an arc):
    /// g(0) = 1/(8α²), g(n) = 0 for even n, −1/(2π² sin²(nα)) for odd n.
    Equiangular { spacing: f64 },
}

impl Kernel {
    fn spacing(&self) -> f64 {
        match *self {
            Kernel::Ramp { spacing } | Kernel::Equiangular { spacing } => spacing,
        }
    }
    /// Kernel value at lag `n` (samples).
    pub fn at(&self, n: i64) -> f64 {
        match *self {
            Kernel::Ramp { spacing: t } => {
                if n == 0 {
                    1.0 / (4.0 * t * t)
                } else if n % 2 == 0 {
                    0.0
                } else {
                    -1.0 / ((n * n) as f64 * PI * PI * t * t)
                }
            }
            Kernel::Equiangular { spacing: a } => {
                if n == 0 {
                    1.0 / (8.0 * a * a)
                } else if n % 2 == 0 {
                    0.0
                } else {
                    let s = (n as f64 * a).sin();
                    -1.0 / (2.0 * PI * PI * s * s)
                }
            }
        }
    }
}

/// The apodisation window at normalised frequency `w` ∈ [0, π] with cut-off `d` ∈ (0, 1]: zero above πd.
pub fn window(kind: Window, w: f64, d: f64) -> f64 {
    if w > PI * d {
        return 0.0;
    }
    let x = w / d;
    match kind {
        Window::RamLak => 1.0,
        Window::SheppLogan => {
            if x == 0.0 {
                1.0
            } else {
                (x / 2.0).sin() / (x / 2.0)
            }
        }
        Window::Cosine => (x / 2.0).cos(),
        Window::Hamming => 0.54 + 0.46 * x.cos(),
        Window::Hann => (1.0 + x.cos()) / 2.0,
    }
}

/// Padded length for rows of `n` samples: the requested one (checked) or the power of two ≥ max(64, 2n).
pub fn padded_len(n: usize, requested: Option<usize>) -> Result<usize, ReconError> {
    let min = (2 * n).saturating_sub(1).max(1);
    match requested {
        Some(p) if p < min => Err(ReconError::param(
            "padded_len",
            format!("must be at least 2N − 1 = {min} for rows of {n} samples, got {p}"),
        )),
        Some(p) if p > MAX_PADDED_LEN => Err(ReconError::param(
            "padded_len",
            format!("at most {MAX_PADDED_LEN}, got {p}"),
        )),
        Some(p) => Ok(p),
        None => {
            let p = (2 * n).max(64).next_power_of_two();
            if p > MAX_PADDED_LEN {
                Err(ReconError::param(
                    "data",
                    format!("detector rows of {n} samples are too long to filter"),
                ))
            } else {
                Ok(p)
            }
        }
    }
}

/// A row filter: convolution with a windowed ramp kernel, times the sample spacing and a constant,
/// optionally returned at `up` samples per input sample (band-limited interpolation by zero-padding the
/// spectrum, so a later linear interpolation loses less resolution).
pub struct RowFilter {
    n: usize,
    padded: usize,
    up: usize,
    /// Real transfer function for bins 0..=padded/2, including spacing, scale and 1/padded.
    response: Vec<f64>,
    r2c: Arc<dyn RealToComplex<f64>>,
    c2r: Arc<dyn ComplexToReal<f64>>,
    /// Two rows filtered together ([`RowFilter::run_pair`]); only without upsampling.
    pair: Option<PairPlans>,
}

/// A complex FFT of the padded length and its inverse, and the real transfer function over all
/// `padded` bins (bin `k` and bin `padded − k` share a value: the kernel is even).
struct PairPlans {
    forward: Arc<dyn Fft<f64>>,
    inverse: Arc<dyn Fft<f64>>,
    response: Vec<f64>,
}

/// Work buffers of one thread using a [`RowFilter`].
pub struct FilterScratch {
    time: Vec<f64>,
    freq: Vec<Complex<f64>>,
    fine_freq: Vec<Complex<f64>>,
    fine: Vec<f64>,
    work: Vec<Complex<f64>>,
    /// The second row of a pair: its input and its filtered output.
    second: Vec<f64>,
    second_out: Vec<f64>,
    /// The two rows of a pair as one complex row, and the complex FFTs' work buffer.
    both: Vec<Complex<f64>>,
    both_work: Vec<Complex<f64>>,
}

impl FilterScratch {
    /// The input row (length N) to fill before [`RowFilter::run`]; padding is zeroed by `run`.
    pub fn input(&mut self, n: usize) -> &mut [f64] {
        &mut self.time[..n]
    }
    /// The filtered row after [`RowFilter::run`]: `up·N` samples, sample `m` at input position `m/up`.
    pub fn output(&self, len: usize) -> &[f64] {
        &self.fine[..len]
    }
    /// The two input rows (length N each) to fill before [`RowFilter::run_pair`].
    pub fn inputs(&mut self, n: usize) -> (&mut [f64], &mut [f64]) {
        (&mut self.time[..n], &mut self.second[..n])
    }
    /// The two filtered rows after [`RowFilter::run_pair`]: `up·N` samples each.
    pub fn outputs(&self, len: usize) -> (&[f64], &[f64]) {
        (&self.fine[..len], &self.second_out[..len])
    }
}

impl RowFilter {
    /// A filter for rows of `n` samples: `out = scale · spacing · (row ⊛ kernel)`, windowed.
    pub fn new(
        n: usize,
        kernel: Kernel,
        scale: f64,
        params: &FbpParams,
    ) -> Result<Self, ReconError> {
        Self::upsampled(n, kernel, scale, params, 1)
    }

    /// As [`RowFilter::new`], returning `up` output samples per input sample.
    pub fn upsampled(
        n: usize,
        kernel: Kernel,
        scale: f64,
        params: &FbpParams,
        up: usize,
    ) -> Result<Self, ReconError> {
        params.validate()?;
        let padded = padded_len(n, params.padded_len)?;
        let up = up.max(1);
        let mut planner = RealFftPlanner::<f64>::new();
        let r2c = planner.plan_fft_forward(padded);
        let c2r = planner.plan_fft_inverse(padded * up);
        let mut k = r2c.make_input_vec();
        for (j, v) in k.iter_mut().enumerate() {
            let lag = if j <= padded / 2 {
                j as i64
            } else {
                j as i64 - padded as i64
            };
            *v = kernel.at(lag);
        }
        let mut spec = r2c.make_output_vec();
        r2c.process(&mut k, &mut spec)
            .map_err(|e| ReconError::param("padded_len", e.to_string()))?;
        let factor = scale * kernel.spacing() / padded as f64;
        let mut response: Vec<f64> = spec
            .iter()
            .enumerate()
            .map(|(j, c)| {
                let w = 2.0 * PI * j as f64 / padded as f64;
                c.re * window(params.filter, w, params.cutoff) * factor
            })
            .collect();
        // Upsampled, the Nyquist bin of an even length stands for ± the Nyquist frequency: halve it.
        if up > 1
            && padded % 2 == 0
            && let Some(last) = response.last_mut()
        {
            *last *= 0.5;
        }
        let pair = (up == 1).then(|| {
            let mut planner = FftPlanner::<f64>::new();
            let half = response.len() - 1;
            PairPlans {
                forward: planner.plan_fft_forward(padded),
                inverse: planner.plan_fft_inverse(padded),
                response: (0..padded)
                    .map(|k| response[if k <= half { k } else { padded - k }])
                    .collect(),
            }
        });
        Ok(Self {
            n,
            padded,
            up,
            response,
            r2c,
            c2r,
            pair,
        })
    }

    /// Samples per input row.
    pub fn len(&self) -> usize {
        self.n
    }

    /// True for rows of zero samples (never: rows have at least one sample).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Output samples per input sample.
    pub fn up(&self) -> usize {
        self.up
    }

    /// Padded length used for the FFT.
    pub fn padded_len(&self) -> usize {
        self.padded
    }

    /// Buffers for one thread.
    pub fn scratch(&self) -> FilterScratch {
        let scratch_len = self.r2c.get_scratch_len().max(self.c2r.get_scratch_len());
        let zero = Complex::new(0.0, 0.0);
        let (both, both_work) = match &self.pair {
            Some(p) => {
                let work = p
                    .forward
                    .get_inplace_scratch_len()
                    .max(p.inverse.get_inplace_scratch_len());
                (vec![zero; self.padded], vec![zero; work])
            }
            None => (Vec::new(), Vec::new()),
        };
        FilterScratch {
            time: self.r2c.make_input_vec(),
            freq: self.r2c.make_output_vec(),
            fine_freq: self.c2r.make_input_vec(),
            fine: self.c2r.make_output_vec(),
            work: vec![zero; scratch_len],
            second: vec![0.0; self.n],
            second_out: vec![0.0; self.n * self.up],
            both,
            both_work,
        }
    }

    /// Filter the two rows in `scratch.inputs(n)`; the results are in `scratch.outputs(up·n)`.
    /// Without upsampling the rows go through one complex FFT of the padded length, the first as its
    /// real part and the second as its imaginary part: the transfer function is real and even, so
    /// the filtered rows come back as the real and the imaginary part, and a pair costs about three
    /// quarters of two real FFTs each way. With upsampling, each row through [`RowFilter::run`].
    pub fn run_pair(&self, s: &mut FilterScratch) {
        let n = self.n;
        let Some(p) = &self.pair else {
            // The FFTs overwrite their input: the second row goes first, the first waits in `second`.
            s.time[..n].swap_with_slice(&mut s.second);
            self.run(s);
            let len = s.second_out.len();
            s.second_out.copy_from_slice(&s.fine[..len]);
            s.time[..n].copy_from_slice(&s.second);
            self.run(s);
            return;
        };
        for (o, (a, b)) in s.both.iter_mut().zip(s.time[..n].iter().zip(&s.second)) {
            *o = Complex::new(*a, *b);
        }
        s.both[n..].fill(Complex::new(0.0, 0.0));
        p.forward
            .process_with_scratch(&mut s.both, &mut s.both_work);
        for (c, h) in s.both.iter_mut().zip(&p.response) {
            *c *= *h;
        }
        p.inverse
            .process_with_scratch(&mut s.both, &mut s.both_work);
        let outputs = s.fine[..n].iter_mut().zip(s.second_out.iter_mut());
        for ((a, b), c) in outputs.zip(&s.both) {
            (*a, *b) = (c.re, c.im);
        }
    }

    /// Filter the row in `scratch.input(n)`; the result is in `scratch.output(up·n)`.
    pub fn run(&self, s: &mut FilterScratch) {
        s.time[self.n..].fill(0.0);
        // Lengths match the plans by construction, so the FFTs cannot fail.
        let _ = self
            .r2c
            .process_with_scratch(&mut s.time, &mut s.freq, &mut s.work);
        s.fine_freq.fill(Complex::new(0.0, 0.0));
        for ((o, f), h) in s.fine_freq.iter_mut().zip(&s.freq).zip(&self.response) {
            *o = *f * *h;
        }
        // The imaginary parts of the DC and Nyquist bins are zero for a real input times a real response.
        s.fine_freq[0].im = 0.0;
        if self.padded.is_multiple_of(2) {
            s.fine_freq[self.padded / 2].im = 0.0;
        }
        let _ = self
            .c2r
            .process_with_scratch(&mut s.fine_freq, &mut s.fine, &mut s.work);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn direct(row: &[f64], kernel: Kernel) -> Vec<f64> {
        let n = row.len() as i64;
        (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| row[j as usize] * kernel.at(i - j))
                    .sum::<f64>()
                    * kernel.spacing()
            })
            .collect()
    }

    #[test]
    fn ram_lak_filtering_equals_the_direct_convolution_with_the_kak_slaney_kernel() {
        for kernel in [
            Kernel::Ramp { spacing: 0.7 },
            Kernel::Equiangular { spacing: 0.01 },
        ] {
            let row: Vec<f64> = (0..37).map(|i| ((i * 7 % 11) as f64).sin()).collect();
            let f = RowFilter::new(row.len(), kernel, 1.0, &FbpParams::default()).unwrap();
            let mut s = f.scratch();
            s.input(row.len()).copy_from_slice(&row);
            f.run(&mut s);
            let want = direct(&row, kernel);
            let scale = want.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            for (a, b) in s.output(row.len()).iter().zip(&want) {
                assert!((a - b).abs() < 1e-12 * scale, "{a} vs {b}");
            }
        }
    }

    /// Two rows filtered as a pair equal each row filtered alone, to f64 rounding of the rows'
    /// largest value, with and without upsampling; the direct convolution agrees as well.
    #[test]
    fn rows_filtered_in_pairs_equal_rows_filtered_alone() {
        let kernel = Kernel::Ramp { spacing: 0.7 };
        let n = 53;
        let a: Vec<f64> = (0..n).map(|i| ((i * 7 % 11) as f64).sin() * 3.0).collect();
        let b: Vec<f64> = (0..n).map(|i| ((i * 5 % 13) as f64).cos() + 0.5).collect();
        for up in [1, 3] {
            let f = RowFilter::upsampled(n, kernel, 1.0, &FbpParams::default(), up).unwrap();
            let mut s = f.scratch();
            let alone = |row: &[f64], s: &mut FilterScratch| {
                s.input(n).copy_from_slice(row);
                f.run(s);
                s.output(up * n).to_vec()
            };
            let (want_a, want_b) = (alone(&a, &mut s), alone(&b, &mut s));
            let (ia, ib) = s.inputs(n);
            ia.copy_from_slice(&a);
            ib.copy_from_slice(&b);
            f.run_pair(&mut s);
            let (got_a, got_b) = s.outputs(up * n);
            let scale = want_a
                .iter()
                .chain(&want_b)
                .fold(0.0f64, |m, v| m.max(v.abs()));
            for (got, want) in [(got_a, &want_a), (got_b, &want_b)] {
                for (x, y) in got.iter().zip(want) {
                    assert!((x - y).abs() < 1e-13 * scale, "up {up}: {x} vs {y}");
                }
            }
            if up == 1 {
                let direct_b = direct(&b, kernel);
                for (x, y) in got_b.iter().zip(&direct_b) {
                    assert!((x - y).abs() < 1e-12 * scale, "{x} vs {y}");
                }
            }
        }
    }

    #[test]
    fn upsampled_output_keeps_the_original_samples_and_interpolates_between_them() {
        let kernel = Kernel::Ramp { spacing: 1.0 };
        let row: Vec<f64> = (0..40)
            .map(|i| (-((i as f64 - 20.0) / 4.0).powi(2)).exp())
            .collect();
        let plain = RowFilter::new(40, kernel, 1.0, &FbpParams::default()).unwrap();
        let fine = RowFilter::upsampled(40, kernel, 1.0, &FbpParams::default(), 2).unwrap();
        let (mut a, mut b) = (plain.scratch(), fine.scratch());
        a.input(40).copy_from_slice(&row);
        b.input(40).copy_from_slice(&row);
        plain.run(&mut a);
        fine.run(&mut b);
        let (coarse, up) = (a.output(40), b.output(80));
        for i in 0..40 {
            assert!((up[2 * i] - coarse[i]).abs() < 1e-12, "{i}");
        }
        // A smooth row: the half-way samples lie near the mean of their neighbours.
        for i in 10..30 {
            let mid = (coarse[i] + coarse[i + 1]) / 2.0;
            assert!((up[2 * i + 1] - mid).abs() < 0.02, "{i}");
        }
    }

    #[test]
    fn windows_are_one_at_dc_and_zero_above_the_cutoff() {
        for kind in [
            Window::RamLak,
            Window::SheppLogan,
            Window::Cosine,
            Window::Hamming,
            Window::Hann,
        ] {
            assert!((window(kind, 0.0, 0.8) - 1.0).abs() < 1e-15);
            assert_eq!(window(kind, 0.81 * PI, 0.8), 0.0);
        }
        assert!((window(Window::Hann, PI, 1.0)).abs() < 1e-15);
        assert!((window(Window::Hamming, PI, 1.0) - 0.08).abs() < 1e-12);
        assert!((window(Window::Cosine, PI, 1.0)).abs() < 1e-15);
        assert!((window(Window::SheppLogan, PI, 1.0) - 2.0 / PI).abs() < 1e-15);
    }

    #[test]
    fn padding_below_two_n_is_refused_and_the_default_is_a_power_of_two() {
        assert_eq!(padded_len(363, None).unwrap(), 1024);
        assert_eq!(padded_len(10, None).unwrap(), 64);
        assert!(padded_len(100, Some(198)).is_err());
        assert_eq!(padded_len(100, Some(199)).unwrap(), 199);
    }
}
