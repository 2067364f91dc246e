use std::f64::consts::PI;

use ndarray::Array3;

use super::*;
use crate::recon::grid::VolumeGrid;
use crate::volume::Frame;

/// A `[z][y][x]` volume of `n³` voxels of `voxel_mm` holding `f(x, y, z)` at voxel centres (mm).
fn field(n: usize, voxel_mm: [f64; 3], f: impl Fn(f64, f64, f64) -> f64) -> (Array3<f32>, Frame) {
    let grid = VolumeGrid {
        nx: n,
        ny: n,
        nz: n,
        spacing_mm: voxel_mm,
        centre_mm: [0.0; 3],
    };
    let frame = Frame::from_grid(&grid);
    let vol = Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        f(grid.x(i), grid.y(j), grid.z(k)) as f32
    });
    (vol, frame)
}

fn rel(got: f64, want: f64) -> f64 {
    (got - want).abs() / want
}

#[test]
fn spheres_have_the_area_and_volume_of_a_sphere_within_2_percent() {
    for (r_vox, voxel) in [
        (10.0f64, [1.0f64, 1.0, 1.0]),
        (16.0, [0.5, 0.5, 0.5]),
        (24.0, [0.8, 0.8, 1.2]),
    ] {
        let r_mm = r_vox * voxel[0];
        let n = (2.0 * r_mm / voxel[0].min(voxel[2])) as usize + 8;
        let (vol, frame) = field(n, voxel, |x, y, z| r_mm - (x * x + y * y + z * z).sqrt());
        let mesh = marching_cubes(vol.view(), &frame, 0.0);
        let (area, volume) = (mesh.area_mm2(), mesh.volume_mm3());
        let (a0, v0) = (4.0 * PI * r_mm * r_mm, 4.0 / 3.0 * PI * r_mm.powi(3));
        assert!(mesh.is_closed(), "r = {r_vox} voxels");
        assert!(rel(area, a0) < 0.02, "area {area} vs {a0}");
        assert!(rel(volume, v0) < 0.02, "volume {volume} vs {v0}");
    }
}

#[test]
fn a_prolate_spheroid_has_its_closed_form_area_and_volume_within_2_percent() {
    let (a, c) = (10.0f64, 16.0f64);
    let (vol, frame) = field(44, [1.0; 3], |x, y, z| {
        1.0 - ((x / a).powi(2) + (y / a).powi(2) + (z / c).powi(2)).sqrt()
    });
    let mesh = marching_cubes(vol.view(), &frame, 0.0);
    let e = (1.0 - a * a / (c * c)).sqrt();
    let area0 = 2.0 * PI * a * a * (1.0 + c / (a * e) * e.asin());
    let volume0 = 4.0 / 3.0 * PI * a * a * c;
    assert!(mesh.is_closed());
    assert!(
        rel(mesh.area_mm2(), area0) < 0.02,
        "{} vs {area0}",
        mesh.area_mm2()
    );
    assert!(
        rel(mesh.volume_mm3(), volume0) < 0.02,
        "{} vs {volume0}",
        mesh.volume_mm3()
    );
}

#[test]
fn a_solid_touching_the_border_is_closed_at_the_border() {
    let vol = Array3::from_elem((4, 5, 6), 1.0f32);
    let frame = Frame::from_grid(&VolumeGrid {
        nx: 6,
        ny: 5,
        nz: 4,
        spacing_mm: [1.0, 2.0, 3.0],
        centre_mm: [0.0; 3],
    });
    let mesh = marching_cubes(vol.view(), &frame, 0.5);
    assert!(mesh.is_closed());
    // The box reaches half a voxel beyond the outer voxel centres on every side; marching cubes bevels its
    // edges and corners by half a voxel, which removes a few percent.
    let full = (6.0 * 1.0) * (5.0 * 2.0) * (4.0 * 3.0);
    let inner = (5.0 * 1.0) * (4.0 * 2.0) * (3.0 * 3.0);
    let v = mesh.volume_mm3();
    assert!(v > inner && v < full, "{v} not in ({inner}, {full})");
}

