//! Volume rendering (`volume_render`) and shaded surface display (`surface_render`) as products of a volume job:
//! checks at submission and execution on the worker pool (the request specs are in [`super::model::RenderSpec`]). One frame, or a rotating sequence of
//! `frames` views evenly spread over 360° of azimuth (about the image-up axis of the camera's view). The volume's
//! min/max bricks are built once per product and shared by its frames. Frames are stored as 8-bit RGB
//! (`product-{i}.npy`, uint8 `[frames][rows][columns][3]`) and sent as PNG, APNG or RGB Secondary Capture
//! ([`super::views::rgb`]).

use super::model::{MAX_RENDER_FRAMES, RenderSpec};
use super::model::{ProductResult, VolumeUnits};
use super::run::RunError;
use super::views::rgb::{encode_rgb_npy, file_info};
use crate::error_code::{ErrorCode, Problem};
use crate::render::{
    DEFAULT_MAX_SIDE, RenderError, RgbImage, Scene, surface_render_frames, volume_render_frames,
};
use crate::storage::{BlobStore, JobId, ResultName};
use crate::volume::Volume;

fn problem(i: usize, e: &RenderError) -> Problem {
    Problem::new(ErrorCode::from(e), format!("products[{i}]: {e}"))
}

/// Check a rendering product against the volume's shape (`dim`, `frame`) before anything runs; returns the
/// bytes it needs. Sizes are checked against the hard limit [`DEFAULT_MAX_SIDE`]; the configured limit is
/// [`check_render_size`].
pub fn plan_render(
    spec: &RenderSpec,
    dim: (usize, usize, usize),
    frame: &crate::volume::Frame,
    i: usize,
) -> Result<u64, Problem> {
    let n = spec.frames();
    if n == 0 || n > MAX_RENDER_FRAMES {
        return Err(Problem::new(
            ErrorCode::InvalidParameter,
            format!("products[{i}]: `frames` must be in 1..={MAX_RENDER_FRAMES}"),
        ));
    }
    match spec {
        RenderSpec::Volume(s) => RenderSpec::vr(s, VolumeUnits::Hu, 1.0)
            .and_then(|o| o.validate())
            .map_err(|e| problem(i, &e))?,
        RenderSpec::Surface(s) => RenderSpec::ssd(s, VolumeUnits::Hu, 1.0)
            .validate()
            .map_err(|e| problem(i, &e))?,
    }
    let [w, h] = spec.size();
    for k in 0..n {
        spec.camera_of(k)
            .rays(frame, dim, w, h, DEFAULT_MAX_SIDE)
            .map_err(|e| problem(i, &e))?;
    }
    let voxels = (dim.0 * dim.1 * dim.2) as u64;
    // The brick grid (8 bytes per 8³ brick) and one occupancy bit per voxel cell (`render::occupancy`).
    let bricks = (voxels / 512 + 1) * 8;
    let cells = voxels / 8 + 8;
    Ok(n as u64 * w as u64 * h as u64 * 7 + bricks + cells)
}

/// The configured largest image side, checked at submission.
pub fn check_render_size(spec: &RenderSpec, i: usize, max_side: usize) -> Result<(), Problem> {
    let [w, h] = spec.size();
    if w == 0 || h == 0 || w > max_side || h > max_side {
        return Err(problem(
            i,
            &RenderError::BadSize {
                width: w,
                height: h,
                max: max_side,
            },
        ));
    }
    Ok(())
}

/// [`check_render_size`] for every rendering of a volume job.
pub fn check_render_sizes(
    req: &super::model::VolumeJobRequest,
    max_side: usize,
) -> Result<(), Problem> {
    use super::model::ProductSpec;
    for (i, p) in req.products.iter().enumerate() {
        match p {
            ProductSpec::VolumeRender(s) => {
                check_render_size(&RenderSpec::Volume(s.clone()), i, max_side)
                    .map_err(|e| e.at(format!("/products/{i}/size")))?
            }
            ProductSpec::SurfaceRender(s) => {
                check_render_size(&RenderSpec::Surface(s.clone()), i, max_side)
                    .map_err(|e| e.at(format!("/products/{i}/size")))?
            }
            _ => {}
        }
    }
    Ok(())
}

