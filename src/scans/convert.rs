//! The minimal conversion of a scan's views into ctrecon's projections: line integrals
//! `p = −ln((I − D)/(F − D))` with the scan's dark `D` and flat `F` when it has both (the view's own
//! flat where the view source has one, [`super::ViewSource::view_flat`]), else
//! `p = −ln(I / white level)` (DESIGN.md §11), the transmission clamped to [`TRANSMISSION_FLOOR`] (clamped
//! pixels counted), moved by the scanner's alignment of the view where it has one
//! ([`super::ViewSource::shift`]), oriented into ctrecon's detector order: [`ViewConverter`] one view at a
//! time (what an import streams), [`line_integrals`] the whole stack (the CLI). To be replaced by the full
//! preprocessing chain.

use ndarray::Array3;

use super::{Intensity, Scan, ScanError};

/// Smallest transmission kept: darker (or non-finite) pixels are clamped to it (p ≤ 13.8).
pub const TRANSMISSION_FLOOR: f32 = 1e-6;

/// Projections `[view][v][u]` as line integrals, how many pixels were clamped and how many views were moved
/// by the scanner's alignment.
#[derive(Debug)]
pub struct LineIntegrals {
    pub projections: Array3<f32>,
    pub clamped: u64,
    pub shifted_views: u64,
}

/// Read every view of `scan` and convert it to line integrals in ctrecon's detector order. Refuses
/// (before allocating) a stack of more than `max_bytes` of `f32`.
pub fn line_integrals(scan: &mut Scan, max_bytes: u64) -> Result<LineIntegrals, ScanError> {
    let (nv, nu) = scan.views.shape();
    let n = scan.views.view_count();
    let bytes = (n as u64)
        .saturating_mul(nv as u64)
        .saturating_mul(nu as u64)
        .saturating_mul(4);
    if bytes > max_bytes {
        return Err(ScanError::Limit {
            file: scan.source.clone(),
            what: format!(
                "{n} views of {nu} × {nv} need {bytes} bytes as floats (at most {max_bytes})"
            ),
        });
    }
    let mut conv = ViewConverter::new(scan);
    let mut out = Array3::<f32>::zeros((n, nv, nu));
    for (i, mut view) in out.outer_iter_mut().enumerate() {
        let Some(dst) = view.as_slice_mut() else {
            unreachable!("a fresh array is contiguous")
        };
        conv.convert(scan, i, dst)?;
    }
    Ok(LineIntegrals {
        projections: out,
        clamped: conv.clamped,
        shifted_views: conv.shifted_views,
    })
}

/// How a view's values become transmissions.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Normalisation {
    /// `(I − D)/(F − D)` with the scan's dark and flat.
    DarkFlat,
    /// `I / F` with the scan's flat (no dark).
    Flat,
    /// `I / white_level` (1 for transmissions).
    WhiteLevel(f64),
}

/// Converts a scan's views to line integrals one at a time, holding one view of its own (the image as read,
/// converted in place) besides the caller's output view; counts the clamped pixels.
#[derive(Debug)]
pub struct ViewConverter {
    nv: usize,
    nu: usize,
    normalisation: Normalisation,
    image: Vec<f32>,
    /// The flat of the view being converted, where the view source has one per view.
    view_flat: Vec<f32>,
    /// Pixels clamped to [`TRANSMISSION_FLOOR`] so far.
    pub clamped: u64,
    /// Views moved by a non-zero [`super::ViewSource::shift`] so far.
    pub shifted_views: u64,
}

impl ViewConverter {
    /// The converter of `scan`'s views (allocates one view: the readers refuse views over
    /// [`super::MAX_VIEW_PIXELS`]).
    pub fn new(scan: &Scan) -> Self {
        let (nv, nu) = scan.views.shape();
        let fits = |r: &Option<Vec<f32>>| r.as_ref().is_some_and(|r| r.len() == nv * nu);
        let normalisation = match (fits(&scan.dark), fits(&scan.flat)) {
            (true, true) => Normalisation::DarkFlat,
            (false, true) if scan.dark.is_none() => Normalisation::Flat,
            _ => Normalisation::WhiteLevel(match scan.intensity {
                Intensity::FlatCorrected { white_level } | Intensity::Raw { white_level } => {
                    white_level
                }
                Intensity::Transmission => 1.0,
            }),
        };
        Self {
            nv,
            nu,
            normalisation,
            image: vec![0f32; nv * nu],
            view_flat: Vec::new(),
            clamped: 0,
            shifted_views: 0,
        }
    }

