//! What a job leaves behind: its result (the files, the quality figures, the notices) and the products of a
//! volume job, with the units of the values they hold.

use serde::{Deserialize, Serialize};

use crate::mesh::MeshStats;
use crate::recon::geometry::vectors::cross3;
use crate::recon::grid::VolumeGrid;
use crate::storage::SeriesId;
use crate::volume::{Frame, ImagePlane, ScreenSides};

/// A file written by a job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileInfo {
    pub bytes: u64,
    pub sha256: String,
}

/// Image quality against the phantom, on the output grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quality {
    pub rmse: f64,
    /// dB, data range = the truth's max − min; `None` (JSON null) when the images are identical.
    pub psnr_db: Option<f64>,
    pub ssim: f64,
    /// Supersampling of the rasterised truth (per axis).
    pub truth_supersample: usize,
}

/// Units of a result volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VolumeUnits {
    /// Linear attenuation μ in 1/mm (reconstructions; phantom units for simulations).
    #[default]
    MuPerMm,
    /// Hounsfield units (CT series and what is derived from them).
    Hu,
}

/// Something a job or an assembly wants the user to know that did not stop it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Notice {
    pub code: String,
    pub message: String,
}

impl From<&crate::series::Warning> for Notice {
    fn from(w: &crate::series::Warning) -> Self {
        Self {
            code: w.code.to_string(),
            message: w.message.clone(),
        }
    }
}

/// What a succeeded job wrote.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobResult {
    /// `[nz, ny, nx]`; 2D reconstructions have nz = 1.
    pub shape: [usize; 3],
    /// The reconstruction grid (2D: one slice of thickness `dx_mm`); for volume jobs the sample counts,
    /// spacing and centre of `frame`.
    pub grid: VolumeGrid,
    pub volume: FileInfo,
    pub min: f32,
    pub max: f32,
    pub mean: f64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metrics: Option<Quality>,
    #[serde(default)]
    pub units: VolumeUnits,
    /// Placement in patient space (LPS, mm) when it is not the axis-aligned frame of `grid` (series).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame: Option<Frame>,
    /// The CT series the volume derives from (its study and patient are kept in DICOM results).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source_series: Option<SeriesId>,
    /// Images and meshes a volume job made, in request order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub products: Vec<ProductResult>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<Notice>,
    /// How the volume was derived from data that is not a DICOM series (a scan: its format, the
    /// preprocessing steps and the centre of rotation), as written to DICOM DerivationDescription.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub derivation: Option<String>,
}

/// Most characters DICOM DerivationDescription (ST) holds.
pub const MAX_DERIVATION_CHARS: usize = 1024;

/// The DerivationDescription of a reconstruction by `algorithm` from an imported scan: the format, every
/// preprocessing step with its parameters, and the centre of rotation used.
pub fn scan_derivation(algorithm: &str, scan: &super::ScanRecord) -> String {
    let step = |v: &serde_json::Value| -> String {
        let Some(obj) = v.as_object() else {
            return v.to_string();
        };
        let name = obj.get("step").and_then(|s| s.as_str()).unwrap_or("step");
        let params: Vec<String> = obj
            .iter()
            .filter(|(k, _)| k.as_str() != "step")
            .map(|(k, v)| format!("{k}={v}"))
            .collect();
        format!("{name}({})", params.join(", "))
    };
    let steps: Vec<String> = scan.preprocessing.iter().map(step).collect();
    let centre = match &scan.calibration {
        Some(c) => format!(
            "; centre of rotation {} ({:.4} mm)",
            c.centre, c.offset_u_mm
        ),
        None => String::new(),
    };
    let text = format!(
        "ctrecon {algorithm} of a {} scan: {}{centre}",
        scan.format,
        steps.join(" > ")
    );
    text.chars().take(MAX_DERIVATION_CHARS).collect()
}

