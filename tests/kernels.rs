//! The pure core's tests (one test binary, see `tests/test_binaries.rs`): analytic truth, projectors, iterative
//! methods, rendering, DICOM reading.

mod analytic_control;
mod analytic_fan_seed;
mod analytic_shepp_logan;
mod analytic_uniform;
mod cli_recon;
mod dicom_corpus;
mod dicom_lidc;
mod dicom_roundtrip;
mod iterative_convergence;
mod iterative_quality;
mod projector_adjoint;
mod projector_exact;
mod purity;
mod render_analytic;
mod render_cutaway;
mod render_orientation;
mod render_skipping;
mod render_vtk;
mod series_synthetic;
mod test_binaries;
