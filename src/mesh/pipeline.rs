//! The surface pipeline a user asks for in one request: iso-surface, largest component, Taubin smoothing,
//! decimation, and the measurements reported with the result.

use serde::{Deserialize, Serialize};

use super::{Mesh, clip::clipped_field, decimate, marching_cubes, taubin};
use crate::render::Clip;
use crate::volume::Volume;

/// Most Taubin iterations accepted.
pub const MAX_SMOOTHING: usize = 500;

fn yes() -> bool {
    true
}

/// Options of a surface extraction. JSON: `{"iso": 300, "largest_component": true, "smoothing": 10,
/// "target_triangles": 200000, "clip": {"planes": [{"point_mm": [0, 0, 0], "normal": [0, 1, 0]}]}}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshOptions {
    /// Iso-value in the volume's units (HU for CT series, 1/mm for reconstructions).
    pub iso: f32,
    /// Keep only the connected piece with the most triangles (default true).
    #[serde(default = "yes")]
    pub largest_component: bool,
    /// Taubin λ|μ iterations (default 0).
    #[serde(default)]
    pub smoothing: usize,
    /// Decimate to at most this many triangles (default: no decimation).
    #[serde(default)]
    pub target_triangles: Option<usize>,
    /// Cut-away: planes and boxes (mm, LPS); the cut face is capped so the surface stays closed.
    #[serde(default, skip_serializing_if = "Clip::is_empty")]
    pub clip: Clip,
}

/// What was built, measured on the final mesh (after smoothing and decimation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeshStats {
    pub triangles: usize,
    /// Vertices the triangles use.
    pub vertices: usize,
    pub area_mm2: f64,
    pub volume_mm3: f64,
    /// Watertight and consistently oriented (see [`super::Topology`]).
    pub closed: bool,
    /// Every edge in exactly two triangles of opposite orientation, one fan per vertex, no zero-area triangle.
    #[serde(default)]
    pub manifold: bool,
    /// V − E + F: 2 for a sphere-like surface, 0 for a torus (summed over pieces).
    #[serde(default)]
    pub euler_characteristic: i64,
    /// What the surface could not honour: an empty surface, a `target_triangles` not reached.
    #[serde(default)]
    pub warnings: Vec<MeshWarning>,
}

/// Code of the warning that the surface is empty although the request was accepted (e.g. smoothing lowered the
/// maximum below the iso-value, or a clip cut every solid away).
pub const EMPTY_SURFACE: &str = "empty_surface";
/// Code of the warning that decimation stopped above `target_triangles`.
pub const TARGET_TRIANGLES_NOT_REACHED: &str = "target_triangles_not_reached";

/// Something a surface could not honour: a stable snake_case `code` ([`EMPTY_SURFACE`],
/// [`TARGET_TRIANGLES_NOT_REACHED`]) and a sentence with the numbers. Stored results that hold the bare sentence
/// read back with the code it stands for.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(from = "StoredWarning")]
pub struct MeshWarning {
    pub code: String,
    pub message: String,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum StoredWarning {
    Coded { code: String, message: String },
    Sentence(String),
}

impl From<StoredWarning> for MeshWarning {
    fn from(w: StoredWarning) -> Self {
        match w {
            StoredWarning::Coded { code, message } => Self { code, message },
            StoredWarning::Sentence(message) => Self {
                code: if message.starts_with("target_triangles") {
                    TARGET_TRIANGLES_NOT_REACHED
                } else {
                    EMPTY_SURFACE
                }
                .into(),
                message,
            },
        }
    }
}

/// A mesh request that cannot be honoured.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshError {
    #[error("invalid mesh option `{name}`: {reason}")]
    InvalidOption { name: &'static str, reason: String },
    #[error("invalid clip: {0}")]
    Clip(String),
}

impl MeshError {
    pub fn code(&self) -> &'static str {
        match self {
            MeshError::InvalidOption { .. } => "invalid_mesh_options",
            MeshError::Clip(_) => "invalid_clip",
        }
    }
}

impl MeshOptions {
    pub fn validate(&self) -> Result<(), MeshError> {
        if !self.iso.is_finite() {
            return Err(MeshError::InvalidOption {
                name: "iso",
                reason: format!("must be finite, got {}", self.iso),
            });
        }
        if self.smoothing > MAX_SMOOTHING {
            return Err(MeshError::InvalidOption {
                name: "smoothing",
                reason: format!("at most {MAX_SMOOTHING} iterations"),
            });
        }
        if self.target_triangles.is_some_and(|t| t < 4) {
            return Err(MeshError::InvalidOption {
                name: "target_triangles",
                reason: "a closed surface needs at least 4 triangles".into(),
            });
        }
        self.clip
            .validate()
            .map_err(|e| MeshError::Clip(e.to_string()))
    }
}

