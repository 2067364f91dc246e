//! Marching cubes over a `[z][y][x]` volume with shared vertices, parallel over z layers.
//!
//! Samples outside the volume count as outside the surface, so a surface that touches the border is closed
//! there and every mesh bounds a solid. Vertices are placed by linear interpolation along cell edges and mapped
//! to patient millimetres through the volume's [`Frame`].

use ndarray::{ArrayView3, s};
use rayon::prelude::*;

use super::Mesh;
use super::cases::{CASES, EDGES};
use crate::volume::Frame;

const NONE: u32 = u32::MAX;

/// Vertices owned by one plane of the padded lattice: on its x and y edges, and on the z edges to the next plane.
struct PlaneVerts {
    /// `[direction][j * nx + i]` → local vertex index or NONE.
    index: [Vec<u32>; 3],
    /// Positions in padded index space (i, j, k).
    points: Vec<[f32; 3]>,
    offset: u32,
}

/// Extract the iso-surface `value = iso` of `vol` (inside where value > iso), in patient mm.
pub fn marching_cubes(vol: ArrayView3<'_, f32>, frame: &Frame, iso: f32) -> Mesh {
    let (nz, ny, nx) = vol.dim();
    if nz == 0 || ny == 0 || nx == 0 || !iso.is_finite() {
        return Mesh::default();
    }
    // Pad by one sample of "outside" on every side.
    let (pz, py, px) = (nz + 2, ny + 2, nx + 2);
    let outside = f32::NEG_INFINITY;
    let mut padded = ndarray::Array3::from_elem((pz, py, px), outside);
    padded.slice_mut(s![1..=nz, 1..=ny, 1..=nx]).assign(&vol);
    // NaN counts as outside.
    padded.mapv_inplace(|v| if v.is_nan() { outside } else { v });
    let p = padded.view();

    let value = |k: usize, j: usize, i: usize| p[[k, j, i]];
    let cross = |a: f32, b: f32| (a > iso) != (b > iso);
    let edge_point = |a: f32, b: f32| -> f32 {
        // Border edges (one end in the padding) sit half-way, i.e. half a voxel outside the volume.
        if a == f32::NEG_INFINITY || b == f32::NEG_INFINITY {
            0.5
        } else {
            ((iso - a) / (b - a)).clamp(0.0, 1.0)
        }
    };

    let mut planes: Vec<PlaneVerts> = (0..pz)
        .into_par_iter()
        .map(|k| {
            let mut index = [
                vec![NONE; px * py],
                vec![NONE; px * py],
                vec![NONE; px * py],
            ];
            let mut points = Vec::new();
            for j in 0..py {
                for i in 0..px {
                    let a = value(k, j, i);
                    let here = j * px + i;
                    if i + 1 < px {
                        let b = value(k, j, i + 1);
                        if cross(a, b) {
                            index[0][here] = points.len() as u32;
                            points.push([i as f32 + edge_point(a, b), j as f32, k as f32]);
                        }
                    }
                    if j + 1 < py {
                        let b = value(k, j + 1, i);
                        if cross(a, b) {
                            index[1][here] = points.len() as u32;
                            points.push([i as f32, j as f32 + edge_point(a, b), k as f32]);
                        }
                    }
                    if k + 1 < pz {
                        let b = value(k + 1, j, i);
                        if cross(a, b) {
                            index[2][here] = points.len() as u32;
                            points.push([i as f32, j as f32, k as f32 + edge_point(a, b)]);
                        }
                    }
                }
            }
            PlaneVerts {
                index,
                points,
                offset: 0,
            }
        })
        .collect();
    let mut total = 0u32;
    for plane in &mut planes {
        plane.offset = total;
        total += plane.points.len() as u32;
    }

    // Global vertex id of cell edge `e` of the cell with low corner (k, j, i).
    let vertex = |k: usize, j: usize, i: usize, e: usize| -> u32 {
        let [a, b] = EDGES[e];
        let (ca, cb) = (a as usize, b as usize);
        let d = (ca ^ cb).trailing_zeros() as usize; // 0: x, 1: y, 2: z
        let (ii, jj, kk) = (i + (ca & 1), j + (ca >> 1 & 1), k + (ca >> 2 & 1));
        let plane = &planes[kk];
        let local = plane.index[d][jj * px + ii];
        debug_assert!(local != NONE, "edge without vertex");
        plane.offset + local
    };

    let triangles: Vec<[u32; 3]> = (0..pz - 1)
        .into_par_iter()
        .flat_map_iter(|k| {
            let mut out = Vec::new();
            for j in 0..py - 1 {
                for i in 0..px - 1 {
                    let mut mask = 0usize;
                    for c in 0..8 {
                        let v = value(k + (c >> 2 & 1), j + (c >> 1 & 1), i + (c & 1));
                        if v > iso {
                            mask |= 1 << c;
                        }
                    }
                    for t in &CASES[mask] {
                        out.push(t.map(|e| vertex(k, j, i, e as usize)));
                    }
                }
            }
            out
        })
        .collect();

    let vertices: Vec<[f32; 3]> = planes
        .iter()
        .flat_map(|pl| pl.points.iter())
        .map(|&[i, j, k]| {
            let q = frame.position(k as f64 - 1.0, j as f64 - 1.0, i as f64 - 1.0);
            [q[0] as f32, q[1] as f32, q[2] as f32]
        })
        .collect();
    Mesh {
        vertices,
        triangles,
    }
}
