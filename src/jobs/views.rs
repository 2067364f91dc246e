//! Views derived from a job's volume: a slice (PNG or `.npy`), a MIP/MinIP/average projection with an
//! optional slab (PNG or `.npy`), an iso-surface mesh (binary STL, mm, LPS). Each view is a pure function of
//! the immutable volume and its parameters, so it is cached under the SHA-256 of the parameters and that
//! hash is its strong ETag.
//!
//! Windows: a `preset` (soft_tissue, lung, liver, bone, brain) is in HU and applies after converting the
//! volume's μ (1/mm) with μ_water (volumes already in HU, from CT series, are used as they are); explicit
//! `ww`/`wl` are in the volume's units, or HU with `units=hu`; with neither, the window spans the 0.5–99.5
//! percentiles of the image.
//!
//! DICOM formats: a 2D view as a Secondary Capture instance (8-bit, through the window), a mesh as an
//! Encapsulated STL instance, the whole volume as a derived CT series (a ZIP). They keep the study, frame of
//! reference and patient of the source series when there is one.

use ndarray::{Array2, Array3, Ix3};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use super::ingest::dicom_problem;
use super::model::{ProductResult, VolumeUnits, fill_value};
use crate::dicom::{
    ScOrientation, SeriesMeta, write_ct_series, write_encapsulated_stl, write_enhanced_ct,
    write_secondary_capture_placed, write_zip,
};
use crate::error_code::{ErrorCode, Problem};
use crate::mesh::{MeshOptions, SURFACE_REVISION, extract};
use crate::render::Clip;
use crate::storage::npy::{decode_f32, encode_f32, hex};
use crate::volume::{
    Axis, BitDepth, DisplayGrid, Frame, ProjectionKind, Volume, VolumeError, Window, WindowPreset,
    encode_apng_annotated, encode_png_annotated, mu_to_hu, oriented_projection, oriented_slice,
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

struct Display {
    preset: Option<WindowPreset>,
    ww: Option<f64>,
    wl: Option<f64>,
    units: Units,
    depth: Option<u8>,
    format: ImageFormat,
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
            if !m.iso.is_finite() {
                return bad("`iso` must be finite");
            }
            mesh_options(m, 1.0, VolumeUnits::MuPerMm)
                .validate()
                .map_err(|e| Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))?;
        }
        Ok(())
    }
}

fn image_media(f: ImageFormat) -> (&'static str, &'static str) {
    match f {
        ImageFormat::Png => ("png", "image/png"),
        ImageFormat::Npy => ("npy", "application/x-npy"),
        ImageFormat::Dicom => ("dcm", "application/dicom"),
    }
}

fn mesh_media(f: MeshFormat) -> (&'static str, &'static str) {
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
    fn to_hu(&self, img: Array2<f32>) -> Array2<f32> {
        match self.units {
            VolumeUnits::Hu => img,
            VolumeUnits::MuPerMm => img.mapv(|v| mu_to_hu(v, self.mu_water)),
        }
    }
}

