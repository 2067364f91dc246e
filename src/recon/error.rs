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

/// Values of contiguous data checked together by [`ensure_finite`].
const FINITE_BLOCK: usize = 4096;

/// Check that every value of `data` is finite; name the first offender (its index in logical order).
pub fn ensure_finite<D: ndarray::Dimension>(
    data: ndarray::ArrayView<'_, f32, D>,
) -> Result<(), ReconError> {
    let first = match data.as_slice() {
        // Contiguous data is checked a block at a time by a test without an early exit, which
        // vectorises; only a block that fails is searched for its first offender.
        Some(values) => values
            .chunks(FINITE_BLOCK)
            .enumerate()
            .find_map(|(b, block)| {
                let finite = block.iter().fold(true, |all, v| all & v.is_finite());
                if finite {
                    None
                } else {
                    let at = block.iter().position(|v| !v.is_finite());
                    at.map(|i| b * FINITE_BLOCK + i)
                }
            }),
        None => data.iter().position(|v| !v.is_finite()),
    };
    match first {
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

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// The first offender by logical index, in contiguous data (in the first block, in a later
    /// block after a finite one, in the last partial block) and in a transposed view.
    #[test]
    fn the_first_value_that_is_not_finite_is_named() {
        let mut data = Array3::<f32>::ones((3, 50, 70));
        assert_eq!(ensure_finite(data.view()), Ok(()));
        let n = data.len();
        for (at, bad) in [
            (5, f32::NAN),
            (FINITE_BLOCK + 17, f32::INFINITY),
            (n - 1, f32::NEG_INFINITY),
        ] {
            let mut d = data.clone();
            if let Some(v) = d.as_slice_mut().and_then(|s| s.get_mut(at)) {
                *v = bad;
            }
            if let Some(v) = d.as_slice_mut().and_then(|s| s.get_mut(n - 2)) {
                *v = f32::NAN;
            }
            let first = at.min(n - 2);
            assert_eq!(
                ensure_finite(d.view()),
                Err(ReconError::NonFinite { index: first })
            );
        }
        data[[1, 2, 3]] = f32::NAN;
        let t = data.view().reversed_axes();
        // Logical index of [3, 2, 1] in the shape [70, 50, 3].
        assert_eq!(
            ensure_finite(t),
            Err(ReconError::NonFinite {
                index: (3 * 50 + 2) * 3 + 1
            })
        );
    }
}
