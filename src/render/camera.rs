//! The camera: where rays start and where they go, in patient space (LPS, mm), about the centre of the volume.
//!
//! Screen axes of the named views (radiological convention, DESIGN §2):
//!
//! | view      | looks along | image right      | image up          |
//! |-----------|-------------|------------------|-------------------|
//! | anterior  | +y          | patient left +x  | superior +z       |
//! | posterior | −y          | patient right −x | superior +z       |
//! | left      | −x          | posterior +y     | superior +z       |
//! | right     | +x          | anterior −y      | superior +z       |
//! | superior  | −z          | patient right −x | anterior −y       |
//! | inferior  | +z          | patient left +x  | anterior −y       |
//!
//! From the named view the camera turns by `azimuth_deg` about the image-up axis (anterior + 90° is the left
//! view), then by `elevation_deg` about the image-right axis (positive: the viewer rises towards image up, so
//! anterior + 90° looks down from above), then by `roll_deg` about the viewing direction (positive turns the
//! picture counter-clockwise on screen).

use serde::{Deserialize, Serialize};

use super::{RenderError, V3, axpy, cross, dot, unit};
use crate::volume::{Frame, ImagePlane, ScreenSides};

/// Largest side of a rendered image (pixels) unless configured otherwise.
pub const DEFAULT_MAX_SIDE: usize = 4096;

/// A named viewing direction (see the module table).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NamedView {
    #[default]
    Anterior,
    Posterior,
    Left,
    Right,
    Superior,
    Inferior,
}

impl NamedView {
    pub const ALL: [NamedView; 6] = [
        NamedView::Anterior,
        NamedView::Posterior,
        NamedView::Left,
        NamedView::Right,
        NamedView::Superior,
        NamedView::Inferior,
    ];
    /// `(forward, right, up)` unit vectors in LPS.
    pub fn axes(self) -> (V3, V3, V3) {
        match self {
            NamedView::Anterior => ([0., 1., 0.], [1., 0., 0.], [0., 0., 1.]),
            NamedView::Posterior => ([0., -1., 0.], [-1., 0., 0.], [0., 0., 1.]),
            NamedView::Left => ([-1., 0., 0.], [0., 1., 0.], [0., 0., 1.]),
            NamedView::Right => ([1., 0., 0.], [0., -1., 0.], [0., 0., 1.]),
            NamedView::Superior => ([0., 0., -1.], [-1., 0., 0.], [0., -1., 0.]),
            NamedView::Inferior => ([0., 0., 1.], [1., 0., 0.], [0., -1., 0.]),
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            NamedView::Anterior => "anterior",
            NamedView::Posterior => "posterior",
            NamedView::Left => "left",
            NamedView::Right => "right",
            NamedView::Superior => "superior",
            NamedView::Inferior => "inferior",
        }
    }
}

/// Parallel rays (default) or rays from one eye point.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Projection {
    #[default]
    Orthographic,
    Perspective,
}

fn one() -> f64 {
    1.0
}

/// A camera about the volume centre. JSON: `{"view": "anterior", "azimuth_deg": 30, "elevation_deg": 10,
/// "roll_deg": 0, "zoom": 1.5, "projection": "perspective", "fov_deg": 30, "distance_mm": 600}`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    #[serde(default)]
    pub view: NamedView,
    #[serde(default)]
    pub azimuth_deg: f64,
    #[serde(default)]
    pub elevation_deg: f64,
    #[serde(default)]
    pub roll_deg: f64,
    /// Magnification: 1 fits the volume's bounding sphere in the shorter image side.
    #[serde(default = "one")]
    pub zoom: f64,
    #[serde(default)]
    pub projection: Projection,
    /// Perspective: full opening angle across the shorter image side at zoom 1 (default 30°).
    #[serde(default)]
    pub fov_deg: Option<f64>,
    /// Distance from the volume centre to the eye (mm). Default: orthographic 2 R, perspective R / sin(fov/2),
    /// with R the radius of the volume's bounding sphere. Orthographic rays start on the plane through the eye.
    #[serde(default)]
    pub distance_mm: Option<f64>,
}