/// The mesh options of a query, with the iso-value in the volume's units.
fn mesh_options(q: &MeshQuery, mu_water: f64, units: VolumeUnits) -> MeshOptions {
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

/// The image in display units and its window.
fn windowed(
    img: Array2<f32>,
    d: &Display,
    ctx: &RenderContext,
) -> Result<(Array2<f32>, Window), Problem> {
    Ok(match (d.preset, d.ww, d.wl) {
        (Some(p), _, _) => (ctx.to_hu(img), p.window()),
        (None, Some(w), Some(l)) => {
            let img = if d.units == Units::Hu {
                ctx.to_hu(img)
            } else {
                img
            };
            (img, Window::new(w, l).map_err(|e| volume_problem(&e))?)
        }
        _ => {
            let img = if d.units == Units::Hu {
                ctx.to_hu(img)
            } else {
                img
            };
            let w = Window::auto(img.view());
            (img, w)
        }
    })
}

/// PNG `tEXt` chunks naming an image's orientation: `Orientation` (the screen sides, JSON) and, for planar
/// images, `ImagePlane` (its placement in patient space, JSON).
fn orientation_text(o: Option<&ScOrientation>) -> Vec<(String, String)> {
    let Some(o) = o else { return Vec::new() };
    let mut text = vec![(
        "Orientation".to_string(),
        serde_json::to_string(&o.sides).unwrap_or_default(),
    )];
    if let Some(p) = &o.plane {
        text.push((
            "ImagePlane".to_string(),
            serde_json::to_string(p).unwrap_or_default(),
        ));
    }
    text
}

fn encode_view(
    img: Array2<f32>,
    placement: Option<&ScOrientation>,
    d: &Display,
    ctx: &RenderContext,
) -> Result<Vec<u8>, Problem> {
    if d.format == ImageFormat::Npy {
        return Ok(encode_f32(img.view()));
    }
    let (img, window) = windowed(img, d, ctx)?;
    if d.format == ImageFormat::Dicom {
        // Without a patient there is no frame of reference to place the image in.
        let placement = placement.filter(|_| ctx.patient);
        return write_secondary_capture_placed(img.view(), window, &ctx.meta, None, placement)
            .map(|(_, bytes)| bytes)
            .map_err(|e| dicom_problem(&e));
    }
    let depth = if d.depth == Some(16) {
        BitDepth::Sixteen
    } else {
        BitDepth::Eight
    };
    encode_png_annotated(img.view(), window, depth, &orientation_text(placement))
        .map_err(|e| volume_problem(&e))
}

/// A rendered view and the stable codes of what it could not honour (a mesh's
/// [`crate::mesh::MeshWarning`] codes: `empty_surface`, `target_triangles_not_reached`).
#[derive(Debug, Clone, PartialEq)]
pub struct Rendered {
    pub bytes: Vec<u8>,
    pub warnings: Vec<String>,
}

impl From<Vec<u8>> for Rendered {
    fn from(bytes: Vec<u8>) -> Self {
        Self {
            bytes,
            warnings: Vec::new(),
        }
    }
}

fn mesh_bytes(vol: Volume, q: &MeshQuery, ctx: &RenderContext) -> Result<Rendered, Problem> {
    q.validate()?;
    let opts = mesh_options(q, ctx.mu_water, ctx.units);
    let max = vol.data.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if opts.iso > max {
        return Err(Problem::new(
            ErrorCode::IsoOutOfRange,
            format!(
                "`iso` {} is above every value of the volume (its maximum is {max} in the volume's units): \
                 the surface would be empty",
                q.iso
            ),
        ));
    }
    let (mesh, stats) = extract(&vol, &opts)
        .map_err(|e| Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))?;
    let stl = mesh.to_stl_binary();
    let bytes = match q.format {
        MeshFormat::Stl => stl,
        MeshFormat::Dicom => encapsulate(&stl, ctx)?,
    };
    Ok(Rendered {
        bytes,
        warnings: stats.warnings.into_iter().map(|w| w.code).collect(),
    })
}

fn encapsulate(stl: &[u8], ctx: &RenderContext) -> Result<Vec<u8>, Problem> {
    write_encapsulated_stl(stl, &ctx.meta, "ctrecon iso-surface")
        .map(|(_, bytes)| bytes)
        .map_err(|e| dicom_problem(&e))
}

/// The volume as a ZIP of a derived CT series (values converted to HU first).
fn series_zip(vol: Volume, q: &SeriesQuery, ctx: &RenderContext) -> Result<Vec<u8>, Problem> {
    let vol = match ctx.units {
        VolumeUnits::Hu => vol,
        VolumeUnits::MuPerMm => Volume {
            data: vol.data.mapv(|v| mu_to_hu(v, ctx.mu_water)),
            frame: vol.frame,
        },
    };
    let written = match q.layout {
        SeriesLayout::Classic => write_ct_series(&vol, &ctx.meta),
        SeriesLayout::Enhanced => write_enhanced_ct(&vol, &ctx.meta),
    }
    .map_err(|e| dicom_problem(&e))?;
    write_zip(&written.files).map_err(|e| dicom_problem(&e))
}

fn decode_volume(bytes: &[u8]) -> Result<Array3<f32>, Problem> {
    decode_f32(bytes)
        .ok()
        .and_then(|a| a.into_dimensionality::<Ix3>().ok())
        .ok_or_else(Problem::internal)
}

