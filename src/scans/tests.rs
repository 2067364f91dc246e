//! Unit tests of the metadata parsers and of each vendor's geometry mapping: an off-centre point must land
//! on the image pixel the vendor's convention (as CIL reads it for Nikon and Zeiss) says.

use std::path::Path;

use super::convert::shift_image;
use super::ini::Ini;
use super::{Orientation, bruker, nikon, sort_naturally, view_number, zeiss};
use crate::recon::geometry::vectors::{add3, cross3, dot3, scale3, sub3};
use crate::recon::geometry::{Geometry, Vec3, Views3};

/// Where point `q` (mm, ctrecon's frame) lands on view `i`: fractional `(row, column)` of ctrecon's
/// detector.
fn project(views: &Views3, i: usize, q: Vec3) -> (f64, f64) {
    let w = &views.views[i];
    let n = cross3(w.det_u, w.det_v);
    let d = sub3(q, w.source);
    let t = dot3(sub3(w.det_centre, w.source), n) / dot3(d, n);
    let x = sub3(add3(w.source, scale3(d, t)), w.det_centre);
    (
        views.detector.row_of(dot3(x, w.det_v)),
        views.detector.col_of(dot3(x, w.det_u)),
    )
}

/// ctrecon's `(row, column)` as the stored image's.
fn to_image(o: Orientation, nv: usize, nu: usize, (r, c): (f64, f64)) -> (f64, f64) {
    (
        if o.flip_rows { nv as f64 - 1.0 - r } else { r },
        if o.flip_cols { nu as f64 - 1.0 - c } else { c },
    )
}

fn rot_z(a: f64, p: Vec3) -> Vec3 {
    let (s, c) = a.sin_cos();
    [c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]]
}

fn views(g: &Geometry) -> Views3 {
    let Ok(crate::recon::geometry::Views::D3(v)) = g.to_views() else {
        panic!("a cone beam")
    };
    v
}

const XTEK: &str = "[XTekCT]
Name=ball
Units=mm
Projections=8
DetectorPixelsX=64
DetectorPixelsY=48
DetectorPixelSizeX=0.2
DetectorPixelSizeY=0.25
SrcToObject=100
SrcToDetector=400
InitialAngle=30
AngularStep=45
ObjectOffsetX=0.3
DetectorOffsetX=0.5
DetectorOffsetY=-0.75
WhiteLevel=60000
";

/// The image pixel `(row, column)` where CIL's model of a Nikon scan puts point `q` (CIL's frame, origin on
/// the rotation axis) at Nikon angle `a_deg`: `NikonDataReader`'s system (source `(0, −SOD)`, axis
/// `(−ox, 0)`, detector `(−DetectorOffsetX, SDD − SOD, DetectorOffsetY)`, panel origin top-right, CIL angle
/// `θ = 180° − a`) turned by `−θ` as CIL's ASTRA conversion does.
fn cil_nikon_pixel(x: &nikon::Xtek, a_deg: f64, q: Vec3) -> (f64, f64) {
    let ox = x.object_offset_x_mm;
    let (sod, sdd) = (x.src_to_object_mm, x.src_to_detector_mm);
    let src0 = [ox, -sod, 0.0];
    let det0 = [
        ox - x.detector_offset_x_mm,
        sdd - sod,
        x.detector_offset_y_mm,
    ];
    let row0 = [-x.pixel_x_mm, 0.0, 0.0]; // one column step (panel origin on the right)
    let col0 = [0.0, 0.0, -x.pixel_y_mm]; // one row step (panel origin at the top)
    let theta = (180.0 - a_deg).to_radians();
    let [s, d, u, v] = [src0, det0, row0, col0].map(|p| rot_z(-theta, p));
    // s + t (q − s) = d + a u + b v
    let dir = sub3(q, s);
    let n = cross3(u, v);
    let t = dot3(sub3(d, s), n) / dot3(dir, n);
    let hit = sub3(add3(s, scale3(dir, t)), d);
    let a = dot3(hit, u) / dot3(u, u);
    let b = dot3(hit, v) / dot3(v, v);
    (
        b + x.pixels_y as f64 / 2.0 - 0.5,
        a + x.pixels_x as f64 / 2.0 - 0.5,
    )
}

