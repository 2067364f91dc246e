//! The checks every acquisition goes through: the slice and projection views, every product, and the DICOM
//! results exported for delivery.

use ctrecon::jobs::export::{ExportOptions, export_dir, export_job};
use ctrecon::storage::{JobId, SeriesId};
use dicom_dictionary_std::tags;
use serde_json::Value;

use super::dicom::{self, Placement, assert_placed, assert_volume_series, open};
use super::geometry::{self, Planar, patient_orientation, sides};
use super::images::{Grey, Plane, get_bytes, npy, png_brightness, png_json, png_text};
use super::phantom::{MARKERS, N, lps};
use super::products::{Expect, Product, display_first_pixel, fixed_axis, patient_box, screen};
use crate::common::TestApp;

pub const AXES: [&str; 3] = ["axial", "coronal", "sagittal"];

/// What every acquisition must show the same: the grey images (path, values) and the marker centroids of
/// the renderings (path, centroids).
#[derive(Default)]
pub struct Seen {
    pub grey: Vec<(String, Grey)>,
    pub renders: Vec<(String, Vec<(f64, f64)>)>,
}

/// The slice and projection views: each marker at its screen pixel, the PNG naming its sides and plane, the
/// DICOM image its Patient Orientation and placement.
pub async fn check_views(app: &TestApp, job: &str, name: &str, seen: &mut Seen) {
    for axis in AXES {
        let (right, down) = geometry::radiological(axis);
        // The image through each marker, then the projection (placed at its middle plane).
        let a = fixed_axis(axis);
        let mut paths = Vec::new();
        for (c, _) in MARKERS {
            let index = c[a];
            let path = format!("/v1/jobs/{job}/result/slice?axis={axis}&index={index}");
            paths.push((path, Some(c), index as f64));
        }
        paths.push((
            format!("/v1/jobs/{job}/result/projection?axis={axis}&kind=mip"),
            None,
            (N[a] - 1) as f64 / 2.0,
        ));
        for (path, only, index) in paths {
            let img = npy(app, &format!("{path}&format=npy")).await;
            for (c, v) in MARKERS {
                if only.is_some_and(|o| o != c) {
                    continue;
                }
                let (r, col) = screen(axis, c);
                assert_eq!(img.at(0, r, col), v, "{name}: {path}: marker {c:?}");
            }
            let png = get_bytes(app, &path).await;
            assert_eq!(
                png_json(&png, "Orientation"),
                sides(right, down),
                "{name}: {path}"
            );
            let plane = png_json(&png, "ImagePlane");
            let place = Placement::from_json(&plane);
            assert!(
                geometry::close(place.first, display_first_pixel(axis, index), 1e-6)
                    && geometry::close(place.right, right, 1e-9)
                    && geometry::close(place.down, down, 1e-9),
                "{name}: {path}: {plane}"
            );
            let dcm = open(&get_bytes(app, &format!("{path}&format=dicom")).await);
            assert_placed(
                &dcm,
                Some(patient_orientation(right, down)),
                Some(place),
                &format!("{name}: {path}"),
            );
            seen.grey.push((path, img));
        }
    }
}

/// The frames of a product whose PNG and DICOM are checked: all of a rotating projection, the first,
/// middle and last of a stack.
fn frames_to_check(e: &Expect, frames: usize) -> Vec<usize> {
    match e {
        Expect::Rotating { .. } => (0..frames).collect(),
        _ => {
            let mut k = vec![0, frames / 2, frames - 1];
            k.dedup();
            k
        }
    }
}

/// Placement of frame `k` of a product, as computed here (planar products only).
fn placement(e: &Expect, p: &Value, k: usize) -> Option<Placement> {
    match e {
        Expect::Projection(_) => Some(Placement::from_json(&p["plane"])),
        Expect::Mpr { .. } => {
            let planar: Planar = e.planar(p).unwrap();
            Some(Placement {
                first: planar.first_pixel(k),
                right: planar.right,
                down: planar.down,
                pixel: [planar.pixel; 2],
            })
        }
        _ => None,
    }
}

