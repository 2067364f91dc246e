//! The parameters of views and of product renderings (what a client asks for), their checks, cache keys and
//! media types, and the context rendering needs besides the data.

use ndarray::Array2;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::dicom::SeriesMeta;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::{ProductResult, VolumeUnits};
use crate::mesh::{MeshOptions, SURFACE_REVISION};
use crate::render::Clip;
use crate::storage::npy::hex;
use crate::volume::{Axis, Frame, ProjectionKind, VolumeError, Window, WindowPreset, mu_to_hu};

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
    /// A DICOM Secondary Capture instance.
    Dicom,
}

/// Encoding of a mesh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MeshFormat {
    /// Binary STL (mm, LPS).
    #[default]
    Stl,
    /// A DICOM Encapsulated STL instance.
    Dicom,
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
    /// Taubin smoothing iterations (default 0).
    #[serde(default)]
    pub smoothing: usize,
    /// Decimate to at most this many triangles.
    #[serde(default)]
    pub target_triangles: Option<usize>,
    #[serde(default)]
    pub format: MeshFormat,
    /// Cut-away, as in the mesh product: the clip planes and boxes as JSON text (`{"planes": [{"point_mm":
    /// [0, 0, 0], "normal": [0, 1, 0]}], "boxes": […]}`); the cut is capped so the mesh stays closed.
    #[serde(default, deserialize_with = "clip_from_json")]
    pub clip: Option<Clip>,
}

/// A `clip` query parameter: the JSON of a [`Clip`].
fn clip_from_json<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Clip>, D::Error> {
    let text = String::deserialize(d)?;
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|e| serde::de::Error::custom(format!("`clip` is not a clip object: {e}")))
}

impl MeshQuery {
    /// The checks of the mesh product: finite iso, smoothing and triangle target within bounds, and a valid
    /// clip (non-zero plane normals, positive box sizes, at most 16); the problem carries the same codes.
    pub fn validate(&self) -> Result<(), Problem> {
        mesh_options(self, 1.0, VolumeUnits::Hu)
            .validate()
            .map_err(|e| Problem::new(ErrorCode::from(&e), e.to_string()))
    }
}

/// Layout of a derived CT series download.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SeriesLayout {
    /// One CT Image Storage file per slice.
    #[default]
    Classic,
    /// One multi-frame Enhanced CT file.
    Enhanced,
}

/// `GET …/series.zip`: the volume as a derived CT series.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeriesQuery {
    #[serde(default)]
    pub layout: SeriesLayout,
}

/// A derived view of a job's volume.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "view", rename_all = "snake_case")]
pub enum ViewRequest {
    Slice(SliceQuery),
    Projection(ProjectionQuery),
    Mesh(MeshQuery),
    Series(SeriesQuery),
}

pub(super) struct Display {
    pub(super) preset: Option<WindowPreset>,
    pub(super) ww: Option<f64>,
    pub(super) wl: Option<f64>,
    pub(super) units: Units,
    pub(super) depth: Option<u8>,
    pub(super) format: ImageFormat,
}

impl ViewRequest {
    /// Hex SHA-256 of the parameters (and μ_water; for meshes the [`SURFACE_REVISION`]): the cache key and
    /// strong ETag of the view.
    pub fn key(&self, mu_water: f64) -> String {
        let text = match self {
            ViewRequest::Mesh(_) => serde_json::to_string(&(self, mu_water, SURFACE_REVISION)),
            _ => serde_json::to_string(&(self, mu_water)),
        }
        .unwrap_or_default();
        hex(&Sha256::digest(text.as_bytes()))
    }

    /// Whether the view can come with warnings ([`Rendered::warnings`]), kept beside the cached file.
    pub fn warns(&self) -> bool {
        matches!(self, ViewRequest::Mesh(_))
    }

    pub(super) fn display(&self) -> Option<Display> {
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
            ViewRequest::Mesh(_) | ViewRequest::Series(_) => None,
        }
    }

    /// File extension and content type of the view.
    pub fn media(&self) -> (&'static str, &'static str) {
        match (self, self.display().map(|d| d.format)) {
            (_, Some(f)) => image_media(f),
            (ViewRequest::Mesh(m), _) => mesh_media(m.format),
            _ => ("zip", "application/zip"),
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
        if let ViewRequest::Mesh(m) = self {
            // As documented: a finite 32-bit float (a value past f32::MAX would round to it or overflow).
            if !m.iso.is_finite() || m.iso.abs() > f64::from(f32::MAX) {
                return bad("`iso` must be a finite 32-bit float");
            }
            mesh_options(m, 1.0, VolumeUnits::MuPerMm)
                .validate()
                .map_err(|e| Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))?;
        }
        Ok(())
    }
}

pub(super) fn image_media(f: ImageFormat) -> (&'static str, &'static str) {
    match f {
        ImageFormat::Png => ("png", "image/png"),
        ImageFormat::Npy => ("npy", "application/x-npy"),
        ImageFormat::Dicom => ("dcm", "application/dicom"),
    }
}

