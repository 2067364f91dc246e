//! Pure series-to-volume assembly: sort slices along the normal, check spacing, tilt and gaps, rescale to HU,
//! patient coordinates.
//!
//! Input is a list of decoded 2D slices with the attributes that place them in patient space (LPS, mm):
//! image position, image orientation, pixel spacing, and the rescale to Hounsfield units. [`assemble`] sorts
//! them by their position along the slice normal, drops exact duplicates, detects missing slices and uneven
//! spacing (refused or resampled onto a uniform grid, with a warning), measures gantry tilt (kept as a
//! non-orthogonal slice axis in the [`Frame`](crate::volume::Frame)) and returns a [`Volume`] in HU in the closest canonical order
//! (patient left, posterior, superior along the array axes x, y, z).
//!
//! This module knows nothing about file formats: the reader that fills [`Slice`] lives elsewhere.

use serde::Serialize;

use crate::recon::error::ReconError;
use crate::volume::Volume;

mod assemble;
mod hu;
mod layout;
mod stack;
mod vector;
pub use assemble::assemble;

/// HU given to pixels marked as padding (outside the scanned field).
pub const PADDING_HU: f32 = -1024.0;

/// Tilt below which the angle between the slice axis and the image normal is rounding noise in the stored
/// positions (degrees): not reported as gantry tilt. Real gantry tilts are whole degrees (commonly 5–30°).
pub const TILT_TOLERANCE_DEG: f64 = 0.1;

/// Widest gap, in nominal slice spacings, that resampling may bridge (four missing slices). A wider gap is
/// two stacks or a lost part of the series and is refused under every [`UnevenPolicy`].
pub const MAX_BRIDGED_GAP: f64 = 5.0;

/// Whether a warning of [`assemble`] describes the assembled grid itself, so that an isotropic resample onto an
/// orthogonal grid makes it stale: gantry tilt (the sheared slice axis is gone after the resample).
pub fn stale_after_resample(code: &str) -> bool {
    code == "gantry_tilt"
}

/// One decoded image plane with its placement.
#[derive(Debug, Clone, PartialEq)]
pub struct Slice {
    /// Rows (y, index `j`) and columns (x, index `i`).
    pub rows: usize,
    pub columns: usize,
    /// Stored pixel values, row-major (`rows × columns`), before the rescale.
    pub stored: Vec<f32>,
    /// HU = stored · slope + intercept.
    pub rescale_slope: f64,
    pub rescale_intercept: f64,
    /// Patient position of the first pixel (mm, LPS).
    pub position_mm: Option<[f64; 3]>,
    /// Direction cosines of a row (increasing column index) then of a column (increasing row index).
    pub orientation: Option<[f64; 6]>,
    /// Spacing between rows, then between columns (mm).
    pub pixel_spacing_mm: Option<[f64; 2]>,
    pub slice_thickness_mm: Option<f64>,
    /// Stored values in `[padding.0, padding.1]` are padding (a single value when both are equal).
    pub padding: Option<(f64, f64)>,
    /// Where the slice came from (file name and frame), for messages only.
    pub label: String,
}

/// What to do when slices are not evenly spaced (including missing slices).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnevenPolicy {
    /// Refuse the series.
    #[default]
    Refuse,
    /// Interpolate linearly onto a uniform grid at the most common spacing.
    Resample,
}

/// Options of [`assemble`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AssemblyOptions {
    pub uneven: UnevenPolicy,
    /// Relative tolerance on slice spacing (fraction of the most common spacing).
    pub spacing_tolerance: f64,
    /// Largest volume accepted (voxels).
    pub max_voxels: usize,
}

impl Default for AssemblyOptions {
    fn default() -> Self {
        Self {
            uneven: UnevenPolicy::Refuse,
            spacing_tolerance: 0.02,
            max_voxels: 1 << 30,
        }
    }
}

/// Something worth telling the user that did not stop the assembly.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Warning {
    /// Stable snake_case code.
    pub code: &'static str,
    pub message: String,
}