#[test]
fn an_off_centre_point_lands_where_cil_puts_it_on_a_nikon_scan() {
    let mut ini = Ini::parse(Path::new("ball.xtekct"), XTEK);
    let x = nikon::parse(&mut ini).expect("parse");
    let g = nikon::geometry(&x, None);
    let v = views(&g);
    // CIL's frame has the source beside the line through the axis; ctrecon's is CIL's turned by φ.
    let phi = (x.object_offset_x_mm / x.src_to_object_mm).atan();
    for q in [[1.0, -0.6, 0.8], [-0.9, 1.1, -0.7], [0.0, 0.0, 0.0]] {
        for i in 0..x.projections {
            let a = x.initial_angle_deg + i as f64 * x.angular_step_deg;
            let want = cil_nikon_pixel(&x, a, q);
            let got = to_image(Orientation::TURNED, 48, 64, project(&v, i, rot_z(-phi, q)));
            assert!(
                (got.0 - want.0).abs() < 0.01 && (got.1 - want.1).abs() < 0.01,
                "view {i} (Nikon angle {a}°), point {q:?}: ctrecon puts it at image {got:?}, CIL at {want:?}"
            );
        }
    }
}

#[test]
fn a_wrong_sign_of_the_nikon_object_offset_moves_the_point_by_pixels() {
    let mut ini = Ini::parse(Path::new("ball.xtekct"), XTEK);
    let x = nikon::parse(&mut ini).expect("parse");
    let mut wrong = x.clone();
    wrong.object_offset_x_mm = -x.object_offset_x_mm;
    let v = views(&nikon::geometry(&wrong, None));
    let want = cil_nikon_pixel(&x, x.initial_angle_deg, [1.0, -0.6, 0.8]);
    let got = to_image(
        Orientation::TURNED,
        48,
        64,
        project(&v, 0, [1.0, -0.6, 0.8]),
    );
    assert!((got.1 - want.1).abs() > 5.0, "{got:?} vs {want:?}");
}

#[test]
fn nikon_angle_lists_give_the_same_views_as_the_step() {
    let mut ini = Ini::parse(Path::new("ball.xtekct"), XTEK);
    let x = nikon::parse(&mut ini).expect("parse");
    let list: Vec<f64> = (0..8).map(|i| 30.0 + 45.0 * i as f64).collect();
    let a = views(&nikon::geometry(&x, None));
    let b = views(&nikon::geometry(&x, Some(&list)));
    for (p, q) in a.views.iter().zip(&b.views) {
        for k in 0..3 {
            assert!((p.source[k] - q.source[k]).abs() < 1e-9);
        }
    }
}

#[test]
fn nikon_angle_files_parse_both_layouts() {
    let ctdata = "Tomography data\nProjection\tAngle(deg)\tAngle(rad)\n\n1\t0.000000\t0.0\n2\t0.500000\t0.0087\n";
    assert_eq!(nikon::parse_angle_rows(ctdata), vec![(1, 0.0), (2, 0.5)]);
    let ang = "Angles\nProjection 1: 10.5\nProjection 2: 11.0\n";
    assert_eq!(nikon::parse_angle_rows(ang), vec![(1, 10.5), (2, 11.0)]);
}

#[test]
fn nikon_keys_that_are_missing_or_not_numbers_are_named() {
    let text = XTEK.replace("SrcToObject=100\n", "");
    let e = nikon::parse(&mut Ini::parse(Path::new("a.xtekct"), &text)).unwrap_err();
    let msg = e.to_string();
    assert!(
        msg.contains("a.xtekct") && msg.contains("SrcToObject"),
        "{msg}"
    );
    let text = XTEK.replace("AngularStep=45", "AngularStep=fast");
    let msg = nikon::parse(&mut Ini::parse(Path::new("a.xtekct"), &text))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("AngularStep") && msg.contains("fast"), "{msg}");
    let text = XTEK.replace("Projections=8", "Projections=-3");
    let msg = nikon::parse(&mut Ini::parse(Path::new("a.xtekct"), &text))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("Projections"), "{msg}");
    let text = XTEK.replace("Units=mm", "Units=inch");
    let msg = nikon::parse(&mut Ini::parse(Path::new("a.xtekct"), &text))
        .unwrap_err()
        .to_string();
    assert!(msg.contains("Units"), "{msg}");
}

