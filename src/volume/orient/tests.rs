use super::*;
use crate::volume::{ScreenSides, direction_label};

type V3 = [f64; 3];
use ndarray::Array3;

/// The 48 signed permutation matrices, as direction rows (index axis → patient unit vector).
fn signed_permutations() -> Vec<[[f64; 3]; 3]> {
    let perms = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    let mut out = Vec::new();
    for p in perms {
        for signs in 0..8 {
            let d: [[f64; 3]; 3] = std::array::from_fn(|a| {
                let mut v = [0.0; 3];
                v[p[a]] = if (signs >> a) & 1 == 1 { -1.0 } else { 1.0 };
                v
            });
            out.push(d);
        }
    }
    out
}

fn ramp(dim: (usize, usize, usize)) -> Array3<f32> {
    Array3::from_shape_fn(dim, |(k, j, i)| (10_000 * k + 100 * j + i) as f32)
}

fn close(a: V3, b: V3, tol: f64) -> bool {
    (0..3).all(|c| (a[c] - b[c]).abs() <= tol)
}

#[test]
fn canonical_order_keeps_every_voxel_at_its_patient_position_for_all_48_orientations() {
    let dim = (3, 4, 5);
    for direction in signed_permutations() {
        let vol = Volume {
            data: ramp(dim),
            frame: Frame {
                spacing_mm: [0.5, 0.75, 2.0],
                origin_mm: [-10.0, 20.0, 30.0],
                direction,
            },
        };
        let canon = to_closest_canonical(vol.clone());
        assert!(
            is_axis_aligned(&canon.frame),
            "{direction:?} → {:?}",
            canon.frame.direction
        );
        let map = canon.frame.index_map().unwrap();
        for ((k, j, i), &v) in vol.data.indexed_iter() {
            let p = vol.frame.position(k as f64, j as f64, i as f64);
            let idx = map.index(p);
            let r = idx.map(|x| x.round());
            assert!(close(idx, r, 1e-9), "{direction:?}: {idx:?}");
            let got = canon.data[[r[0] as usize, r[1] as usize, r[2] as usize]];
            assert_eq!(got, v, "{direction:?} at [{k}][{j}][{i}]");
        }
        // The canonical origin is the voxel with the smallest x, y and z.
        let lo: V3 = std::array::from_fn(|c| {
            vol.data
                .indexed_iter()
                .map(|((k, j, i), _)| vol.frame.position(k as f64, j as f64, i as f64)[c])
                .fold(f64::INFINITY, f64::min)
        });
        assert!(close(canon.frame.origin_mm, lo, 1e-9));
    }
}

#[test]
fn an_oblique_frame_is_reordered_exactly_and_keeps_its_residual_rotation() {
    let t = 12f64.to_radians();
    // A feet-first series with a 12° gantry tilt: rows run right (−x), columns posterior-inferior,
    // slices step inferior.
    let vol = Volume {
        data: ramp((4, 3, 2)),
        frame: Frame {
            spacing_mm: [0.7, 0.7, 2.5],
            origin_mm: [100.0, -50.0, 0.0],
            direction: [[-1.0, 0.0, 0.0], [0.0, t.cos(), -t.sin()], [0.0, 0.0, -1.0]],
        },
    };
    let canon = to_closest_canonical(vol.clone());
    assert!(!is_axis_aligned(&canon.frame));
    let d = canon.frame.direction;
    assert!(d[0][0] > 0.99 && d[1][1] > 0.97 && d[2][2] > 0.99, "{d:?}");
    let map = canon.frame.index_map().unwrap();
    for ((k, j, i), &v) in vol.data.indexed_iter() {
        let idx = map.index(vol.frame.position(k as f64, j as f64, i as f64));
        let r = idx.map(|x| x.round());
        assert!(close(idx, r, 1e-9));
        assert_eq!(canon.data[[r[0] as usize, r[1] as usize, r[2] as usize]], v);
    }
}

#[test]
fn screen_sides_follow_the_radiological_convention() {
    let frame = Frame {
        spacing_mm: [1.0; 3],
        origin_mm: [0.0; 3],
        direction: Frame::AXIS_ALIGNED,
    };
    let grid = DisplayGrid::of(&frame, (5, 6, 7)).unwrap();
    let sides = |axis| grid.plane(axis, 0.0).sides();
    let want = |l: &str, r: &str, t: &str, b: &str| ScreenSides {
        left: l.into(),
        right: r.into(),
        top: t.into(),
        bottom: b.into(),
    };
    assert_eq!(sides(Axis::Axial), want("R", "L", "A", "P"));
    assert_eq!(sides(Axis::Coronal), want("R", "L", "S", "I"));
    assert_eq!(sides(Axis::Sagittal), want("A", "P", "S", "I"));
    assert_eq!(
        grid.plane(Axis::Coronal, 0.0).patient_orientation(),
        ["L".to_string(), "F".to_string()]
    );
    assert_eq!(direction_label([0.6, -0.8, 0.0]), "AL");
    assert_eq!(direction_label([0.0, 0.05, -1.0]), "I");
}