/// An assembled series.
#[derive(Debug, Clone, PartialEq)]
pub struct Assembled {
    /// HU, `[z][y][x]` in the closest canonical order (see [`crate::volume::to_closest_canonical`]): the
    /// column axis runs as nearly as it can to the patient's left, the row axis posterior, the slice axis
    /// superior, whatever the acquisition's orientation and the order of its rows, columns and slices.
    pub volume: Volume,
    pub warnings: Vec<Warning>,
    /// Angle between the slice axis and the image normal (degrees); 0 for an untilted series.
    pub tilt_deg: f64,
    /// Slice spacing measured along the normal (mm).
    pub normal_spacing_mm: f64,
}

/// Why slices could not be assembled into a volume. Messages say which slices.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SeriesError {
    #[error("the series has no image slices")]
    Empty,
    #[error("slice {label} is {rows}×{columns} but the series is {want_rows}×{want_columns}")]
    SizeMismatch {
        label: String,
        rows: usize,
        columns: usize,
        want_rows: usize,
        want_columns: usize,
    },
    #[error("slice {label} lacks {what}, needed to place it in patient space")]
    MissingAttribute { label: String, what: &'static str },
    #[error("slice {label}: {reason}")]
    InvalidAttribute { label: String, reason: String },
    #[error("slices {a} and {b} have different orientations")]
    OrientationMismatch { a: String, b: String },
    #[error("slices {a} and {b} have different pixel spacings")]
    SpacingMismatch { a: String, b: String },
    #[error("slices {a} and {b} are at the same position with different pixels")]
    DuplicatePosition { a: String, b: String },
    #[error("slice positions do not lie on a line (slice {label} is {offset_mm:.3} mm off)")]
    NotCollinear { label: String, offset_mm: f64 },
    #[error(
        "{missing} slice(s) missing: gap of {gap_mm:.3} mm between {a} and {b}, expected {spacing_mm:.3} mm; resample to accept"
    )]
    MissingSlices {
        missing: usize,
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
    },
    #[error(
        "uneven slice spacing: {gap_mm:.3} mm between {a} and {b}, expected {spacing_mm:.3} mm; resample to accept"
    )]
    UnevenSpacing {
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
    },
    #[error(
        "gap of {gap_mm:.3} mm between {a} and {b}, {slices:.1}× the {spacing_mm:.3} mm slice spacing: \
         two stacks or a large part of the series missing, too wide to interpolate; upload the stacks as separate series"
    )]
    SpacingJump {
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
        slices: f64,
    },
    #[error("the volume would have {voxels} voxels, more than the limit of {limit}")]
    TooLarge { voxels: usize, limit: usize },
    #[error(
        "its headers declare {samples} samples: decoding and assembling them would hold about {} MiB, more than \
         the memory budget of {} MiB (memory_budget_bytes)",
        bytes.div_ceil(1 << 20),
        budget >> 20
    )]
    OverBudget {
        samples: u64,
        bytes: u64,
        budget: u64,
    },
    #[error("canceled")]
    Canceled,
}

impl SeriesError {
    /// Stable code for the API error catalogue.
    pub fn code(&self) -> &'static str {
        match self {
            SeriesError::Empty => "series_empty",
            SeriesError::SizeMismatch { .. } => "series_size_mismatch",
            SeriesError::MissingAttribute { .. } => "series_missing_attribute",
            SeriesError::InvalidAttribute { .. } => "series_invalid_attribute",
            SeriesError::OrientationMismatch { .. } => "series_orientation_mismatch",
            SeriesError::SpacingMismatch { .. } => "series_spacing_mismatch",
            SeriesError::DuplicatePosition { .. } => "series_duplicate_position",
            SeriesError::NotCollinear { .. } => "series_not_collinear",
            SeriesError::MissingSlices { .. } => "series_missing_slices",
            SeriesError::UnevenSpacing { .. } => "series_uneven_spacing",
            SeriesError::SpacingJump { .. } => "series_spacing_jump",
            SeriesError::TooLarge { .. } | SeriesError::OverBudget { .. } => "series_too_large",
            SeriesError::Canceled => "canceled",
        }
    }
}

impl From<ReconError> for SeriesError {
    fn from(_: ReconError) -> Self {
        SeriesError::Canceled
    }
}

mod fuzz;
#[doc(hidden)]
pub use fuzz::{fuzz_entry, fuzz_slices};

#[cfg(test)]
mod tests;