#[test]
fn an_old_nikon_file_gives_the_object_offset_from_the_centre_of_rotation() {
    let text = XTEK.replace(
        "ObjectOffsetX=0.3",
        "CentreOfRotationTop=1.2\nCentreOfRotationBottom=1.2",
    );
    let x = nikon::parse(&mut Ini::parse(Path::new("a.xtekct"), &text)).expect("parse");
    assert!((x.object_offset_x_mm - 0.3).abs() < 1e-12);
}

const LOG: &str = "[System]
Scanner=Skyscan1172
Camera Pixel Size (um)=  11.32
[Acquisition]
Filename Prefix=ball_
Number of Files=  12
Number of Rows=  40
Number of Columns=  56
Image Pixel Size (um)=  50.0
Object to Source (mm)=120.0
Camera to Source (mm)=360.0
Optical Axis (line)= 23
Rotation Step (deg)=15.0
Use 360 Rotation=YES
Depth (bits)=16
Flat Field Correction=ON
[Reconstruction]
Post alignment=1.5
";

#[test]
fn a_point_in_the_orbit_plane_lands_on_the_skyscan_optical_axis_line() {
    let mut ini = Ini::parse(Path::new("ball_.log"), LOG);
    let l = bruker::parse(&mut ini).expect("parse");
    assert!((l.detector_pixel_mm - 0.15).abs() < 1e-12);
    let v = views(&bruker::geometry(&l));
    assert_eq!(v.views.len(), 12);
    for i in 0..12 {
        let (row, _) = to_image(
            Orientation::TURNED,
            40,
            56,
            project(&v, i, [3.0, -2.0, 0.0]),
        );
        assert!((row - 23.0).abs() < 1e-9, "view {i}: row {row}");
        // Above the orbit plane is above the optical axis line in the image.
        let (row, _) = to_image(
            Orientation::TURNED,
            40,
            56,
            project(&v, i, [3.0, -2.0, 1.0]),
        );
        assert!(row < 23.0 - 5.0, "view {i}: row {row}");
    }
    assert!(l.notes.iter().any(|n| n.contains("Post alignment")));
}

#[test]
fn skyscan_keys_that_are_missing_or_not_numbers_are_named() {
    let text = LOG.replace("Object to Source (mm)=120.0\n", "");
    let msg = bruker::parse(&mut Ini::parse(Path::new("s.log"), &text))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("s.log") && msg.contains("Object to Source (mm)"),
        "{msg}"
    );
    let text = LOG.replace("Number of Rows=  40", "Number of Rows=  forty");
    let msg = bruker::parse(&mut Ini::parse(Path::new("s.log"), &text))
        .unwrap_err()
        .to_string();
    assert!(
        msg.contains("Number of Rows") && msg.contains("forty"),
        "{msg}"
    );
}

#[test]
fn a_point_above_the_orbit_lands_above_the_centre_of_a_stack_image() {
    let g: Geometry = serde_json::from_str(
        r#"{"type": "cone", "angles": {"count": 4}, "dso_mm": 100, "dsd_mm": 200,
            "detector": {"nu": 32, "nv": 32, "du_mm": 1, "dv_mm": 1}}"#,
    )
    .expect("geometry");
    let v = views(&g);
    let (row, col) = to_image(
        Orientation::ROWS_UP,
        32,
        32,
        project(&v, 0, [5.0, 0.0, 5.0]),
    );
    // Magnification 2: 10 mm = 10 pixels up (smaller row) and, at β = 0, 10 pixels toward +u (right).
    assert!((row - (15.5 - 10.0)).abs() < 1e-9, "{row}");
    assert!((col - (15.5 + 10.0)).abs() < 1e-9, "{col}");
}

