//! Views derived from a job's volume: a slice (PNG or `.npy`), a MIP/MinIP/average projection with an
//! optional slab (PNG or `.npy`), an iso-surface mesh (binary STL, mm, LPS). Each view is a pure function of
//! the immutable volume and its parameters, so it is cached under the SHA-256 of the parameters and that
//! hash is its strong ETag.
//!
//! Windows: a `preset` (soft_tissue, lung, liver, bone, brain) is in HU and applies after converting the
//! volume's μ (1/mm) with μ_water; explicit `ww`/`wl` are in the volume's units, or HU with `units=hu`;
//! with neither, the window spans the 0.5–99.5 percentiles of the image.

use ndarray::{Array2, ArrayView3, Ix3};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error_code::{ErrorCode, Problem};
use crate::mesh::marching_cubes;
use crate::recon::grid::VolumeGrid;
use crate::storage::npy::{decode_f32, encode_f32, hex};
use crate::volume::{
    Axis, BitDepth, Frame, ProjectionKind, VolumeError, Window, WindowPreset, encode_png, mu_to_hu,
    project, slice,
};

/// Units of explicit window values and iso levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Units {
    /// The volume's own units (μ in 1/mm, or phantom units).
    #[default]
    Native,
    /// Hounsfield units, through μ_water.
    Hu,
}

/// Encoding of a 2D view.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageFormat {
    #[default]
    Png,
    Npy,
}

fn axial() -> Axis {
    Axis::Axial
}
fn mip() -> ProjectionKind {
    ProjectionKind::Max
}

/// `GET …/slice`: one slice along `axis` (default the middle one).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SliceQuery {
    #[serde(default = "axial")]
    pub axis: Axis,
    pub index: Option<usize>,
    #[serde(default)]
    pub format: ImageFormat,
    pub preset: Option<WindowPreset>,
    pub ww: Option<f64>,
    pub wl: Option<f64>,
    #[serde(default)]
    pub units: Units,
    /// 8 (default) or 16 bits per PNG sample.
    pub depth: Option<u8>,
}

/// `GET …/projection`: MIP (`mip`), MinIP (`minip`) or `average` along `axis` over slices
/// `slab_start..slab_end` (default all).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectionQuery {
    #[serde(default = "axial")]
    pub axis: Axis,
    #[serde(default = "mip")]
    pub kind: ProjectionKind,
    pub slab_start: Option<usize>,
    pub slab_end: Option<usize>,
    #[serde(default)]
    pub format: ImageFormat,
    pub preset: Option<WindowPreset>,
    pub ww: Option<f64>,
    pub wl: Option<f64>,
    #[serde(default)]
    pub units: Units,
    pub depth: Option<u8>,
}

/// `GET …/mesh.stl`: the iso-surface at `iso` (volume units, or HU with `units=hu`); inside is above iso.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshQuery {
    pub iso: f64,
    #[serde(default)]
    pub units: Units,
    /// Keep only the largest connected component.
    #[serde(default)]
    pub largest: bool,
}

/// A derived view of a job's volume.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "view", rename_all = "snake_case")]
pub enum ViewRequest {
    Slice(SliceQuery),
    Projection(ProjectionQuery),
    Mesh(MeshQuery),
}

struct Display {
    preset: Option<WindowPreset>,
    ww: Option<f64>,
    wl: Option<f64>,
    units: Units,
    depth: Option<u8>,
    format: ImageFormat,
}

impl ViewRequest {
    /// Hex SHA-256 of the parameters (and μ_water): the cache key and strong ETag of the view.
    pub fn key(&self, mu_water: f64) -> String {
        let text = serde_json::to_string(&(self, mu_water)).unwrap_or_default();
        hex(&Sha256::digest(text.as_bytes()))
    }

    fn display(&self) -> Option<Display> {
        match self {
            ViewRequest::Slice(q) => Some(Display {
                preset: q.preset,
                ww: q.ww,
                wl: q.wl,
                units: q.units,
                depth: q.depth,
                format: q.format,
            }),
            ViewRequest::Projection(q) => Some(Display {
                preset: q.preset,
                ww: q.ww,
                wl: q.wl,
                units: q.units,
                depth: q.depth,
                format: q.format,
            }),
            ViewRequest::Mesh(_) => None,
        }
    }

    /// File extension and content type of the view.
    pub fn media(&self) -> (&'static str, &'static str) {
        match self.display().map(|d| d.format) {
            Some(ImageFormat::Png) => ("png", "image/png"),
            Some(ImageFormat::Npy) => ("npy", "application/x-npy"),
            None => ("stl", "model/stl"),
        }
    }

