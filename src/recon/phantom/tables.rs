//! The named phantom tables, in phantom units (the cube [−1, 1]^N): 2D Shepp–Logan (original and
//! modified, DESIGN §3) and the three 3D tables of the seed program `phantom3d` (seed-phantom3d.md).

use serde::{Deserialize, Serialize};

use super::{Ellipse, Ellipsoid};

/// A named 2D ellipse table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Table2 {
    /// Shepp & Logan (1974): values 2, −0.98, −0.02, −0.02, 0.01 × 6.
    SheppLogan,
    /// Toft's higher-contrast variant: values 1, −0.8, −0.2, −0.2, 0.1 × 6.
    ModifiedSheppLogan,
}

/// A named 3D ellipsoid table, exactly as in the seed program `phantom3d`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Table3 {
    /// `phantom3d`'s default: Toft/Schabel's modified Shepp–Logan.
    ModifiedSheppLogan,
    /// Same geometry, Kak–Slaney values 1, −0.98, −0.02, −0.02, 0.01 × 6.
    SheppLogan,
    /// Yu, Ye & Wang, "Katsevich-type algorithms for variable radius spiral cone-beam CT".
    YuYeWang,
}

/// Original value, modified value, a, b, x0, y0, φ (degrees).
const SHEPP_LOGAN_2D: [[f64; 7]; 10] = [
    [2.0, 1.0, 0.69, 0.92, 0.0, 0.0, 0.0],
    [-0.98, -0.8, 0.6624, 0.874, 0.0, -0.0184, 0.0],
    [-0.02, -0.2, 0.11, 0.31, 0.22, 0.0, -18.0],
    [-0.02, -0.2, 0.16, 0.41, -0.22, 0.0, 18.0],
    [0.01, 0.1, 0.21, 0.25, 0.0, 0.35, 0.0],
    [0.01, 0.1, 0.046, 0.046, 0.0, 0.1, 0.0],
    [0.01, 0.1, 0.046, 0.046, 0.0, -0.1, 0.0],
    [0.01, 0.1, 0.046, 0.023, -0.08, -0.605, 0.0],
    [0.01, 0.1, 0.023, 0.023, 0.0, -0.606, 0.0],
    [0.01, 0.1, 0.023, 0.046, 0.06, -0.605, 0.0],
];

/// Modified value, original value, a, b, c, x0, y0, z0, φ, θ, ψ (degrees).
const SHEPP_LOGAN_3D: [[f64; 11]; 10] = [
    [1.0, 1.0, 0.69, 0.92, 0.81, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [
        -0.8, -0.98, 0.6624, 0.874, 0.78, 0.0, -0.0184, 0.0, 0.0, 0.0, 0.0,
    ],
    [
        -0.2, -0.02, 0.11, 0.31, 0.22, 0.22, 0.0, 0.0, -18.0, 0.0, 10.0,
    ],
    [
        -0.2, -0.02, 0.16, 0.41, 0.28, -0.22, 0.0, 0.0, 18.0, 0.0, 10.0,
    ],
    [0.1, 0.01, 0.21, 0.25, 0.41, 0.0, 0.35, -0.15, 0.0, 0.0, 0.0],
    [0.1, 0.01, 0.046, 0.046, 0.05, 0.0, 0.1, 0.25, 0.0, 0.0, 0.0],
    [
        0.1, 0.01, 0.046, 0.046, 0.05, 0.0, -0.1, 0.25, 0.0, 0.0, 0.0,
    ],
    [
        0.1, 0.01, 0.046, 0.023, 0.05, -0.08, -0.605, 0.0, 0.0, 0.0, 0.0,
    ],
    [
        0.1, 0.01, 0.023, 0.023, 0.02, 0.0, -0.606, 0.0, 0.0, 0.0, 0.0,
    ],
    [
        0.1, 0.01, 0.023, 0.046, 0.02, 0.06, -0.605, 0.0, 0.0, 0.0, 0.0,
    ],
];

/// Value, a, b, c, x0, y0, z0, φ, θ, ψ (degrees).
const YU_YE_WANG_3D: [[f64; 10]; 10] = [
    [1.0, 0.69, 0.92, 0.9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-0.8, 0.6624, 0.874, 0.88, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [-0.2, 0.41, 0.16, 0.21, -0.22, 0.0, -0.25, 108.0, 0.0, 0.0],
    [-0.2, 0.31, 0.11, 0.22, 0.22, 0.0, -0.25, 72.0, 0.0, 0.0],
    [0.2, 0.21, 0.25, 0.5, 0.0, 0.35, -0.25, 0.0, 0.0, 0.0],
    [0.2, 0.046, 0.046, 0.046, 0.0, 0.1, -0.25, 0.0, 0.0, 0.0],
    [0.1, 0.046, 0.023, 0.02, -0.08, -0.65, -0.25, 0.0, 0.0, 0.0],
    [0.1, 0.046, 0.023, 0.02, 0.06, -0.65, -0.25, 90.0, 0.0, 0.0],
    [0.2, 0.056, 0.04, 0.1, 0.06, -0.105, 0.625, 90.0, 0.0, 0.0],
    [-0.2, 0.056, 0.056, 0.1, 0.0, 0.1, 0.625, 0.0, 0.0, 0.0],
];

impl Table2 {
    /// The ten ellipses of the table, in phantom units.
    pub fn ellipses(self) -> Vec<Ellipse> {
        SHEPP_LOGAN_2D
            .iter()
            .map(|r| Ellipse {
                value: match self {
                    Table2::SheppLogan => r[0],
                    Table2::ModifiedSheppLogan => r[1],
                },
                a: r[2],
                b: r[3],
                x0: r[4],
                y0: r[5],
                phi_deg: r[6],
            })
            .collect()
    }
}

fn ellipsoid(value: f64, g: &[f64]) -> Ellipsoid {
    Ellipsoid {
        value,
        a: g[0],
        b: g[1],
        c: g[2],
        x0: g[3],
        y0: g[4],
        z0: g[5],
        phi_deg: g[6],
        theta_deg: g[7],
        psi_deg: g[8],
    }
}

impl Table3 {
    /// The ten ellipsoids of the table, in phantom units.
    pub fn ellipsoids(self) -> Vec<Ellipsoid> {
        match self {
            Table3::ModifiedSheppLogan => SHEPP_LOGAN_3D
                .iter()
                .map(|r| ellipsoid(r[0], &r[2..]))
                .collect(),
            Table3::SheppLogan => SHEPP_LOGAN_3D
                .iter()
                .map(|r| ellipsoid(r[1], &r[2..]))
                .collect(),
            Table3::YuYeWang => YU_YE_WANG_3D
                .iter()
                .map(|r| ellipsoid(r[0], &r[1..]))
                .collect(),
        }
    }
}