/// Every product: its JSON, the markers on screen, the PNG text chunks and DICOM attributes of its frames.
pub async fn check_products(
    app: &TestApp,
    job: &Value,
    list: &[Product],
    name: &str,
    seen: &mut Seen,
) {
    let id = job["id"].as_str().unwrap();
    let (frame, dim) = patient_box();
    for (i, product) in list.iter().enumerate() {
        let p = &job["result"]["products"][i];
        let what = format!("{name}: product {i} {}", product.spec);
        let e = &product.expect;
        e.check_json(p, &what);
        let frames = p["shape"][0].as_u64().unwrap() as usize;
        let path = format!("/v1/jobs/{id}/result/products/{i}");
        // Frames seen from different sides (a rotating projection, a turning rendering) name each frame's
        // sides in the JSON, as their PNGs do; other stacks share the first frame's `orientation`.
        let turning = frames > 1 && matches!(e, Expect::Rotating { .. } | Expect::Render { .. });
        match p["frame_orientations"].as_array() {
            Some(list) => {
                assert!(
                    turning,
                    "{what}: frame_orientations on a stack facing one way"
                );
                assert_eq!(list.len(), frames, "{what}: frame_orientations");
                for (k, listed) in list.iter().enumerate() {
                    let want = match e {
                        Expect::Render { .. } => e.sides(k, frames),
                        _ => {
                            let (r, d) = e.axes(k, frames);
                            sides(r, d)
                        }
                    };
                    assert_eq!(listed, &want, "{what}: frame_orientations[{k}]");
                }
            }
            None => assert!(!turning, "{what}: no frame_orientations"),
        }
        if let Expect::Render { .. } = e {
            let at: Vec<[f64; 3]> = MARKERS.iter().map(|(c, _)| lps(*c)).collect();
            for k in 0..frames {
                let png = get_bytes(app, &format!("{path}?frame={k}")).await;
                let what = format!("{what}: frame {k}");
                assert_eq!(png_json(&png, "Orientation"), e.sides(k, frames), "{what}");
                assert!(
                    png_text(&png)
                        .iter()
                        .any(|(k, v)| k == "Description" && v.contains("anterior view")),
                    "{what}"
                );
                let (rows, cols, light) = png_brightness(&png);
                let img = Plane {
                    rows,
                    cols,
                    values: &light,
                };
                let centroids = e.check_render(img, k, (&frame, dim), &at, 1.0, &what);
                seen.renders.push((format!("{path}?frame={k}"), centroids));
                let dcm = open(&get_bytes(app, &format!("{path}?format=dicom&frame={k}")).await);
                let (r, d) = e.axes(k, frames);
                assert_placed(&dcm, Some(patient_orientation(r, d)), None, &what);
            }
            // Every frame in one instance: one Patient Orientation only if they share it.
            let dcm = open(&get_bytes(app, &format!("{path}?format=dicom")).await);
            let (r, d) = e.axes(0, frames);
            let po = (frames == 1).then(|| patient_orientation(r, d));
            assert_placed(&dcm, po, None, &what);
            continue;
        }
        let img = npy(app, &format!("{path}?format=npy")).await;
        e.check_grey(p, &img, &what);
        seen.grey.push((path.clone(), img));
        for k in frames_to_check(e, frames) {
            let (r, d) = e.axes(k, frames);
            let png = get_bytes(app, &format!("{path}?frame={k}")).await;
            assert_eq!(
                png_json(&png, "Orientation"),
                sides(r, d),
                "{what}: frame {k}"
            );
            let place = placement(e, p, k);
            let text = png_text(&png);
            match place {
                Some(_) => {
                    let plane = png_json(&png, "ImagePlane");
                    if let Some(planar) = e.planar(p) {
                        planar.assert_plane(&plane, k, &what);
                    } else {
                        assert_eq!(plane, p["plane"], "{what}");
                    }
                }
                None => assert!(
                    !text.iter().any(|(k, _)| k == "ImagePlane"),
                    "{what}: {text:?}"
                ),
            }
            let dcm = open(&get_bytes(app, &format!("{path}?format=dicom&frame={k}")).await);
            assert_placed(
                &dcm,
                Some(patient_orientation(r, d)),
                place,
                &format!("{what}: frame {k}"),
            );
        }
    }
}

