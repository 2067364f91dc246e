//! Rendering a view or a stored product: windowing, encoding as PNG / `.npy` / DICOM, meshes and derived
//! series.

use ndarray::{Array2, Array3, Ix3};

use super::query::*;
use super::rgb;
use crate::dicom::{
    ScOrientation, write_ct_series, write_encapsulated_stl, write_enhanced_ct,
    write_secondary_capture_placed, write_zip,
};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::ingest::dicom_problem;
use crate::jobs::model::{ProductResult, VolumeUnits, fill_value};
use crate::mesh::extract;
use crate::storage::npy::{decode_f32, encode_f32};
use crate::volume::{
    BitDepth, DisplayGrid, Volume, Window, encode_apng_annotated, encode_png_annotated, mu_to_hu,
    oriented_projection, oriented_slice,
};

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
    if rgb::is_rendering(p) {
        return rgb::render_rgb_product(bytes, p, q, format, ctx);
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
