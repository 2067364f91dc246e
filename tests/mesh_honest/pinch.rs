//! Where merging vertices onto samples equal to the iso-value would pinch the surface: solids of value = iso that
//! share one sample or one line of samples, a rod whose waist sample equals the iso-value, and noisy integer
//! volumes at an integer iso-value. Each mesh is a closed 2-manifold with no zero-area triangle and no two
//! vertices at one place, its Euler characteristic what the solids' topology says, and smoothing and
//! decimation keep it so.

use ctrecon::mesh::{MeshOptions, SNAP, extract, marching_cubes};
use ndarray::Array3;

use super::{assert_no_degeneracy, assert_surface, field, rel};

/// 1 inside the closed boxes `boxes` (`[lo, hi]` per axis, mm; 1 mm voxels centred on the origin), 0 elsewhere.
fn boxes(n: usize, boxes: &[[[f64; 2]; 3]]) -> ctrecon::volume::Volume {
    field(n, [1.0; 3], |x, y, z| {
        let within = |b: &[[f64; 2]; 3]| {
            [x, y, z]
                .iter()
                .zip(b)
                .all(|(c, [lo, hi])| *c > lo - 0.1 && *c < hi + 0.1)
        };
        if boxes.iter().any(within) { 1.0 } else { 0.0 }
    })
}

#[test]
fn two_cubes_at_the_iso_value_sharing_a_corner_or_an_edge_are_one_manifold_solid() {
    // 3 × 3 × 3 samples each, meeting in the sample at the origin, or in the line of samples on the z axis.
    let corner = boxes(11, &[[[-2.0, 0.0]; 3], [[0.0, 2.0]; 3]]);
    let edge = boxes(
        11,
        &[
            [[-2.0, 0.0], [-2.0, 0.0], [-2.0, 2.0]],
            [[0.0, 2.0], [0.0, 2.0], [-2.0, 2.0]],
        ],
    );
    for (vol, what, boxes_mm3, shared) in [(corner, "corner", 16.0, 1.0), (edge, "edge", 32.0, 5.0)]
    {
        let ties = vol.data.iter().filter(|&&v| v == 1.0).count();
        let mesh = marching_cubes(vol.data.view(), &vol.frame, 1.0);
        // One solid through the shared samples: a sphere-like surface.
        assert_surface(&mesh, 2, what);
        // The two boxes through their outer samples, and part of the cells bridging them around the shared
        // samples (at most the 8 cells of 1 mm³ around each).
        let v = mesh.volume_mm3();
        println!("cubes sharing a {what}: {ties} samples at iso, volume {v:.3} mm³");
        assert!(v > boxes_mm3 && v < boxes_mm3 + 8.0 * shared, "{what}: {v}");
    }
}

#[test]
fn two_cubes_at_the_iso_value_touching_diagonally_stay_two_boxes() {
    // Nearest samples of the two cubes are diagonal neighbours (a cell corner, or a cell face diagonal along a
    // line): marching cubes keeps diagonal inside corners apart, so these are two boxes, χ = 2 + 2.
    let corner = boxes(11, &[[[-3.0, -1.0]; 3], [[0.0, 2.0]; 3]]);
    let edge = boxes(
        11,
        &[
            [[-3.0, -1.0], [-3.0, -1.0], [-2.0, 0.0]],
            [[0.0, 2.0], [0.0, 2.0], [-2.0, 0.0]],
        ],
    );
    let side = 2.0 + 2.0 * f64::from(SNAP);
    for (vol, what) in [(corner, "corner"), (edge, "edge")] {
        let mesh = marching_cubes(vol.data.view(), &vol.frame, 1.0);
        assert_surface(&mesh, 4, what);
        let v = mesh.volume_mm3();
        assert!(
            rel(v, 2.0 * side.powi(3)) < 1e-5,
            "{what}: {v} vs {}",
            2.0 * side.powi(3)
        );
    }
}

#[test]
fn a_rod_whose_waist_sample_equals_the_iso_value_is_one_capsule_not_two_cones() {
    // 101 HU along the x axis, 100 HU at the origin, 0 around; meshed at 100 HU. Welding the waist's vertices
    // onto its sample would join two cones at their apex (χ = 3); the surface passes SNAP around it instead.
    let vol = field(13, [1.0; 3], |x, y, z| {
        if y.abs() < 0.1 && z.abs() < 0.1 && x.abs() < 4.1 {
            if x.abs() < 0.1 { 100.0 } else { 101.0 }
        } else {
            0.0
        }
    });
    let mesh = marching_cubes(vol.data.view(), &vol.frame, 100.0);
    assert_surface(&mesh, 2, "rod with a waist");
    assert_eq!(
        mesh.largest_component().triangle_count(),
        mesh.triangle_count()
    );
}

