//! Taubin λ|μ smoothing: alternating shrinking and inflating Laplacian steps, which smooths staircase
//! artefacts without the shrinkage of plain Laplacian smoothing.

use super::Mesh;

/// Smooth `mesh` in place with `iterations` λ|μ pairs (λ = 0.5, μ = −0.53, pass band ≈ 0.1).
pub fn taubin(mesh: &mut Mesh, iterations: usize) {
    let n = mesh.vertices.len();
    if n == 0 || iterations == 0 {
        return;
    }
    let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); n];
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            neighbours[a as usize].push(b);
            neighbours[b as usize].push(a);
        }
    }
    for list in &mut neighbours {
        list.sort_unstable();
        list.dedup();
    }
    let mut scratch = mesh.vertices.clone();
    for _ in 0..iterations {
        for factor in [0.5f32, -0.53] {
            for (v, list) in neighbours.iter().enumerate() {
                if list.is_empty() {
                    continue;
                }
                let mut avg = [0.0f32; 3];
                for &w in list {
                    let p = mesh.vertices[w as usize];
                    for c in 0..3 {
                        avg[c] += p[c];
                    }
                }
                let p = mesh.vertices[v];
                for c in 0..3 {
                    let d = avg[c] / list.len() as f32 - p[c];
                    scratch[v][c] = p[c] + factor * d;
                }
            }
            std::mem::swap(&mut mesh.vertices, &mut scratch);
        }
    }
}
