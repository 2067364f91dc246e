//! Marching cubes over a `[z][y][x]` volume with shared vertices, parallel over z layers.
//!
//! Samples outside the volume count as outside the surface, so a surface that touches the border is closed
//! there and every mesh bounds a solid. Vertices are placed by linear interpolation along cell edges and mapped
//! to patient millimetres through the volume's [`Frame`].
//!
//! Ties are resolved one way everywhere: a sample equal to the iso-value is inside (`value >= iso`), and the
//! interpolation parameter along an edge is kept within [[`SNAP`], 1 − [`SNAP`]], so every vertex stays on its
//! own cell edge, at least `SNAP` of the edge away from either sample. Integer data meshed at an integer
//! iso-value (HU, label maps) would otherwise put every crossing edge of a sample equal to the iso-value on that
//! one sample; merging those vertices joins separate triangle fans at one point, and the mesh stops being a
//! 2-manifold (two solids touching at a corner, a CT surface with hundreds of pinches). With the clamp the
//! surface around such a sample passes a hair (`SNAP` of a voxel, 0.1 %) outside it, and the mesh is exactly
//! the combinatorial marching-cubes surface of the inside flags: closed, a 2-manifold (see [`super::cases`]),
//! no triangle of zero area (three points inside three different edges of a cell are never collinear) and no
//! two vertices at one place (the interiors of different edges are disjoint). The alternative — merge the
//! vertices and split every pinched vertex into one copy per triangle fan — would leave copies at the same
//! position, which an STL reader that welds by position joins again.
//!
//! What that means for a solid made of samples equal to the iso-value: it is inside, and its surface runs
//! `SNAP` of a voxel outside its outer samples. A sheet one sample thick at exactly the iso-value is therefore a
//! thin closed slab `2 SNAP` voxels thick around the sheet, with the sheet's area on each side and a volume of
//! area × `2 SNAP` × spacing, rather than nothing: the samples are inside, and the mesh says so.
//!
//! The lattice is the volume padded by one sample on every side. Each lattice plane owns the vertices on its x
//! and y edges and on the z edges to the next plane. Vertices are numbered plane by plane, direction by
//! direction, in scan order, and found again through the bitsets of crossed edges and a count per 64-bit word
//! (a rank query: one population count), so the index needs a bit and a half per lattice edge instead of a full
//! integer.

use ndarray::ArrayView3;
use rayon::prelude::*;

use super::Mesh;
use super::cases::{CASES, EDGES};
use crate::volume::Frame;

/// Crossed edges of one direction in one lattice plane.
struct EdgeBits {
    /// `words` u64 words per row: bit `i % 64` of word `j·words + i / 64` is the edge from lattice point
    /// `(j, i)` of the plane.
    bits: Vec<u64>,
    /// Number of crossed edges before each word (in the rows before it and the words before it in its row).
    word_start: Vec<u32>,
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

/// Least distance, as a fraction of a cell edge, between a vertex and the samples at the ends of its edge.
pub const SNAP: f32 = 1.0 / 1024.0;

/// The bits of row word `w` shifted down by one lattice point: bit `b` is point `64·w + b + 1`.
#[inline(always)]
fn next_point(row: &[u64], w: usize) -> u64 {
    (row[w] >> 1) | row.get(w + 1).map_or(0, |x| x << 63)
}

/// Extract the iso-surface `value = iso` of `vol` (inside where value ≥ iso), in patient mm.
///
/// Three passes over the padded lattice, each parallel over planes, on one bit per lattice point: the inside
/// flags; the crossed edges of each direction (an exclusive or of neighbouring rows, 64 points at a time),
/// whose vertices are placed in scan order; the cells with corners on both sides (64 cells at a time), whose
/// triangles find their vertices by a rank query on the crossed-edge bits. Work outside the surface's cells
/// is a few word operations per 64 lattice points.
///
/// Where the CPU has the population count instruction the passes are compiled with it (one instruction
/// per rank query instead of a dozen shifts and masks); the mesh is the same either way.
#[allow(unsafe_code)]
pub fn marching_cubes(vol: ArrayView3<'_, f32>, frame: &Frame, iso: f32) -> Mesh {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("popcnt") {
        // SAFETY: the CPU has POPCNT, checked just above.
        return unsafe { marching_popcnt(vol, frame, iso) };
    }
    marching(vol, frame, iso)
}

/// [`marching`] compiled with POPCNT (closures inherit the feature).
///
/// # Safety
/// The CPU must have POPCNT.
#[cfg(target_arch = "x86_64")]
#[allow(unsafe_code)]
#[target_feature(enable = "popcnt")]
unsafe fn marching_popcnt(vol: ArrayView3<'_, f32>, frame: &Frame, iso: f32) -> Mesh {
    marching(vol, frame, iso)
}