    /// Parameter checks that need no volume.
    pub fn validate(&self) -> Result<(), Problem> {
        let bad = |m: &str| Err(Problem::new(ErrorCode::InvalidParameter, m));
        if let Some(d) = self.display() {
            if !matches!(d.depth, None | Some(8) | Some(16)) {
                return bad("`depth` must be 8 or 16");
            }
            if d.preset.is_some() && (d.ww.is_some() || d.wl.is_some()) {
                return bad("give either `preset` or `ww` and `wl`, not both");
            }
            if d.ww.is_some() != d.wl.is_some() {
                return bad("`ww` and `wl` go together");
            }
            if let (Some(w), Some(l)) = (d.ww, d.wl) {
                Window::new(w, l).map_err(|e| volume_problem(&e))?;
            }
        }
        if let ViewRequest::Mesh(m) = self
            && !m.iso.is_finite()
        {
            return bad("`iso` must be finite");
        }
        Ok(())
    }
}

/// The catalogue problem of an image-domain error.
pub fn volume_problem(e: &VolumeError) -> Problem {
    Problem::new(
        ErrorCode::from_code(e.code()).unwrap_or(ErrorCode::InvalidParameter),
        e.to_string(),
    )
}

fn encode_view(img: Array2<f32>, d: &Display, mu_water: f64) -> Result<Vec<u8>, Problem> {
    if d.format == ImageFormat::Npy {
        return Ok(encode_f32(img.view()));
    }
    let to_hu = |img: Array2<f32>| img.mapv(|v| mu_to_hu(v, mu_water));
    let (img, window) = match (d.preset, d.ww, d.wl) {
        (Some(p), _, _) => (to_hu(img), p.window()),
        (None, Some(w), Some(l)) => {
            let img = if d.units == Units::Hu {
                to_hu(img)
            } else {
                img
            };
            (img, Window::new(w, l).map_err(|e| volume_problem(&e))?)
        }
        _ => {
            let img = if d.units == Units::Hu {
                to_hu(img)
            } else {
                img
            };
            let w = Window::auto(img.view());
            (img, w)
        }
    };
    let depth = if d.depth == Some(16) {
        BitDepth::Sixteen
    } else {
        BitDepth::Eight
    };
    encode_png(img.view(), window, depth).map_err(|e| volume_problem(&e))
}

fn mesh_stl(vol: ArrayView3<'_, f32>, grid: &VolumeGrid, q: &MeshQuery, mu_water: f64) -> Vec<u8> {
    let iso = match q.units {
        Units::Native => q.iso as f32,
        // HU → μ: μ = μ_water (1 + HU/1000).
        Units::Hu => (mu_water * (1.0 + q.iso / 1000.0)) as f32,
    };
    let mesh = marching_cubes(vol, &Frame::from_grid(grid), iso);
    let mesh = if q.largest {
        mesh.largest_component()
    } else {
        mesh
    };
    mesh.to_stl_binary()
}

/// Render `req` from the bytes of a job's `volume.npy` on `grid`.
pub fn render(
    volume_npy: &[u8],
    grid: &VolumeGrid,
    req: &ViewRequest,
    mu_water: f64,
) -> Result<Vec<u8>, Problem> {
    let vol = decode_f32(volume_npy)
        .ok()
        .and_then(|a| a.into_dimensionality::<Ix3>().ok())
        .ok_or_else(Problem::internal)?;
    match req {
        ViewRequest::Slice(q) => {
            let index = q.index.unwrap_or(q.axis.len(&vol.view()) / 2);
            let img = slice(vol.view(), q.axis, index).map_err(|e| volume_problem(&e))?;
            encode_view(img, &req.display().ok_or_else(Problem::internal)?, mu_water)
        }
        ViewRequest::Projection(q) => {
            let len = q.axis.len(&vol.view());
            let slab = match (q.slab_start, q.slab_end) {
                (None, None) => None,
                (s, e) => Some(s.unwrap_or(0)..e.unwrap_or(len)),
            };
            let img = project(vol.view(), q.axis, q.kind, slab).map_err(|e| volume_problem(&e))?;
            encode_view(img, &req.display().ok_or_else(Problem::internal)?, mu_water)
        }
        ViewRequest::Mesh(q) => Ok(mesh_stl(vol.view(), grid, q, mu_water)),
    }
}
