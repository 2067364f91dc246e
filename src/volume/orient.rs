//! Patient orientation of volumes and of every derived 2D image.
//!
//! One rule, applied in one place: a volume from a patient is kept in its **closest canonical order**
//! ([`to_closest_canonical`], as nibabel's `as_closest_canonical`): exact flips and permutations of the
//! `[z][y][x]` array so that the column axis points as nearly as it can to the patient's left (+x, LPS), the
//! row axis posterior (+y) and the slice axis superior (+z). A series acquired head-first or feet-first, supine
//! or prone, with rows, columns or slices stored in reverse, or as coronal or sagittal images, becomes the same
//! array as its axial head-first-supine twin. Oblique frames (gantry tilt, angulated planes) keep their
//! residual direction matrix; their axial, coronal and sagittal images are sampled on an axis-aligned
//! [`DisplayGrid`] (only when such an image is asked for).
//!
//! Display orientation of every derived image (radiological convention):
//! - axial (fixed z), seen from the feet: patient right on the image left, anterior up;
//! - coronal (fixed y), seen from the front: superior up, patient right on the left;
//! - sagittal (fixed x), seen from the patient's left: superior up, anterior on the left.
//!
//! Each image comes with its [`ImagePlane`]: where its first pixel sits in patient space, the patient
//! directions of its rows and columns, and the names of its screen sides ([`ScreenSides`]).

use std::ops::Range;

use ndarray::{Array2, Array3, Axis as NdAxis};
use rayon::prelude::*;

use super::display::{Axis, ProjectionKind, project, slice};
use super::error::VolumeError;
use super::frame::{Frame, Volume};
use super::image_plane::ImagePlane;
use super::resample::trilinear;

/// Largest deviation of a direction cosine from the identity for which a frame counts as axis-aligned
/// (about 0.006°: 0.05 mm over a 500 mm field).
pub const AXIS_ALIGNED_TOLERANCE: f64 = 1e-4;

/// Largest side of a display grid (samples).
pub const MAX_DISPLAY_SIDE: usize = 8192;

/// The assignment of a frame's index axes to patient axes: `axis_of[c]` is the index axis (0 column, 1 row,
/// 2 slice) that runs closest to patient axis `c` (0 x/L, 1 y/P, 2 z/S), and `flip[c]` says it runs the other
/// way.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Reorientation {
    pub axis_of: [usize; 3],
    pub flip: [bool; 3],
}

impl Reorientation {
    /// True when the array is already in canonical order.
    pub fn is_identity(&self) -> bool {
        self.axis_of == [0, 1, 2] && self.flip == [false; 3]
    }
}

/// The closest canonical assignment of `frame`: the largest direction cosines pick the pairs first, so every
/// patient axis gets exactly one index axis even for 45° obliques.
pub fn closest_canonical(frame: &Frame) -> Reorientation {
    let mut cells: Vec<(f64, usize, usize)> = (0..3)
        .flat_map(|a| (0..3).map(move |c| (a, c)))
        .map(|(a, c)| (frame.direction[a][c].abs(), a, c))
        .collect();
    // Largest first; ties broken by the diagonal, then by index, so the result is deterministic.
    cells.sort_by(|x, y| {
        y.0.total_cmp(&x.0)
            .then_with(|| ((x.1 != x.2) as u8).cmp(&((y.1 != y.2) as u8)))
            .then_with(|| (x.1, x.2).cmp(&(y.1, y.2)))
    });
    let mut axis_of = [usize::MAX; 3];
    let mut used = [false; 3];
    for (_, a, c) in cells {
        if axis_of[c] == usize::MAX && !used[a] {
            axis_of[c] = a;
            used[a] = true;
        }
    }
    let flip = std::array::from_fn(|c| frame.direction[axis_of[c]][c] < 0.0);
    Reorientation { axis_of, flip }
}

/// Bring `vol` into its closest canonical order by exact flips and permutations (no interpolation). Every
/// voxel keeps its value and its patient position.
pub fn to_closest_canonical(vol: Volume) -> Volume {
    let r = closest_canonical(&vol.frame);
    if r.is_identity() {
        return vol;
    }
    let f = vol.frame;
    let (nz, ny, nx) = vol.data.dim();
    let n = [nx, ny, nz];
    // Array axis of index axis a is 2 − a ([k][j][i]); the new array is [z][y][x].
    let arr = |a: usize| 2 - a;
    let mut data =
        vol.data
            .permuted_axes([arr(r.axis_of[2]), arr(r.axis_of[1]), arr(r.axis_of[0])]);
    for c in 0..3 {
        if r.flip[c] {
            data.invert_axis(NdAxis(2 - c));
        }
    }
    let data = data.as_standard_layout().into_owned();
    let mut origin = f.origin_mm;
    for c in 0..3 {
        let a = r.axis_of[c];
        if r.flip[c] {
            let reach = (n[a] - 1) as f64 * f.spacing_mm[a];
            for (o, d) in origin.iter_mut().zip(f.direction[a]) {
                *o += reach * d;
            }
        }
    }
    let frame = Frame {
        spacing_mm: std::array::from_fn(|c| f.spacing_mm[r.axis_of[c]]),
        origin_mm: origin,
        direction: std::array::from_fn(|c| {
            let s = if r.flip[c] { -1.0 } else { 1.0 };
            f.direction[r.axis_of[c]].map(|v| s * v)
        }),
    };
    Volume { data, frame }
}

