//! Rendered views keep the patient's directions: a marker phantom (balls at known LPS points) seen from every
//! named view puts each marker on the side of the image the radiological convention says, whatever the order
//! in which the volume's samples are stored.

use ctrecon::render::{
    Camera, Clip, ControlPoint, NamedView, RgbImage, Scene, Shading, TransferFunction, VrOptions,
    volume_render,
};
use ctrecon::volume::{Frame, Volume};
use ndarray::{Array3, Axis};

/// Where the markers sit (mm, LPS): at the patient's left, anterior, superior.
const MARKERS: [[f64; 3]; 3] = [[30.0, 0.0, 0.0], [0.0, -30.0, 0.0], [0.0, 0.0, 30.0]];

/// A 6 mm ball of value 1 at marker `m` (one marker a volume, so that no marker hides another).
fn phantom(m: usize) -> Volume {
    let n = 49;
    let frame = Frame {
        spacing_mm: [1.5; 3],
        origin_mm: [-36.0; 3],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        let p = frame.position(k as f64, j as f64, i as f64);
        let inside = (0..3).map(|a| (p[a] - MARKERS[m][a]).powi(2)).sum::<f64>() < 36.0;
        if inside { 1.0 } else { 0.0 }
    });
    Volume { data, frame }
}

/// The same patient stored feet-first and prone: slices, rows and columns all reversed.
fn reversed(vol: &Volume) -> Volume {
    let mut data = vol.data.clone();
    for a in 0..3 {
        data.invert_axis(Axis(a));
    }
    let (nz, ny, nx) = vol.data.dim();
    let f = vol.frame;
    let far = f.position((nz - 1) as f64, (ny - 1) as f64, (nx - 1) as f64);
    Volume {
        data: data.as_standard_layout().into_owned(),
        frame: Frame {
            origin_mm: far,
            direction: f.direction.map(|d| d.map(|c| -c)),
            ..f
        },
    }
}

/// The marker white and opaque, the rest transparent.
fn options() -> VrOptions {
    let p = |value: f64| ControlPoint {
        value,
        color: [1.0; 3],
        opacity: if value > 0.45 { 1.0 } else { 0.0 },
    };
    VrOptions {
        transfer_function: TransferFunction {
            points: vec![p(0.0), p(0.4999), p(0.5), p(1.0)],
        },
        shading: Shading::FLAT,
        clip: Clip::default(),
        background: [0.0; 3],
        step_mm: None,
    }
}

/// Centroid (row, column) of the lit pixels, relative to the image centre; `None` if the marker is not seen.
fn centroid(img: &RgbImage) -> Option<(f64, f64)> {
    let (mut sr, mut sc, mut n) = (0.0, 0.0, 0.0);
    for r in 0..img.height {
        for c in 0..img.width {
            if img.pixel(r, c)[0] > 128 {
                sr += r as f64;
                sc += c as f64;
                n += 1.0;
            }
        }
    }
    let mid = (img.width as f64 - 1.0) / 2.0;
    (n > 0.0).then(|| (sr / n - mid, sc / n - mid))
}

/// Where each marker must appear, as (screen right, screen up) in units of its 30 mm offset:
/// `[left marker, anterior marker, superior marker]`.
fn expected(view: NamedView) -> [(f64, f64); 3] {
    match view {
        // From the front: the patient's left on the image right, superior up.
        NamedView::Anterior => [(1.0, 0.0), (0.0, 0.0), (0.0, 1.0)],
        // From behind: the patient's left on the image left.
        NamedView::Posterior => [(-1.0, 0.0), (0.0, 0.0), (0.0, 1.0)],
        // From the patient's left: anterior on the image left (as a sagittal image).
        NamedView::Left => [(0.0, 0.0), (-1.0, 0.0), (0.0, 1.0)],
        NamedView::Right => [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)],
        // From above: anterior up, the patient's left on the image left.
        NamedView::Superior => [(-1.0, 0.0), (0.0, 1.0), (0.0, 0.0)],
        // From the feet (as an axial image): anterior up, the patient's left on the image right.
        NamedView::Inferior => [(1.0, 0.0), (0.0, 1.0), (0.0, 0.0)],
    }
}

#[test]
fn every_named_view_puts_the_markers_where_the_radiological_convention_says() {
    for m in 0..3 {
        for stored in [phantom(m), reversed(&phantom(m))] {
            let scene = Scene::new(&stored).unwrap();
            for view in NamedView::ALL {
                let cam = Camera {
                    view,
                    ..Camera::default()
                };
                let rays = cam
                    .rays(&stored.frame, stored.data.dim(), 101, 101, 4096)
                    .unwrap();
                let img = volume_render(&scene, &rays, &options()).unwrap();
                let offset_px = 30.0 / rays.pixel;
                let (right, up) = expected(view)[m];
                let (row, col) =
                    centroid(&img).unwrap_or_else(|| panic!("{view:?}: marker {} not seen", m + 1));
                assert!(
                    (col - right * offset_px).abs() < 1.0 && (-row - up * offset_px).abs() < 1.0,
                    "{view:?}: marker {} at (row {row:.1}, col {col:.1}) from the centre, want right {:.1} up {:.1}",
                    m + 1,
                    right * offset_px,
                    up * offset_px
                );
            }
        }
    }
}

#[test]
fn azimuth_turns_the_anterior_view_into_the_left_view_and_elevation_looks_down_from_above() {
    let render = |m: usize, cam: Camera| {
        let vol = phantom(m);
        let scene = Scene::new(&vol).unwrap();
        let rays = cam.rays(&vol.frame, vol.data.dim(), 64, 64, 4096).unwrap();
        volume_render(&scene, &rays, &options()).unwrap()
    };
    for m in 0..3 {
        let turned = centroid(&render(
            m,
            Camera {
                azimuth_deg: 90.0,
                ..Camera::default()
            },
        ));
        let left = centroid(&render(
            m,
            Camera {
                view: NamedView::Left,
                ..Camera::default()
            },
        ));
        let (a, b) = (turned.unwrap(), left.unwrap());
        assert!(
            (a.0 - b.0).abs() < 0.01 && (a.1 - b.1).abs() < 0.01,
            "marker {m}: {a:?} vs {b:?}"
        );
    }
    // Elevation 90° from the front looks down from the head with posterior up: the anterior marker is low.
    let above = Camera {
        elevation_deg: 90.0,
        ..Camera::default()
    };
    let (row, col) = centroid(&render(1, above)).unwrap();
    assert!(
        row > 10.0 && col.abs() < 1.0,
        "anterior marker at ({row}, {col})"
    );
    let (_, col) = centroid(&render(0, above)).unwrap();
    assert!(
        col > 10.0,
        "the patient's left stays on the image right: {col}"
    );
}