/// A sphere of radius 10 mm in whole HU (20 HU per mm, 0 HU on the sphere) plus integer noise in [−30, 30] HU,
/// on 1 mm voxels: the surface wanders by ±1.5 mm, and islands and handles come and go.
fn noisy_sphere() -> ctrecon::volume::Volume {
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut vol = field(41, [1.0; 3], |x, y, z| {
        let r = (x * x + y * y + z * z).sqrt();
        (20.0 * (10.0 - r)).clamp(-1000.0, 1000.0).round()
    });
    vol.data.mapv_inplace(|v| {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        v + ((state >> 33) % 61) as f32 - 30.0
    });
    vol
}

#[test]
fn a_noisy_integer_volume_at_integer_iso_values_is_a_closed_manifold_everywhere() {
    let vol = noisy_sphere();
    // Merging the vertices at the samples equal to the iso-value made each of these closed but not manifold.
    for iso in [0.0f32, 50.0, -100.0] {
        let ties = vol.data.iter().filter(|&&v| v == iso).count();
        assert!(ties >= 10, "only {ties} samples at {iso}");
        // Every piece, the noise's islands included.
        let mesh = marching_cubes(vol.data.view(), &vol.frame, iso);
        let t = mesh.topology();
        println!(
            "noisy sphere at {iso}: {ties} samples at iso, {} triangles, χ {}",
            mesh.triangle_count(),
            t.euler_characteristic
        );
        assert!(t.closed && t.manifold, "iso {iso}: {t:?}");
        // A union of closed orientable surfaces: χ = 2 (pieces − handles), even.
        assert_eq!(t.euler_characteristic % 2, 0, "iso {iso}");
        assert_no_degeneracy(&mesh);
        // The largest piece is the sphere r = 10 − iso/20 mm, its surface jittered by ±1.5 mm of noise.
        let big = mesh.largest_component();
        let r = 10.0 - f64::from(iso) / 20.0;
        let v0 = 4.0 / 3.0 * std::f64::consts::PI * r.powi(3);
        assert!(
            rel(big.volume_mm3(), v0) < 0.08,
            "iso {iso}: {} vs {v0}",
            big.volume_mm3()
        );
    }
}

#[test]
fn smoothing_and_decimating_a_noisy_integer_sphere_keep_it_a_closed_manifold() {
    let vol = noisy_sphere();
    let raw = MeshOptions {
        iso: 0.0,
        largest_component: true,
        smoothing: 0,
        target_triangles: None,
        clip: Default::default(),
    };
    let (mesh, stats) = extract(&vol, &raw).unwrap();
    assert!(stats.closed && stats.manifold, "{stats:?}");
    let chi = stats.euler_characteristic;
    let target = mesh.triangle_count() / 5;
    for smoothing in [0, 10] {
        let opts = MeshOptions {
            smoothing,
            target_triangles: Some(target),
            ..raw.clone()
        };
        let (small, stats) = extract(&vol, &opts).unwrap();
        println!(
            "smoothing {smoothing}: {} → {} triangles (target {target}), χ {chi}",
            mesh.triangle_count(),
            stats.triangles
        );
        // Smoothing moves vertices and decimation collapses edges only where the link condition holds: the
        // topology is the raw mesh's.
        assert_surface(&small, chi, &format!("smoothing {smoothing}, decimated"));
        assert!(stats.triangles <= target, "{}", stats.triangles);
        assert!(stats.warnings.is_empty(), "{:?}", stats.warnings);
        assert!(
            rel(stats.volume_mm3, mesh.volume_mm3()) < 0.05,
            "{} vs {}",
            stats.volume_mm3,
            mesh.volume_mm3()
        );
    }
}

#[test]
fn random_labels_meshed_at_each_label_value_are_closed_manifolds() {
    // Label values 0..=3 at random, meshed at every label: the worst case for ties.
    let mut state = 7u64;
    let data = Array3::from_shape_fn((12, 13, 14), |_| {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 33) % 4) as f32
    });
    let vol = ctrecon::volume::Volume {
        data,
        frame: field(1, [1.0; 3], |_, _, _| 0.0).frame,
    };
    for iso in [1.0f32, 2.0, 3.0] {
        let mesh = marching_cubes(vol.data.view(), &vol.frame, iso);
        let t = mesh.topology();
        assert!(t.closed && t.manifold, "labels at {iso}: {t:?}");
        assert_no_degeneracy(&mesh);
    }
}
