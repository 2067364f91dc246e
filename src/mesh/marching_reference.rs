//! The byte-per-lattice-point marching cubes that the bitset passes of `super::marching` replaced, kept as a
//! reference: both must give the same mesh, vertex for vertex and triangle for triangle.

use ndarray::ArrayView3;
use rayon::prelude::*;

use super::Mesh;
use super::cases::{CASES, EDGES};
use super::marching::SNAP;
use crate::volume::Frame;

/// Crossed edges of one direction in one lattice plane.
struct EdgeBits {
    /// `words_per_row` u64 words per row.
    bits: Vec<u64>,
    /// Number of crossed edges before each row.
    row_start: Vec<u32>,
}

/// Vertices owned by one lattice plane.
struct PlaneVerts {
    dirs: [EdgeBits; 3],
    /// Number of vertices of directions before each direction.
    dir_start: [u32; 3],
    /// Positions in padded index space (i, j, k), direction-major, scan order.
    points: Vec<[f32; 3]>,
    offset: u32,
}

/// The byte-per-lattice-point implementation the bitset passes replaced, kept to check that they give the
/// same mesh. Extract the iso-surface `value = iso` of `vol` (inside where value ≥ iso), in patient mm.
pub(super) fn marching_cubes(vol: ArrayView3<'_, f32>, frame: &Frame, iso: f32) -> Mesh {
    let (nz, ny, nx) = vol.dim();
    if nz == 0 || ny == 0 || nx == 0 || !iso.is_finite() {
        return Mesh::default();
    }
    let owned;
    let src: &[f32] = match vol.as_slice() {
        Some(s) => s,
        None => {
            owned = vol.as_standard_layout().into_owned();
            owned.as_slice().unwrap_or(&[])
        }
    };
    let (pz, py, px) = (nz + 2, ny + 2, nx + 2);
    let outside = f32::NEG_INFINITY;
    // Value at padded lattice point (k, j, i); NaN and the padding count as outside.
    let value = |k: usize, j: usize, i: usize| -> f32 {
        if k == 0 || j == 0 || i == 0 || k > nz || j > ny || i > nx {
            return outside;
        }
        let v = src[((k - 1) * ny + (j - 1)) * nx + (i - 1)];
        if v.is_nan() { outside } else { v }
    };
    // Inside flags of the padded lattice, one byte per point.
    let plane_len = px * py;
    let mut inside = vec![0u8; pz * plane_len];
    inside
        .par_chunks_mut(plane_len)
        .enumerate()
        .for_each(|(k, plane)| {
            if k == 0 || k > nz {
                return;
            }
            for j in 1..=ny {
                let row = &src[((k - 1) * ny + (j - 1)) * nx..][..nx];
                for (d, &v) in plane[j * px + 1..][..nx].iter_mut().zip(row) {
                    *d = (v >= iso) as u8;
                }
            }
        });
    let inside = &inside[..];
    // Border edges (one end in the padding) sit half-way, i.e. half a voxel outside the volume; so does an
    // edge from an infinite sample. Every other vertex keeps SNAP of its edge from both samples.
    let edge_point = |a: f32, b: f32| -> f32 {
        let t = (iso - a) / (b - a);
        if a == outside || b == outside || t.is_nan() {
            0.5
        } else {
            t.clamp(SNAP, 1.0 - SNAP)
        }
    };
    let words = px.div_ceil(64);
    let strides = [1, px, plane_len];

    let mut planes: Vec<PlaneVerts> = (0..pz)
        .into_par_iter()
        .map(|k| {
            let mut dirs: [EdgeBits; 3] = std::array::from_fn(|_| EdgeBits {
                bits: vec![0; words * py],
                row_start: vec![0; py + 1],
            });
            let mut points: [Vec<[f32; 3]>; 3] = Default::default();
            for j in 0..py {
                for (d, dir) in dirs.iter_mut().enumerate() {
                    dir.row_start[j] = points[d].len() as u32;
                }
                let base = k * plane_len + j * px;
                for i in 0..px {
                    let here = base + i;
                    let a_in = inside[here];
                    let limits = [i + 1 < px, j + 1 < py, k + 1 < pz];
                    for d in 0..3 {
                        if limits[d] && inside[here + strides[d]] != a_in {
                            dirs[d].bits[j * words + i / 64] |= 1 << (i % 64);
                            let a = value(k, j, i);
                            let mut p = [i as f32, j as f32, k as f32];
                            let b = [value(k, j, i + 1), value(k, j + 1, i), value(k + 1, j, i)];
                            p[d] += edge_point(a, b[d]);
                            points[d].push(p);
                        }
                    }
                }
            }
            for (d, dir) in dirs.iter_mut().enumerate() {
                dir.row_start[py] = points[d].len() as u32;
            }
            let dir_start = [
                0,
                points[0].len() as u32,
                (points[0].len() + points[1].len()) as u32,
            ];
            let [p0, p1, p2] = points;
            let mut all = p0;
            all.extend(p1);
            all.extend(p2);
            PlaneVerts {
                dirs,
                dir_start,
                points: all,
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
        let dir = &plane.dirs[d];
        let row = &dir.bits[jj * words..][..words];
        let w = ii / 64;
        let before: u32 = row[..w].iter().map(|x| x.count_ones()).sum::<u32>()
            + (row[w] & ((1u64 << (ii % 64)) - 1)).count_ones();
        plane.offset + plane.dir_start[d] + dir.row_start[jj] + before
    };

    let triangles: Vec<[u32; 3]> = (0..pz - 1)
        .into_par_iter()
        .flat_map_iter(|k| {
            let mut out = Vec::new();
            for j in 0..py - 1 {
                let rows = [
                    &inside[k * plane_len + j * px..][..px],
                    &inside[k * plane_len + (j + 1) * px..][..px],
                    &inside[(k + 1) * plane_len + j * px..][..px],
                    &inside[(k + 1) * plane_len + (j + 1) * px..][..px],
                ];
                // Corner bits of the x = 0 face of cell i are the x = 1 face of cell i − 1.
                let face = |i: usize| -> usize {
                    (rows[0][i] as usize)
                        | (rows[1][i] as usize) << 2
                        | (rows[2][i] as usize) << 4
                        | (rows[3][i] as usize) << 6
                };
                let mut low = face(0);
                for i in 0..px - 1 {
                    let high = face(i + 1);
                    let mask = low | high << 1;
                    low = high;
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
        .par_iter()
        .flat_map_iter(|pl| pl.points.iter())
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
