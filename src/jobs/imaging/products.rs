//! Making the products of a volume job from the processed volume: projections, MPR planes and series, curved
//! MPR, rotating projections, meshes and renderings.

use ndarray::{Array3, Axis as NdAxis};
use sha2::{Digest, Sha256};

use super::plan::Planned;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::*;
use crate::jobs::model::{FileInfo, Job, ProductResult, VolumeUnits};
use crate::jobs::render_products::make_render_product;
use crate::jobs::run::RunError;
use crate::jobs::views::volume_problem;
use crate::mesh::extract;
use crate::storage::npy::{encode_f32, hex};
use crate::storage::{BlobStore, ResultName};
use crate::volume::{
    DisplayGrid, ImagePlane, ProjectionKind, ScreenSides, Slab, Volume, curved, direction_label,
    oriented_projection, reformat, rotating_axes, rotating_projection, slab_series,
};

pub(super) fn io_failure(what: &str, e: std::io::Error) -> RunError {
    tracing::error!(error = %e, "{what}");
    RunError::Failed(Problem::internal())
}

pub(super) fn file_info(bytes: &[u8]) -> FileInfo {
    FileInfo {
        bytes: bytes.len() as u64,
        sha256: hex(&Sha256::digest(bytes)),
    }
}

pub(super) fn stack(images: Vec<ndarray::Array2<f32>>) -> Result<Array3<f32>, RunError> {
    let views: Vec<_> = images.iter().map(|a| a.view()).collect();
    ndarray::stack(NdAxis(0), &views).map_err(|e| {
        tracing::error!(error = %e, "stacking product images failed");
        RunError::Failed(Problem::internal())
    })
}

fn product_kind(p: &ProductSpec) -> &'static str {
    match p {
        ProductSpec::Projection(_) => "projection",
        ProductSpec::Mpr(_) => "mpr",
        ProductSpec::Curved(_) => "curved",
        ProductSpec::Rotating(_) => "rotating",
        ProductSpec::Mesh(_) => "mesh",
        ProductSpec::VolumeRender(_) => "volume_render",
        ProductSpec::SurfaceRender(_) => "surface_render",
    }
}

/// How a volume's products look: the value outside the volume, and whether the volume is a patient's (patient
/// directions on screen) or a reconstruction's (its own axes).
#[derive(Debug, Clone, Copy)]
pub(super) struct Looks {
    pub(super) fill: f32,
    pub(super) patient: bool,
    pub(super) units: VolumeUnits,
    /// μ of water (/mm) for requests in HU on a μ volume (`mu_water_per_mm`).
    pub(super) mu_water: f64,
}

