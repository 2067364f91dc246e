//! A gantry-tilted series: its slice views, MPR planes through each marker, a rotating projection and an
//! anterior rendering put the markers where their image geometry says (within a pixel of where the tilted
//! grid sampled them).

use serde_json::{Value, json};

use super::checks::AXES;
use super::dicom::Placement;
use super::geometry::{self, Planar, bounds, sides};
use super::images::{Plane, assert_marker, get_bytes, npy, png_brightness, png_json};
use super::phantom::{MARKERS, S, tilted, upload};
use super::products::Expect;
use super::volume_job;
use crate::common::spawn_app;

/// Where the tilted series has each marker: the mean position of the samples that hold its value (its
/// sampling shifts it by up to 0.8 mm from the lattice point).
fn sampled(vol: &ctrecon::volume::Volume) -> Vec<[f64; 3]> {
    MARKERS
        .iter()
        .map(|(_, v)| {
            let inside: Vec<[f64; 3]> = vol
                .data
                .indexed_iter()
                .filter(|(_, x)| *x == v)
                .map(|((k, j, i), _)| vol.frame.position(k as f64, j as f64, i as f64))
                .collect();
            assert!(inside.len() >= 8, "{v}: {}", inside.len());
            std::array::from_fn(|a| inside.iter().map(|p| p[a]).sum::<f64>() / inside.len() as f64)
        })
        .collect()
}

