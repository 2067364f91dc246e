//! Meshes report what they are: integer data meshed at an integer iso-value (label maps, HU) gives no
//! zero-area triangle and no two vertices at one place, and `closed`, `manifold` and the Euler characteristic
//! are read from the final mesh. Truth: boxes and spheres of known size, a torus (χ = 0). Over HTTP: an iso-value
//! above the data is refused before any work, and what a surface could not honour comes back as a warning.

mod common;

use std::collections::HashSet;
use std::f64::consts::PI;

use ctrecon::mesh::{Mesh, MeshOptions, extract, marching_cubes};
use ctrecon::recon::VolumeGrid;
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;
use serde_json::json;

use common::{assert_problem, spawn_app};
use ctrecon::dicom::{SeriesMeta, write_ct_series};

/// An `n³` volume of `voxel_mm` voxels centred on the origin holding `f(x, y, z)` (mm) at voxel centres.
fn field(n: usize, voxel_mm: [f64; 3], f: impl Fn(f64, f64, f64) -> f64) -> Volume {
    let grid = VolumeGrid {
        nx: n,
        ny: n,
        nz: n,
        spacing_mm: voxel_mm,
        centre_mm: [0.0; 3],
    };
    Volume {
        data: Array3::from_shape_fn((n, n, n), |(k, j, i)| {
            f(grid.x(i), grid.y(j), grid.z(k)) as f32
        }),
        frame: Frame::from_grid(&grid),
    }
}

fn rel(got: f64, want: f64) -> f64 {
    (got - want).abs() / want
}

/// No triangle of zero area, no repeated corner, no two used vertices at the same position.
fn assert_no_degeneracy(m: &Mesh) {
    let used: HashSet<u32> = m.triangles.iter().flatten().copied().collect();
    let mut seen = HashSet::new();
    for &v in &used {
        let p = m.vertices[v as usize];
        assert!(seen.insert(p.map(f32::to_bits)), "two vertices at {p:?}");
    }
    for t in &m.triangles {
        let [a, b, c] = t.map(|v| m.vertices[v as usize].map(f64::from));
        let (u, w) = (
            [b[0] - a[0], b[1] - a[1], b[2] - a[2]],
            [c[0] - a[0], c[1] - a[1], c[2] - a[2]],
        );
        let n = [
            u[1] * w[2] - u[2] * w[1],
            u[2] * w[0] - u[0] * w[2],
            u[0] * w[1] - u[1] * w[0],
        ];
        assert!(n.iter().any(|&c| c != 0.0), "zero-area triangle {t:?}");
    }
}

/// Closed, manifold, Euler characteristic `chi`, no degeneracy.
fn assert_surface(m: &Mesh, chi: i64, what: &str) {
    let t = m.topology();
    assert!(t.closed && t.manifold, "{what}: {t:?}");
    assert_eq!(t.euler_characteristic, chi, "{what}");
    assert_no_degeneracy(m);
}

#[test]
fn a_cube_of_ones_at_iso_one_exactly_is_the_box_through_its_outer_voxel_centres() {
    // 6 voxels a side: the outer voxel centres span 5 voxels.
    for voxel in [[1.0, 1.0, 1.0], [0.8, 1.0, 1.5]] {
        let vol = field(12, voxel, |x, y, z| {
            let inside = |c: f64, s: f64| c.abs() < 3.0 * s;
            if inside(x, voxel[0]) && inside(y, voxel[1]) && inside(z, voxel[2]) {
                1.0
            } else {
                0.0
            }
        });
        let mesh = marching_cubes(vol.data.view(), &vol.frame, 1.0);
        assert_surface(&mesh, 2, "cube at iso 1");
        let side = voxel.map(|s| 5.0 * s);
        let volume = side[0] * side[1] * side[2];
        let area = 2.0 * (side[0] * side[1] + side[1] * side[2] + side[0] * side[2]);
        assert!(
            rel(mesh.volume_mm3(), volume) < 1e-5,
            "{} vs {volume}",
            mesh.volume_mm3()
        );
        assert!(
            rel(mesh.area_mm2(), area) < 1e-5,
            "{} vs {area}",
            mesh.area_mm2()
        );
        // Half-way between the labels, the classic box with bevelled edges and corners.
        let half = marching_cubes(vol.data.view(), &vol.frame, 0.5);
        assert_surface(&half, 2, "cube at iso 0.5");
        let full = voxel.map(|s| 6.0 * s);
        let v = half.volume_mm3();
        assert!(v > volume && v < full[0] * full[1] * full[2], "{v}");
    }
}