pub(super) fn make_product(
    store: &BlobStore,
    job: &Job,
    vol: &Volume,
    index: usize,
    planned: &Planned,
    spec: &ProductSpec,
    looks: Looks,
) -> Result<ProductResult, RunError> {
    let Looks {
        fill,
        patient,
        units,
        mu_water,
    } = looks;
    let fail = |e: crate::volume::VolumeError| RunError::Failed(volume_problem(&e));
    // The plane of the first frame and the step between frames, for planar products.
    let mut placed: Option<(ImagePlane, Option<f64>)> = None;
    // Screen sides of the first frame of non-planar products.
    let mut sides: Option<ScreenSides> = None;
    // Frames that face different ways (a rotating projection): each frame's sides.
    let mut frame_orientations: Vec<ScreenSides> = Vec::new();
    let (images, pixel_mm) = match planned {
        Planned::Render(spec) => {
            return make_render_product(store, job.id, vol, index, spec, units, mu_water, patient);
        }
        Planned::Mesh(opts) => {
            let (mesh, stats) = extract(vol, opts).map_err(|e| {
                RunError::Failed(Problem::new(ErrorCode::InvalidMeshOptions, e.to_string()))
            })?;
            let stl = mesh.to_stl_binary();
            let file = file_info(&stl);
            store
                .write_atomic(
                    &store.result_path(job.id, &ResultName::Product { index, ext: "stl" }),
                    &stl,
                )
                .map_err(|e| io_failure("writing a mesh", e))?;
            return Ok(ProductResult {
                index,
                kind: product_kind(spec).into(),
                shape: None,
                pixel_mm: None,
                mesh: Some(stats),
                orientation: None,
                plane: None,
                frame_spacing_mm: None,
                frame_orientations: Vec::new(),
                description: None,
                file,
            });
        }
        Planned::Projection { axis, kind, slab } => {
            // Display orientation whatever the acquisition: axial [y][x]; coronal [z↓][x]; sagittal [z↓][y]
            // on the volume's display grid (its own samples when axis-aligned).
            let grid = DisplayGrid::for_volume(vol, patient).map_err(fail)?;
            let (img, p) =
                oriented_projection(vol, &grid, *axis, *kind, slab.clone(), fill).map_err(fail)?;
            placed = Some((p, None));
            (vec![img], p.pixel_mm)
        }
        Planned::Mpr {
            plane,
            slab,
            series,
        } => {
            let (images, first_offset, step) = match series {
                None => (
                    vec![reformat(vol, plane, *slab, fill).map_err(fail)?],
                    0.0,
                    None,
                ),
                Some((spacing, extent)) => {
                    let slab = slab.unwrap_or(Slab {
                        thickness_mm: 0.0,
                        kind: ProjectionKind::Mean,
                    });
                    let images =
                        slab_series(vol, plane, slab, *spacing, *extent, fill).map_err(fail)?;
                    let first = -(images.len() as f64 - 1.0) / 2.0 * spacing;
                    (images, first, Some(*spacing))
                }
            };
            placed = Some((
                ImagePlane {
                    first_pixel_mm: plane.point(0, 0, first_offset),
                    row_direction: plane.u,
                    column_direction: plane.v,
                    pixel_mm: [plane.pixel_mm; 2],
                },
                step,
            ));
            (images, [plane.pixel_mm; 2])
        }
        Planned::Curved {
            points,
            down,
            height,
            pixel_mm,
        } => {
            // Columns follow the curve from its first point to its last; rows run `down`. Labels name unit
            // directions: a component counts when it is above a tenth of the whole.
            let (a, b) = (points[0], points[points.len() - 1]);
            let unit = |v: [f64; 3]| {
                let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if n > 0.0 && n.is_finite() {
                    v.map(|c| c / n)
                } else {
                    v
                }
            };
            let along = unit([b[0] - a[0], b[1] - a[1], b[2] - a[2]]);
            let down = unit(down.unwrap_or([0.0, 0.0, -1.0]));
            let neg = |v: [f64; 3]| v.map(|c| -c);
            sides = Some(if patient {
                ScreenSides {
                    left: direction_label(neg(along)),
                    right: direction_label(along),
                    top: direction_label(neg(down)),
                    bottom: direction_label(down),
                }
            } else {
                ImagePlane {
                    first_pixel_mm: a,
                    row_direction: along,
                    column_direction: down,
                    pixel_mm: [*pixel_mm; 2],
                }
                .axis_sides()
            });
            (
                vec![curved(vol, points, Some(down), *height, *pixel_mm, fill).map_err(fail)?],
                [*pixel_mm; 2],
            )
        }
        Planned::Rotating { angles, kind } => {
            // Frame k is seen from angles[k] about the superior axis, screen down inferior; the first looks
            // from anterior, as a coronal image.
            let seen_from = |angle: f64| {
                ImagePlane {
                    first_pixel_mm: [0.0; 3],
                    row_direction: rotating_axes(angle).1,
                    column_direction: [0.0, 0.0, -1.0],
                    pixel_mm: [1.0; 2],
                }
                .sides_for(patient)
            };
            sides = Some(seen_from(angles.first().copied().unwrap_or(0.0)));
            if angles.len() > 1 {
                frame_orientations = angles.iter().map(|&a| seen_from(a)).collect();
            }
            let px = vol
                .frame
                .spacing_mm
                .iter()
                .copied()
                .fold(f64::INFINITY, f64::min)
                .max(0.5);
            (
                rotating_projection(vol, angles, *kind, fill).map_err(fail)?,
                [px; 2],
            )
        }
    };
    let stacked = stack(images)?;
    let (n, h, w) = stacked.dim();
    let encoded = encode_f32(stacked.view());
    let file = file_info(&encoded);
    store
        .write_atomic(
            &store.result_path(job.id, &ResultName::Product { index, ext: "npy" }),
            &encoded,
        )
        .map_err(|e| io_failure("writing a product", e))?;
    Ok(ProductResult {
        index,
        kind: product_kind(spec).into(),
        shape: Some([n, h, w]),
        pixel_mm: Some(pixel_mm),
        mesh: None,
        orientation: placed.map(|(p, _)| p.sides_for(patient)).or(sides),
        plane: placed.map(|(p, _)| p),
        frame_spacing_mm: placed.and_then(|(_, step)| step),
        frame_orientations,
        description: None,
        file,
    })
}
