//! The 256 marching-cubes cases, generated once from first principles instead of typed-in tables.
//!
//! Corner `c` of a cell sits at `(c & 1, c >> 1 & 1, c >> 2 & 1)` (x, y, z). A corner is inside when its value
//! exceeds the iso-value. For each of the 6 faces, walked counter-clockwise seen from outside the cell, every
//! run of inside corners is cut off by one segment from the edge where the walk enters the run to the edge where
//! it leaves. Each crossed cell edge is entered on one face and left on the other, so the segments chain into
//! closed polygons, which are fanned into triangles. Because the decision on an ambiguous face (inside corners
//! on a diagonal are kept apart) depends only on that face's corners, neighbouring cells agree and the surface
//! has no cracks. The winding makes normals point from inside to outside; `tests` check it.

use std::sync::LazyLock;

/// The 12 cell edges as corner pairs.
pub const EDGES: [[u8; 2]; 12] = [
    [0, 1],
    [2, 3],
    [4, 5],
    [6, 7], // along x
    [0, 2],
    [1, 3],
    [4, 6],
    [5, 7], // along y
    [0, 4],
    [1, 5],
    [2, 6],
    [3, 7], // along z
];

/// Corners of each face in counter-clockwise order seen from outside the cell.
const FACES: [[u8; 4]; 6] = [
    [0, 4, 6, 2], // x = 0, outward −x
    [1, 3, 7, 5], // x = 1, outward +x
    [0, 1, 5, 4], // y = 0, outward −y
    [2, 6, 7, 3], // y = 1, outward +y
    [0, 2, 3, 1], // z = 0, outward −z
    [4, 5, 7, 6], // z = 1, outward +z
];

fn edge_of(a: u8, b: u8) -> usize {
    EDGES
        .iter()
        .position(|e| (e[0] == a && e[1] == b) || (e[0] == b && e[1] == a))
        .unwrap_or(usize::MAX)
}

fn share_face(a: u8, b: u8) -> bool {
    let [a0, a1] = EDGES[a as usize];
    let [b0, b1] = EDGES[b as usize];
    FACES.iter().any(|f| {
        let on = |c: u8| f.contains(&c);
        on(a0) && on(a1) && on(b0) && on(b1)
    })
}

/// Triangles of one case, as triples of cell-edge indices.
pub type Case = Vec<[u8; 3]>;

fn build_case(mask: u8) -> Case {
    let inside = |c: u8| mask >> c & 1 == 1;
    let mut next = [u8::MAX; 12];
    for face in FACES {
        // Crossings in walk order: (edge, entering_inside).
        let mut crossings = Vec::with_capacity(4);
        for k in 0..4 {
            let (a, b) = (face[k], face[(k + 1) % 4]);
            if inside(a) != inside(b) {
                crossings.push((edge_of(a, b), inside(b)));
            }
        }
        for (k, &(e, entering)) in crossings.iter().enumerate() {
            if entering {
                let (exit, _) = crossings[(k + 1) % crossings.len()];
                next[e] = exit as u8;
            }
        }
    }
    let mut used = [false; 12];
    let mut tris = Vec::new();
    for start in 0..12 {
        if next[start] == u8::MAX || used[start] {
            continue;
        }
        let mut cycle = Vec::new();
        let mut e = start;
        while !used[e] {
            used[e] = true;
            cycle.push(e as u8);
            e = next[e] as usize;
        }
        // Fan from an apex whose diagonals never join two vertices of the same cell face: a neighbouring cell
        // may use that pair too, and an edge shared by four triangles would make the surface non-manifold.
        let len = cycle.len();
        let apex = (0..len)
            .find(|&a| {
                (2..len.saturating_sub(1)).all(|d| !share_face(cycle[a], cycle[(a + d) % len]))
            })
            .unwrap_or(0);
        for k in 1..len.saturating_sub(1) {
            tris.push([
                cycle[apex],
                cycle[(apex + k) % len],
                cycle[(apex + k + 1) % len],
            ]);
        }
    }
    tris
}

/// Triangles for every inside-corner mask.
pub static CASES: LazyLock<Vec<Case>> = LazyLock::new(|| (0..=255u8).map(build_case).collect());

#[cfg(test)]
mod tests {
    use super::*;

    fn corner(c: u8) -> [f64; 3] {
        [(c & 1) as f64, (c >> 1 & 1) as f64, (c >> 2 & 1) as f64]
    }
    fn mid(e: u8) -> [f64; 3] {
        let [a, b] = EDGES[e as usize];
        let (p, q) = (corner(a), corner(b));
        [
            (p[0] + q[0]) / 2.0,
            (p[1] + q[1]) / 2.0,
            (p[2] + q[2]) / 2.0,
        ]
    }

    #[test]
    fn every_case_has_as_many_crossings_as_its_polygons_use_and_empty_cases_have_none() {
        assert!(CASES[0].is_empty() && CASES[255].is_empty());
        for mask in 0..=255u8 {
            let crossed = EDGES
                .iter()
                .filter(|e| (mask >> e[0] & 1) != (mask >> e[1] & 1))
                .count();
            let mut seen: Vec<u8> = CASES[mask as usize].iter().flatten().copied().collect();
            seen.sort_unstable();
            seen.dedup();
            assert_eq!(seen.len(), crossed, "case {mask}");
        }
    }

    #[test]
    fn edges_on_a_cell_face_belong_to_one_triangle_only() {
        for (mask, case) in CASES.iter().enumerate() {
            let mut uses = std::collections::HashMap::new();
            for t in case {
                for k in 0..3 {
                    let (a, b) = (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]));
                    *uses.entry((a, b)).or_insert(0) += 1;
                }
            }
            for ((a, b), n) in uses {
                let want = if share_face(a, b) { 1 } else { 2 };
                assert_eq!(n, want, "case {mask}, edge {a}-{b}");
            }
        }
    }

    #[test]
    fn one_inside_corner_gives_one_triangle_facing_away_from_it() {
        let t = &CASES[1];
        assert_eq!(t.len(), 1);
        let [a, b, c] = t[0].map(mid);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        // Corner 0 is inside, at the origin: the outward normal points to +x+y+z.
        assert!(n.iter().all(|&c| c > 0.0), "{n:?}");
    }
}