/// Label 2 inside radius 6 mm, label 1 out to 11 mm, 0 outside; 1 mm voxels.
fn labels() -> Volume {
    field(30, [1.0; 3], |x, y, z| {
        let r = (x * x + y * y + z * z).sqrt();
        if r <= 6.0 {
            2.0
        } else if r <= 11.0 {
            1.0
        } else {
            0.0
        }
    })
}

#[test]
fn a_labelled_volume_at_integer_iso_values_gives_honest_spheres() {
    let vol = labels();
    // At an integer iso-value the surface runs through the outermost samples of the label, which lie on
    // average half a voxel inside the labelled ball: the volume is within 6 % of the ball of radius R − ½ and
    // between the balls of radius R − 1 and R. The faceted surface through voxel centres overestimates the
    // area of the smooth sphere by about a tenth (staircase): within [1.0, 1.2] × 4π(R − ½)².
    let ball = |r: f64| 4.0 / 3.0 * PI * r.powi(3);
    for (iso, r) in [(1.0f32, 11.0f64), (2.0, 6.0)] {
        let mesh = marching_cubes(vol.data.view(), &vol.frame, iso);
        let (v, a) = (mesh.volume_mm3(), mesh.area_mm2());
        let a0 = 4.0 * PI * (r - 0.5).powi(2);
        println!(
            "iso {iso}: volume {v:.1} mm³ (ball R−½ {:.1}), area {a:.1} mm² (sphere R−½ {a0:.1})",
            ball(r - 0.5)
        );
        assert_surface(&mesh, 2, &format!("labels at iso {iso}"));
        assert!(v > ball(r - 1.0) && v < ball(r), "{v}");
        assert!(rel(v, ball(r - 0.5)) < 0.06, "volume {v}");
        assert!(a / a0 > 1.0 && a / a0 < 1.2, "area {a}");
    }
    // Between the labels, the surfaces sit half-way: the balls of radius R within 6 %.
    for (iso, r) in [(0.5f32, 11.0f64), (1.5, 6.0)] {
        let mesh = marching_cubes(vol.data.view(), &vol.frame, iso);
        let v = mesh.volume_mm3();
        println!("iso {iso}: volume {v:.1} mm³ (ball R {:.1})", ball(r));
        assert_surface(&mesh, 2, &format!("labels at iso {iso}"));
        assert!(rel(v, ball(r)) < 0.06, "iso {iso}: {v}");
    }
}

#[test]
fn a_sphere_in_integer_hu_at_integer_iso_values_is_a_closed_manifold_sphere() {
    // A CT-like radial ramp rounded to whole HU: 0 HU at 10 mm from the centre, 50 HU more per mm inwards.
    // Samples sit on integer millimetres, so every sample at a whole radius r (e.g. (6, 8, 0) for 10 mm)
    // equals the iso-value of that sphere exactly.
    let vol = field(37, [1.0; 3], |x, y, z| {
        let r = (x * x + y * y + z * z).sqrt();
        (50.0 * (10.0 - r)).clamp(-1000.0, 1000.0).round()
    });
    let ties = |iso: f32| vol.data.iter().filter(|&&v| v == iso).count();
    for iso in [0.0f32, 250.0, -250.0, 100.0] {
        assert!(ties(iso) >= 6, "only {} samples at {iso}", ties(iso));
        let mesh = marching_cubes(vol.data.view(), &vol.frame, iso);
        assert_surface(&mesh, 2, &format!("HU sphere at {iso}"));
        // The surface is the sphere r = 10 − iso/50 mm; sampling and rounding cost under 3 %.
        let r = 10.0 - f64::from(iso) / 50.0;
        let v0 = 4.0 / 3.0 * PI * r.powi(3);
        let v = mesh.volume_mm3();
        assert!(rel(v, v0) < 0.03, "iso {iso}: {v} vs {v0}");
    }
}

#[test]
fn a_torus_has_euler_characteristic_zero_and_its_closed_form_measures() {
    let (big, small) = (10.0f64, 4.0f64);
    let vol = field(36, [1.0; 3], |x, y, z| {
        let q = ((x * x + y * y).sqrt() - big).hypot(z);
        small - q
    });
    let mesh = marching_cubes(vol.data.view(), &vol.frame, 0.0);
    assert_surface(&mesh, 0, "smooth torus");
    let (v0, a0) = (
        2.0 * PI * PI * big * small * small,
        4.0 * PI * PI * big * small,
    );
    assert!(rel(mesh.volume_mm3(), v0) < 0.02, "{}", mesh.volume_mm3());
    assert!(rel(mesh.area_mm2(), a0) < 0.02, "{}", mesh.area_mm2());
    // The same torus as a label map meshed at its label.
    let binary = vol.data.mapv(|v| if v >= 0.0 { 1.0f32 } else { 0.0 });
    let mesh = marching_cubes(binary.view(), &vol.frame, 1.0);
    assert_surface(&mesh, 0, "labelled torus at iso 1");
}