#[test]
fn the_image_plane_gives_the_patient_position_of_every_displayed_pixel() {
    let vol = Volume {
        data: ramp((3, 4, 5)),
        frame: Frame {
            spacing_mm: [0.5, 0.75, 2.0],
            origin_mm: [-10.0, 20.0, 30.0],
            direction: Frame::AXIS_ALIGNED,
        },
    };
    let map = vol.frame.index_map().unwrap();
    for (axis, index) in [(Axis::Axial, 1), (Axis::Coronal, 2), (Axis::Sagittal, 3)] {
        let (img, plane) = oriented_slice(
            &vol,
            &DisplayGrid::of(&vol.frame, vol.data.dim()).unwrap(),
            axis,
            index,
            0.0,
        )
        .unwrap();
        for ((r, c), &v) in img.indexed_iter() {
            let idx = map
                .index(plane.position(r as f64, c as f64))
                .map(|x| x.round() as usize);
            assert_eq!(vol.data[[idx[0], idx[1], idx[2]]], v, "{axis:?} ({r}, {c})");
        }
    }
}

#[test]
fn an_oblique_volume_is_shown_on_an_axis_aligned_grid_with_markers_where_the_patient_has_them() {
    // A 10° tilted volume with one bright voxel; the axial image through its height shows it at the pixel
    // whose plane position is the marker's patient position.
    let t = 10f64.to_radians();
    let frame = Frame {
        spacing_mm: [1.0, 1.0, 1.0],
        origin_mm: [0.0, 0.0, 0.0],
        direction: [[1.0, 0.0, 0.0], [0.0, t.cos(), t.sin()], [0.0, 0.0, 1.0]],
    };
    let mut data = Array3::<f32>::zeros((20, 20, 20));
    for dk in 0..2 {
        for dj in 0..2 {
            for di in 0..2 {
                data[[9 + dk, 9 + dj, 9 + di]] = 1000.0;
            }
        }
    }
    let vol = Volume { data, frame };
    let marker = frame.position(9.5, 9.5, 9.5);
    let grid = DisplayGrid::of(&frame, vol.data.dim()).unwrap();
    assert!(!grid.native);
    for axis in [Axis::Axial, Axis::Coronal, Axis::Sagittal] {
        let c = match axis {
            Axis::Axial => 2,
            Axis::Coronal => 1,
            Axis::Sagittal => 0,
        };
        let index =
            ((marker[c] - grid.frame.origin_mm[c]) / grid.frame.spacing_mm[c]).round() as usize;
        let (img, plane) = oriented_slice(&vol, &grid, axis, index, -1.0).unwrap();
        // Centroid of the bright pixels.
        let (mut sr, mut sc, mut sw) = (0.0, 0.0, 0.0);
        for ((r, col), &v) in img.indexed_iter() {
            if v > 100.0 {
                sr += r as f64 * v as f64;
                sc += col as f64 * v as f64;
                sw += v as f64;
            }
        }
        assert!(sw > 0.0, "{axis:?}: marker not seen");
        let p = plane.position(sr / sw, sc / sw);
        let in_plane: Vec<usize> = (0..3).filter(|&a| a != c).collect();
        for a in in_plane {
            assert!(
                (p[a] - marker[a]).abs() < 1.0,
                "{axis:?}: {p:?} vs {marker:?}"
            );
        }
        // Outside the sheared volume (above and below it in coronal and sagittal images) the fill shows.
        if axis != Axis::Axial {
            assert!(img.iter().any(|&v| v == -1.0), "{axis:?}");
        }
        let (mip, _) =
            oriented_projection(&vol, &grid, axis, ProjectionKind::Max, None, -1.0).unwrap();
        assert_eq!(mip.dim(), img.dim());
        assert!(mip.iter().copied().fold(f32::MIN, f32::max) > 500.0);
    }
}

#[test]
fn an_axis_aligned_volume_projects_as_the_array_functions_do() {
    let vol = Volume {
        data: ramp((3, 4, 5)),
        frame: Frame {
            spacing_mm: [1.0; 3],
            origin_mm: [0.0; 3],
            direction: Frame::AXIS_ALIGNED,
        },
    };
    let grid = DisplayGrid::of(&vol.frame, vol.data.dim()).unwrap();
    let (a, plane) = oriented_projection(
        &vol,
        &grid,
        Axis::Coronal,
        ProjectionKind::Mean,
        Some(1..3),
        0.0,
    )
    .unwrap();
    let b = project(
        vol.data.view(),
        Axis::Coronal,
        ProjectionKind::Mean,
        Some(1..3),
    )
    .unwrap();
    assert_eq!(a, b);
    // The plane of a slab is its middle.
    assert!(close(plane.first_pixel_mm, [0.0, 1.5, 2.0], 1e-12));
    assert!(
        oriented_projection(
            &vol,
            &grid,
            Axis::Axial,
            ProjectionKind::Max,
            Some(2..4),
            0.0
        )
        .is_err()
    );
}

#[test]
fn astra_rows_run_the_other_way() {
    let d = flip_rows(ramp((1, 3, 2)));
    assert_eq!(d[[0, 0, 1]], 201.0);
    assert_eq!(d[[0, 2, 0]], 0.0);
}
