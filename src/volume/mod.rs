//! Image-domain volume operations: slices, MPR, MIP/MinIP/average projections, window/level, resampling,
//! smoothing, PNG and JPEG encoding, pictures fitted to a viewport.
//!
//! [`Volume`] is the one 3D image type shared by reconstructions, DICOM series and meshes: samples
//! `[z][y][x]` (slice, row, column) and a [`Frame`] that places every voxel in patient space (LPS, mm).

mod display;
mod error;
mod filter;
mod frame;
mod image_plane;
mod mpr;
mod orient;
mod picture;
mod resample;
mod rotating;
mod window;

pub use display::{Axis, ProjectionKind, project, slice};
pub use error::VolumeError;
pub use filter::{gaussian, largest_component, median3, threshold};
pub use frame::{Frame, IndexMap, Volume};
pub use image_plane::{ImagePlane, ScreenSides, direction_label};
pub use mpr::{MAX_SIDE, Plane, Slab, curved, reformat, series_count, slab_series, whole_ceil};
pub use orient::{
    AXIS_ALIGNED_TOLERANCE, DisplayGrid, Reorientation, closest_canonical, flip_rows,
    is_axis_aligned, oriented_projection, oriented_slice, to_closest_canonical,
};
pub use picture::{MAX_VIEWPORT_SIDE, encode_jpeg, fit_viewport};
pub use resample::{isotropic_grid, resample_isotropic, trilinear};
pub use rotating::{rotating_axes, rotating_projection};
pub use window::{
    BitDepth, MU_WATER_PER_MM, Window, WindowPreset, encode_apng, encode_apng_annotated,
    encode_png, encode_png_annotated, mu_to_hu,
};
