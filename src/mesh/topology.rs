//! What a triangle mesh is, read from its triangles: watertight, a 2-manifold, and its Euler characteristic.
//!
//! - `closed` (watertight): the mesh has triangles and every edge is traversed as often in one direction as in
//!   the other, at least once each way. A closed mesh bounds a solid, so its enclosed volume means something.
//! - `manifold`: every edge is shared by exactly two triangles traversing it in opposite directions, the
//!   triangles around every vertex form one fan (no two sheets touching at a point) and no triangle has zero
//!   area. A closed manifold mesh is a union of closed orientable surfaces.
//! - Euler characteristic χ = V − E + F over the vertices that triangles use, the distinct edges and the
//!   triangles: 2 for a sphere-like surface, 0 for a torus, 2 − 2g for genus g, summed over the pieces.

use rayon::prelude::*;

use super::Mesh;

/// Topology of a mesh (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Topology {
    /// Vertices that triangles use.
    pub vertices: usize,
    pub closed: bool,
    pub manifold: bool,
    pub euler_characteristic: i64,
}

impl Mesh {
    /// Closedness, manifoldness and Euler characteristic of the mesh as it is.
    pub fn topology(&self) -> Topology {
        if self.triangles.is_empty() {
            return Topology {
                vertices: 0,
                closed: false,
                manifold: false,
                euler_characteristic: 0,
            };
        }
        // Directed edges as (smaller << 32 | larger) with the direction in the lowest bit of a u128 key.
        let mut edges: Vec<u128> = self
            .triangles
            .par_iter()
            .flat_map_iter(|t| {
                (0..3).map(move |k| {
                    let (a, b) = (t[k], t[(k + 1) % 3]);
                    let key = (a.min(b) as u128) << 32 | a.max(b) as u128;
                    key << 1 | (a < b) as u128
                })
            })
            .collect();
        edges.par_sort_unstable();
        let mut closed = true;
        let mut two_sided = true;
        let mut distinct = 0i64;
        for group in edges.chunk_by(|a, b| a >> 1 == b >> 1) {
            distinct += 1;
            let forward = group.iter().filter(|&&e| e & 1 == 1).count();
            let backward = group.len() - forward;
            if forward != backward {
                closed = false;
            }
            if forward != 1 || backward != 1 {
                two_sided = false;
            }
        }
        let n = self.vertices.len();
        let mut degree = vec![0u32; n + 1];
        for t in &self.triangles {
            for &v in t {
                degree[v as usize] += 1;
            }
        }
        let used = degree[..n].iter().filter(|&&d| d > 0).count() as i64;
        let euler_characteristic = used - distinct + self.triangles.len() as i64;
        let manifold = closed && two_sided && self.no_zero_area() && self.single_fans(&degree);
        Topology {
            vertices: used as usize,
            closed,
            manifold,
            euler_characteristic,
        }
    }

    fn no_zero_area(&self) -> bool {
        self.triangles.par_iter().all(|t| {
            let n = self.area_vector(t);
            n[0] != 0.0 || n[1] != 0.0 || n[2] != 0.0
        })
    }

    /// True when, around every vertex, the edges opposite it chain into one cycle. Needs every edge shared by
    /// exactly two triangles in opposite directions; `degree` counts triangles per vertex (one spare slot).
    fn single_fans(&self, degree: &[u32]) -> bool {
        let n = self.vertices.len();
        let mut start = vec![0u32; n + 1];
        for v in 0..n {
            start[v + 1] = start[v] + degree[v];
        }
        let mut fill = start.clone();
        // The edge opposite each vertex in each triangle, in the triangle's direction.
        let mut link = vec![[0u32; 2]; start[n] as usize];
        for t in &self.triangles {
            for k in 0..3 {
                let v = t[k] as usize;
                link[fill[v] as usize] = [t[(k + 1) % 3], t[(k + 2) % 3]];
                fill[v] += 1;
            }
        }
        (0..n).into_par_iter().all(|v| {
            let fan = &link[start[v] as usize..start[v + 1] as usize];
            let Some(&[first, mut at]) = fan.first() else {
                return true;
            };
            let mut steps = 1;
            while at != first {
                match fan.iter().find(|e| e[0] == at) {
                    Some(e) if steps < fan.len() => {
                        at = e[1];
                        steps += 1;
                    }
                    _ => return false,
                }
            }
            steps == fan.len()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tetrahedron() -> Mesh {
        Mesh {
            vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            triangles: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        }
    }

    #[test]
    fn a_tetrahedron_is_a_closed_manifold_sphere() {
        let t = tetrahedron().topology();
        assert_eq!(
            t,
            Topology {
                vertices: 4,
                closed: true,
                manifold: true,
                euler_characteristic: 2
            }
        );
    }

    #[test]
    fn an_open_or_misoriented_tetrahedron_is_neither_closed_nor_manifold() {
        let mut open = tetrahedron();
        open.triangles.pop();
        let t = open.topology();
        assert!(!t.closed && !t.manifold);
        assert_eq!(t.euler_characteristic, 1);
        let mut flipped = tetrahedron();
        flipped.triangles[3] = [1, 3, 2];
        let t = flipped.topology();
        assert!(!t.closed && !t.manifold);
    }

    #[test]
    fn two_tetrahedra_sharing_a_vertex_are_closed_but_not_manifold() {
        let mut m = tetrahedron();
        m.vertices
            .extend([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]);
        // The mirror image through the origin, wound outward.
        m.triangles
            .extend([[0, 4, 5], [0, 6, 4], [0, 5, 6], [4, 6, 5]]);
        let t = m.topology();
        assert!(t.closed && !t.manifold, "{t:?}");
        // Two spheres (χ = 4) glued at one vertex: one vertex fewer.
        assert_eq!(t.euler_characteristic, 3);
    }

    #[test]
    fn a_zero_area_triangle_is_not_manifold() {
        let mut m = tetrahedron();
        m.vertices[3] = [0.5, 0.5, 0.0];
        assert!(!m.topology().manifold);
    }

    #[test]
    fn an_empty_mesh_is_neither_closed_nor_manifold() {
        let t = Mesh::default().topology();
        assert!(!t.closed && !t.manifold && t.euler_characteristic == 0);
    }
}