#[test]
fn two_spheres_count_twice_and_the_pipeline_reports_the_final_mesh() {
    let vol = field(40, [1.0; 3], |x, y, z| {
        let a = 8.0 - ((x + 9.0).powi(2) + y * y + z * z).sqrt();
        let b = 5.0 - ((x - 10.0).powi(2) + y * y + z * z).sqrt();
        a.max(b)
    });
    let both = MeshOptions {
        iso: 0.0,
        largest_component: false,
        smoothing: 0,
        target_triangles: None,
        clip: Default::default(),
    };
    let (mesh, stats) = extract(&vol, &both).unwrap();
    assert_eq!(stats.euler_characteristic, 4);
    assert!(stats.closed && stats.manifold && stats.warnings.is_empty());
    assert_eq!(stats.triangles, mesh.triangle_count());
    // Smoothed and decimated: still one closed manifold sphere, measured after both.
    let smooth = MeshOptions {
        largest_component: true,
        smoothing: 10,
        target_triangles: Some(1500),
        ..both
    };
    let (mesh, stats) = extract(&vol, &smooth).unwrap();
    assert_surface(&mesh, 2, "smoothed, decimated sphere");
    assert!(stats.triangles <= 1500 && stats.triangles == mesh.triangle_count());
    assert!(stats.manifold && stats.euler_characteristic == 2);
    assert!((stats.volume_mm3 - mesh.volume_mm3()).abs() < 1e-9);
    assert!(rel(stats.volume_mm3, 4.0 / 3.0 * PI * 512.0) < 0.04);
    assert!(stats.warnings.is_empty(), "{:?}", stats.warnings);
}

/// A torus (χ = 0) of tube radius `small` around a circle of radius `big` (mm), in HU: 1000 on the circle,
/// falling by 2000 HU per tube radius (0 HU at half the tube radius), −1000 outside; 1 mm voxels.
fn hu_torus(big: f64, small: f64, n: [usize; 3]) -> Volume {
    let grid = VolumeGrid {
        nx: n[0],
        ny: n[1],
        nz: n[2],
        spacing_mm: [1.0; 3],
        centre_mm: [0.0; 3],
    };
    Volume {
        data: Array3::from_shape_fn((n[2], n[1], n[0]), |(k, j, i)| {
            let (x, y, z) = (grid.x(i), grid.y(j), grid.z(k));
            let q = ((x * x + y * y).sqrt() - big).hypot(z);
            (1000.0 - 2000.0 * q / small).max(-1000.0) as f32
        }),
        frame: Frame::from_grid(&grid),
    }
}

#[test]
fn an_unreachable_triangle_target_and_an_empty_surface_are_reported_as_warnings() {
    // A torus needs at least 14 triangles, so decimation that keeps it a closed manifold stops above 4.
    let vol = hu_torus(14.0, 8.0, [48, 48, 24]);
    let opts = MeshOptions {
        iso: 0.0,
        largest_component: true,
        smoothing: 0,
        target_triangles: Some(4),
        clip: Default::default(),
    };
    let (mesh, stats) = extract(&vol, &opts).unwrap();
    assert!(mesh.triangle_count() >= 14, "{}", mesh.triangle_count());
    assert!(stats.closed && stats.manifold && stats.euler_characteristic == 0);
    assert_eq!(stats.warnings.len(), 1, "{:?}", stats.warnings);
    assert!(stats.warnings[0].contains("target_triangles 4 not reached"));
    // A sphere can go down to a tetrahedron: no warning.
    let sphere = field(20, [1.0; 3], |x, y, z| 6.0 - (x * x + y * y + z * z).sqrt());
    let (mesh, stats) = extract(&sphere, &opts).unwrap();
    assert_eq!(mesh.triangle_count(), 4);
    assert!(stats.manifold && stats.euler_characteristic == 2 && stats.warnings.is_empty());
    let above = MeshOptions {
        iso: 100.0,
        target_triangles: None,
        ..opts
    };
    let (mesh, stats) = extract(&sphere, &above).unwrap();
    assert_eq!(mesh.triangle_count(), 0);
    assert!(!stats.closed && !stats.manifold);
    assert_eq!(stats.warnings.len(), 1, "{:?}", stats.warnings);
    assert!(stats.warnings[0].contains("is empty"));
}