impl Default for Camera {
    fn default() -> Self {
        Self {
            view: NamedView::Anterior,
            azimuth_deg: 0.0,
            elevation_deg: 0.0,
            roll_deg: 0.0,
            zoom: 1.0,
            projection: Projection::Orthographic,
            fov_deg: None,
            distance_mm: None,
        }
    }
}

/// The centre of a volume's box and the radius of its bounding sphere (mm), from the corner voxel centres.
pub fn volume_bounds(frame: &Frame, dim: (usize, usize, usize)) -> (V3, f64) {
    let c = frame.corners(dim);
    let centre: V3 = std::array::from_fn(|a| c.iter().map(|p| p[a]).sum::<f64>() / 8.0);
    let r = c
        .iter()
        .map(|p| super::norm([p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]]))
        .fold(0.0, f64::max);
    (centre, r.max(1e-6))
}

/// A resolved camera: the ray of every pixel of a `width × height` image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ViewRays {
    pub width: usize,
    pub height: usize,
    pub forward: V3,
    pub right: V3,
    pub up: V3,
    pub eye: V3,
    pub projection: Projection,
    /// Orthographic: pixel size (mm). Perspective: pixel size on the plane one millimetre from the eye.
    pub pixel: f64,
}

fn rotate(v: V3, axis: V3, deg: f64) -> V3 {
    // Rodrigues: v cos + (k × v) sin + k (k·v)(1 − cos).
    let (s, c) = deg.to_radians().sin_cos();
    let kv = cross(axis, v);
    let kd = dot(axis, v);
    std::array::from_fn(|i| v[i] * c + kv[i] * s + axis[i] * kd * (1.0 - c))
}

impl Camera {
    /// Checks that need no volume.
    pub fn validate(&self) -> Result<(), RenderError> {
        let bad = |name, reason: &str| {
            Err(RenderError::InvalidParameter {
                name,
                reason: reason.into(),
            })
        };
        if ![self.azimuth_deg, self.elevation_deg, self.roll_deg]
            .iter()
            .all(|a| a.is_finite())
        {
            return bad("camera", "angles must be finite");
        }
        if !(self.zoom.is_finite() && self.zoom > 0.0 && self.zoom <= 100.0) {
            return bad("zoom", "must be in (0, 100]");
        }
        if let Some(f) = self.fov_deg
            && !(f.is_finite() && f > 0.0 && f < 170.0)
        {
            return bad("fov_deg", "must be in (0, 170)");
        }
        if let Some(d) = self.distance_mm
            && !(d.is_finite() && d > 0.0)
        {
            return bad("distance_mm", "must be finite and positive");
        }
        Ok(())
    }

    /// `(forward, right, up)` after the named view, azimuth, elevation and roll.
    pub fn axes(&self) -> (V3, V3, V3) {
        let (f, r, u) = self.view.axes();
        let (f, r) = (
            rotate(f, u, self.azimuth_deg),
            rotate(r, u, self.azimuth_deg),
        );
        let (f, u) = (
            rotate(f, r, -self.elevation_deg),
            rotate(u, r, -self.elevation_deg),
        );
        let (r, u) = (rotate(r, f, self.roll_deg), rotate(u, f, self.roll_deg));
        (f, r, u)
    }

    fn half_fov(&self) -> f64 {
        self.fov_deg.unwrap_or(30.0).to_radians() / 2.0
    }

    /// The eye point (mm) for a volume of bounding sphere (`centre`, `radius`).
    pub fn eye(&self, centre: V3, radius: f64) -> V3 {
        let (f, _, _) = self.axes();
        let d = self.distance_mm.unwrap_or(match self.projection {
            Projection::Orthographic => 2.0 * radius,
            Projection::Perspective => radius / self.half_fov().sin(),
        });
        axpy(centre, -d, f)
    }