pub(super) fn mesh_media(f: MeshFormat) -> (&'static str, &'static str) {
    match f {
        MeshFormat::Stl => ("stl", "model/stl"),
        MeshFormat::Dicom => ("dcm", "application/dicom"),
    }
}

/// What rendering needs besides the data: placement, units, μ_water and the identity of DICOM outputs.
#[derive(Debug, Clone)]
pub struct RenderContext {
    pub frame: Frame,
    pub units: VolumeUnits,
    pub mu_water: f64,
    pub meta: SeriesMeta,
    /// The volume comes from a patient (a CT series): images are labelled with patient directions and DICOM
    /// outputs carry their placement; otherwise with the volume's axes.
    pub patient: bool,
}

impl RenderContext {
    /// Values in HU.
    pub(super) fn to_hu(&self, img: Array2<f32>) -> Array2<f32> {
        match self.units {
            VolumeUnits::Hu => img,
            VolumeUnits::MuPerMm => img.mapv(|v| mu_to_hu(v, self.mu_water)),
        }
    }
}

/// The mesh options of a query, with the iso-value in the volume's units.
pub(super) fn mesh_options(q: &MeshQuery, mu_water: f64, units: VolumeUnits) -> MeshOptions {
    let iso = match (q.units, units) {
        // HU → μ: μ = μ_water (1 + HU/1000).
        (Units::Hu, VolumeUnits::MuPerMm) => (mu_water * (1.0 + q.iso / 1000.0)) as f32,
        _ => q.iso as f32,
    };
    MeshOptions {
        iso,
        largest_component: q.largest,
        smoothing: q.smoothing,
        target_triangles: q.target_triangles,
        clip: q.clip.clone().unwrap_or_default(),
    }
}

/// The catalogue problem of an image-domain error.
pub fn volume_problem(e: &VolumeError) -> Problem {
    Problem::new(ErrorCode::from(e), e.to_string())
}

/// Encoding of a product of a volume job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ProductFormat {
    /// One frame of an image stack.
    Png,
    /// Every frame of an image stack as an animated PNG.
    Apng,
    /// The image stack as float32 `[frames][rows][columns]`.
    Npy,
    /// A mesh as binary STL.
    Stl,
    /// One frame as Secondary Capture, or a mesh as Encapsulated STL.
    Dicom,
}

/// `GET …/products/{index}`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProductQuery {
    /// Default: `png` for images, `stl` for meshes.
    pub format: Option<ProductFormat>,
    /// Frame of a stack (default the middle one).
    pub frame: Option<usize>,
    pub preset: Option<WindowPreset>,
    pub ww: Option<f64>,
    pub wl: Option<f64>,
    #[serde(default)]
    pub units: Units,
    pub depth: Option<u8>,
    /// Animated PNG: milliseconds per frame (default 100).
    pub delay_ms: Option<u16>,
}

impl ProductQuery {
    /// The format asked for, checked against the product.
    pub fn format_for(&self, p: &ProductResult) -> Result<ProductFormat, Problem> {
        let f = self.format.unwrap_or(if p.is_mesh() {
            ProductFormat::Stl
        } else {
            ProductFormat::Png
        });
        let ok = match f {
            ProductFormat::Stl => p.is_mesh(),
            ProductFormat::Png | ProductFormat::Apng | ProductFormat::Npy => !p.is_mesh(),
            ProductFormat::Dicom => true,
        };
        if !ok {
            return Err(Problem::new(
                ErrorCode::InvalidParameter,
                format!("a {} product cannot be sent as {f:?}", p.kind).to_lowercase(),
            ));
        }
        Ok(f)
    }

    pub(super) fn display(&self, format: ImageFormat) -> Display {
        Display {
            preset: self.preset,
            ww: self.ww,
            wl: self.wl,
            units: self.units,
            depth: self.depth,
            format,
        }
    }

    /// Checks that need no data.
    pub fn validate(&self) -> Result<(), Problem> {
        ViewRequest::Slice(SliceQuery {
            axis: Axis::Axial,
            index: None,
            format: ImageFormat::Png,
            preset: self.preset,
            ww: self.ww,
            wl: self.wl,
            units: self.units,
            depth: self.depth,
        })
        .validate()?;
        if self.delay_ms == Some(0) {
            return Err(Problem::new(
                ErrorCode::InvalidParameter,
                "`delay_ms` must be positive",
            ));
        }
        Ok(())
    }

    /// Hex SHA-256 of the product, format and parameters: cache key and ETag of a rendering.
    pub fn key(&self, index: usize, format: ProductFormat, mu_water: f64) -> String {
        let text = serde_json::to_string(&(index, format, self, mu_water)).unwrap_or_default();
        hex(&Sha256::digest(text.as_bytes()))
    }
}

impl ProductFormat {
    pub fn media(self) -> (&'static str, &'static str) {
        match self {
            ProductFormat::Png => ("png", "image/png"),
            ProductFormat::Apng => ("png", "image/apng"),
            ProductFormat::Npy => ("npy", "application/x-npy"),
            ProductFormat::Stl => ("stl", "model/stl"),
            ProductFormat::Dicom => ("dcm", "application/dicom"),
        }
    }
}