impl JobResult {
    /// The volume's placement in patient space.
    pub fn frame(&self) -> Frame {
        self.frame.unwrap_or_else(|| Frame::from_grid(&self.grid))
    }
}

/// One product of a volume job: an image stack (`[frames, rows, columns]`, volume units) or a mesh.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProductResult {
    pub index: usize,
    /// The product's `type` in the request (`projection`, `mpr`, `curved`, `rotating`, `mesh`,
    /// `volume_render`, `surface_render`).
    #[serde(rename = "type")]
    pub kind: String,
    /// Image stacks: `[frames, rows, columns]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shape: Option<[usize; 3]>,
    /// Image stacks: pixel size (mm) along rows and columns.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<[f64; 2]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mesh: Option<MeshStats>,
    /// Image stacks: the patient directions at the screen sides of the first frame (`R`/`L`, `A`/`P`,
    /// `S`/`I`; the volume axes `±x`, `±y`, `±z` for a reconstruction without a patient).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orientation: Option<ScreenSides>,
    /// Planar image stacks: where the first frame lies in patient space (mm).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plane: Option<ImagePlane>,
    /// Planar stacks of several frames: the step (mm) from one frame to the next along the normal
    /// `row_direction × column_direction`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_spacing_mm: Option<f64>,
    /// Rotating projections and renderings of several frames (a sequence turning about the superior or the
    /// camera's up axis): the screen sides of every frame, the first being `orientation`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frame_orientations: Vec<ScreenSides>,
    /// Renderings: what the picture shows (preset or surfaces, camera), as written to DICOM
    /// DerivationDescription.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    pub file: FileInfo,
}

impl ProductResult {
    pub fn is_mesh(&self) -> bool {
        self.mesh.is_some()
    }

    /// The screen sides of frame `k`: the frames of a rotating projection are seen from 360° k / frames about
    /// the superior axis ([`crate::volume::rotating_axes`]) and those of a turning rendering are listed in
    /// `frame_orientations`, so each has its own; every other stack keeps the sides of its first frame.
    /// `patient` as for [`ImagePlane::sides_for`].
    pub fn frame_sides(&self, k: usize, patient: bool) -> Option<ScreenSides> {
        if let Some(sides) = self.frame_orientations.get(k) {
            return Some(sides.clone());
        }
        let frames = self.shape.map_or(1, |s| s[0]).max(1);
        if self.kind != "rotating" || self.orientation.is_none() {
            return self.orientation.clone();
        }
        let (_, right) = crate::volume::rotating_axes(360.0 * k as f64 / frames as f64);
        Some(
            ImagePlane {
                first_pixel_mm: [0.0; 3],
                row_direction: right,
                column_direction: [0.0, 0.0, -1.0],
                pixel_mm: [1.0; 2],
            }
            .sides_for(patient),
        )
    }

    /// The screen sides every frame shares: the first frame's, unless a frame has others.
    pub fn shared_sides(&self, patient: bool) -> Option<ScreenSides> {
        let frames = self.shape.map_or(1, |s| s[0]).max(1);
        let first = self.frame_sides(0, patient)?;
        (1..frames)
            .all(|k| self.frame_sides(k, patient).as_ref() == Some(&first))
            .then_some(first)
    }

    /// Where frame `k` of a planar stack lies.
    pub fn frame_plane(&self, k: usize) -> Option<ImagePlane> {
        let p = self.plane?;
        let step = self.frame_spacing_mm.unwrap_or(0.0) * k as f64;
        let n = cross3(p.row_direction, p.column_direction);
        Some(ImagePlane {
            first_pixel_mm: std::array::from_fn(|c| p.first_pixel_mm[c] + step * n[c]),
            ..p
        })
    }
}

/// Value given to samples outside the input volume: air for HU, nothing for μ.
pub fn fill_value(units: VolumeUnits) -> f32 {
    match units {
        VolumeUnits::Hu => crate::series::PADDING_HU,
        VolumeUnits::MuPerMm => 0.0,
    }
}
