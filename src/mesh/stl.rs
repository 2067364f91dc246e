//! Binary STL writing and reading (80-byte header, u32 count, 50 bytes per triangle; size 84 + 50 n).

use super::Mesh;

const HEADER: &[u8] = b"ctrecon iso-surface, millimetres, SPACE=LPS";

pub(super) fn write(mesh: &Mesh) -> Vec<u8> {
    let mut out = Vec::with_capacity(84 + 50 * mesh.triangles.len());
    let mut header = [b' '; 80];
    header[..HEADER.len()].copy_from_slice(HEADER);
    out.extend_from_slice(&header);
    out.extend_from_slice(&(mesh.triangles.len() as u32).to_le_bytes());
    for t in &mesh.triangles {
        let n = mesh.area_vector(t);
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let unit = if len > 0.0 {
            n.map(|c| (c / len) as f32)
        } else {
            [0.0; 3]
        };
        for c in unit {
            out.extend_from_slice(&c.to_le_bytes());
        }
        for &v in t {
            for c in mesh.vertices[v as usize] {
                out.extend_from_slice(&c.to_le_bytes());
            }
        }
        out.extend_from_slice(&0u16.to_le_bytes());
    }
    out
}

/// A binary STL that cannot be read.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StlError {
    #[error("a binary STL needs at least 84 bytes, got {0}")]
    TooShort(usize),
    #[error(
        "the header declares {declared} triangles ({expected} bytes) but the file has {got} bytes"
    )]
    SizeMismatch {
        declared: u32,
        expected: u64,
        got: usize,
    },
}

/// Read a binary STL into triangle soup (vertices not shared) and its header.
pub fn parse_stl_binary(bytes: &[u8]) -> Result<(Mesh, [u8; 80]), StlError> {
    if bytes.len() < 84 {
        return Err(StlError::TooShort(bytes.len()));
    }
    let mut header = [0u8; 80];
    header.copy_from_slice(&bytes[..80]);
    let declared = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]);
    let expected = 84 + 50 * declared as u64;
    if expected != bytes.len() as u64 {
        return Err(StlError::SizeMismatch {
            declared,
            expected,
            got: bytes.len(),
        });
    }
    let f = |o: usize| f32::from_le_bytes([bytes[o], bytes[o + 1], bytes[o + 2], bytes[o + 3]]);
    let mut mesh = Mesh::default();
    for t in 0..declared as usize {
        let base = 84 + 50 * t + 12;
        let mut tri = [0u32; 3];
        for (k, slot) in tri.iter_mut().enumerate() {
            let o = base + 12 * k;
            *slot = mesh.vertices.len() as u32;
            mesh.vertices.push([f(o), f(o + 4), f(o + 8)]);
        }
        mesh.triangles.push(tri);
    }
    Ok((mesh, header))
}