impl Mesh {
    pub fn stats(&self) -> MeshStats {
        let topology = self.topology();
        MeshStats {
            triangles: self.triangle_count(),
            vertices: topology.vertices,
            area_mm2: self.area_mm2(),
            volume_mm3: self.volume_mm3(),
            closed: topology.closed,
            manifold: topology.manifold,
            euler_characteristic: topology.euler_characteristic,
            warnings: Vec::new(),
        }
    }
}

/// Run the surface pipeline on `vol`.
pub fn extract(vol: &Volume, opts: &MeshOptions) -> Result<(Mesh, MeshStats), MeshError> {
    opts.validate()?;
    let mut mesh = if opts.clip.is_empty() {
        marching_cubes(vol.data.view(), &vol.frame, opts.iso)
    } else {
        let field = clipped_field(vol, opts.iso, &opts.clip);
        marching_cubes(field.data.view(), &field.frame, opts.iso)
    };
    if opts.largest_component {
        mesh = mesh.largest_component();
    }
    taubin(&mut mesh, opts.smoothing);
    if let Some(t) = opts.target_triangles {
        mesh = decimate(&mesh, t);
    }
    let mut stats = mesh.stats();
    if mesh.triangles.is_empty() {
        stats.warnings.push(MeshWarning {
            code: EMPTY_SURFACE.into(),
            message: format!(
                "the iso-surface at {} is empty: no sample of the volume{} is at or above it",
                opts.iso,
                if opts.clip.is_empty() {
                    ""
                } else {
                    " left by the clip"
                }
            ),
        });
    }
    if let Some(t) = opts.target_triangles.filter(|&t| stats.triangles > t) {
        stats.warnings.push(MeshWarning {
            code: TARGET_TRIANGLES_NOT_REACHED.into(),
            message: format!(
                "target_triangles {t} not reached: decimation stopped at {} triangles, where every further \
                 edge collapse would open, pinch or fold the surface",
                stats.triangles
            ),
        });
    }
    Ok((mesh, stats))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recon::grid::VolumeGrid;
    use crate::volume::Frame;

    #[test]
    fn the_pipeline_keeps_the_big_sphere_smooths_and_decimates() {
        let grid = VolumeGrid::cube(40, 1.0);
        let data = ndarray::Array3::from_shape_fn((40, 40, 40), |(k, j, i)| {
            let (x, y, z) = (grid.x(i), grid.y(j), grid.z(k));
            let big = 10.0 - ((x + 7.0).powi(2) + y * y + z * z).sqrt();
            let small = 3.0 - ((x - 13.0).powi(2) + y * y + z * z).sqrt();
            big.max(small) as f32
        });
        let vol = Volume {
            data,
            frame: Frame::from_grid(&grid),
        };
        let opts: MeshOptions =
            serde_json::from_str(r#"{"iso": 0, "smoothing": 5, "target_triangles": 2000}"#)
                .unwrap();
        let (mesh, stats) = extract(&vol, &opts).unwrap();
        assert!(stats.closed);
        assert!(stats.triangles <= 2000 && stats.triangles == mesh.triangle_count());
        let v0 = 4.0 / 3.0 * std::f64::consts::PI * 1000.0;
        assert!(
            (stats.volume_mm3 - v0).abs() / v0 < 0.04,
            "{}",
            stats.volume_mm3
        );
        let bad = MeshOptions {
            iso: f32::NAN,
            ..opts.clone()
        };
        assert!(extract(&vol, &bad).is_err());
        assert!(serde_json::from_str::<MeshOptions>(r#"{"iso": 1, "colour": 3}"#).is_err());
    }

    #[test]
    fn warnings_carry_stable_codes_and_stored_sentences_read_back_with_theirs() {
        let w = MeshWarning {
            code: EMPTY_SURFACE.into(),
            message: "the iso-surface at 3 is empty".into(),
        };
        let text = serde_json::to_string(&w).unwrap();
        assert_eq!(
            text,
            r#"{"code":"empty_surface","message":"the iso-surface at 3 is empty"}"#
        );
        assert_eq!(serde_json::from_str::<MeshWarning>(&text).unwrap(), w);
        let stored: Vec<MeshWarning> = serde_json::from_str(
            r#"["target_triangles 4 not reached: decimation stopped at 16 triangles",
                "the iso-surface at 3 is empty: no sample is above it"]"#,
        )
        .unwrap();
        let codes: Vec<&str> = stored.iter().map(|w| w.code.as_str()).collect();
        assert_eq!(codes, [TARGET_TRIANGLES_NOT_REACHED, EMPTY_SURFACE]);
        assert!(stored[0].message.contains("16 triangles"));
    }
}
