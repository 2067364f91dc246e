//! Errors of the image-domain operations, each with a stable snake_case code for the API catalogue.

/// Something asked of a volume that it cannot give.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumeError {
    #[error("index {index} is outside the {axis} axis of {len} samples")]
    IndexOutOfRange {
        axis: &'static str,
        index: usize,
        len: usize,
    },
    #[error("slab {start}..{end} is empty or outside the {axis} axis of {len} samples")]
    BadSlab {
        axis: &'static str,
        start: usize,
        end: usize,
        len: usize,
    },
    #[error(
        "window width must be finite and positive and the level finite, got width {width}, level {level}"
    )]
    BadWindow { width: f64, level: f64 },
    #[error("the image is empty")]
    Empty,
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error("PNG encoding failed: {0}")]
    Encode(String),
}

impl VolumeError {
    /// Stable code for the API error catalogue.
    pub fn code(&self) -> &'static str {
        match self {
            VolumeError::IndexOutOfRange { .. } => "slice_out_of_range",
            VolumeError::BadSlab { .. } => "invalid_slab",
            VolumeError::BadWindow { .. } => "invalid_window",
            VolumeError::Empty => "empty_image",
            VolumeError::InvalidParameter { .. } => "invalid_parameter",
            VolumeError::Encode(_) => "encoding_failed",
        }
    }
}
