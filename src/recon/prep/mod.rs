//! Preprocessing and automatic calibration of measured projections (DESIGN §11): the steps between what a
//! scanner writes (counts, with darks and flats) and what the reconstruction algorithms read (line
//! integrals on a calibrated geometry).
//!
//! Every step is a named, parameterised value (serde, `deny_unknown_fields`) so that a dataset can record
//! it in its provenance, and works on one view at a time (`[v][u]`, rows along u) so that a scan is
//! streamed view by view; only stripe suppression needs a sinogram (`[view][u]`, one detector row).
//!
//! - [`normalise`]: dark/flat normalisation, −ln, clamping with a count; white-level input (Nikon).
//! - [`pixels`]: dead and hot pixels found in a flat or dark and repaired from valid neighbours.
//! - [`reshape`]: binning, cropping (with the panel they imply) and angle subsets.
//! - [`stripes`]: ring suppression in the sinogram (Vo's sorting-based filter).
//! - [`hardening`]: beam-hardening linearisation by a polynomial.
//! - [`plan`]: the optional steps a user asks for, as one value applied and recorded in one order.
//! - [`centre`]: the detector u offset (centre of rotation) and in-plane tilt, from opposite views of a
//!   full turn; [`conjugate`]: the u offset of any scan of at least π + fan angle from the consistency of
//!   conjugate rays in the mid-plane.
//!
//! # Sign conventions
//! - The u offset found is the value [`Panel::offset_u_mm`](crate::recon::geometry::Panel) must hold for
//!   the data: the rotation axis projects onto the detector column `(nu − 1)/2 − offset_u_mm/du_mm`.
//! - The tilt is the roll of the panel's u and v axes about the central ray, counter-clockwise seen from
//!   the source (at β = 0, u points to +x and v to +z; a roll θ turns u toward v):
//!   `u' = u cos θ + v sin θ`, `v' = v cos θ − u sin θ`. The rotation axis then projects onto the line
//!   `u = v · tan θ` of the rolled panel ([`views::roll_views`]).

pub mod centre;
pub mod conjugate;
pub mod hardening;
pub mod normalise;
pub mod pixels;
pub mod plan;
pub mod reshape;
pub mod stripes;
pub mod views;

pub use centre::{
    CentreEstimate, CentreMethod, CentreOptions, apply_to_cone, apply_to_views, find_centre,
};
pub use conjugate::{ConjugateOptions, find_centre_conjugate};
pub use hardening::Linearise;
pub use normalise::{FlatField, Normalise, average_frames};
pub use pixels::{RepairPixels, find_outliers, repair_pixels};
pub use plan::PrepPlan;
pub use reshape::{AngleSubset, Bin, Crop};
pub use stripes::SortingStripeFilter;
pub use views::{ViewSource, roll_views};

#[cfg(test)]
mod centre_tests;
#[cfg(test)]
mod plan_tests;
#[cfg(test)]
mod scan_tests;
#[cfg(test)]
mod tests;
