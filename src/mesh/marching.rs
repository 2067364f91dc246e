//! Marching cubes over a `[z][y][x]` volume with shared vertices, parallel over z layers.
//!
//! Samples outside the volume count as outside the surface, so a surface that touches the border is closed
//! there and every mesh bounds a solid. Vertices are placed by linear interpolation along cell edges and mapped
//! to patient millimetres through the volume's [`Frame`].

use ndarray::ArrayView3;
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
    // Pad by one sample of "outside" on every side (NaN counts as outside), as one contiguous buffer.
    let (pz, py, px) = (nz + 2, ny + 2, nx + 2);
    let outside = f32::NEG_INFINITY;
    let plane_len = px * py;
    let mut p = vec![outside; pz * plane_len];
    p.par_chunks_mut(plane_len)
        .enumerate()
        .filter(|(k, _)| (1..=nz).contains(k))
        .for_each(|(k, plane)| {
            for (j, src) in vol
                .index_axis(ndarray::Axis(0), k - 1)
                .rows()
                .into_iter()
                .enumerate()
            {
                let row = &mut plane[(j + 1) * px + 1..(j + 1) * px + 1 + nx];
                for (d, &v) in row.iter_mut().zip(src.iter()) {
                    *d = if v.is_nan() { outside } else { v };
                }
            }
        });
    let inside: Vec<bool> = p.par_iter().map(|&v| v > iso).collect();
    let p = &p[..];
    let inside = &inside[..];
    let at = |k: usize, j: usize, i: usize| (k * py + j) * px + i;
    // Border edges (one end in the padding) sit half-way, i.e. half a voxel outside the volume.
    let edge_point = |a: f32, b: f32| -> f32 {
        if a == outside || b == outside {
            0.5
        } else {
            ((iso - a) / (b - a)).clamp(0.0, 1.0)
        }
    };

    let mut planes: Vec<PlaneVerts> = (0..pz)
        .into_par_iter()
        .map(|k| {
            let mut index = [
                vec![NONE; plane_len],
                vec![NONE; plane_len],
                vec![NONE; plane_len],
            ];
            let mut points = Vec::new();
            for j in 0..py {
                for i in 0..px {
                    let here = at(k, j, i);
                    let a_in = inside[here];
                    let local = j * px + i;
                    if i + 1 < px && inside[here + 1] != a_in {
                        index[0][local] = points.len() as u32;
                        let t = edge_point(p[here], p[here + 1]);
                        points.push([i as f32 + t, j as f32, k as f32]);
                    }
                    if j + 1 < py && inside[here + px] != a_in {
                        index[1][local] = points.len() as u32;
                        let t = edge_point(p[here], p[here + px]);
                        points.push([i as f32, j as f32 + t, k as f32]);
                    }
                    if k + 1 < pz && inside[here + plane_len] != a_in {
                        index[2][local] = points.len() as u32;
                        let t = edge_point(p[here], p[here + plane_len]);
                        points.push([i as f32, j as f32, k as f32 + t]);
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
    // Offsets of the 8 cell corners from the low corner, in corner order.
    let corner_offset: [usize; 8] =
        std::array::from_fn(|c| (c >> 2 & 1) * plane_len + (c >> 1 & 1) * px + (c & 1));

    let triangles: Vec<[u32; 3]> = (0..pz - 1)
        .into_par_iter()
        .flat_map_iter(|k| {
            let mut out = Vec::new();
            for j in 0..py - 1 {
                for i in 0..px - 1 {
                    let base = at(k, j, i);
                    let mut mask = 0usize;
                    for (c, &off) in corner_offset.iter().enumerate() {
                        mask |= (inside[base + off] as usize) << c;
                    }
                    if mask == 0 || mask == 255 {
                        continue;
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
