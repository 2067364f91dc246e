//! Errors of the reconstruction core, split by cause: the geometry, the data, a parameter, a limit, a cancel.

/// A geometry that cannot describe a real scanner.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    #[error("`{field}` must be finite, got {value}")]
    NonFinite { field: &'static str, value: f64 },
    #[error("`{field}` must be positive, got {value}")]
    NonPositive { field: &'static str, value: f64 },
    #[error("`{field}` must be at least 1")]
    Zero { field: &'static str },
    #[error("`{field}` = {value} exceeds the maximum of {max}")]
    TooMany {
        field: &'static str,
        value: usize,
        max: usize,
    },
    #[error(
        "the source-to-detector distance ({dsd_mm} mm) must exceed the source-to-isocentre distance ({dso_mm} mm)"
    )]
    DetectorInsideOrbit { dso_mm: f64, dsd_mm: f64 },
    #[error(
        "the source orbit (radius {dso_mm} mm) passes through the field of view (radius {fov_radius_mm} mm)"
    )]
    SourceInsideFov { dso_mm: f64, fov_radius_mm: f64 },
    #[error("the fan half-angle {half_fan_deg}° must be below 90°")]
    FanTooWide { half_fan_deg: f64 },
    #[error(
        "a short scan needs π + 2δ = {needed_deg:.3}° of rotation, the angles cover {covered_deg:.3}°"
    )]
    ShortScanTooShort { needed_deg: f64, covered_deg: f64 },
    #[error("view angles must be strictly monotonic (view {index})")]
    AnglesNotMonotonic { index: usize },
    #[error("{0}")]
    Invalid(String),
}

/// Everything that can go wrong in a reconstruction-core call.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReconError {
    #[error("invalid geometry: {0}")]
    Geometry(#[from] GeometryError),
    #[error("data shape {got:?} does not match the geometry, which expects {expected:?}")]
    ShapeMismatch {
        expected: Vec<usize>,
        got: Vec<usize>,
    },
    #[error("data contain a non-finite value at flat index {index}")]
    NonFinite { index: usize },
    #[error("invalid parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error("the problem needs {needed_bytes} bytes, more than the limit of {limit_bytes} bytes")]
    TooLarge { needed_bytes: u64, limit_bytes: u64 },
    #[error("canceled")]
    Canceled,
}

impl ReconError {
    /// Shorthand for [`ReconError::InvalidParameter`].
    pub fn param(name: &'static str, reason: impl Into<String>) -> Self {
        Self::InvalidParameter {
            name,
            reason: reason.into(),
        }
    }
}

/// Check that every value of `data` is finite; name the first offender.
pub fn ensure_finite<'a>(data: impl IntoIterator<Item = &'a f32>) -> Result<(), ReconError> {
    match data.into_iter().position(|v| !v.is_finite()) {
        Some(index) => Err(ReconError::NonFinite { index }),
        None => Ok(()),
    }
}

pub(crate) fn finite(field: &'static str, value: f64) -> Result<f64, GeometryError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(GeometryError::NonFinite { field, value })
    }
}

pub(crate) fn positive(field: &'static str, value: f64) -> Result<f64, GeometryError> {
    finite(field, value)?;
    if value > 0.0 {
        Ok(value)
    } else {
        Err(GeometryError::NonPositive { field, value })
    }
}

pub(crate) fn count(field: &'static str, value: usize, max: usize) -> Result<usize, GeometryError> {
    if value == 0 {
        Err(GeometryError::Zero { field })
    } else if value > max {
        Err(GeometryError::TooMany { field, value, max })
    } else {
        Ok(value)
    }
}