#[test]
fn noisy_random_volumes_always_give_closed_consistently_oriented_meshes() {
    let mut state = 12345u64;
    let vol = Array3::from_shape_fn((9, 10, 11), |_| {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    });
    let frame = Frame::from_grid(&VolumeGrid::cube(1, 1.0));
    let mesh = marching_cubes(vol.view(), &frame, 0.5);
    assert!(mesh.triangle_count() > 100);
    let t = mesh.topology();
    assert!(t.closed && t.manifold, "{t:?}");
    assert_eq!(t.euler_characteristic % 2, 0);
    assert!(mesh.volume_mm3() > 0.0);
    // Quantised to 0, 0.5 and 1 and meshed at 0.5: a third of the samples tie, still a closed manifold.
    let ties = vol.mapv(|v| (v * 2.0).round() / 2.0);
    let mesh = marching_cubes(ties.view(), &frame, 0.5);
    let t = mesh.topology();
    assert!(t.closed && t.manifold, "{t:?}");
}

#[test]
fn vertices_keep_snap_from_the_samples_at_the_ends_of_their_edges() {
    // One sample of 1 in zeros at iso 1: the six vertices sit SNAP of a voxel from it, an octahedron.
    let mut vol = Array3::<f32>::zeros((3, 3, 3));
    vol[[1, 1, 1]] = 1.0;
    let frame = Frame::from_grid(&VolumeGrid::cube(3, 2.0));
    let mesh = marching_cubes(vol.view(), &frame, 1.0);
    assert_eq!((mesh.vertices.len(), mesh.triangle_count()), (6, 8));
    let centre = frame.position(1.0, 1.0, 1.0);
    for p in &mesh.vertices {
        let d = (0..3)
            .map(|a| (f64::from(p[a]) - centre[a]).powi(2))
            .sum::<f64>()
            .sqrt();
        assert!((d - 2.0 * f64::from(SNAP)).abs() < 1e-5, "{d}");
    }
    let t = mesh.topology();
    assert!(t.closed && t.manifold && t.euler_characteristic == 2);
    // Its volume: the octahedron of radius 2 SNAP mm.
    let v0 = 4.0 / 3.0 * (2.0 * f64::from(SNAP)).powi(3);
    assert!(rel(mesh.volume_mm3(), v0) < 1e-3, "{}", mesh.volume_mm3());
}

#[test]
fn the_largest_component_keeps_the_bigger_of_two_spheres() {
    let (vol, frame) = field(40, [1.0; 3], |x, y, z| {
        let a = 8.0 - ((x + 9.0).powi(2) + y * y + z * z).sqrt();
        let b = 5.0 - ((x - 10.0).powi(2) + y * y + z * z).sqrt();
        a.max(b)
    });
    let mesh = marching_cubes(vol.view(), &frame, 0.0);
    let big = mesh.largest_component();
    assert!(big.is_closed());
    assert!(rel(big.volume_mm3(), 4.0 / 3.0 * PI * 512.0) < 0.03);
    assert!(big.triangle_count() < mesh.triangle_count());
}

#[test]
fn taubin_smoothing_keeps_the_volume_of_a_blocky_sphere() {
    let (vol, frame) = field(32, [1.0; 3], |x, y, z| {
        if x * x + y * y + z * z < 144.0 {
            1.0
        } else {
            0.0
        }
    });
    let mut mesh = marching_cubes(vol.view(), &frame, 0.5);
    let before = mesh.volume_mm3();
    taubin(&mut mesh, 10);
    let t = mesh.topology();
    assert!(
        t.closed && t.manifold && t.euler_characteristic == 2,
        "{t:?}"
    );
    assert!(
        rel(mesh.volume_mm3(), before) < 0.03,
        "{} vs {before}",
        mesh.volume_mm3()
    );
    // Smoothing brings the staircase area closer to the sphere's.
    let sphere = 4.0 * PI * 144.0;
    assert!(
        rel(mesh.area_mm2(), sphere) < 0.08,
        "{} vs {sphere}",
        mesh.area_mm2()
    );
}

#[test]
fn binary_stl_has_the_lps_header_and_round_trips() {
    let (vol, frame) = field(16, [1.0; 3], |x, y, z| 5.0 - (x * x + y * y + z * z).sqrt());
    let mesh = marching_cubes(vol.view(), &frame, 0.0);
    let bytes = mesh.to_stl_binary();
    assert_eq!(bytes.len(), 84 + 50 * mesh.triangle_count());
    assert!(!bytes.starts_with(b"solid"));
    assert!(String::from_utf8_lossy(&bytes[..80]).contains("SPACE=LPS"));
    let (back, _) = parse_stl_binary(&bytes).unwrap();
    assert_eq!(back.triangle_count(), mesh.triangle_count());
    assert!(rel(back.volume_mm3(), mesh.volume_mm3()) < 1e-6);
    assert!(matches!(
        parse_stl_binary(&bytes[..100]),
        Err(StlError::SizeMismatch { .. })
    ));
}

