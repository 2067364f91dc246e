//! Iterative reconstruction (ART, SART, OS-SART, SIRT, CGLS, MLEM/OSEM, TV) over the matched projector
//! pair of [`crate::recon::projector`].

pub mod params;
