//! Transmission to line integrals: `p = −ln((I − D)/(F − D))` with a per-pixel dark `D` and flat `F`
//! (several flats averaged; flats taken before and after the scan interpolated linearly by view index),
//! or `p = −ln(I / W)` for data a scanner already divided by its white level `W` (Nikon). Counts at or
//! below the floor are clamped to it and counted, so that a dataset can report how many pixels were
//! clamped. Views are `[v][u]`.

use ndarray::{Array2, ArrayView2, ArrayViewMut2, Axis, Zip};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;

fn one() -> f32 {
    1.0
}

fn tiny() -> f32 {
    1e-6
}

/// The normalisation step. JSON: `{"method": "flat_field", "floor_counts": 1}` or
/// `{"method": "white_level", "white_level": 60000, "floor_ratio": 1e-6}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "method", rename_all = "snake_case", deny_unknown_fields)]
pub enum Normalise {
    /// `p = −ln(max(I − D, floor) / max(F − D, floor))`; `floor_counts` (default 1) in detector counts.
    FlatField {
        #[serde(default = "one")]
        floor_counts: f32,
    },
    /// `p = −ln(max(I / W, floor))` for data already flat-corrected to a white level `W` (counts);
    /// `floor_ratio` default 1e-6.
    WhiteLevel {
        white_level: f32,
        #[serde(default = "tiny")]
        floor_ratio: f32,
    },
}

/// Mean of several frames of one shape (darks or flats), `[v][u]`.
pub fn average_frames(frames: &[ArrayView2<'_, f32>]) -> Result<Array2<f32>, ReconError> {
    let first = frames
        .first()
        .ok_or_else(|| ReconError::param("frames", "at least one frame is needed"))?;
    let mut sum = Array2::<f32>::zeros(first.raw_dim());
    for f in frames {
        if f.shape() != first.shape() {
            return Err(ReconError::ShapeMismatch {
                expected: first.shape().to_vec(),
                got: f.shape().to_vec(),
            });
        }
        sum += f;
    }
    sum /= frames.len() as f32;
    Ok(sum)
}

/// The dark and flat(s) of a scan of `view_count` views: `dark` (already averaged), the flat taken before
/// the scan, and optionally one taken after it. View `k` is normalised by
/// `F_k = (1 − t)·pre + t·post`, `t = k / (view_count − 1)`.
#[derive(Debug, Clone, PartialEq)]
pub struct FlatField {
    dark: Array2<f32>,
    pre: Array2<f32>,
    post: Option<Array2<f32>>,
    view_count: usize,
}

impl FlatField {
    pub fn new(
        dark: Array2<f32>,
        pre: Array2<f32>,
        post: Option<Array2<f32>>,
        view_count: usize,
    ) -> Result<Self, ReconError> {
        let same = |name: &'static str, a: &Array2<f32>| {
            if a.shape() == dark.shape() {
                Ok(())
            } else {
                Err(ReconError::param(
                    name,
                    format!(
                        "shape {:?} differs from the dark's {:?}",
                        a.shape(),
                        dark.shape()
                    ),
                ))
            }
        };
        same("flat", &pre)?;
        if let Some(p) = &post {
            same("post_flat", p)?;
        }
        if view_count == 0 {
            return Err(ReconError::param("view_count", "must be at least 1"));
        }
        for (name, a) in [
            ("dark", Some(&dark)),
            ("flat", Some(&pre)),
            ("post_flat", post.as_ref()),
        ] {
            if a.is_some_and(|a| a.iter().any(|v| !v.is_finite())) {
                return Err(ReconError::param(name, "contains a non-finite value"));
            }
        }
        Ok(Self {
            dark,
            pre,
            post,
            view_count,
        })
    }

    /// `[v][u]` shape of every frame.
    pub fn shape(&self) -> [usize; 2] {
        [self.dark.nrows(), self.dark.ncols()]
    }

    /// Weight of the post-scan flat for view `view`.
    fn post_weight(&self, view: usize) -> f32 {
        match self.post {
            Some(_) if self.view_count > 1 => view as f32 / (self.view_count - 1) as f32,
            _ => 0.0,
        }
    }
}

impl Normalise {
    fn check(&self) -> Result<(), ReconError> {
        let ok = |name, v: f32| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(ReconError::param(
                    name,
                    format!("must be positive and finite, got {v}"),
                ))
            }
        };
        match *self {
            Normalise::FlatField { floor_counts } => ok("floor_counts", floor_counts),
            Normalise::WhiteLevel {
                white_level,
                floor_ratio,
            } => {
                ok("white_level", white_level)?;
                ok("floor_ratio", floor_ratio)
            }
        }
    }

    /// Normalise view `view` in place (counts in, line integrals out); returns how many pixels were
    /// clamped to the floor. `field` is required by [`Normalise::FlatField`] and ignored otherwise.
    pub fn apply_view(
        &self,
        field: Option<&FlatField>,
        view: usize,
        mut data: ArrayViewMut2<'_, f32>,
    ) -> Result<usize, ReconError> {
        self.check()?;
        match *self {
            Normalise::WhiteLevel {
                white_level,
                floor_ratio,
            } => {
                let inv = 1.0 / white_level;
                let clamped = data
                    .axis_iter_mut(Axis(0))
                    .into_par_iter()
                    .map(|mut row| {
                        let mut n = 0;
                        for x in row.iter_mut() {
                            let t = *x * inv;
                            let c = if t > floor_ratio {
                                t
                            } else {
                                n += 1;
                                floor_ratio
                            };
                            *x = -c.ln();
                        }
                        n
                    })
                    .sum();
                Ok(clamped)
            }
            Normalise::FlatField { floor_counts } => {
                let f = field.ok_or_else(|| {
                    ReconError::param(
                        "flat_field",
                        "flat-field normalisation needs a dark and a flat",
                    )
                })?;
                if data.shape() != f.shape() {
                    return Err(ReconError::ShapeMismatch {
                        expected: f.shape().to_vec(),
                        got: data.shape().to_vec(),
                    });
                }
                if view >= f.view_count {
                    return Err(ReconError::param(
                        "view",
                        format!("view {view} of a scan of {} views", f.view_count),
                    ));
                }
                let t = f.post_weight(view);
                let post = f.post.as_ref().unwrap_or(&f.pre);
                let clamped = Zip::from(data.rows_mut())
                    .and(f.dark.rows())
                    .and(f.pre.rows())
                    .and(post.rows())
                    .into_par_iter()
                    .map(|(mut row, dark, pre, post)| {
                        let mut n = 0;
                        for (((x, &d), &a), &b) in row.iter_mut().zip(dark).zip(pre).zip(post) {
                            let flat = a + t * (b - a) - d;
                            let signal = *x - d;
                            let low = signal <= floor_counts || flat <= floor_counts;
                            n += usize::from(low);
                            *x = (flat.max(floor_counts) / signal.max(floor_counts)).ln();
                        }
                        n
                    })
                    .sum();
                Ok(clamped)
            }
        }
    }
}
