//! Cut-away meshes: a clipped iso-surface is capped on the cut, so it stays closed and encloses exactly the kept
//! part of the solid.

use ctrecon::mesh::{MeshOptions, extract};
use ctrecon::render::{Clip, ClipBox, ClipPlane, Keep};
use ctrecon::volume::{Frame, Volume};
use ndarray::Array3;

/// A ball of radius `r` mm as a signed distance (inside positive) on `n³` voxels of 1 mm centred on the origin.
fn ball(n: usize, r: f64) -> Volume {
    let h = (n as f64 - 1.0) / 2.0;
    let frame = Frame {
        spacing_mm: [1.0; 3],
        origin_mm: [-h; 3],
        direction: Frame::AXIS_ALIGNED,
    };
    let data = Array3::from_shape_fn((n, n, n), |(k, j, i)| {
        let p = frame.position(k as f64, j as f64, i as f64);
        (r - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()) as f32
    });
    Volume { data, frame }
}

fn options(clip: Clip) -> MeshOptions {
    MeshOptions {
        iso: 0.0,
        largest_component: false,
        smoothing: 0,
        target_triangles: None,
        clip,
    }
}

#[test]
fn a_sphere_clipped_through_its_centre_is_a_closed_half_ball_of_half_the_volume() {
    let r = 15.0;
    let vol = ball(40, r);
    let half = 2.0 / 3.0 * std::f64::consts::PI * r * r * r;
    for normal in [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 1.0, 0.0]] {
        let clip = Clip {
            planes: vec![ClipPlane {
                point_mm: [0.0; 3],
                normal,
            }],
            boxes: Vec::new(),
        };
        let (mesh, stats) = extract(&vol, &options(clip)).unwrap();
        assert!(stats.closed && stats.manifold, "{normal:?}: {stats:?}");
        assert_eq!(stats.euler_characteristic, 2, "{normal:?}");
        assert!(
            (stats.volume_mm3 - half).abs() / half < 0.01,
            "{normal:?}: {} mm³ vs half ball {half:.1}",
            stats.volume_mm3
        );
        // Every vertex lies on the kept side (within the marching-cubes interpolation of the cap).
        let n = (normal[0] * normal[0] + normal[1] * normal[1] + normal[2] * normal[2]).sqrt();
        let worst = mesh
            .vertices
            .iter()
            .map(|v| (0..3).map(|a| v[a] as f64 * normal[a] / n).sum::<f64>())
            .fold(f64::INFINITY, f64::min);
        assert!(
            worst > -0.05,
            "{normal:?}: a vertex {worst} mm on the cut side"
        );
    }
}

#[test]
fn a_box_cut_out_of_a_sphere_leaves_a_closed_surface_of_the_rest() {
    let r = 15.0;
    let vol = ball(40, r);
    // Remove the octant x > 0, y < 0, z > 0 (a classic cut-away).
    let clip = Clip {
        planes: Vec::new(),
        boxes: vec![ClipBox {
            centre_mm: [20.0, -20.0, 20.0],
            half_size_mm: [20.0, 20.0, 20.0],
            axes: None,
            keep: Keep::Outside,
        }],
    };
    let (_, stats) = extract(&vol, &options(clip)).unwrap();
    let seven_eighths = 7.0 / 8.0 * 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
    assert!(stats.closed && stats.manifold, "{stats:?}");
    assert!(
        (stats.volume_mm3 - seven_eighths).abs() / seven_eighths < 0.01,
        "{} vs {seven_eighths:.1}",
        stats.volume_mm3
    );
}

#[test]
fn a_zero_normal_is_refused() {
    let clip = Clip {
        planes: vec![ClipPlane {
            point_mm: [0.0; 3],
            normal: [0.0; 3],
        }],
        boxes: Vec::new(),
    };
    let e = extract(&ball(8, 2.0), &options(clip)).unwrap_err();
    assert_eq!(e.code(), "invalid_clip");
}
