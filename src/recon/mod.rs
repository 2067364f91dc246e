//! The reconstruction core: geometries, phantoms, projectors, filters, analytic and iterative algorithms,
//! quality metrics.
//!
//! Everything here is pure computation over `ndarray` arrays: no async runtime, HTTP, database, DICOM, clock,
//! environment or file path. The service and the CLI wrap it.
//!
//! # Conventions (tested in `geometry` and `phantom`)
//! - Lengths in millimetres; attenuation μ in 1/mm; a projection value is a line integral of μ.
//! - Images are `[y][x]` arrays and volumes `[z][y][x]` (slowest to fastest). Sample `i` along an axis of
//!   `n` samples with spacing `d` sits at `(i − (n−1)/2)·d + centre` (see [`grid`]). With a DICOM frame of
//!   reference, x points to the patient's left, y posterior and z superior (LPS), so row index grows with y.
//! - View angle β in radians, counter-clockwise from +x toward +y; at β = 0 the source of a fan or cone beam
//!   sits on −y at `(0, −DSO)` and the central ray travels along +y. In general the source is at
//!   `DSO·(sin β, −cos β)`, the central ray direction is `(−sin β, cos β)` and the detector u axis is
//!   `(cos β, sin β)`. A parallel beam at angle θ has rays along `(−sin θ, cos θ)` and detector coordinate
//!   `t = x cos θ + y sin θ`.
//! - Projection data are `[view][u]` for 2D and `[view][v][u]` for 3D.

pub mod algorithm;
pub mod analytic;
pub mod control;
pub mod cpu;
pub mod error;
pub mod geometry;
pub mod grid;
pub mod iterative;
pub mod metrics;
#[cfg(target_arch = "x86_64")]
mod pairs;
pub mod phantom;
pub mod prep;
pub mod projector;
pub(crate) mod team;

pub use control::{Cancel, Control, NoProgress, Progress};
pub use error::{GeometryError, ReconError};
pub use grid::{ImageGrid, Limits, VolumeGrid};