    /// How the values are normalised.
    pub fn normalisation(&self) -> Normalisation {
        self.normalisation
    }

    /// Read view `i` of `scan` and write its line integrals, in ctrecon's detector order, to `out`
    /// (`nv · nu` values).
    pub fn convert(&mut self, scan: &mut Scan, i: usize, out: &mut [f32]) -> Result<(), ScanError> {
        scan.views.read_view(i, &mut self.image)?;
        let empty: &[f32] = &[];
        let per_view = matches!(
            self.normalisation,
            Normalisation::DarkFlat | Normalisation::Flat
        ) && {
            self.view_flat.resize(self.nv * self.nu, 0.0);
            scan.views.view_flat(i, &mut self.view_flat)
        };
        let (dark, flat) = (
            scan.dark.as_deref().unwrap_or(empty),
            if per_view {
                &self.view_flat[..]
            } else {
                scan.flat.as_deref().unwrap_or(empty)
            },
        );
        let white = match self.normalisation {
            Normalisation::WhiteLevel(w) => w as f32,
            _ => 1.0,
        };
        let mut clamped = 0u64;
        for (k, p) in self.image.iter_mut().enumerate() {
            let t = match self.normalisation {
                Normalisation::DarkFlat => (*p - dark[k]) / (flat[k] - dark[k]),
                Normalisation::Flat => *p / flat[k],
                Normalisation::WhiteLevel(_) => *p / white,
            };
            *p = if t.is_finite() && t >= TRANSMISSION_FLOOR {
                t
            } else {
                clamped += 1;
                TRANSMISSION_FLOOR
            };
        }
        self.clamped += clamped;
        if let Some([rows, cols]) = scan.views.shift(i)
            && (rows != 0.0 || cols != 0.0)
        {
            shift_image(&mut self.image, self.nv, self.nu, rows, cols);
            self.shifted_views += 1;
        }
        for p in self.image.iter_mut() {
            *p = -p.ln();
        }
        scan.orientation.apply(&self.image, self.nv, self.nu, out);
        Ok(())
    }
}

/// Move an image (`nv × nu`, row-major) by `rows` and `cols` pixels in place: its value at `(r, c)` becomes
/// the one at `(r − rows, c − cols)`, linearly interpolated, the edge value beyond the image (as
/// `scipy.ndimage.shift` with `order=1, mode="nearest"`; for whole pixels, `numpy.roll` without the wrap).
pub fn shift_image(image: &mut [f32], nv: usize, nu: usize, rows: f64, cols: f64) {
    if cols != 0.0 {
        for r in 0..nv {
            shift_line(image, r * nu, 1, nu, cols);
        }
    }
    if rows != 0.0 {
        for c in 0..nu {
            shift_line(image, c, nu, nv, rows);
        }
    }
}

/// Move the `n` samples `data[start + k·stride]` by `s`: sample `k` becomes the old value at `k − s`
/// (linear, clamped to the ends). In place: the walk runs against the shift, so every sample is read
/// before it is written.
fn shift_line(data: &mut [f32], start: usize, stride: usize, n: usize, s: f64) {
    let last = (n - 1) as f64;
    let mut at = |k: usize| {
        let x = (k as f64 - s).clamp(0.0, last);
        let i0 = x.floor() as usize;
        let f = (x - i0 as f64) as f32;
        let v0 = data[start + i0 * stride];
        let v = if f > 0.0 && i0 + 1 < n {
            v0 + f * (data[start + (i0 + 1) * stride] - v0)
        } else {
            v0
        };
        data[start + k * stride] = v;
    };
    if s > 0.0 {
        (0..n).rev().for_each(&mut at);
    } else {
        (0..n).for_each(&mut at);
    }
}
