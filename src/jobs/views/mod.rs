//! Views derived from a job's volume: a slice (PNG or `.npy`), a MIP/MinIP/average projection with an
//! optional slab (PNG or `.npy`), an iso-surface mesh (binary STL, mm, LPS). Each view is a pure function of
//! the immutable volume and its parameters, so it is cached under the SHA-256 of the parameters and that
//! hash is its strong ETag.
//!
//! Windows: a `preset` (soft_tissue, lung, liver, bone, brain) is in HU and applies after converting the
//! volume's μ (1/mm) with μ_water (volumes already in HU, from CT series, are used as they are); explicit
//! `ww`/`wl` are in the volume's units, or HU with `units=hu`; with neither, the window spans the 0.5–99.5
//! percentiles of the image.
//!
//! DICOM formats: a 2D view as a Secondary Capture instance (8-bit, through the window), a mesh as an
//! Encapsulated STL instance, the whole volume as a derived CT series (a ZIP). They keep the study, frame of
//! reference and patient of the source series when there is one.

mod query;
mod render;
pub mod rgb;

pub use query::*;
pub use render::*;