#[test]
fn decimation_to_a_quarter_keeps_a_sphere_closed_and_its_measures_within_3_percent() {
    let r = 12.0;
    let (vol, frame) = field(32, [1.0; 3], |x, y, z| r - (x * x + y * y + z * z).sqrt());
    let mesh = marching_cubes(vol.view(), &frame, 0.0);
    let target = mesh.triangle_count() / 4;
    let small = decimate(&mesh, target);
    assert!(
        small.triangle_count() <= target,
        "{} > {target}",
        small.triangle_count()
    );
    assert!(small.triangle_count() > target / 2);
    let t = small.topology();
    assert!(
        t.closed && t.manifold && t.euler_characteristic == 2,
        "{t:?}"
    );
    assert!(
        rel(small.area_mm2(), 4.0 * PI * r * r) < 0.03,
        "{}",
        small.area_mm2()
    );
    assert!(
        rel(small.volume_mm3(), 4.0 / 3.0 * PI * r.powi(3)) < 0.03,
        "{}",
        small.volume_mm3()
    );
    assert_eq!(decimate(&mesh, usize::MAX), mesh);
}

#[test]
fn the_bitset_passes_give_the_mesh_of_the_byte_per_point_reference_exactly() {
    let mut state = 99u64;
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    // Row lengths around the 64-bit word (padded rows of 63, 64, 65 and 130 points), thin volumes, ties,
    // NaN and infinite samples, a strided view.
    for (nz, ny, nx) in [
        (1, 1, 1),
        (3, 4, 61),
        (2, 5, 62),
        (4, 3, 63),
        (3, 3, 128),
        (5, 6, 70),
        (7, 2, 1),
    ] {
        let noise = Array3::from_shape_fn((nz, ny, nx), |_| next());
        let ties = noise.mapv(|v| (v * 2.0).round() / 2.0);
        let mut odd = noise.clone();
        for (n, v) in odd.iter_mut().enumerate() {
            match n % 13 {
                3 => *v = f32::NAN,
                7 => *v = f32::INFINITY,
                11 => *v = f32::NEG_INFINITY,
                _ => {}
            }
        }
        let frame = Frame::from_grid(&VolumeGrid::cube(1, 0.7));
        for (name, vol) in [("noise", &noise), ("ties", &ties), ("odd", &odd)] {
            for iso in [0.5f32, 0.0, 1.0, 0.25] {
                let got = marching_cubes(vol.view(), &frame, iso);
                let want = super::marching_reference::marching_cubes(vol.view(), &frame, iso);
                assert_eq!(
                    got.triangles, want.triangles,
                    "{name} {nz}×{ny}×{nx} at {iso}"
                );
                let bits = |m: &Mesh| {
                    m.vertices
                        .iter()
                        .map(|p| p.map(f32::to_bits))
                        .collect::<Vec<_>>()
                };
                assert_eq!(bits(&got), bits(&want), "{name} {nz}×{ny}×{nx} at {iso}");
            }
        }
        let strided = noise.slice(ndarray::s![.., .., ..;2]);
        let got = marching_cubes(strided, &frame, 0.5);
        let want = super::marching_reference::marching_cubes(strided, &frame, 0.5);
        assert_eq!(
            (got.triangles, got.vertices),
            (want.triangles, want.vertices)
        );
    }
    // A smooth closed surface in a volume whose rows span several words.
    let (vol, frame) = field(140, [0.5, 0.6, 0.7], |x, y, z| {
        30.0 - (x * x + 1.5 * y * y + 0.7 * z * z).sqrt() + 3.0 * (x / 4.0).sin()
    });
    let got = marching_cubes(vol.view(), &frame, 0.0);
    let want = super::marching_reference::marching_cubes(vol.view(), &frame, 0.0);
    assert!(got.triangle_count() > 20_000, "{}", got.triangle_count());
    // The form compiled without POPCNT (what a CPU without it runs) gives the same mesh.
    let plain = super::marching::marching(vol.view(), &frame, 0.0);
    assert_eq!(
        (&plain.triangles, &plain.vertices),
        (&want.triangles, &want.vertices)
    );
    assert_eq!(
        (got.triangles, got.vertices),
        (want.triangles, want.vertices)
    );
}
