//! Meshes report what they are: integer data meshed at an integer iso-value (label maps, HU) gives a closed
//! 2-manifold with no zero-area triangle and no two vertices at one place, and `closed`, `manifold` and the Euler
//! characteristic are read from the final mesh. Truth: boxes and spheres of known size, a torus (χ = 0), solids
//! touching at a corner or an edge, noisy integer volumes (`pinch`). Over HTTP (`http`): an iso-value above the
//! data is refused before any work, and what a surface could not honour comes back as a warning, in the mesh
//! product and in the mesh view's `X-Ctrecon-Warnings` header.

use crate::common;

mod http;
mod pinch;

use std::collections::HashSet;
use std::f64::consts::PI;

use ctrecon::mesh::{
    EMPTY_SURFACE, Mesh, MeshOptions, SNAP, TARGET_TRIANGLES_NOT_REACHED, extract, marching_cubes,
};
use ctrecon::recon::VolumeGrid;
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

/// An `n³` volume of `voxel_mm` voxels centred on the origin holding `f(x, y, z)` (mm) at voxel centres.
pub fn field(n: usize, voxel_mm: [f64; 3], f: impl Fn(f64, f64, f64) -> f64) -> Volume {
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

pub fn rel(got: f64, want: f64) -> f64 {
    (got - want).abs() / want
}

/// No triangle of zero area, no repeated corner, no two used vertices at the same position.
pub fn assert_no_degeneracy(m: &Mesh) {
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
pub fn assert_surface(m: &Mesh, chi: i64, what: &str) {
    let t = m.topology();
    assert!(t.closed && t.manifold, "{what}: {t:?}");
    assert_eq!(t.euler_characteristic, chi, "{what}");
    assert_no_degeneracy(m);
}

#[test]
fn a_cube_of_ones_at_iso_one_exactly_is_the_box_through_its_outer_voxel_centres() {
    // 6 voxels a side: the outer voxel centres span 5 voxels, and the surface passes SNAP of a voxel outside
    // them (the samples equal to the iso-value are inside), bevelled by SNAP along edges and corners.
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
        let snap = f64::from(SNAP);
        let side = voxel.map(|s| (5.0 + 2.0 * snap) * s);
        let volume = side[0] * side[1] * side[2];
        // Each of the 4 edges along axis a trades the two strips of width SNAP of its faces for their chord.
        let bevels: f64 = (0..3)
            .map(|a| {
                let (b, c) = (voxel[(a + 1) % 3], voxel[(a + 2) % 3]);
                4.0 * 5.0 * voxel[a] * snap * (b + c - b.hypot(c))
            })
            .sum();
        let area = 2.0 * (side[0] * side[1] + side[1] * side[2] + side[0] * side[2]) - bevels;
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
        // The hair outside the samples is what it says: 0.1 % of a voxel, over 1e-3 of the volume here.
        let inner = voxel.map(|s| 5.0 * s);
        assert!(rel(mesh.volume_mm3(), inner[0] * inner[1] * inner[2]) < 1.3e-3);
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
    // At an integer iso-value the surface runs (SNAP outside) through the outermost samples of the label, which lie on
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
pub fn hu_torus(big: f64, small: f64, n: [usize; 3]) -> Volume {
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
    assert_eq!(stats.warnings[0].code, TARGET_TRIANGLES_NOT_REACHED);
    assert!(
        stats.warnings[0].message.contains(&format!(
            "target_triangles 4 not reached: decimation stopped at {} triangles",
            mesh.triangle_count()
        )),
        "{:?}",
        stats.warnings
    );
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
    assert_eq!(stats.warnings[0].code, EMPTY_SURFACE);
    assert!(stats.warnings[0].message.contains("is empty"));
}

#[test]
fn a_sheet_one_sample_thick_at_exactly_the_iso_value_is_a_slab_two_snaps_thin() {
    // A plane of 7 × 7 samples equal to the iso-value between samples below it. The samples are inside, so the
    // mesh is a closed slab around them, SNAP of a voxel to either side: a sphere-like surface (χ = 2) with the
    // sheet's 6 × 6 mm on each side and a volume of 36 mm² × 2 SNAP, not two coincident sheets and not nothing.
    let vol = field(9, [1.0; 3], |x, y, z| {
        if x.abs() < 3.5 && y.abs() < 3.5 && z.abs() < 0.1 {
            1.0
        } else {
            0.0
        }
    });
    assert_eq!(vol.data.iter().filter(|&&v| v == 1.0).count(), 49);
    let mesh = marching_cubes(vol.data.view(), &vol.frame, 1.0);
    assert_surface(&mesh, 2, "sheet at its value");
    let snap = f64::from(SNAP);
    let (v, a) = (mesh.volume_mm3(), mesh.area_mm2());
    println!("sheet: volume {v:.5} mm³, area {a:.4} mm²");
    assert!(rel(v, 36.0 * 2.0 * snap) < 2e-3, "volume {v}");
    assert!(rel(a, 72.0) < 2e-3, "area {a}");
    // Above its value the sheet is gone: no sample is inside.
    assert_eq!(
        marching_cubes(vol.data.view(), &vol.frame, 1.5).triangle_count(),
        0
    );
}