#[test]
fn orientation_turns_an_image_and_back() {
    let image: Vec<f32> = (0..6).map(|x| x as f32).collect();
    let mut out = vec![0f32; 6];
    Orientation::TURNED.apply(&image, 2, 3, &mut out);
    assert_eq!(out, [5.0, 4.0, 3.0, 2.0, 1.0, 0.0]);
    Orientation::ROWS_UP.apply(&image, 2, 3, &mut out);
    assert_eq!(out, [3.0, 4.0, 5.0, 0.0, 1.0, 2.0]);
}

#[test]
fn views_sort_by_the_number_in_their_names() {
    assert_eq!(view_number("ball_0012.tif"), Some(12));
    assert_eq!(view_number("p7x.tiff"), Some(7));
    assert_eq!(view_number("none.tif"), None);
    let mut files: Vec<std::path::PathBuf> = ["p_10.tif", "p_9.tif", "p_100.tif", "p_1.tif"]
        .iter()
        .map(Into::into)
        .collect();
    sort_naturally(&mut files);
    let names: Vec<_> = files
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["p_1.tif", "p_9.tif", "p_10.tif", "p_100.tif"]);
}

/// A Zeiss scan as read: 7 views at uneven angles, source 20 mm and detector 60 mm from the axis, 5 µm pixels
/// at the object (20 µm on the panel), 64 × 48.
fn xradia() -> zeiss::Xradia {
    zeiss::Xradia {
        views: 7,
        width: 64,
        height: 48,
        sample: zeiss::Sample::U16,
        angles_deg: vec![-170.0, -100.0, -35.0, 0.0, 10.0, 90.0, 170.0],
        source_to_axis_mm: 20.0,
        detector_to_axis_mm: 60.0,
        pixel_um: 5.0,
        shifts: None,
        reference: None,
        notes: Vec::new(),
    }
}

/// The image pixel `(row, column)` where CIL's model of a Zeiss scan puts point `q` at Zeiss angle
/// `theta_deg`: `ZEISSDataReader`'s system (source `(0, −|StoRA|, 0)`, panel centre `(0, |DtoRA|, 0)`, panel
/// origin bottom-left, pixel `PixelSize · (|StoRA| + |DtoRA|)/|StoRA|`, CIL angle `θ` = the Zeiss angle)
/// turned by `−θ` as CIL's ASTRA conversion does.
fn cil_zeiss_pixel(x: &zeiss::Xradia, theta_deg: f64, q: Vec3) -> (f64, f64) {
    let (s, d) = (x.source_to_axis_mm, x.detector_to_axis_mm);
    let p = x.pixel_um / 1000.0 * (s + d) / s;
    let src0 = [0.0, -s, 0.0];
    let det0 = [0.0, d, 0.0];
    let row0 = [p, 0.0, 0.0]; // one column step (panel origin on the left)
    let col0 = [0.0, 0.0, p]; // one row step (panel origin at the bottom)
    let [src, det, u, v] = [src0, det0, row0, col0].map(|w| rot_z(-theta_deg.to_radians(), w));
    let dir = sub3(q, src);
    let n = cross3(u, v);
    let t = dot3(sub3(det, src), n) / dot3(dir, n);
    let hit = sub3(add3(src, scale3(dir, t)), det);
    let a = dot3(hit, u) / dot3(u, u);
    let b = dot3(hit, v) / dot3(v, v);
    (
        b + (x.height as f64 - 1.0) / 2.0,
        a + (x.width as f64 - 1.0) / 2.0,
    )
}

#[test]
fn an_off_centre_point_lands_where_cil_puts_it_on_a_zeiss_scan() {
    let x = xradia();
    assert!((x.detector_pixel_mm() - 0.02).abs() < 1e-15);
    let v = views(&zeiss::geometry(&x));
    assert_eq!(v.views.len(), 7);
    for q in [[0.11, -0.06, 0.08], [-0.09, 0.12, -0.07], [0.0, 0.0, 0.0]] {
        for (i, &a) in x.angles_deg.iter().enumerate() {
            let want = cil_zeiss_pixel(&x, a, q);
            let got = to_image(Orientation::AS_STORED, 48, 64, project(&v, i, q));
            assert!(
                (got.0 - want.0).abs() < 1e-6 && (got.1 - want.1).abs() < 1e-6,
                "view {i} (Zeiss angle {a}°), point {q:?}: ctrecon puts it at image {got:?}, CIL at {want:?}"
            );
        }
    }
}

