//! Analytic phantoms (2D ellipses, 3D ellipsoids), voxelisation and exact analytic projections.
//!
//! # Conventions
//! - Phantoms are defined in phantom units, the square [−1, 1]² or cube [−1, 1]³, and mapped to
//!   millimetres by `scale_mm` (millimetres per phantom unit, half the side of the field of view they
//!   cover): a point at `p` mm sits at `p / scale_mm` in phantom units. Values are μ (1/mm) and add
//!   where shapes overlap.
//! - 2D ([`Ellipse`]): the standard Shepp–Logan definition in ctrecon's frame (image rows grow with y):
//!   the `a` axis is turned by φ counter-clockwise from +x toward +y about the unrotated centre.
//! - 3D ([`Ellipsoid`]): the seed program `phantom3d`'s Euler matrix α(φ, θ, ψ), with its quirk that the
//!   centre is compared in the rotated frame: `p` is inside when `Σ_k ((α p)_k − c0_k)² / axis_k² ≤ 1`.
//! - Images are `[y][x]`, volumes `[z][y][x]`, 2D projections `[view][u]`, 3D projections `[view][v][u]`.
//! - Exact projections integrate μ along the whole line through the source (or along the ray direction of
//!   a parallel beam) and the detector element, with the chord formula of DESIGN §3 in f64: the phantom
//!   is assumed to lie between source and detector. Projection values are dimensionless.
//! - Rasterisation averages `s` point samples per pixel axis (`s²` per pixel, `s³` per voxel) spread
//!   evenly over the pixel; `s = 1` samples the centre, as the seed program does.

mod ellipse;
mod ellipsoid;
mod noise;
mod quadric;
mod spec;
mod tables;

pub use ellipse::{Ellipse, Phantom2};
pub use ellipsoid::{Ellipsoid, Phantom3, euler_matrix, seed_grid};
pub use noise::{MAX_INCIDENT_PHOTONS, poisson_noise};
pub use spec::{PhantomSpec, TableName};
pub use tables::{Table2, Table3};

use crate::recon::error::ReconError;

/// Most ellipses or ellipsoids a phantom accepts.
pub const MAX_BODIES: usize = 10_000;

fn finite_field(name: &'static str, what: &str, value: f64) -> Result<(), ReconError> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(ReconError::param(
            name,
            format!("{what} must be finite, got {value}"),
        ))
    }
}

fn positive_field(name: &'static str, what: &str, value: f64) -> Result<(), ReconError> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(ReconError::param(
            name,
            format!("{what} must be positive and finite, got {value}"),
        ))
    }
}

fn check_scale(scale_mm: f64) -> Result<(), ReconError> {
    positive_field("scale_mm", "`scale_mm`", scale_mm)
}

#[cfg(test)]
mod ellipsoid_tests;
#[cfg(test)]
mod tests;
