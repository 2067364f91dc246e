//! Typed parameters of the iterative algorithms, with documented defaults. JSON field names match.

use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;

/// Most iterations any method accepts.
pub const MAX_ITERATIONS: usize = 100_000;

/// Where an iterative method starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InitialImage {
    /// All zeros (all ones for MLEM, which cannot start from zero).
    #[default]
    Zero,
    /// The FBP/FDK reconstruction (ram-lak) of the same data.
    Fbp,
}

fn iterations_default() -> usize {
    50
}
fn one() -> f64 {
    1.0
}

/// ART (Kaczmarz): one ray at a time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArtParams {
    /// Full sweeps over all rays (default 5).
    #[serde(default = "art_iterations")]
    pub iterations: usize,
    /// Relaxation λ ∈ (0, 2) (default 0.5).
    #[serde(default = "half")]
    pub relaxation: f64,
    /// Visit rays in a shuffled order (fixed seed) instead of sequentially (default true).
    #[serde(default = "yes")]
    pub shuffle: bool,
    #[serde(default)]
    pub nonnegative: bool,
    /// Upper bound of a box constraint (default none); with `nonnegative` the box is [0, upper].
    #[serde(default)]
    pub upper: Option<f64>,
    #[serde(default)]
    pub initial: InitialImage,
}
fn art_iterations() -> usize {
    5
}
fn half() -> f64 {
    0.5
}
fn yes() -> bool {
    true
}

/// SART (one view per update) and OS-SART (`subsets` > 1 views per update).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SartParams {
    /// Full sweeps over all views (default 10).
    #[serde(default = "sart_iterations")]
    pub iterations: usize,
    /// Relaxation λ ∈ (0, 2) (default 1).
    #[serde(default = "one")]
    pub relaxation: f64,
    /// Number of ordered subsets for OS-SART (default 10; SART uses one view per subset).
    #[serde(default = "sart_subsets")]
    pub subsets: usize,
    #[serde(default)]
    pub nonnegative: bool,
    /// Upper bound of a box constraint (default none); with `nonnegative` the box is [0, upper].
    #[serde(default)]
    pub upper: Option<f64>,
    #[serde(default)]
    pub initial: InitialImage,
    /// Stop when the relative residual ‖Ax − b‖/‖b‖ drops below this (default: never).
    #[serde(default)]
    pub tolerance: Option<f64>,
}
fn sart_iterations() -> usize {
    10
}
fn sart_subsets() -> usize {
    10
}

/// SIRT: x ← x + λ C Aᵀ R (b − A x).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SirtParams {
    /// Default 100.
    #[serde(default = "sirt_iterations")]
    pub iterations: usize,
    /// Relaxation λ ∈ (0, 2) (default 1).
    #[serde(default = "one")]
    pub relaxation: f64,
    #[serde(default)]
    pub nonnegative: bool,
    /// Upper bound of a box constraint (default none); with `nonnegative` the box is [0, upper].
    #[serde(default)]
    pub upper: Option<f64>,
    #[serde(default)]
    pub initial: InitialImage,
    #[serde(default)]
    pub tolerance: Option<f64>,
}
fn sirt_iterations() -> usize {
    100
}

/// CGLS on the normal equations.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CglsParams {
    /// Default 50.
    #[serde(default = "iterations_default")]
    pub iterations: usize,
    #[serde(default)]
    pub initial: InitialImage,
    #[serde(default)]
    pub tolerance: Option<f64>,
    /// The back projector (default `matched`).
    #[serde(default)]
    pub back_projector: BackProjector,
}

/// The back projector of CGLS.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BackProjector {
    /// The transpose of the forward projector: CGLS proper, which minimises ‖Ax − b‖ over its
    /// Krylov spaces.
    #[default]
    Matched,
    /// Cone beams only: FDK's voxel-driven back projection without its filter (bilinear samples of
    /// each view at every voxel's centre, weighted Δβ·D²/lc²), RTK's default back projector. It is
    /// not the transpose, so the method runs conjugate gradients on B A x = B b instead (as RTK's
    /// conjugate gradient filter does); each iteration is cheaper by about a third.
    Voxel,
}

/// MLEM, or OSEM when `subsets` > 1. Needs non-negative data.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MlemParams {
    /// Default 50.
    #[serde(default = "iterations_default")]
    pub iterations: usize,
    /// Ordered subsets (default 1 = MLEM).
    #[serde(default = "one_usize")]
    pub subsets: usize,
    #[serde(default)]
    pub tolerance: Option<f64>,
}
fn one_usize() -> usize {
    1
}

/// Most inner TV iterations per outer iteration.
pub const MAX_TV_ITERATIONS: usize = 10_000;

/// Total-variation regularised reconstruction for sparse-view data.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TvParams {
    /// Outer iterations (default 50).
    #[serde(default = "iterations_default")]
    pub iterations: usize,
    /// TV weight (default 0.0 = chosen from the data by the method).
    #[serde(default)]
    pub tv_weight: f64,
    /// Inner TV iterations per outer iteration (default 20).
    #[serde(default = "tv_inner")]
    pub tv_iterations: usize,
    /// Ordered subsets of the OS-SART data pass of each outer iteration (default 10; lowered to the
    /// number of views when larger).
    #[serde(default = "sart_subsets")]
    pub subsets: usize,
    #[serde(default = "yes")]
    pub nonnegative: bool,
    /// Upper bound of a box constraint (default none); with `nonnegative` the box is [0, upper].
    #[serde(default)]
    pub upper: Option<f64>,
    #[serde(default)]
    pub initial: InitialImage,
}
fn tv_inner() -> usize {
    20
}