/// True when the frame's index axes are the patient axes x, y, z in that order (within
/// [`AXIS_ALIGNED_TOLERANCE`]).
pub fn is_axis_aligned(frame: &Frame) -> bool {
    (0..3).all(|a| {
        (0..3).all(|c| {
            let want = if a == c { 1.0 } else { 0.0 };
            (frame.direction[a][c] - want).abs() <= AXIS_ALIGNED_TOLERANCE
        })
    })
}

/// The axis-aligned grid on which axial, coronal and sagittal images of a volume are shown: the volume's own
/// samples when its frame is axis-aligned, otherwise a grid over the volume's bounding box in patient space
/// with, per patient axis, the step that the nearest index axis makes along it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DisplayGrid {
    /// `[z][y][x]` sample counts.
    pub dim: (usize, usize, usize),
    /// Axis-aligned frame (direction = identity).
    pub frame: Frame,
    /// True when the grid is the volume's own samples (no interpolation).
    pub native: bool,
}

impl DisplayGrid {
    /// The display grid of a volume of `dim` samples in `frame`.
    pub fn of(frame: &Frame, dim: (usize, usize, usize)) -> Result<Self, VolumeError> {
        let (nz, ny, nx) = dim;
        if nz == 0 || ny == 0 || nx == 0 {
            return Err(VolumeError::Empty);
        }
        if is_axis_aligned(frame) {
            return Ok(Self {
                dim,
                frame: *frame,
                native: true,
            });
        }
        let r = closest_canonical(frame);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in frame.corners(dim) {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        let step: [f64; 3] = std::array::from_fn(|c| {
            let a = r.axis_of[c];
            (frame.spacing_mm[a] * frame.direction[a][c].abs()).max(1e-3)
        });
        let n: [usize; 3] = std::array::from_fn(|c| {
            let k = ((hi[c] - lo[c]) / step[c] + 1e-6).floor();
            if k.is_finite() { k as usize + 1 } else { 0 }
        });
        if n.iter().any(|&k| k == 0 || k > MAX_DISPLAY_SIDE) {
            return Err(VolumeError::InvalidParameter {
                name: "frame",
                reason: format!(
                    "the volume's display grid would be {}×{}×{} samples (at most {MAX_DISPLAY_SIDE} a side)",
                    n[2], n[1], n[0]
                ),
            });
        }
        Ok(Self {
            dim: (n[2], n[1], n[0]),
            frame: Frame {
                spacing_mm: step,
                origin_mm: lo,
                direction: Frame::AXIS_ALIGNED,
            },
            native: false,
        })
    }

    /// The volume's own samples shown in array order, whatever its frame: the rule for reconstructions,
    /// which have no patient (their `[y][x]` convention, or ASTRA's rows, is kept on screen).
    pub fn array(frame: &Frame, dim: (usize, usize, usize)) -> Result<Self, VolumeError> {
        let (nz, ny, nx) = dim;
        if nz == 0 || ny == 0 || nx == 0 {
            return Err(VolumeError::Empty);
        }
        Ok(Self {
            dim,
            frame: *frame,
            native: true,
        })
    }

    /// The grid of `vol` under the patient rule ([`DisplayGrid::of`]) or in array order
    /// ([`DisplayGrid::array`]).
    pub fn for_volume(vol: &Volume, patient: bool) -> Result<Self, VolumeError> {
        if patient {
            Self::of(&vol.frame, vol.data.dim())
        } else {
            Self::array(&vol.frame, vol.data.dim())
        }
    }

    /// Number of images along `axis`.
    pub fn len(&self, axis: Axis) -> usize {
        match axis {
            Axis::Axial => self.dim.0,
            Axis::Coronal => self.dim.1,
            Axis::Sagittal => self.dim.2,
        }
    }

    /// Placement of image `index` along `axis` (for a projection: the middle of its slab).
    pub fn plane(&self, axis: Axis, index: f64) -> ImagePlane {
        let f = &self.frame;
        let (nz, _, _) = self.dim;
        let top = (nz - 1) as f64;
        let [x, y, z] = f.direction;
        let down = z.map(|v| -v);
        let sp = f.spacing_mm;
        match axis {
            Axis::Axial => ImagePlane {
                first_pixel_mm: f.position(index, 0.0, 0.0),
                row_direction: x,
                column_direction: y,
                pixel_mm: [sp[1], sp[0]],
            },
            Axis::Coronal => ImagePlane {
                first_pixel_mm: f.position(top, index, 0.0),
                row_direction: x,
                column_direction: down,
                pixel_mm: [sp[2], sp[0]],
            },
            Axis::Sagittal => ImagePlane {
                first_pixel_mm: f.position(top, 0.0, index),
                row_direction: y,
                column_direction: down,
                pixel_mm: [sp[2], sp[1]],
            },
        }
    }

    /// Sample image `index` along `axis` of `vol` on this grid, in display orientation; `fill` outside the
    /// volume.
    fn sample(
        &self,
        vol: &Volume,
        map: &super::frame::IndexMap,
        axis: Axis,
        index: usize,
        fill: f32,
    ) -> Array2<f32> {
        let plane = self.plane(axis, index as f64);
        let (rows, cols) = match axis {
            Axis::Axial => (self.dim.1, self.dim.2),
            Axis::Coronal => (self.dim.0, self.dim.2),
            Axis::Sagittal => (self.dim.0, self.dim.1),
        };
        let src = vol.data.view();
        let mut img = Array2::from_elem((rows, cols), fill);
        img.axis_iter_mut(NdAxis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(r, mut row)| {
                for (c, out) in row.iter_mut().enumerate() {
                    let p = plane.position(r as f64, c as f64);
                    if let Some(v) = trilinear(&src, map.index(p)) {
                        *out = v;
                    }
                }
            });
        img
    }
}

/// Image `index` along `axis` in display orientation, with its placement; `index` counts along `grid` (from
/// [`DisplayGrid::for_volume`]: the volume's own slices when it is axis-aligned or has no patient). `fill`
/// marks samples outside an oblique volume.
pub fn oriented_slice(
    vol: &Volume,
    grid: &DisplayGrid,
    axis: Axis,
    index: usize,
    fill: f32,
) -> Result<(Array2<f32>, ImagePlane), VolumeError> {
    let len = grid.len(axis);
    if index >= len {
        return Err(VolumeError::IndexOutOfRange {
            axis: axis_name(axis),
            index,
            len,
        });
    }
    let plane = grid.plane(axis, index as f64);
    if grid.native {
        return Ok((slice(vol.data.view(), axis, index)?, plane));
    }
    let map = index_map(vol)?;
    Ok((grid.sample(vol, &map, axis, index, fill), plane))
}

/// A MIP, MinIP or average over images `slab` along `axis` (default all), in display orientation, with the
/// placement of the slab's middle plane. Oblique volumes are sampled one display plane at a time.
pub fn oriented_projection(
    vol: &Volume,
    grid: &DisplayGrid,
    axis: Axis,
    kind: ProjectionKind,
    slab: Option<Range<usize>>,
    fill: f32,
) -> Result<(Array2<f32>, ImagePlane), VolumeError> {
    let len = grid.len(axis);
    let slab = slab.unwrap_or(0..len);
    if slab.start >= slab.end || slab.end > len {
        return Err(VolumeError::BadSlab {
            axis: axis_name(axis),
            start: slab.start,
            end: slab.end,
            len,
        });
    }
    let plane = grid.plane(axis, (slab.start + slab.end - 1) as f64 / 2.0);
    if grid.native {
        return Ok((project(vol.data.view(), axis, kind, Some(slab))?, plane));
    }
    let map = index_map(vol)?;
    let n = (slab.end - slab.start) as f32;
    let mut acc: Option<Array2<f32>> = None;
    for k in slab {
        let img = grid.sample(vol, &map, axis, k, fill);
        acc = Some(match acc {
            None => img,
            Some(mut a) => {
                ndarray::Zip::from(&mut a).and(&img).for_each(|a, &v| {
                    *a = match kind {
                        ProjectionKind::Max => a.max(v),
                        ProjectionKind::Min => a.min(v),
                        ProjectionKind::Mean => *a + v,
                    }
                });
                a
            }
        });
    }
    let mut img = acc.ok_or(VolumeError::Empty)?;
    if kind == ProjectionKind::Mean {
        img.mapv_inplace(|v| v / n);
    }
    Ok((img, plane))
}

fn index_map(vol: &Volume) -> Result<super::frame::IndexMap, VolumeError> {
    vol.frame
        .index_map()
        .ok_or_else(|| VolumeError::InvalidParameter {
            name: "frame",
            reason: "the volume's direction vectors are degenerate".into(),
        })
}

fn axis_name(axis: Axis) -> &'static str {
    match axis {
        Axis::Axial => "axial",
        Axis::Coronal => "coronal",
        Axis::Sagittal => "sagittal",
    }
}

/// Flip the row axis (y) of a `[z][y][x]` array: between ctrecon's reconstruction convention (row 0 at the
/// smallest y) and ASTRA's and scikit-image's (row 0 at the largest y, y up on screen).
pub fn flip_rows(data: Array3<f32>) -> Array3<f32> {
    let mut d = data;
    d.invert_axis(NdAxis(1));
    d.as_standard_layout().into_owned()
}

#[cfg(test)]
mod tests;
