//! The layout every slice of a series shares: size, orientation (unit, orthogonal direction cosines and
//! their normal), pixel spacing and rescale, taken from the first slice and checked against every other; a
//! lone slice may lack its placement (assumed, with a warning).

use super::vector::{V3, cross, dot, norm, scale};
use super::{SeriesError, Slice, Warning};

/// Row direction, column direction and normal of a validated orientation.
fn axes(label: &str, o: [f64; 6]) -> Result<[V3; 3], SeriesError> {
    let bad = |reason: String| SeriesError::InvalidAttribute {
        label: label.to_string(),
        reason,
    };
    if o.iter().any(|v| !v.is_finite()) {
        return Err(bad("image orientation is not finite".into()));
    }
    let r = [o[0], o[1], o[2]];
    let c = [o[3], o[4], o[5]];
    let (nr, nc) = (norm(r), norm(c));
    if (nr - 1.0).abs() > 1e-3 || (nc - 1.0).abs() > 1e-3 {
        return Err(bad(format!(
            "image orientation vectors are not unit length ({nr:.4}, {nc:.4})"
        )));
    }
    let (r, c) = (scale(r, 1.0 / nr), scale(c, 1.0 / nc));
    if dot(r, c).abs() > 1e-3 {
        return Err(bad("image orientation vectors are not orthogonal".into()));
    }
    let n = cross(r, c);
    Ok([r, c, scale(n, 1.0 / norm(n))])
}

/// What every slice of the series shares.
pub(super) struct Layout {
    pub(super) rows: usize,
    pub(super) columns: usize,
    /// Row direction, column direction, unit normal.
    pub(super) axes: [V3; 3],
    /// Between rows, then between columns (mm).
    pub(super) pixel_spacing: [f64; 2],
}

/// The first slice's size, orientation and spacing, checked against every other slice; a lone slice may lack
/// its placement (assumed, with a warning).
pub(super) fn check_layout(
    slices: &[Slice],
    warnings: &mut Vec<Warning>,
) -> Result<Layout, SeriesError> {
    let first = slices.first().ok_or(SeriesError::Empty)?;
    let (rows, columns) = (first.rows, first.columns);
    if rows == 0 || columns == 0 {
        return Err(SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: "the image has no pixels".into(),
        });
    }
    let single = slices.len() == 1;
    let orientation = match first.orientation {
        Some(o) => o,
        None if single => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        None => {
            return Err(SeriesError::MissingAttribute {
                label: first.label.clone(),
                what: "image orientation (0020,0037)",
            });
        }
    };
    if single && first.orientation.is_none() {
        warnings.push(Warning {
            code: "orientation_assumed",
            message: format!(
                "slice {} has no image orientation (0020,0037): axial (rows along +x, columns along +y) assumed",
                first.label
            ),
        });
    }
    if single && first.position_mm.is_none() {
        warnings.push(Warning {
            code: "position_assumed",
            message: format!(
                "slice {} has no image position (0020,0032): its first pixel is placed at the origin",
                first.label
            ),
        });
    }
    if single
        && first
            .slice_thickness_mm
            .is_none_or(|t| !(t.is_finite() && t > 0.0))
    {
        warnings.push(Warning {
            code: "slice_thickness_assumed",
            message: format!(
                "slice {} has no slice thickness (0018,0050): 1 mm assumed for the volume's third axis",
                first.label
            ),
        });
    }
    let axes = axes(&first.label, orientation)?;
    let pixel_spacing = match first.pixel_spacing_mm {
        Some(ps) => ps,
        None => {
            warnings.push(Warning {
                code: "pixel_spacing_assumed",
                message: "no pixel spacing: 1 mm assumed".into(),
            });
            [1.0, 1.0]
        }
    };
    if pixel_spacing.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: format!("pixel spacing {pixel_spacing:?} is not positive"),
        });
    }
    for s in slices {
        check_slice(s, rows, columns)?;
        if !single {
            check_same_plane(first, s, orientation, pixel_spacing)?;
        }
    }
    Ok(Layout {
        rows,
        columns,
        axes,
        pixel_spacing,
    })
}

/// One slice's size, pixel count and rescale.
fn check_slice(s: &Slice, rows: usize, columns: usize) -> Result<(), SeriesError> {
    if (s.rows, s.columns) != (rows, columns) {
        return Err(SeriesError::SizeMismatch {
            label: s.label.clone(),
            rows: s.rows,
            columns: s.columns,
            want_rows: rows,
            want_columns: columns,
        });
    }
    if s.stored.len() != rows * columns {
        return Err(SeriesError::InvalidAttribute {
            label: s.label.clone(),
            reason: format!(
                "{} pixel values for a {rows}×{columns} image",
                s.stored.len()
            ),
        });
    }
    if !(s.rescale_slope.is_finite() && s.rescale_intercept.is_finite()) || s.rescale_slope == 0.0 {
        return Err(SeriesError::InvalidAttribute {
            label: s.label.clone(),
            reason: "rescale slope/intercept invalid".into(),
        });
    }
    Ok(())
}

/// A slice of a stack has the first slice's orientation and pixel spacing.
fn check_same_plane(
    first: &Slice,
    s: &Slice,
    orientation: [f64; 6],
    pixel_spacing: [f64; 2],
) -> Result<(), SeriesError> {
    let o = s.orientation.ok_or_else(|| SeriesError::MissingAttribute {
        label: s.label.clone(),
        what: "image orientation (0020,0037)",
    })?;
    if o.iter().zip(orientation).any(|(a, b)| (a - b).abs() > 1e-4) {
        return Err(SeriesError::OrientationMismatch {
            a: first.label.clone(),
            b: s.label.clone(),
        });
    }
    let ps = s.pixel_spacing_mm.unwrap_or([1.0, 1.0]);
    if ps
        .iter()
        .zip(pixel_spacing)
        .any(|(a, b)| (a - b).abs() > 1e-4 * b.max(1.0))
    {
        return Err(SeriesError::SpacingMismatch {
            a: first.label.clone(),
            b: s.label.clone(),
        });
    }
    Ok(())
}
