//! Typed algorithm specifications and the one entry point that runs any of them on any geometry.
//!
//! [`AlgorithmSpec`] is what the CLI and the service accept (JSON: `{"name": "fbp", "filter": "hann"}`).
//! [`reconstruct`] validates the data against the geometry, checks the memory estimate against
//! [`crate::recon::grid::Limits`], and dispatches to the analytic ([`crate::recon::analytic`]) or iterative
//! ([`crate::recon::iterative`]) implementation.

use serde::{Deserialize, Serialize};

use crate::recon::error::ReconError;
use crate::recon::grid::{ImageGrid, VolumeGrid};
mod run;
mod slices;
#[cfg(test)]
mod slices_tests;
pub use run::{check_grid, estimate_bytes, reconstruct};

pub use crate::recon::iterative::params::{
    ArtParams, BackProjector, CglsParams, InitialImage, MlemParams, SartParams, SirtParams,
    TvParams,
};

/// Apodisation window applied to the ramp filter (on normalised frequency w ∈ [0, π], cut-off d).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Window {
    /// Plain ramp: 1.
    #[default]
    RamLak,
    /// sin(w/2d)/(w/2d).
    SheppLogan,
    /// cos(w/2d).
    Cosine,
    /// 0.54 + 0.46 cos(w/d).
    Hamming,
    /// (1 + cos(w/d))/2.
    Hann,
}

fn one() -> f64 {
    1.0
}

/// Parameters of the filtered-backprojection family (parallel FBP, fan-beam FBP, FDK).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FbpParams {
    #[serde(default)]
    pub filter: Window,
    /// Frequency cut-off d ∈ (0, 1] as a fraction of the Nyquist frequency; zero above it.
    #[serde(default = "one")]
    pub cutoff: f64,
    /// Zero-padded length of each filtered row; default the power of two ≥ max(64, 2N).
    #[serde(default)]
    pub padded_len: Option<usize>,
}

impl Default for FbpParams {
    fn default() -> Self {
        Self {
            filter: Window::RamLak,
            cutoff: 1.0,
            padded_len: None,
        }
    }
}

impl FbpParams {
    pub fn validate(&self) -> Result<(), ReconError> {
        if !(self.cutoff > 0.0 && self.cutoff <= 1.0) {
            return Err(ReconError::param(
                "cutoff",
                format!("must be in (0, 1], got {}", self.cutoff),
            ));
        }
        Ok(())
    }
}

/// A reconstruction algorithm with its parameters. Analytic: `fbp` (2D parallel and fan beams; Parker
/// weights for short scans) and `fdk` (cone beams; Parker for short scans, Wang for offset detectors).
/// Iterative: `art`, `sart`, `os_sart`, `sirt`, `cgls`, `mlem` (OSEM with subsets > 1), `tv`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "name", rename_all = "snake_case")]
pub enum AlgorithmSpec {
    Fbp(FbpParams),
    Fdk(FbpParams),
    Art(ArtParams),
    Sart(SartParams),
    OsSart(SartParams),
    Sirt(SirtParams),
    Cgls(CglsParams),
    Mlem(MlemParams),
    Tv(TvParams),
}

impl AlgorithmSpec {
    /// The spec's name as used in JSON.
    pub fn name(&self) -> &'static str {
        match self {
            AlgorithmSpec::Fbp(_) => "fbp",
            AlgorithmSpec::Fdk(_) => "fdk",
            AlgorithmSpec::Art(_) => "art",
            AlgorithmSpec::Sart(_) => "sart",
            AlgorithmSpec::OsSart(_) => "os_sart",
            AlgorithmSpec::Sirt(_) => "sirt",
            AlgorithmSpec::Cgls(_) => "cgls",
            AlgorithmSpec::Mlem(_) => "mlem",
            AlgorithmSpec::Tv(_) => "tv",
        }
    }
    /// True for the analytic family.
    pub fn is_analytic(&self) -> bool {
        matches!(self, AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_))
    }
}

/// The grid a reconstruction is computed on: an image for 2D geometries, a volume for cone beams.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "a grid: {\"nx\", \"ny\", \"dx_mm\", \"dy_mm\"} for a 2D geometry, or {\"nx\", \"ny\", \"nz\", \
                 \"spacing_mm\": [x, y, z]} (three numbers) for a cone beam; \"centre_mm\" optional in both"
)]
pub enum OutputGrid {
    Volume(VolumeGrid),
    Image(ImageGrid),
}