/// Render every frame of `spec` from `vol` (in `units`; HU values of the request convert to μ through
/// `mu_water`, /mm) and store them as `product-{index}.npy` (uint8 RGB).
#[allow(clippy::too_many_arguments)]
pub fn make_render_product(
    store: &BlobStore,
    job: JobId,
    vol: &Volume,
    index: usize,
    spec: &RenderSpec,
    units: VolumeUnits,
    mu_water: f64,
    patient: bool,
) -> Result<ProductResult, RunError> {
    let fail = |e: RenderError| RunError::Failed(problem(index, &e));
    let scene = Scene::new(vol).map_err(fail)?;
    let [w, h] = spec.size();
    let rays = (0..spec.frames())
        .map(|k| {
            spec.camera_of(k)
                .rays(&vol.frame, vol.data.dim(), w, h, DEFAULT_MAX_SIDE)
        })
        .collect::<Result<Vec<_>, _>>()
        .map_err(fail)?;
    let sides: Vec<_> = rays
        .iter()
        .map(|r| r.screen_plane().sides_for(patient))
        .collect();
    // All frames at once: the threads go on to the next frame without waiting for the last rows of one.
    let frames: Vec<RgbImage> = match spec {
        RenderSpec::Volume(s) => volume_render_frames(
            &scene,
            &rays,
            &RenderSpec::vr(s, units, mu_water).map_err(fail)?,
        ),
        RenderSpec::Surface(s) => {
            surface_render_frames(&scene, &rays, &RenderSpec::ssd(s, units, mu_water))
        }
    }
    .map_err(fail)?;
    let rays = rays
        .first()
        .ok_or_else(|| RunError::Failed(Problem::internal()))?;
    let encoded = encode_rgb_npy(&frames);
    let file = file_info(&encoded);
    store
        .write_atomic(
            &store.result_path(job, &ResultName::Product { index, ext: "npy" }),
            &encoded,
        )
        .map_err(|e| {
            tracing::error!(error = %e, "writing a rendering failed");
            RunError::Failed(Problem::internal())
        })?;
    let plane = rays.screen_plane();
    Ok(ProductResult {
        index,
        kind: spec.kind().into(),
        shape: Some([frames.len(), h, w]),
        pixel_mm: (rays.projection == crate::render::Projection::Orthographic)
            .then_some([rays.pixel; 2]),
        mesh: None,
        orientation: Some(plane.sides_for(patient)),
        plane: None,
        frame_spacing_mm: None,
        // Each frame of a turning sequence is seen from its own side.
        frame_orientations: if sides.len() > 1 { sides } else { Vec::new() },
        description: Some(spec.describe()),
        file,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::jobs::model::{SurfaceRenderSpec, VolumeRenderSpec};
    use crate::render::Preset;

    #[test]
    fn hu_values_of_a_request_convert_to_mu_through_the_configured_mu_water() {
        let ssd: SurfaceRenderSpec =
            serde_json::from_value(serde_json::json!({"surfaces": [{"iso": 500}, {"iso": -1000}]}))
                .unwrap();
        let vr: VolumeRenderSpec =
            serde_json::from_value(serde_json::json!({"preset": "bone"})).unwrap();
        let bone = Preset::Bone.transfer_function();
        for mu_water in [0.0192, 0.02, 0.0251] {
            // On a μ volume: μ = μ_water (1 + HU/1000), so 500 HU is 1.5 μ_water and −1000 HU is 0.
            let o = RenderSpec::ssd(&ssd, VolumeUnits::MuPerMm, mu_water);
            assert!((o.surfaces[0].iso - 1.5 * mu_water).abs() < 1e-15, "{o:?}");
            assert!(o.surfaces[1].iso.abs() < 1e-15, "{o:?}");
            let o = RenderSpec::vr(&vr, VolumeUnits::MuPerMm, mu_water).unwrap();
            for (got, hu) in o.transfer_function.points.iter().zip(&bone.points) {
                let want = mu_water * (1.0 + hu.value / 1000.0);
                assert!(
                    (got.value - want).abs() < 1e-15,
                    "{} HU: {}",
                    hu.value,
                    got.value
                );
                assert_eq!((got.color, got.opacity), (hu.color, hu.opacity));
            }
            // On a HU volume the values stay as given.
            let o = RenderSpec::ssd(&ssd, VolumeUnits::Hu, mu_water);
            assert_eq!(o.surfaces[0].iso, 500.0);
            let o = RenderSpec::vr(&vr, VolumeUnits::Hu, mu_water).unwrap();
            assert_eq!(o.transfer_function, bone);
        }
        // Values in the volume's own units are never converted.
        let native: SurfaceRenderSpec = serde_json::from_value(
            serde_json::json!({"surfaces": [{"iso": 0.03}], "units": "native"}),
        )
        .unwrap();
        assert_eq!(
            RenderSpec::ssd(&native, VolumeUnits::MuPerMm, 0.02).surfaces[0].iso,
            0.03
        );
    }
}
