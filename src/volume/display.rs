//! Slices and projections of a `[z][y][x]` volume in radiological display orientation.
//!
//! Orientation (LPS volumes: x to the patient's left, y posterior, z superior):
//! - axial (fixed z): rows run anterior → posterior (y), columns patient right → left (x), so the patient's right
//!   appears on the viewer's left;
//! - coronal (fixed y): rows superior → inferior (z reversed), columns right → left (x);
//! - sagittal (fixed x): rows superior → inferior (z reversed), columns anterior → posterior (y).

use std::ops::Range;

use ndarray::{Array2, ArrayView2, ArrayView3, Axis as NdAxis, Zip, s};
use serde::{Deserialize, Serialize};

use super::error::VolumeError;

/// A principal viewing direction.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Axis {
    /// Perpendicular to z: the array axis 0.
    Axial,
    /// Perpendicular to y: the array axis 1.
    Coronal,
    /// Perpendicular to x: the array axis 2.
    Sagittal,
}

impl Axis {
    /// The array axis this direction indexes (`[z][y][x]`).
    pub fn array_axis(self) -> usize {
        match self {
            Axis::Axial => 0,
            Axis::Coronal => 1,
            Axis::Sagittal => 2,
        }
    }
    fn name(self) -> &'static str {
        match self {
            Axis::Axial => "axial",
            Axis::Coronal => "coronal",
            Axis::Sagittal => "sagittal",
        }
    }
    /// Number of slices a volume has along this direction.
    pub fn len(self, vol: &ArrayView3<'_, f32>) -> usize {
        vol.len_of(NdAxis(self.array_axis()))
    }
}

/// Put a plane that is `[z][*]` (coronal, sagittal) into display orientation (superior at the top).
fn orient(axis: Axis, plane: ArrayView2<'_, f32>) -> Array2<f32> {
    match axis {
        Axis::Axial => plane.to_owned(),
        Axis::Coronal | Axis::Sagittal => plane.slice(s![..;-1, ..]).to_owned(),
    }
}

/// One slice along `axis`, in display orientation.
pub fn slice(
    vol: ArrayView3<'_, f32>,
    axis: Axis,
    index: usize,
) -> Result<Array2<f32>, VolumeError> {
    let len = axis.len(&vol);
    if index >= len {
        return Err(VolumeError::IndexOutOfRange {
            axis: axis.name(),
            index,
            len,
        });
    }
    Ok(orient(
        axis,
        vol.index_axis(NdAxis(axis.array_axis()), index),
    ))
}

/// How samples along a ray are combined.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum ProjectionKind {
    /// Maximum intensity projection.
    #[serde(rename = "mip")]
    Max,
    /// Minimum intensity projection.
    #[serde(rename = "minip")]
    Min,
    /// Average along the ray (a thick-slab average).
    #[serde(rename = "average")]
    Mean,
}

/// Project the slab `slab` (indices along `axis`; default the whole volume) with `kind`, in display orientation.
pub fn project(
    vol: ArrayView3<'_, f32>,
    axis: Axis,
    kind: ProjectionKind,
    slab: Option<Range<usize>>,
) -> Result<Array2<f32>, VolumeError> {
    let len = axis.len(&vol);
    let slab = slab.unwrap_or(0..len);
    if slab.start >= slab.end || slab.end > len {
        return Err(VolumeError::BadSlab {
            axis: axis.name(),
            start: slab.start,
            end: slab.end,
            len,
        });
    }
    let ax = NdAxis(axis.array_axis());
    let part = vol.slice_axis(ax, ndarray::Slice::from(slab.clone()));
    if axis == Axis::Sagittal {
        // Rays run along contiguous rows: reduce each row, one z plane per task.
        let n = (slab.end - slab.start) as f32;
        let mut acc = Array2::<f32>::zeros((part.dim().0, part.dim().1));
        Zip::from(acc.rows_mut())
            .and(part.outer_iter())
            .par_for_each(|mut out, plane| {
                for (o, row) in out.iter_mut().zip(plane.rows()) {
                    *o = match kind {
                        ProjectionKind::Max => {
                            row.iter().copied().fold(f32::NEG_INFINITY, f32::max)
                        }
                        ProjectionKind::Min => row.iter().copied().fold(f32::INFINITY, f32::min),
                        ProjectionKind::Mean => row.sum() / n,
                    };
                }
            });
        return Ok(orient(axis, acc.view()));
    }
    let first = part.index_axis(ax, 0);
    let mut acc = first.to_owned();
    for plane in part.axis_iter(ax).skip(1) {
        match kind {
            ProjectionKind::Max => Zip::from(&mut acc).and(&plane).for_each(|a, &v| {
                if v > *a {
                    *a = v
                }
            }),
            ProjectionKind::Min => Zip::from(&mut acc).and(&plane).for_each(|a, &v| {
                if v < *a {
                    *a = v
                }
            }),
            ProjectionKind::Mean => Zip::from(&mut acc).and(&plane).for_each(|a, &v| *a += v),
        }
    }
    if kind == ProjectionKind::Mean {
        let n = (slab.end - slab.start) as f32;
        acc.mapv_inplace(|a| a / n);
    }
    Ok(orient(axis, acc.view()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    fn ramp() -> Array3<f32> {
        // value = 100 z + 10 y + x
        Array3::from_shape_fn((3, 4, 5), |(z, y, x)| (100 * z + 10 * y + x) as f32)
    }

    #[test]
    fn axial_slices_keep_rows_as_y_and_columns_as_x() {
        let v = ramp();
        let a = slice(v.view(), Axis::Axial, 2).unwrap();
        assert_eq!(a.dim(), (4, 5));
        assert_eq!(a[[1, 3]], 213.0);
    }

    #[test]
    fn coronal_and_sagittal_slices_put_superior_at_the_top() {
        let v = ramp();
        let c = slice(v.view(), Axis::Coronal, 1).unwrap();
        assert_eq!(c.dim(), (3, 5));
        assert_eq!(c[[0, 4]], 214.0); // top row is the highest z
        let s = slice(v.view(), Axis::Sagittal, 4).unwrap();
        assert_eq!(s.dim(), (3, 4));
        assert_eq!(s[[2, 3]], 34.0); // bottom row z = 0, column y = 3
    }

    #[test]
    fn out_of_range_slices_are_refused() {
        let v = ramp();
        assert!(matches!(
            slice(v.view(), Axis::Sagittal, 5),
            Err(VolumeError::IndexOutOfRange { len: 5, .. })
        ));
    }

    #[test]
    fn projections_combine_the_slab_only() {
        let v = ramp();
        let mip = project(v.view(), Axis::Axial, ProjectionKind::Max, None).unwrap();
        assert_eq!(mip[[0, 0]], 200.0);
        let minip = project(v.view(), Axis::Axial, ProjectionKind::Min, Some(1..3)).unwrap();
        assert_eq!(minip[[1, 1]], 111.0);
        let mean = project(v.view(), Axis::Coronal, ProjectionKind::Mean, None).unwrap();
        // mean over y of 10y is 15; top row is z = 2
        assert!((mean[[0, 2]] - 217.0).abs() < 1e-4);
        assert!(project(v.view(), Axis::Axial, ProjectionKind::Max, Some(2..2)).is_err());
        assert!(project(v.view(), Axis::Axial, ProjectionKind::Max, Some(0..4)).is_err());
    }
}