/// The job's DICOM results as exported for delivery (and the instance index): the volume as a derived CT
/// series, MPR stacks as derived CT series, other images as Secondary Capture of one series each, renderings
/// as RGB Secondary Capture, every one placed as its product says.
pub async fn check_export(app: &TestApp, job: &Value, list: &[Product], name: &str) {
    let core = app.core.as_ref().unwrap();
    let id = JobId::parse(job["id"].as_str().unwrap()).unwrap();
    let stored = core.db.get_job(id).await.unwrap().unwrap();
    let result = stored.result.clone().unwrap();
    let source = core
        .db
        .get_series(SeriesId::parse(&result.source_series.unwrap().to_string()).unwrap())
        .await
        .unwrap();
    let opts = ExportOptions {
        window: None,
        send_volume: true,
        mu_water: core.settings.mu_water_per_mm,
    };
    let files = export_job(
        &core.store,
        id,
        &stored.request,
        &result,
        source.as_ref(),
        &opts,
    )
    .unwrap();
    let dir = export_dir(&core.store, id);
    let mut by_series: std::collections::BTreeMap<i64, Vec<Vec<u8>>> = Default::default();
    for f in files {
        let bytes = std::fs::read(dir.join(&f.file)).unwrap();
        let obj = open(&bytes);
        by_series
            .entry(dicom::int(&obj, tags::SERIES_NUMBER))
            .or_default()
            .push(bytes);
    }
    // The result indexer may have exported the job first, without the volume (its index holds the volume's
    // series, written as series.zip writes it).
    if let Some(volume) = by_series.get(&900) {
        assert_volume_series(volume, &format!("{name}: exported volume"));
    }
    for (i, product) in list.iter().enumerate() {
        let p = &job["result"]["products"][i];
        let e = &product.expect;
        let what = format!("{name}: exported product {i} {}", product.spec);
        let files = by_series.get(&(901 + i as i64)).unwrap_or_else(|| {
            panic!("{what}: no series {} among {:?}", 901 + i, by_series.keys())
        });
        let frames = p["shape"][0].as_u64().unwrap() as usize;
        if let Expect::Render { .. } = e {
            // One instance of every frame: one Patient Orientation only if they share it.
            assert_eq!(files.len(), 1, "{what}");
            let (r, d) = e.axes(0, frames);
            let po = (frames == 1).then(|| patient_orientation(r, d));
            assert_placed(&open(&files[0]), po, None, &what);
            continue;
        }
        assert_eq!(files.len(), frames, "{what}");
        for f in files {
            let obj = open(f);
            let k = dicom::int(&obj, tags::INSTANCE_NUMBER) as usize - 1;
            let (r, d) = e.axes(k, frames);
            let class = obj
                .meta()
                .media_storage_sop_class_uid
                .trim_end_matches('\0')
                .to_string();
            // Stacks of several planes are CT series, single images and non-planar frames Secondary Capture.
            let ct = frames > 1 && e.planar(p).is_some();
            let want = if ct {
                dicom_dictionary_std::uids::CT_IMAGE_STORAGE
            } else {
                dicom_dictionary_std::uids::SECONDARY_CAPTURE_IMAGE_STORAGE
            };
            assert_eq!(class, want, "{what}: frame {k}");
            assert_placed(
                &obj,
                Some(patient_orientation(r, d)),
                placement(e, p, k),
                &format!("{what}: frame {k}"),
            );
        }
    }
}
