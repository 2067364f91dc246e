//! Where the markers must appear: the screen geometry of each kind of image, computed here from the
//! conventions the API documents (radiological display, MPR planes, rotating projections, cameras), not
//! read back from the images.

use ctrecon::volume::{Frame, direction_label};
use serde_json::{Value, json};

pub type V3 = [f64; 3];

pub fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
pub fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub fn axpy(a: V3, s: f64, b: V3) -> V3 {
    [a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2]]
}
pub fn unit(a: V3) -> V3 {
    let n = dot(a, a).sqrt();
    a.map(|c| c / n)
}

/// A vector of a JSON array.
pub fn v3(v: &Value) -> V3 {
    std::array::from_fn(|a| v[a].as_f64().unwrap_or_else(|| panic!("not a vector: {v}")))
}

pub fn close(a: V3, b: V3, tol: f64) -> bool {
    (0..3).all(|c| (a[c] - b[c]).abs() <= tol)
}

/// Screen sides as the API writes them, from the row (screen right) and column (screen down) directions.
pub fn sides(right: V3, down: V3) -> Value {
    let neg = |v: V3| v.map(|c| -c);
    json!({
        "left": direction_label(neg(right)),
        "right": direction_label(right),
        "top": direction_label(neg(down)),
        "bottom": direction_label(down),
    })
}

/// DICOM Patient Orientation of those sides: the directions of the rows and of the columns, H/F for S/I.
pub fn patient_orientation(right: V3, down: V3) -> [String; 2] {
    let hf = |s: String| s.replace('S', "H").replace('I', "F");
    [hf(direction_label(right)), hf(direction_label(down))]
}

/// Screen right and down of the radiological display: axial seen from the feet (patient left on the image
/// right, posterior down), coronal from the front (left on the right, inferior down), sagittal from the
/// patient's left (posterior on the right, inferior down).
pub fn radiological(axis: &str) -> (V3, V3) {
    match axis {
        "axial" => ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        "coronal" => ([1.0, 0.0, 0.0], [0.0, 0.0, -1.0]),
        "sagittal" => ([0.0, 1.0, 0.0], [0.0, 0.0, -1.0]),
        _ => panic!("{axis}"),
    }
}

/// The screen axes of an oblique MPR plane as documented: rows run as close to inferior as the normal allows
/// (posterior for planes within 25° of axial), and the normal is `right × down`.
pub fn oblique(normal: V3) -> (V3, V3) {
    let n = unit(normal);
    let down: V3 = if n[2].abs() > 0.9 {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, -1.0]
    };
    let v = unit(axpy(down, -dot(down, n), n));
    (cross(v, n), v)
}

/// A planar stack: `frames` images of `size` (columns, rows) pixels of `pixel` mm centred on `centre`,
/// `spacing` mm apart along the normal `right × down` and centred on the plane.
#[derive(Debug, Clone, Copy)]
pub struct Planar {
    pub centre: V3,
    pub right: V3,
    pub down: V3,
    pub pixel: f64,
    pub size: [usize; 2],
    pub frames: usize,
    pub spacing: f64,
}

impl Planar {
    pub fn normal(&self) -> V3 {
        cross(self.right, self.down)
    }
    /// Offset of frame `k` along the normal.
    pub fn shift(&self, k: usize) -> f64 {
        (k as f64 - (self.frames as f64 - 1.0) / 2.0) * self.spacing
    }
    /// Patient position of the first (top-left) pixel of frame `k`.
    pub fn first_pixel(&self, k: usize) -> V3 {
        let half_w = (self.size[0] as f64 - 1.0) / 2.0 * self.pixel;
        let half_h = (self.size[1] as f64 - 1.0) / 2.0 * self.pixel;
        let c = axpy(self.centre, self.shift(k), self.normal());
        axpy(axpy(c, -half_w, self.right), -half_h, self.down)
    }
    /// The frame nearest `p` and the distance of `p` from its plane.
    pub fn frame_of(&self, p: V3) -> (usize, f64) {
        let d = dot(sub(p, self.centre), self.normal());
        (0..self.frames)
            .map(|k| (k, (d - self.shift(k)).abs()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap()
    }
    /// Screen (row, column) of `p` projected on frame `k`.
    pub fn pixel_of(&self, p: V3, k: usize) -> (f64, f64) {
        let rel = sub(p, self.first_pixel(k));
        (
            dot(rel, self.down) / self.pixel,
            dot(rel, self.right) / self.pixel,
        )
    }
    /// The `plane` JSON of frame `k`, as a product or a PNG `ImagePlane` says it.
    pub fn assert_plane(&self, plane: &Value, k: usize, what: &str) {
        let ok = close(v3(&plane["first_pixel_mm"]), self.first_pixel(k), 1e-6)
            && close(v3(&plane["row_direction"]), self.right, 1e-9)
            && close(v3(&plane["column_direction"]), self.down, 1e-9)
            && (0..2).all(|a| (plane["pixel_mm"][a].as_f64().unwrap() - self.pixel).abs() < 1e-9);
        assert!(ok, "{what}: frame {k} is placed at {plane}, want {self:?}");
    }
}

/// The frames of a rotating projection: seen from `angle` degrees about the superior axis through the volume
/// centre (0: from the front, 90: from the patient's left), superior up, `pixel` mm pixels, the axis on the
/// middle column and the centre on the middle row.
#[derive(Debug, Clone, Copy)]
pub struct Turning {
    pub centre: V3,
    pub pixel: f64,
    pub rows: usize,
    pub cols: usize,
}

impl Turning {
    /// Screen right of the frame seen from `angle` degrees (down is inferior); also the anterior view of a
    /// rendering turned by `angle` degrees of azimuth.
    pub fn right(angle: f64) -> V3 {
        let (s, c) = angle.to_radians().sin_cos();
        [c, s, 0.0]
    }
    pub fn pixel_of(&self, p: V3, angle: f64) -> (f64, f64) {
        let rel = sub(p, self.centre);
        (
            (self.rows as f64 - 1.0) / 2.0 - rel[2] / self.pixel,
            (self.cols as f64 - 1.0) / 2.0 + dot(rel, Self::right(angle)) / self.pixel,
        )
    }
}

/// Centre of a volume's box and the radius of its bounding sphere, from its corner samples.
pub fn bounds(frame: &Frame, dim: (usize, usize, usize)) -> (V3, f64) {
    let corners = frame.corners(dim);
    let centre: V3 = std::array::from_fn(|a| corners.iter().map(|p| p[a]).sum::<f64>() / 8.0);
    let r = corners
        .iter()
        .map(|p| dot(sub(*p, centre), sub(*p, centre)).sqrt())
        .fold(0.0, f64::max);
    (centre, r)
}

/// Screen (row, column) of `p` in an orthographic view of `width × height` pixels at zoom 1 with screen
/// `right` and superior up (the anterior view turned about the superior axis): the bounding sphere fills the
/// shorter side.
pub fn rendered(
    frame: &Frame,
    dim: (usize, usize, usize),
    size: [usize; 2],
    right: V3,
    p: V3,
) -> (f64, f64) {
    let (centre, r) = bounds(frame, dim);
    let pixel = 2.0 * r / size[0].min(size[1]) as f64;
    let rel = sub(p, centre);
    (
        (size[1] as f64 - 1.0) / 2.0 - rel[2] / pixel,
        (size[0] as f64 - 1.0) / 2.0 + dot(rel, right) / pixel,
    )
}