/// [`marching_cubes`] for whichever instructions the caller is compiled with (baseline x86-64 when
/// called directly, as the tests do to check the form without POPCNT).
#[inline(always)]
pub(super) fn marching(vol: ArrayView3<'_, f32>, frame: &Frame, iso: f32) -> Mesh {
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
    // Inside flags of the padded lattice, one bit per point, `words` words per row; the padding (and every bit
    // beyond the row's end) is clear.
    let words = px.div_ceil(64);
    let row_words = |k: usize, j: usize| (k * py + j) * words;
    let mut inside = vec![0u64; pz * py * words];
    inside
        .par_chunks_mut(py * words)
        .enumerate()
        .for_each(|(k, plane)| {
            if k == 0 || k > nz {
                return;
            }
            for j in 1..=ny {
                let row = &src[((k - 1) * ny + (j - 1)) * nx..][..nx];
                let out = &mut plane[j * words..][..words];
                // Lattice point i + 1 holds sample i.
                for (w, word) in out.iter_mut().enumerate() {
                    let first = (64 * w).max(1);
                    let end = (64 * w + 64).min(nx + 1);
                    let mut acc = 0u64;
                    for p in first..end {
                        acc |= u64::from(row[p - 1] >= iso) << (p - 64 * w);
                    }
                    *word = acc;
                }
            }
        });
    let inside = &inside[..];
    let row = |k: usize, j: usize| &inside[row_words(k, j)..][..words];
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

    let mut planes: Vec<PlaneVerts> = (0..pz)
        .into_par_iter()
        .map(|k| {
            let mut dirs: [EdgeBits; 3] = std::array::from_fn(|_| EdgeBits {
                bits: vec![0; words * py],
                word_start: vec![0; words * py],
            });
            let mut points: [Vec<[f32; 3]>; 3] = Default::default();
            for j in 0..py {
                let here = row(k, j);
                // Rows beyond the lattice have no edges to them: compare with the row itself.
                let up = if j + 1 < py { row(k, j + 1) } else { here };
                let next = if k + 1 < pz { row(k + 1, j) } else { here };
                for w in 0..words {
                    // The edges from each point of the word to its neighbour along x, y and z; the last point
                    // of a row is padding, as is the bit after it, so no x edge leaves the row.
                    let crossed = [
                        here[w] ^ next_point(here, w),
                        here[w] ^ up[w],
                        here[w] ^ next[w],
                    ];
                    for (d, mut bits) in crossed.into_iter().enumerate() {
                        dirs[d].word_start[j * words + w] = points[d].len() as u32;
                        dirs[d].bits[j * words + w] = bits;
                        while bits != 0 {
                            let i = 64 * w + bits.trailing_zeros() as usize;
                            bits &= bits - 1;
                            let a = value(k, j, i);
                            let b = match d {
                                0 => value(k, j, i + 1),
                                1 => value(k, j + 1, i),
                                _ => value(k + 1, j, i),
                            };
                            let mut p = [i as f32, j as f32, k as f32];
                            p[d] += edge_point(a, b);
                            points[d].push(p);
                        }
                    }
                }
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
        let at = jj * words + ii / 64;
        let before = (dir.bits[at] & ((1u64 << (ii % 64)) - 1)).count_ones();
        plane.offset + plane.dir_start[d] + dir.word_start[at] + before
    };

    let triangles: Vec<[u32; 3]> = (0..pz - 1)
        .into_par_iter()
        .flat_map_iter(|k| {
            let mut out = Vec::new();
            for j in 0..py - 1 {
                let rows = [row(k, j), row(k, j + 1), row(k + 1, j), row(k + 1, j + 1)];
                for w in 0..words {
                    // Corner x = i (`low`) and x = i + 1 (`high`) of the cells i of this word, per row.
                    let low = rows.map(|r| r[w]);
                    let high = rows.map(|r| next_point(r, w));
                    let (mut all_in, mut any_in) = (!0u64, 0u64);
                    for m in 0..4 {
                        all_in &= low[m] & high[m];
                        any_in |= low[m] | high[m];
                    }
                    let mut cells = any_in & !all_in;
                    while cells != 0 {
                        let b = cells.trailing_zeros();
                        cells &= cells - 1;
                        let i = 64 * w + b as usize;
                        // Corner bits: x + 2y + 4z, with the four rows at y, z = (0, 0), (1, 0), (0, 1), (1, 1).
                        let mut mask = 0usize;
                        for m in 0..4 {
                            mask |= ((low[m] >> b & 1) as usize) << (2 * m);
                            mask |= ((high[m] >> b & 1) as usize) << (2 * m + 1);
                        }
                        for t in &CASES[mask] {
                            out.push(t.map(|e| vertex(k, j, i, e as usize)));
                        }
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
