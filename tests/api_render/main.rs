//! Volume renderings and shaded surfaces as products of a volume job, over HTTP against the real server: the
//! PNG, APNG and RGB Secondary Capture outputs, checked by their numbers (silhouette size, where a marker at the
//! patient's left appears, frame counts, DICOM identity), and bad render requests refused at submission (a shaded
//! surface above every value of the volume among them, in `iso`; one that smoothing pushed above is warned
//! about).

use crate::common;

mod iso;

use common::{TestApp, assert_problem, spawn_app, spawn_app_with};
use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::volume::{Frame, Volume};
use dicom_dictionary_std::tags;
use ndarray::Array3;
use serde_json::{Value, json};

const STUDY_UID: &str = "1.2.826.0.1.3680043.8.498.91";
const FOR_UID: &str = "1.2.826.0.1.3680043.8.498.92";
/// Radius (mm) of the central ball and of the marker at the patient's left, and the marker's x (mm).
const BALL_MM: f64 = 40.0;
const MARKER_MM: f64 = 10.0;
const MARKER_X: f64 = 56.0;

/// 1000 HU balls in air on 3 mm voxels, ±72 mm in x and y, ±62 mm in z, as a CT series.
fn series() -> Vec<(String, Vec<u8>)> {
    let frame = Frame {
        spacing_mm: [3.0, 3.0, 4.0],
        origin_mm: [-70.5, -70.5, -62.0],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((32, 48, 48), |(k, j, i)| {
        let [x, y, z] = frame.position(k as f64, j as f64, i as f64);
        let ball = BALL_MM - (x * x + y * y + z * z).sqrt();
        let marker = MARKER_MM - ((x - MARKER_X).powi(2) + y * y + z * z).sqrt();
        // A signed distance in HU (100 HU per mm), clamped: iso 0 is the surface.
        (ball.max(marker) * 100.0).clamp(-1000.0, 1000.0) as f32
    });
    let meta = SeriesMeta {
        study_uid: Some(STUDY_UID.into()),
        frame_of_reference_uid: Some(FOR_UID.into()),
        patient_id: Some("RENDER-1".into()),
        series_description: "balls".into(),
        series_number: 4,
        ..Default::default()
    };
    write_ct_series(&Volume { data, frame }, &meta)
        .unwrap()
        .files
}

async fn upload(app: &TestApp) -> String {
    upload_files(app, series()).await
}

async fn upload_files(app: &TestApp, files: Vec<(String, Vec<u8>)>) -> String {
    let form = files
        .into_iter()
        .fold(reqwest::multipart::Form::new(), |f, (name, bytes)| {
            f.part(
                "file",
                reqwest::multipart::Part::bytes(bytes)
                    .file_name(name)
                    .mime_str("application/dicom")
                    .unwrap(),
            )
        });
    let r = app
        .client
        .post(app.url("/v1/series"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap());
    let v: Value = r.json().await.unwrap();
    v["series"][0]["series"]["id"].as_str().unwrap().to_string()
}

async fn get(app: &TestApp, path: &str, content_type: &str) -> Vec<u8> {
    let r = app.get(path).await;
    assert_eq!(r.status(), 200, "{path}");
    assert_eq!(
        r.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some(content_type),
        "{path}"
    );
    r.bytes().await.unwrap().to_vec()
}

/// `(width, height, frames of RGB bytes)` of a PNG or APNG, with its colour type checked to be 8-bit RGB.
fn decode(png_bytes: &[u8]) -> (usize, usize, Vec<Vec<u8>>) {
    let mut r = png::Decoder::new(std::io::Cursor::new(png_bytes.to_vec()))
        .read_info()
        .unwrap();
    let info = r.info();
    assert_eq!(
        (info.color_type, info.bit_depth),
        (png::ColorType::Rgb, png::BitDepth::Eight)
    );
    let (w, h) = (info.width as usize, info.height as usize);
    let n = info
        .animation_control()
        .map_or(1, |a| a.num_frames as usize);
    let mut buf = vec![0; r.output_buffer_size().unwrap()];
    let frames = (0..n)
        .map(|_| {
            let f = r.next_frame(&mut buf).unwrap();
            buf[..f.buffer_size()].to_vec()
        })
        .collect();
    (w, h, frames)
}

/// Pixels brighter than the black background: their count and mean column.
fn lit(rgb: &[u8], w: usize, from_col: usize) -> (usize, f64) {
    let (mut n, mut sum) = (0usize, 0.0);
    for (k, p) in rgb.chunks(3).enumerate() {
        let c = k % w;
        if c >= from_col && p.iter().any(|&v| v > 8) {
            n += 1;
            sum += c as f64;
        }
    }
    (n, if n > 0 { sum / n as f64 } else { f64::NAN })
}

#[tokio::test]
async fn a_volume_job_renders_vr_ssd_and_a_rotation_as_png_apng_and_rgb_secondary_capture() {
    let app = spawn_app().await;
    let sid = upload(&app).await;
    let job = app
        .submit(&json!({"kind": "volume", "input": sid, "products": [
            {"type": "volume_render", "preset": "bone", "size": [96, 96]},
            {"type": "surface_render", "surfaces": [{"iso": 0, "color": [1, 1, 1]}], "depth_cue": 0,
             "size": [96, 96], "frames": 4},
            {"type": "surface_render", "surfaces": [{"iso": 0}], "size": [96, 96],
             "clip": {"planes": [{"point_mm": [0, 0, 0], "normal": [0, 1, 0]}]}}
        ]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let products = done["result"]["products"].as_array().unwrap().clone();
    assert_eq!(products[0]["type"], "volume_render");
    assert_eq!(products[0]["shape"], json!([1, 96, 96]));
    assert_eq!(products[1]["shape"], json!([4, 96, 96]));
    // Anterior view: the patient's right on the image left, superior up.
    assert_eq!(
        products[0]["orientation"],
        json!({"left": "R", "right": "L", "top": "S", "bottom": "I"})
    );
    assert!(
        products[0]["description"]
            .as_str()
            .unwrap()
            .contains("preset bone")
    );
    // The box is ±70.5 × ±70.5 × ±62 mm: bounding radius √(2·70.5² + 62²).
    let radius = (2.0f64 * 70.5 * 70.5 + 62.0 * 62.0).sqrt();
    let pixel = 2.0 * radius / 96.0;
    assert!((products[0]["pixel_mm"][0].as_f64().unwrap() - pixel).abs() < 1e-9);

    let base = format!("/v1/jobs/{id}/result/products");
    // VR PNG: the marker at the patient's left shows on the image right.
    let (w, h, frames) = decode(&get(&app, &format!("{base}/0?format=png"), "image/png").await);
    assert_eq!((w, h, frames.len()), (96, 96, 1));
    let right_of_ball = (47.5 + (BALL_MM + 2.0) / pixel) as usize;
    let (n, col) = lit(&frames[0], w, right_of_ball);
    let want_col = 47.5 + MARKER_X / pixel;
    assert!(
        n > 5 && (col - want_col).abs() < 1.5,
        "marker at column {col:.1}, want {want_col:.1} ({n} px)"
    );
    let (n_left, _) = lit(&frames[0][..], w, 0);
    assert!(n_left > n, "the ball is seen too");

    // SSD rotation as APNG: 4 frames; the ball's disc has its radius in every frame, and the marker goes from
    // the image right (0°) to the centre (90°: behind the ball, seen from the patient's left) to the left.
    let (w, _, frames) = decode(&get(&app, &format!("{base}/1?format=apng"), "image/apng").await);
    assert_eq!(frames.len(), 4);
    let (right0, _) = lit(&frames[0], w, right_of_ball);
    let (right2, _) = lit(&frames[2], w, right_of_ball);
    assert!(
        right0 > 5 && right2 == 0,
        "marker pixels right of the ball: {right0} at 0°, {right2} at 180°"
    );
    let ball_px = std::f64::consts::PI * (BALL_MM / pixel).powi(2);
    let (all1, _) = lit(&frames[1], w, 0);
    assert!(
        (all1 as f64 - ball_px).abs() / ball_px < 0.06,
        "90°: {all1} px lit, the ball alone covers {ball_px:.0}"
    );

    // The rotation as one multi-frame RGB Secondary Capture in the source's study and frame of reference.
    let dcm = get(&app, &format!("{base}/1?format=dicom"), "application/dicom").await;
    let obj = dicom_object::OpenFileOptions::new()
        .from_reader(&dcm[128..])
        .unwrap();
    let s = |t| obj.element(t).unwrap().to_str().unwrap().trim().to_string();
    assert_eq!(s(tags::SOP_CLASS_UID), "1.2.840.10008.5.1.4.1.1.7.4");
    assert_eq!(s(tags::STUDY_INSTANCE_UID), STUDY_UID);
    assert_eq!(s(tags::FRAME_OF_REFERENCE_UID), FOR_UID);
    assert_eq!(s(tags::PHOTOMETRIC_INTERPRETATION), "RGB");
    assert_eq!(s(tags::NUMBER_OF_FRAMES), "4");
    assert_eq!(s(tags::SAMPLES_PER_PIXEL), "3");
    assert!(s(tags::DERIVATION_DESCRIPTION).contains("shaded surface display, iso 0"));
    assert_eq!(
        obj.element(tags::PIXEL_DATA)
            .unwrap()
            .to_bytes()
            .unwrap()
            .len(),
        4 * 96 * 96 * 3
    );
    // One frame of it as a single-frame Secondary Capture.
    let one = get(
        &app,
        &format!("{base}/1?format=dicom&frame=2"),
        "application/dicom",
    )
    .await;
    let obj = dicom_object::OpenFileOptions::new()
        .from_reader(&one[128..])
        .unwrap();
    assert_eq!(
        obj.element(tags::SOP_CLASS_UID)
            .unwrap()
            .to_str()
            .unwrap()
            .trim_end_matches('\0'),
        "1.2.840.10008.5.1.4.1.1.7"
    );

    // The cut-away keeps the posterior half: seen from the front, the cap is a full disc of the ball's radius
    // with the marker's cap beside it.
    let (w, _, frames) = decode(&get(&app, &format!("{base}/2"), "image/png").await);
    let (all, _) = lit(&frames[0], w, 0);
    let caps = ball_px + std::f64::consts::PI * (MARKER_MM / pixel).powi(2);
    assert!(
        (all as f64 - caps).abs() / caps < 0.06,
        "{all} px vs {caps:.0}"
    );
}

#[tokio::test]
async fn bad_render_requests_are_refused_at_submission_with_problem_json() {
    let app = spawn_app_with(|s| s.render_max_side = 256).await;
    let sid = upload(&app).await;
    let cases = [
        (
            json!({"type": "volume_render", "size": [32, 32], "transfer_function": {"points": []}}),
            "empty_transfer_function",
        ),
        (
            json!({"type": "surface_render", "surfaces": [{"iso": 0}], "size": [32, 32],
                   "clip": {"planes": [{"point_mm": [0, 0, 0], "normal": [0, 0, 0]}]}}),
            "invalid_clip",
        ),
        (
            json!({"type": "mesh", "iso": 0,
                   "clip": {"planes": [{"point_mm": [0, 0, 0], "normal": [0, 0, 0]}]}}),
            "invalid_clip",
        ),
        (
            json!({"type": "volume_render", "size": [32, 32], "camera": {"distance_mm": 10}}),
            "camera_inside_volume",
        ),
        (
            json!({"type": "surface_render", "surfaces": [{"iso": 0}], "size": [0, 64]}),
            "invalid_render_size",
        ),
        (
            json!({"type": "volume_render", "size": [512, 512]}),
            "invalid_render_size",
        ),
        (
            json!({"type": "volume_render", "size": [32, 32], "preset": "bone", "transfer_function": {"points": [
                {"value": 0, "color": [1, 1, 1], "opacity": 1}]}}),
            "invalid_parameter",
        ),
        (
            json!({"type": "volume_render", "size": [32, 32], "preset": "marble"}),
            "invalid_request",
        ),
    ];
    for (product, code) in cases {
        let r = app
            .post_json(
                "/v1/jobs",
                &json!({"kind": "volume", "input": sid, "products": [product]}),
            )
            .await;
        assert_problem(r, 422, code).await;
    }
    // A perspective camera may fly inside the volume.
    app.submit(&json!({"kind": "volume", "input": sid, "products": [
        {"type": "volume_render", "size": [32, 32],
         "camera": {"projection": "perspective", "distance_mm": 10}}]}))
        .await;
}

/// The triangles of a binary STL (84-byte header and count, 50 bytes a triangle).
fn stl_triangles(b: &[u8]) -> Vec<[[f32; 3]; 3]> {
    let n = u32::from_le_bytes(b[80..84].try_into().unwrap()) as usize;
    assert_eq!(b.len(), 84 + 50 * n);
    (0..n)
        .map(|t| {
            let f = |k: usize| {
                let o = 84 + 50 * t + 12 + 4 * k;
                f32::from_le_bytes(b[o..o + 4].try_into().unwrap())
            };
            std::array::from_fn(|v| std::array::from_fn(|c| f(3 * v + c)))
        })
        .collect()
}

/// Whether every edge of the triangles is used once in each direction (a closed, consistently oriented
/// surface), with vertices matched by their exact coordinates; and the volume it encloses (mm³).
fn closed_and_volume(tris: &[[[f32; 3]; 3]]) -> (bool, f64) {
    use std::collections::HashMap;
    let key = |p: [f32; 3]| p.map(f32::to_bits);
    let mut edges: HashMap<([u32; 3], [u32; 3]), i32> = HashMap::new();
    let mut volume = 0.0;
    for t in tris {
        for e in 0..3 {
            *edges.entry((key(t[e]), key(t[(e + 1) % 3]))).or_default() += 1;
        }
        let [a, b, c] = t.map(|p| p.map(|x| x as f64));
        volume += (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
            + a[2] * (b[0] * c[1] - b[1] * c[0]))
            / 6.0;
    }
    let closed = edges
        .iter()
        .all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1));
    (closed, volume)
}

#[tokio::test]
async fn the_mesh_view_takes_the_clip_of_the_mesh_product_and_caps_the_cut() {
    let app = spawn_app().await;
    let sid = upload(&app).await;
    let clip = json!({"planes": [{"point_mm": [0, 0, 0], "normal": [0, 1, 0]}]});
    let job = app
        .submit(&json!({"kind": "volume", "input": sid, "products": [
            {"type": "mesh", "iso": 0, "largest_component": false, "clip": clip}]}))
        .await;
    let id = job["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let mesh_url = |clip: Option<String>| {
        let clip = clip.map_or(String::new(), |c| format!("&clip={}", url_encode(&c)));
        format!("/v1/jobs/{id}/result/mesh.stl?iso=0{clip}")
    };
    let whole = stl_triangles(&get(&app, &mesh_url(None), "model/stl").await);
    let cut_bytes = get(&app, &mesh_url(Some(clip.to_string())), "model/stl").await;
    let cut = stl_triangles(&cut_bytes);
    let (whole_closed, whole_volume) = closed_and_volume(&whole);
    let (cut_closed, cut_volume) = closed_and_volume(&cut);
    assert!(
        whole_closed && cut_closed,
        "closed: {whole_closed} {cut_closed}"
    );
    // The ball and the marker are symmetric about y = 0, as is the grid: the cut keeps half of each.
    let exact = 4.0 / 3.0 * std::f64::consts::PI * (BALL_MM.powi(3) + MARKER_MM.powi(3));
    assert!(
        (whole_volume - exact).abs() / exact < 0.02,
        "whole {whole_volume:.0} mm³ vs {exact:.0}"
    );
    assert!(
        (cut_volume - whole_volume / 2.0).abs() / (whole_volume / 2.0) < 0.01,
        "cut {cut_volume:.0} mm³ vs half of {whole_volume:.0}"
    );
    let min_y = cut
        .iter()
        .flatten()
        .map(|p| p[1])
        .fold(f32::INFINITY, f32::min);
    assert!(
        min_y > -1e-3,
        "the cut keeps y ≥ 0, lowest vertex at {min_y}"
    );
    // The view and the product with the same clip are the same mesh.
    let product = stl_triangles(
        &get(
            &app,
            &format!("/v1/jobs/{id}/result/products/0"),
            "model/stl",
        )
        .await,
    );
    assert!(
        product == cut,
        "the product has {} triangles, the view {}",
        product.len(),
        cut.len()
    );

    // Refused as in a job: a zero normal (422 invalid_clip), text that is no clip (400 invalid_query).
    let zero = json!({"planes": [{"point_mm": [0, 0, 0], "normal": [0, 0, 0]}]});
    let r = app.get(&mesh_url(Some(zero.to_string()))).await;
    assert_problem(r, 422, "invalid_clip").await;
    let r = app.get(&mesh_url(Some("planes".into()))).await;
    assert_problem(r, 400, "invalid_query").await;
}

/// `s` percent-encoded for a query string.
fn url_encode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}