/// Render `req` from the bytes of a job's `volume.npy`.
pub fn render(
    volume_npy: &[u8],
    ctx: &RenderContext,
    req: &ViewRequest,
) -> Result<Rendered, Problem> {
    let vol = decode_volume(volume_npy)?;
    let placed = |plane: crate::volume::ImagePlane| ScOrientation {
        sides: plane.sides_for(ctx.patient),
        plane: Some(plane),
    };
    match req {
        ViewRequest::Slice(q) => {
            let vol = Volume {
                data: vol,
                frame: ctx.frame,
            };
            let grid =
                DisplayGrid::for_volume(&vol, ctx.patient).map_err(|e| volume_problem(&e))?;
            let index = q.index.unwrap_or(grid.len(q.axis) / 2);
            let (img, plane) = oriented_slice(&vol, &grid, q.axis, index, fill_value(ctx.units))
                .map_err(|e| volume_problem(&e))?;
            let d = req.display().ok_or_else(Problem::internal)?;
            encode_view(img, Some(&placed(plane)), &d, ctx).map(Rendered::from)
        }
        ViewRequest::Projection(q) => {
            let vol = Volume {
                data: vol,
                frame: ctx.frame,
            };
            let grid =
                DisplayGrid::for_volume(&vol, ctx.patient).map_err(|e| volume_problem(&e))?;
            let len = grid.len(q.axis);
            let slab = match (q.slab_start, q.slab_end) {
                (None, None) => None,
                (s, e) => Some(s.unwrap_or(0)..e.unwrap_or(len)),
            };
            let (img, plane) =
                oriented_projection(&vol, &grid, q.axis, q.kind, slab, fill_value(ctx.units))
                    .map_err(|e| volume_problem(&e))?;
            let d = req.display().ok_or_else(Problem::internal)?;
            encode_view(img, Some(&placed(plane)), &d, ctx).map(Rendered::from)
        }
        ViewRequest::Mesh(q) => mesh_bytes(
            Volume {
                data: vol,
                frame: ctx.frame,
            },
            q,
            ctx,
        ),
        ViewRequest::Series(q) => series_zip(
            Volume {
                data: vol,
                frame: ctx.frame,
            },
            q,
            ctx,
        )
        .map(Rendered::from),
    }
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

    fn display(&self, format: ImageFormat) -> Display {
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

/// Render a stored product (`product-{i}.npy` or `.stl` bytes) in a format other than the stored one.
pub fn render_product(
    bytes: &[u8],
    p: &ProductResult,
    q: &ProductQuery,
    format: ProductFormat,
    ctx: &RenderContext,
) -> Result<Vec<u8>, Problem> {
    if p.is_mesh() {
        return encapsulate(bytes, ctx);
    }
    if super::render_outputs::is_rendering(p) {
        return super::render_outputs::render_rgb_product(bytes, p, q, format, ctx);
    }
    let stack = decode_volume(bytes)?;
    let n = stack.dim().0;
    let frame_at = |k: usize| -> Result<Array2<f32>, Problem> {
        if k >= n {
            return Err(Problem::new(
                ErrorCode::SliceOutOfRange,
                format!("frame {k} is outside the {n} frames of the product"),
            ));
        }
        Ok(stack.index_axis(ndarray::Axis(0), k).to_owned())
    };
    let k = q.frame.unwrap_or(n / 2);
    let placement = |k: usize| {
        p.frame_sides(k, ctx.patient).map(|sides| ScOrientation {
            sides,
            plane: p.frame_plane(k),
        })
    };
    match format {
        ProductFormat::Png => encode_view(
            frame_at(k)?,
            placement(k).as_ref(),
            &q.display(ImageFormat::Png),
            ctx,
        ),
        ProductFormat::Dicom => encode_view(
            frame_at(k)?,
            placement(k).as_ref(),
            &q.display(ImageFormat::Dicom),
            ctx,
        ),
        ProductFormat::Apng => {
            // One window for every frame: the one the chosen frame would get.
            let d = q.display(ImageFormat::Png);
            let (_, window) = windowed(frame_at(k)?, &d, ctx)?;
            let frames: Vec<Array2<f32>> = (0..n)
                .map(|i| {
                    let f = stack.index_axis(ndarray::Axis(0), i).to_owned();
                    let hu = d.preset.is_some() || d.units == Units::Hu;
                    if hu { ctx.to_hu(f) } else { f }
                })
                .collect();
            encode_apng_annotated(
                &frames,
                window,
                q.delay_ms.unwrap_or(100),
                &orientation_text(placement(0).as_ref()),
            )
            .map_err(|e| volume_problem(&e))
        }
        ProductFormat::Npy | ProductFormat::Stl => Err(Problem::internal()),
    }
}