#[test]
fn a_sheet_one_sample_thick_at_exactly_the_iso_value_encloses_nothing() {
    // A plane of samples equal to the iso-value between samples below it has no volume: it vanishes instead
    // of leaving two coincident sheets of opposite orientation.
    let vol = field(9, [1.0; 3], |x, y, z| {
        if x.abs() < 3.5 && y.abs() < 3.5 && z.abs() < 0.1 {
            1.0
        } else {
            0.0
        }
    });
    assert_eq!(vol.data.iter().filter(|&&v| v == 1.0).count(), 49);
    let mesh = marching_cubes(vol.data.view(), &vol.frame, 1.0);
    assert_eq!(mesh.triangle_count(), 0, "{:?}", mesh.topology());
}

/// Upload `vol` as a CT series (multipart, one part per file); returns the series JSON.
async fn upload_series(app: &common::TestApp, vol: &Volume) -> serde_json::Value {
    let meta = SeriesMeta {
        series_description: "torus".into(),
        ..Default::default()
    };
    let files = write_ct_series(vol, &meta).unwrap().files;
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
    assert_eq!(r.status(), 201);
    let v: serde_json::Value = r.json().await.unwrap();
    v["series"][0]["series"].clone()
}

#[tokio::test]
async fn an_iso_value_above_the_data_is_refused_and_unmet_requests_are_warned_about() {
    let app = spawn_app().await;
    let series = upload_series(&app, &hu_torus(14.0, 8.0, [48, 48, 24])).await;
    let sid = series["id"].as_str().unwrap().to_string();
    let max = series["hu_max"].as_f64().unwrap();
    assert!(max > 500.0 && max <= 1000.5, "{series}");
    let above = max + 10.0;

    // Above the maximum: refused at submission, with or without a smoothing step (which cannot raise it).
    for steps in [json!([]), json!([{"op": "gaussian", "sigma_mm": 1.0}])] {
        let r = app
            .post_json(
                "/v1/jobs",
                &json!({"kind": "volume", "input": sid, "steps": steps,
                                            "products": [{"type": "mesh", "iso": above}]}),
            )
            .await;
        let p = assert_problem(r, 422, "iso_out_of_range").await;
        assert!(p["detail"].as_str().unwrap().contains("products[0]"), "{p}");
    }

    // The torus at 0 HU (half the tube radius): closed, manifold, χ = 0 after decimation; four triangles
    // cannot be reached and that is said.
    let v = app
        .submit(&json!({"kind": "volume", "input": sid,
                        "products": [{"type": "mesh", "iso": 0, "target_triangles": 4}]}))
        .await;
    let id = v["id"].as_str().unwrap().to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let mesh = &done["result"]["products"][0]["mesh"];
    let n = mesh["triangles"].as_u64().unwrap();
    assert!(n >= 14, "{mesh}");
    assert_eq!(
        (mesh["closed"].as_bool(), mesh["manifold"].as_bool()),
        (Some(true), Some(true)),
        "{mesh}"
    );
    assert_eq!(mesh["euler_characteristic"], 0, "{mesh}");
    let warning = mesh["warnings"][0].as_str().unwrap();
    assert!(
        warning.contains("target_triangles 4 not reached")
            && warning.contains(&format!("{n} triangles")),
        "{warning}"
    );
    // The view of that result refuses an iso-value above its data too.
    let r = app
        .get(&format!("/v1/jobs/{id}/result/mesh.stl?iso={above}"))
        .await;
    assert_problem(r, 422, "iso_out_of_range").await;
    let r = app
        .get(&format!("/v1/jobs/{id}/result/mesh.stl?iso=0"))
        .await;
    assert_eq!(r.status(), 200);

    // At the maximum, after smoothing lowered the ridge: accepted, and the empty surface says why.
    let v = app
        .submit(&json!({"kind": "volume", "input": sid,
                        "steps": [{"op": "gaussian", "sigma_mm": 1.5}],
                        "products": [{"type": "mesh", "iso": max}]}))
        .await;
    let done = app.finish(v["id"].as_str().unwrap()).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let product = &done["result"]["products"][0];
    assert_eq!(product["mesh"]["triangles"], 0, "{product}");
    assert_eq!(product["file"]["bytes"], 84);
    assert_eq!(product["mesh"]["closed"], false);
    assert!(
        product["mesh"]["warnings"][0]
            .as_str()
            .unwrap()
            .contains("is empty"),
        "{product}"
    );
}
