//! Surface meshes: marching cubes, cut-away clipping with capped cuts, Taubin smoothing, decimation, measurements (area, enclosed volume), topology
//! (closed, manifold, Euler characteristic), connected components and binary STL in patient millimetres (LPS).

mod cases;
mod clip;
mod decimate;
mod marching;
#[cfg(test)]
mod marching_reference;
mod pipeline;
mod smooth;
mod stl;
mod topology;

use std::collections::HashMap;

use crate::recon::geometry::vectors::{cross3 as cross, sub3 as sub};

pub use clip::clipped_field;
pub use decimate::decimate;
pub use marching::{SNAP, marching_cubes};
pub use pipeline::{
    EMPTY_SURFACE, MAX_SMOOTHING, MeshError, MeshOptions, MeshStats, MeshWarning,
    TARGET_TRIANGLES_NOT_REACHED, extract,
};
pub use smooth::taubin;
pub use stl::{StlError, parse_stl_binary};
pub use topology::Topology;

/// Revision of the surface that a volume and a set of [`MeshOptions`] give. Meshes rendered on request are cached
/// under a key that includes it, so a change to what marching cubes, smoothing or decimation make is never
/// answered from a cache of an earlier revision. Revision 2: vertices keep [`SNAP`] from the samples instead
/// of being welded onto them.
pub const SURFACE_REVISION: u32 = 2;

/// A triangle mesh with shared vertices (mm, patient LPS). Triangles wind counter-clockwise seen from outside.
/// Every measurement counts the vertices that triangles use only, so a mesh read from elsewhere may carry
/// unused ones.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

fn f64s(p: [f32; 3]) -> [f64; 3] {
    p.map(f64::from)
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    fn corners(&self, t: &[u32; 3]) -> [[f64; 3]; 3] {
        t.map(|v| f64s(self.vertices[v as usize]))
    }

    /// Unnormalised normal (twice the area vector) of a triangle.
    fn area_vector(&self, t: &[u32; 3]) -> [f64; 3] {
        let [a, b, c] = self.corners(t);
        cross(sub(b, a), sub(c, a))
    }

    /// Total surface area (mm²).
    pub fn area_mm2(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let n = self.area_vector(t);
                (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt() / 2.0
            })
            .sum()
    }

    /// Enclosed volume (mm³) by the divergence theorem; positive for outward-facing closed meshes.
    pub fn volume_mm3(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = self.corners(t);
                let n = cross(b, c);
                (a[0] * n[0] + a[1] * n[1] + a[2] * n[2]) / 6.0
            })
            .sum()
    }

    /// True when the mesh is watertight and consistently oriented (see [`Topology`]).
    pub fn is_closed(&self) -> bool {
        self.topology().closed
    }

    /// The connected component (through shared vertices) with the most triangles; vertices re-indexed.
    pub fn largest_component(&self) -> Mesh {
        let n = self.vertices.len();
        let mut parent: Vec<u32> = (0..n as u32).collect();
        fn find(parent: &mut [u32], mut x: u32) -> u32 {
            while parent[x as usize] != x {
                let up = parent[parent[x as usize] as usize];
                parent[x as usize] = up;
                x = up;
            }
            x
        }
        for t in &self.triangles {
            let r0 = find(&mut parent, t[0]);
            for &v in &t[1..] {
                let r = find(&mut parent, v);
                if r != r0 {
                    parent[r as usize] = r0;
                }
            }
        }
        let mut count: HashMap<u32, usize> = HashMap::new();
        for t in &self.triangles {
            *count.entry(find(&mut parent, t[0])).or_default() += 1;
        }
        let Some((&best, _)) = count
            .iter()
            .max_by_key(|&(&r, &c)| (c, std::cmp::Reverse(r)))
        else {
            return Mesh::default();
        };
        let mut remap = vec![u32::MAX; n];
        let mut out = Mesh::default();
        for t in &self.triangles {
            if find(&mut parent, t[0]) != best {
                continue;
            }
            out.triangles.push(t.map(|v| {
                if remap[v as usize] == u32::MAX {
                    remap[v as usize] = out.vertices.len() as u32;
                    out.vertices.push(self.vertices[v as usize]);
                }
                remap[v as usize]
            }));
        }
        out
    }

    /// Binary STL: an 80-byte header carrying `SPACE=LPS`, the triangle count, then 50 bytes per triangle with
    /// its unit normal. Coordinates are millimetres.
    pub fn to_stl_binary(&self) -> Vec<u8> {
        stl::write(self)
    }
}

#[cfg(test)]
mod tests;