/// The box every iterate is clamped into: `[0, upper]` with non-negativity, `(−∞, upper]` without.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Bounds {
    pub lower: Option<f32>,
    pub upper: Option<f32>,
}

impl Bounds {
    pub fn new(nonnegative: bool, upper: Option<f64>) -> Self {
        Self {
            lower: nonnegative.then_some(0.0),
            upper: upper.map(|u| u as f32),
        }
    }

    pub fn is_none(&self) -> bool {
        self.lower.is_none() && self.upper.is_none()
    }

    pub fn clamp(&self, v: f32) -> f32 {
        let v = self.lower.map_or(v, |l| v.max(l));
        self.upper.map_or(v, |u| v.min(u))
    }
}

/// An upper bound must be finite and, with non-negativity, positive.
pub fn check_upper(upper: Option<f64>, nonnegative: bool) -> Result<(), ReconError> {
    match upper {
        Some(u) if !u.is_finite() => Err(ReconError::param(
            "upper",
            format!("must be finite, got {u}"),
        )),
        Some(u) if nonnegative && u <= 0.0 => Err(ReconError::param(
            "upper",
            format!("must be above the lower bound 0 of `nonnegative`, got {u}"),
        )),
        _ => Ok(()),
    }
}

pub fn check_iterations(n: usize) -> Result<(), ReconError> {
    if n == 0 || n > MAX_ITERATIONS {
        return Err(ReconError::param(
            "iterations",
            format!("must be in 1..={MAX_ITERATIONS}, got {n}"),
        ));
    }
    Ok(())
}

pub fn check_relaxation(l: f64) -> Result<(), ReconError> {
    if !(l > 0.0 && l < 2.0) {
        return Err(ReconError::param(
            "relaxation",
            format!("must be in (0, 2), got {l}"),
        ));
    }
    Ok(())
}

pub fn check_subsets(s: usize, views: usize) -> Result<(), ReconError> {
    if s == 0 || s > views {
        return Err(ReconError::param(
            "subsets",
            format!("must be in 1..={views} (the number of views), got {s}"),
        ));
    }
    Ok(())
}

pub fn check_tolerance(t: Option<f64>) -> Result<(), ReconError> {
    match t {
        Some(t) if !(t.is_finite() && t >= 0.0) => Err(ReconError::param(
            "tolerance",
            format!("must be finite and non-negative, got {t}"),
        )),
        _ => Ok(()),
    }
}

macro_rules! defaults_from_json {
    ($($t:ty),*) => {$(
        impl Default for $t {
            /// The documented defaults (those of an empty JSON object).
            fn default() -> Self {
                serde_json::from_str("{}").expect("every field has a default")
            }
        }
    )*};
}
defaults_from_json!(
    ArtParams, SartParams, SirtParams, CglsParams, MlemParams, TvParams
);

impl ArtParams {
    pub fn validate(&self) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_relaxation(self.relaxation)?;
        check_upper(self.upper, self.nonnegative)
    }
}

impl SartParams {
    /// `views`: number of views of the geometry (bounds `subsets`).
    pub fn validate(&self, views: usize) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_relaxation(self.relaxation)?;
        check_subsets(self.subsets, views)?;
        check_tolerance(self.tolerance)?;
        check_upper(self.upper, self.nonnegative)
    }
}

impl SirtParams {
    pub fn validate(&self) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_relaxation(self.relaxation)?;
        check_tolerance(self.tolerance)?;
        check_upper(self.upper, self.nonnegative)
    }
}

impl CglsParams {
    pub fn validate(&self) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_tolerance(self.tolerance)
    }
}

impl MlemParams {
    pub fn validate(&self, views: usize) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_subsets(self.subsets, views)?;
        check_tolerance(self.tolerance)
    }
}

impl TvParams {
    /// `views` bounds `subsets` (a default above the number of views is lowered to it).
    pub fn validate(&self, views: usize) -> Result<(), ReconError> {
        check_iterations(self.iterations)?;
        check_subsets(self.subsets.min(views), views)?;
        check_upper(self.upper, self.nonnegative)?;
        if !(self.tv_weight.is_finite() && self.tv_weight >= 0.0) {
            return Err(ReconError::param(
                "tv_weight",
                format!("must be finite and non-negative, got {}", self.tv_weight),
            ));
        }
        if self.tv_iterations == 0 || self.tv_iterations > MAX_TV_ITERATIONS {
            return Err(ReconError::param(
                "tv_iterations",
                format!(
                    "must be in 1..={MAX_TV_ITERATIONS}, got {}",
                    self.tv_iterations
                ),
            ));
        }
        Ok(())
    }
}

macro_rules! bounded {
    ($($t:ty),*) => {$(
        impl $t {
            /// The box constraint of these parameters.
            pub fn bounds(&self) -> Bounds {
                Bounds::new(self.nonnegative, self.upper)
            }
        }
    )*};
}
bounded!(ArtParams, SartParams, SirtParams, TvParams);
