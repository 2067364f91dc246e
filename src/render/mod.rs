//! 3D pictures of a volume: volume rendering (VR), shaded surface display (SSD) and cut-away views, on the CPU.
//!
//! Everything is in patient space (LPS, millimetres) about the centre of the volume's box:
//! - [`Camera`]: named views (anterior: looking along +y with the patient's left on the image right and superior
//!   up; posterior, left, right, superior, inferior) turned by azimuth, elevation and roll, zoomed, orthographic
//!   (default) or perspective ([`ViewRays`] is one resolved camera);
//! - [`TransferFunction`]: piecewise-linear colour and opacity (opacity per millimetre) in the volume's units,
//!   with the [`Preset`]s bone, soft tissue (skin), CT angiography and lung in HU;
//! - [`Clip`]: clip planes (point and normal; the half-space the normal points into is kept) and clip boxes
//!   (axis-aligned or oriented; the inside or the outside is kept), applied before compositing;
//! - [`volume_render`]: front-to-back ray casting of trilinear samples every `step ≤ ½` of the smallest spacing,
//!   opacity corrected for the step (α' = 1 − (1 − α)^(Δ/1 mm)), gradient shading (central differences;
//!   ambient, diffuse, specular with a head light), early termination at accumulated α ≥ 0.99 and
//!   empty-space skipping over a min/max [`BrickGrid`] of 8³ voxels and, inside busy bricks, over the voxel
//!   cells whose eight corners all lie outside the transfer function's visible window (one bit a cell, built
//!   once per transfer function and kept by the [`Scene`]), a clear block of 2 × 2 × 2 such cells crossed in
//!   one jump;
//! - [`surface_render`]: the iso-surfaces crossed by each ray, each hit refined between samples by secant steps on
//!   the trilinear field, Phong shading with the gradient as normal and depth cueing; several iso-values with
//!   their own colours and opacities are composited front to back (a transparent skin over bone); a clip that
//!   cuts into the solid shows the cut face as a flat cap.
//!
//! Rays run in parallel over 32 × 32 pixel tiles (rayon); volume rendering keeps two rays in flight per
//! thread, one step of each in turn. The volume's min/max bricks are built once per volume, the cell occupancy
//! once per transfer function or set of iso-values, and both are shared by every frame of a rotating sequence.

mod bricks;
mod camera;
mod clip;
mod composite;
mod image;
mod occupancy;
mod sampler;
mod scene;
mod shading;
mod surface;
mod transfer;

pub use bricks::{BRICK, BrickGrid};
pub use camera::{
    Camera, DEFAULT_MAX_SIDE, NamedView, Projection, ViewRays, inside_box, volume_bounds,
};
pub use clip::{Clip, ClipBox, ClipPlane, Keep};
pub use composite::{VrOptions, volume_render, volume_render_frames};
pub use image::{RgbImage, encode_rgb_apng, encode_rgb_png};
pub use sampler::Sampler;
pub use scene::Scene;
pub use shading::Shading;
pub use surface::{SsdOptions, Surface, surface_render, surface_render_frames};
pub use transfer::{ControlPoint, Preset, TransferFunction};

/// A render request that cannot be honoured, with a stable code for the API catalogue.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    #[error("the transfer function has no control point")]
    EmptyTransferFunction,
    #[error("clip plane {0} has a zero or non-finite normal")]
    ZeroClipNormal(usize),
    #[error("invalid clip: {0}")]
    BadClip(String),
    #[error("the camera is inside the volume, which an orthographic projection cannot show")]
    CameraInsideVolume,
    #[error("invalid image size {width}×{height}: each side must be within 1..={max}")]
    BadSize {
        width: usize,
        height: usize,
        max: usize,
    },
    #[error("invalid render parameter `{name}`: {reason}")]
    InvalidParameter { name: &'static str, reason: String },
    #[error("the volume is empty or its frame is degenerate")]
    BadVolume,
    #[error("PNG encoding failed: {0}")]
    Encode(String),
}

impl RenderError {
    /// Stable code for the API error catalogue.
    pub fn code(&self) -> &'static str {
        match self {
            RenderError::EmptyTransferFunction => "empty_transfer_function",
            RenderError::ZeroClipNormal(_) | RenderError::BadClip(_) => "invalid_clip",
            RenderError::CameraInsideVolume => "camera_inside_volume",
            RenderError::BadSize { .. } => "invalid_render_size",
            RenderError::InvalidParameter { .. } => "invalid_parameter",
            RenderError::BadVolume => "invalid_parameter",
            RenderError::Encode(_) => "encoding_failed",
        }
    }
}

pub(crate) type V3 = [f64; 3];

pub(crate) fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub(crate) fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn axpy(a: V3, s: f64, b: V3) -> V3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}
pub(crate) fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
/// `a` scaled to unit length, `None` for a zero or non-finite vector.
pub(crate) fn unit(a: V3) -> Option<V3> {
    let n = norm(a);
    (n.is_finite() && n > 1e-12).then(|| a.map(|c| c / n))
}
