//! Decimation to a target triangle count by shortest-edge collapse.
//!
//! Edges are collapsed to their midpoint, shortest first. A collapse is skipped when it would make the surface
//! non-manifold (the link condition: the two end vertices share exactly the two vertices opposite the edge) or
//! flip a neighbouring triangle, so a closed, consistently oriented mesh stays closed and oriented.

use std::cmp::Reverse;
use std::collections::BinaryHeap;

use super::Mesh;
use crate::recon::geometry::vectors::{cross3 as cross, dot3 as dot, sub3 as sub};

type P = [f64; 3];

struct State {
    pos: Vec<P>,
    tris: Vec<[u32; 3]>,
    alive: Vec<bool>,
    /// Triangles around each vertex (may hold dead ones).
    around: Vec<Vec<u32>>,
}

impl State {
    fn live_around(&self, v: u32) -> impl Iterator<Item = u32> + '_ {
        self.around[v as usize]
            .iter()
            .copied()
            .filter(|&t| self.alive[t as usize])
    }
    fn neighbours(&self, v: u32) -> Vec<u32> {
        let mut n: Vec<u32> = self
            .live_around(v)
            .flat_map(|t| self.tris[t as usize])
            .filter(|&w| w != v)
            .collect();
        n.sort_unstable();
        n.dedup();
        n
    }
    fn normal(&self, t: [u32; 3], moved: u32, to: P) -> P {
        let p = |v: u32| if v == moved { to } else { self.pos[v as usize] };
        cross(sub(p(t[1]), p(t[0])), sub(p(t[2]), p(t[0])))
    }
    fn edge_len2(&self, a: u32, b: u32) -> f64 {
        let d = sub(self.pos[a as usize], self.pos[b as usize]);
        dot(d, d)
    }
}

/// Collapse edges until at most `target` triangles remain (or no edge can be collapsed safely).
pub fn decimate(mesh: &Mesh, target: usize) -> Mesh {
    if mesh.triangles.len() <= target {
        return mesh.clone();
    }
    let n = mesh.vertices.len();
    let mut s = State {
        pos: mesh.vertices.iter().map(|p| p.map(f64::from)).collect(),
        tris: mesh.triangles.clone(),
        alive: vec![true; mesh.triangles.len()],
        around: vec![Vec::new(); n],
    };
    for (t, tri) in s.tris.iter().enumerate() {
        for &v in tri {
            s.around[v as usize].push(t as u32);
        }
    }
    let mut heap = BinaryHeap::new();
    for tri in &s.tris {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            if a < b {
                heap.push(Reverse((s.edge_len2(a, b).to_bits(), a, b)));
            }
        }
    }
    let mut vertex_alive = vec![true; n];
    let mut live = s.tris.len();
    while live > target {
        let Some(Reverse((bits, a, b))) = heap.pop() else {
            break;
        };
        if !vertex_alive[a as usize] || !vertex_alive[b as usize] {
            continue;
        }
        let len2 = s.edge_len2(a, b);
        if len2.to_bits() != bits {
            heap.push(Reverse((len2.to_bits(), a, b)));
            continue;
        }
        let shared: Vec<u32> = s
            .live_around(a)
            .filter(|&t| s.tris[t as usize].contains(&b))
            .collect();
        if shared.len() != 2 {
            continue;
        }
        // Link condition.
        let (na, nb) = (s.neighbours(a), s.neighbours(b));
        let common = na.iter().filter(|v| nb.binary_search(v).is_ok()).count();
        if common != 2 {
            continue;
        }
        let mid = {
            let (p, q) = (s.pos[a as usize], s.pos[b as usize]);
            [
                (p[0] + q[0]) / 2.0,
                (p[1] + q[1]) / 2.0,
                (p[2] + q[2]) / 2.0,
            ]
        };
        // No flipped or degenerate neighbour.
        let flips = |v: u32| {
            s.live_around(v).filter(|t| !shared.contains(t)).any(|t| {
                let tri = s.tris[t as usize];
                let before = s.normal(tri, u32::MAX, mid);
                let after = s.normal(tri, v, mid);
                dot(before, after) <= 0.2 * dot(before, before).sqrt() * dot(after, after).sqrt()
            })
        };
        if flips(a) || flips(b) {
            continue;
        }
        for &t in &shared {
            s.alive[t as usize] = false;
            live -= 1;
        }
        s.pos[a as usize] = mid;
        let moved: Vec<u32> = s.live_around(b).collect();
        for t in moved {
            for v in s.tris[t as usize].iter_mut() {
                if *v == b {
                    *v = a;
                }
            }
            s.around[a as usize].push(t);
        }
        vertex_alive[b as usize] = false;
        s.around[b as usize].clear();
        let live_tris: Vec<u32> = s.live_around(a).collect();
        s.around[a as usize] = live_tris;
        for w in s.neighbours(a) {
            let (x, y) = (a.min(w), a.max(w));
            heap.push(Reverse((s.edge_len2(x, y).to_bits(), x, y)));
        }
    }
    // Compact.
    let mut remap = vec![u32::MAX; n];
    let mut out = Mesh::default();
    for (t, tri) in s.tris.iter().enumerate() {
        if !s.alive[t] {
            continue;
        }
        out.triangles.push(tri.map(|v| {
            if remap[v as usize] == u32::MAX {
                remap[v as usize] = out.vertices.len() as u32;
                out.vertices.push(s.pos[v as usize].map(|c| c as f32));
            }
            remap[v as usize]
        }));
    }
    out
}