#[test]
fn zeiss_rows_run_up_and_the_sample_turns_counter_clockwise_as_the_angle_grows() {
    let x = xradia();
    let v = views(&zeiss::geometry(&x));
    let at = |i: usize, q: Vec3| to_image(Orientation::AS_STORED, 48, 64, project(&v, i, q));
    // Magnification 4, panel pixel 20 µm: 0.1 mm at the axis is 20 pixels.
    let (rc, cc) = (23.5, 31.5);
    // View 3 (0°): +x lands 20 columns right of the centre, +z 20 rows above it (image row 0 is the bottom).
    let (r, c) = at(3, [0.1, 0.0, 0.0]);
    assert!(
        (r - rc).abs() < 1e-9 && (c - (cc + 20.0)).abs() < 1e-9,
        "{r} {c}"
    );
    let (r, c) = at(3, [0.0, 0.0, 0.1]);
    assert!(
        (r - (rc + 20.0)).abs() < 1e-9 && (c - cc).abs() < 1e-9,
        "{r} {c}"
    );
    // View 5 (90°): the sample has turned by +90° about z, so its +y side faces the panel's −x edge.
    let (r, c) = at(5, [0.0, 0.1, 0.0]);
    assert!(
        (r - rc).abs() < 1e-9 && (c - (cc - 20.0)).abs() < 1e-9,
        "{r} {c}"
    );
}

#[test]
fn a_wrong_sign_of_the_zeiss_angle_moves_the_point_by_pixels() {
    let x = xradia();
    let mut wrong = x.clone();
    wrong.angles_deg = x.angles_deg.iter().map(|a| -a).collect();
    let v = views(&zeiss::geometry(&wrong));
    let q = [0.11, -0.06, 0.08];
    let want = cil_zeiss_pixel(&x, x.angles_deg[5], q);
    let got = to_image(Orientation::AS_STORED, 48, 64, project(&v, 5, q));
    assert!((got.1 - want.1).abs() > 5.0, "{got:?} vs {want:?}");
}

#[test]
fn zeiss_views_live_in_folders_of_a_hundred() {
    assert_eq!(zeiss::image_stream(0), "ImageData1/Image1");
    assert_eq!(zeiss::image_stream(99), "ImageData1/Image100");
    assert_eq!(zeiss::image_stream(100), "ImageData2/Image101");
    assert_eq!(zeiss::image_stream(1799), "ImageData18/Image1800");
}

#[test]
fn a_shift_moves_the_image_and_keeps_the_edge_values() {
    // 3 × 5, value 10·r + c.
    let image: Vec<f32> = (0..15).map(|k| (10 * (k / 5) + k % 5) as f32).collect();
    // Whole pixels: (r, c) takes (r − 1, c + 2), clamped to the image.
    let mut a = image.clone();
    shift_image(&mut a, 3, 5, 1.0, -2.0);
    let want = |r: i32, c: i32| (10 * (r - 1).clamp(0, 2) + (c + 2).clamp(0, 4)) as f32;
    for r in 0..3 {
        for c in 0..5 {
            assert_eq!(a[(r * 5 + c) as usize], want(r, c), "({r}, {c})");
        }
    }
    // Half a pixel along the columns: the mean of the two neighbours, the edge where one is outside.
    let mut b = image.clone();
    shift_image(&mut b, 3, 5, 0.0, 0.5);
    assert_eq!(&b[5..10], &[10.0, 10.5, 11.5, 12.5, 13.5]);
    let mut c = image.clone();
    shift_image(&mut c, 3, 5, -0.25, 0.0);
    for k in 0..5 {
        assert!((c[k] - (image[k] + 0.25 * 10.0)).abs() < 1e-6);
        assert!((c[10 + k] - image[10 + k]).abs() < 1e-6);
    }
}
