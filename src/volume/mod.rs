//! Image-domain volume operations: slices, MPR, MIP/MinIP/average projections, window/level, resampling,
//! smoothing, PNG encoding.
//!
//! [`Volume`] is the one 3D image type shared by reconstructions, DICOM series and meshes: samples
//! `[z][y][x]` (slice, row, column) and a [`Frame`] that places every voxel in patient space (LPS, mm).

mod frame;

pub use frame::{Frame, Volume};