    /// Resolve the camera for a volume (`frame`, `dim`) and an image of `width × height` pixels (each side in
    /// `1..=max_side`). An orthographic eye inside the volume's box is refused.
    pub fn rays(
        &self,
        frame: &Frame,
        dim: (usize, usize, usize),
        width: usize,
        height: usize,
        max_side: usize,
    ) -> Result<ViewRays, RenderError> {
        if width == 0 || height == 0 || width > max_side || height > max_side {
            return Err(RenderError::BadSize {
                width,
                height,
                max: max_side,
            });
        }
        self.validate()?;
        let (centre, radius) = volume_bounds(frame, dim);
        let eye = self.eye(centre, radius);
        if self.projection == Projection::Orthographic && inside_box(frame, dim, eye) {
            return Err(RenderError::CameraInsideVolume);
        }
        let (forward, right, up) = self.axes();
        let short = width.min(height) as f64;
        let pixel = match self.projection {
            Projection::Orthographic => 2.0 * radius / (self.zoom * short),
            Projection::Perspective => 2.0 * self.half_fov().tan() / (self.zoom * short),
        };
        Ok(ViewRays {
            width,
            height,
            forward,
            right,
            up,
            eye,
            projection: self.projection,
            pixel,
        })
    }
}

/// True when `p` lies inside the box of the volume's voxel centres.
pub fn inside_box(frame: &Frame, dim: (usize, usize, usize), p: V3) -> bool {
    let Some(map) = frame.index_map() else {
        return false;
    };
    let idx = map.index(p);
    let n = [dim.0, dim.1, dim.2];
    (0..3).all(|a| idx[a] >= 0.0 && idx[a] <= n[a].saturating_sub(1) as f64)
}

impl ViewRays {
    /// Origin and unit direction of the ray through the centre of pixel (`row`, `col`).
    pub fn ray(&self, row: f64, col: f64) -> (V3, V3) {
        let x = (col - (self.width as f64 - 1.0) / 2.0) * self.pixel;
        let y = ((self.height as f64 - 1.0) / 2.0 - row) * self.pixel;
        match self.projection {
            Projection::Orthographic => (
                axpy(axpy(self.eye, x, self.right), y, self.up),
                self.forward,
            ),
            Projection::Perspective => {
                let d = axpy(axpy(self.forward, x, self.right), y, self.up);
                (self.eye, unit(d).unwrap_or(self.forward))
            }
        }
    }

    /// Pixel (`row`, `col`) where patient point `p` is seen (the inverse of [`ViewRays::ray`]); `None` behind
    /// a perspective eye.
    pub fn project(&self, p: V3) -> Option<(f64, f64)> {
        let d = [p[0] - self.eye[0], p[1] - self.eye[1], p[2] - self.eye[2]];
        let (mut x, mut y) = (dot(d, self.right), dot(d, self.up));
        if self.projection == Projection::Perspective {
            let z = dot(d, self.forward);
            if z <= 0.0 {
                return None;
            }
            x /= z;
            y /= z;
        }
        Some((
            (self.height as f64 - 1.0) / 2.0 - y / self.pixel,
            x / self.pixel + (self.width as f64 - 1.0) / 2.0,
        ))
    }

    /// The patient directions at the screen sides.
    pub fn sides(&self) -> ScreenSides {
        self.screen_plane().sides()
    }

    /// A plane with the image's row and column directions (for orientation labels; its position is the eye).
    pub fn screen_plane(&self) -> ImagePlane {
        ImagePlane {
            first_pixel_mm: self.eye,
            row_direction: self.right,
            column_direction: self.up.map(|c| -c),
            pixel_mm: [self.pixel; 2],
        }
    }

    /// A short description of the camera, for image labels.
    pub fn describe(&self, cam: &Camera) -> String {
        format!(
            "{} view, azimuth {}°, elevation {}°, roll {}°, zoom {}, {}",
            cam.view.name(),
            cam.azimuth_deg,
            cam.elevation_deg,
            cam.roll_deg,
            cam.zoom,
            match cam.projection {
                Projection::Orthographic => "orthographic",
                Projection::Perspective => "perspective",
            }
        )
    }
}