#[tokio::test]
async fn a_tilted_series_shows_its_markers_where_the_image_plane_says() {
    let app = spawn_app().await;
    let vol = tilted();
    let at = sampled(&vol);
    let series = upload(&app, &vol, "tilted", false).await;
    assert!(
        (series["tilt_deg"].as_f64().unwrap() - 12.0).abs() < 0.01,
        "{series}"
    );
    let frame: ctrecon::volume::Frame = serde_json::from_value(series["frame"].clone()).unwrap();
    let shape = &series["shape"];
    let dim = |a: usize| shape[a].as_u64().unwrap() as usize;
    let dim = (dim(0), dim(1), dim(2));
    let mut specs: Vec<Value> = AXES
        .iter()
        .map(|axis| json!({"type": "projection", "axis": axis, "kind": "mip"}))
        .collect();
    // MPR planes through each marker, centred on the volume's middle in the plane (so that a mirrored image
    // would not put the marker back in its place).
    let middle = bounds(&frame, dim).0;
    let through = |p: [f64; 3], axis: &str| match axis {
        "coronal" => [middle[0], p[1], middle[2]],
        _ => [p[0], middle[1], middle[2]],
    };
    for p in &at {
        for plane in ["coronal", "sagittal"] {
            specs.push(json!({"type": "mpr", "plane": plane, "centre_mm": through(*p, plane)}));
        }
    }
    specs.push(json!({"type": "rotating", "frames": 4}));
    let render = Expect::Render {
        size: [48, 48],
        level: 450.0,
        frames: 1,
    };
    specs.push(
        json!({"type": "volume_render", "size": [48, 48], "camera": {"view": "anterior"},
        "shading": {"ambient": 1.0, "diffuse": 0.0, "specular": 0.0, "shininess": 1.0},
        "transfer_function": {"points": [
            {"value": -1100.0, "color": [1.0, 1.0, 1.0], "opacity": 0.0},
            {"value": 450.0, "color": [1.0, 1.0, 1.0], "opacity": 0.0},
            {"value": 460.0, "color": [1.0, 1.0, 1.0], "opacity": 1.0},
            {"value": 1000.0, "color": [1.0, 1.0, 1.0], "opacity": 1.0}]}}),
    );
    let job = volume_job(&app, series["id"].as_str().unwrap(), &specs).await;
    let id = job["id"].as_str().unwrap();
    let products = &job["result"]["products"];
    // The projection products are the projection views, and say where they lie.
    for (p, axis) in AXES.iter().enumerate() {
        let product = npy(
            &app,
            &format!("/v1/jobs/{id}/result/products/{p}?format=npy"),
        )
        .await;
        let view = npy(
            &app,
            &format!("/v1/jobs/{id}/result/projection?axis={axis}&kind=mip&format=npy"),
        )
        .await;
        assert_eq!(product.data, view.data, "{axis}");
        let plane = &products[p]["plane"];
        assert!(plane["first_pixel_mm"].is_array(), "{axis}: {plane}");
    }
    // Slice views: each marker on the display-grid image through it, where its ImagePlane says.
    for axis in AXES {
        let placed = |png: &[u8]| Placement::from_json(&png_json(png, "ImagePlane"));
        let p0 = placed(
            &get_bytes(
                &app,
                &format!("/v1/jobs/{id}/result/slice?axis={axis}&index=0"),
            )
            .await,
        );
        let p1 = placed(
            &get_bytes(
                &app,
                &format!("/v1/jobs/{id}/result/slice?axis={axis}&index=1"),
            )
            .await,
        );
        // Display grids are axis-aligned: the fixed coordinate of image `index` grows by the grid step.
        let fixed = match axis {
            "axial" => 2,
            "coronal" => 1,
            _ => 0,
        };
        let step = p1.first[fixed] - p0.first[fixed];
        assert!(step > 0.0, "{axis}: {p0:?} → {p1:?}");
        for (m, (c, v)) in MARKERS.iter().enumerate() {
            let p = at[m];
            let index = ((p[fixed] - p0.first[fixed]) / step).round() as usize;
            let path = format!("/v1/jobs/{id}/result/slice?axis={axis}&index={index}");
            let img = npy(&app, &format!("{path}&format=npy")).await;
            let place = placed(&get_bytes(&app, &path).await);
            let rel = geometry::sub(p, place.first);
            let want = (
                geometry::dot(rel, place.down) / place.pixel[0],
                geometry::dot(rel, place.right) / place.pixel[1],
            );
            assert_marker(
                img.frame(0),
                want,
                v / 4.0,
                1.0,
                &format!("tilted {path}: marker {c:?}"),
            );
        }
    }
    // The MPR planes: each marker where the radiological plane through it puts it.
    let mut i = 3;
    for (m, (c, v)) in MARKERS.iter().enumerate() {
        for axis in ["coronal", "sagittal"] {
            let p = &products[i];
            let what = format!("tilted product {i}: {axis} MPR through {c:?}");
            let (right, down) = geometry::radiological(axis);
            let planar = Planar {
                centre: through(at[m], axis),
                right,
                down,
                pixel: S[0],
                size: [
                    p["shape"][2].as_u64().unwrap() as usize,
                    p["shape"][1].as_u64().unwrap() as usize,
                ],
                frames: 1,
                spacing: 0.0,
            };
            planar.assert_plane(&p["plane"], 0, &what);
            assert_eq!(p["orientation"], sides(right, down), "{what}");
            let img = npy(
                &app,
                &format!("/v1/jobs/{id}/result/products/{i}?format=npy"),
            )
            .await;
            let want = planar.pixel_of(at[m], 0);
            assert_marker(img.frame(0), want, v / 4.0, 1.0, &what);
            i += 1;
        }
    }
    // The rotating projection turns about the superior axis through the volume's centre.
    let p = &products[i];
    let rotating = Expect::Rotating { frames: 4 };
    rotating.check_json(p, "tilted rotating");
    let img = npy(
        &app,
        &format!("/v1/jobs/{id}/result/products/{i}?format=npy"),
    )
    .await;
    let turning = geometry::Turning {
        centre: bounds(&frame, dim).0,
        pixel: S[0],
        rows: img.rows,
        cols: img.cols,
    };
    for k in 0..4 {
        let angle = 90.0 * k as f64;
        for (m, (c, v)) in MARKERS.iter().enumerate() {
            let want = turning.pixel_of(at[m], angle);
            assert_marker(
                img.frame(k),
                want,
                v / 4.0,
                1.0,
                &format!("tilted rotating at {angle}°: marker {c:?}"),
            );
        }
    }
    // The anterior rendering about the centre of the tilted box.
    i += 1;
    render.check_json(&products[i], "tilted rendering");
    let png = get_bytes(&app, &format!("/v1/jobs/{id}/result/products/{i}")).await;
    let (rows, cols, light) = png_brightness(&png);
    render.check_render(
        Plane {
            rows,
            cols,
            values: &light,
        },
        0,
        (&frame, dim),
        &at,
        1.0,
        "tilted rendering",
    );
}
