//! The dispatcher: one call that validates, checks limits and runs any algorithm on any geometry.

use ndarray::{ArrayD, ArrayViewD, Ix2, Ix3};

use super::{AlgorithmSpec, FbpParams, OutputGrid};
use crate::recon::analytic;
use crate::recon::control::Control;
use crate::recon::error::{ReconError, ensure_finite};
use crate::recon::geometry::Views;
use crate::recon::grid::Limits;
use crate::recon::iterative;
use crate::recon::iterative::params::InitialImage;

/// Check that `grid` has the dimensionality of `views` and is valid.
pub fn check_grid(views: &Views, grid: &OutputGrid) -> Result<(), ReconError> {
    match (views, grid) {
        (Views::D2(_), OutputGrid::Image(g)) => g.validate()?,
        (Views::D3(_) | Views::Slices(_), OutputGrid::Volume(g)) => g.validate()?,
        (Views::D2(_), OutputGrid::Volume(_)) => {
            return Err(ReconError::param(
                "grid",
                "a 2D geometry reconstructs an image: {nx, ny, dx_mm, dy_mm}",
            ));
        }
        (Views::D3(_) | Views::Slices(_), OutputGrid::Image(_)) => {
            return Err(ReconError::param(
                "grid",
                "a 3D geometry (cone or parallel3d) reconstructs a volume: {nx, ny, nz, spacing_mm}",
            ));
        }
    }
    Ok(())
}

fn grid_elements(grid: &OutputGrid) -> u64 {
    match grid {
        OutputGrid::Image(g) => (g.nx as u64).saturating_mul(g.ny as u64),
        OutputGrid::Volume(g) => g.voxels(),
    }
}

fn data_elements(views: &Views) -> u64 {
    views
        .data_shape()
        .iter()
        .fold(1u64, |a, &n| a.saturating_mul(n as u64))
}

/// Bytes a reconstruction allocates besides its input: the output, working copies and per-thread buffers.
pub fn estimate_bytes(spec: &AlgorithmSpec, views: &Views, grid: &OutputGrid) -> u64 {
    if let (Views::Slices(v), OutputGrid::Volume(g)) = (views, grid) {
        return super::slices::estimate_bytes(spec, v, g);
    }
    let out = Limits::f32_bytes(grid_elements(grid));
    if let AlgorithmSpec::Fbp(p) | AlgorithmSpec::Fdk(p) = spec {
        analytic::estimate_bytes(views, grid, p)
    } else {
        iterative::estimate_bytes(spec, views, grid).max(
            out.saturating_mul(3)
                .saturating_add(Limits::f32_bytes(data_elements(views)).saturating_mul(2)),
        )
    }
}

/// Reconstruct `data` (`[view][u]` or `[view][v][u]`, line integrals) measured with `views` on `grid`.
///
/// `fbp` and `fdk` name the same family: a 2D geometry runs parallel or fan-beam FBP, a cone beam FDK, a 3D
/// parallel beam 2D FBP slice by slice ([`super::slices`], as every iterative method on it).
/// Validation (shape, finiteness, parameters, memory) happens before any large allocation.
pub fn reconstruct(
    spec: &AlgorithmSpec,
    views: &Views,
    data: ArrayViewD<'_, f32>,
    grid: &OutputGrid,
    limits: &Limits,
    ctl: Control<'_>,
) -> Result<ArrayD<f32>, ReconError> {
    let expected = views.data_shape();
    if data.shape() != expected.as_slice() {
        return Err(ReconError::ShapeMismatch {
            expected,
            got: data.shape().to_vec(),
        });
    }
    check_grid(views, grid)?;
    limits.check(estimate_bytes(spec, views, grid))?;
    ensure_finite(data.view())?;
    if let (Views::Slices(v), OutputGrid::Volume(g)) = (views, grid) {
        let data = data
            .into_dimensionality::<Ix3>()
            .map_err(|_| ReconError::ShapeMismatch {
                expected: views.data_shape(),
                got: expected.clone(),
            })?;
        return Ok(super::slices::reconstruct(spec, v, data, g, limits, ctl)?.into_dyn());
    }
    match spec {
        AlgorithmSpec::Fbp(p) | AlgorithmSpec::Fdk(p) => analytic_run(p, views, data, grid, ctl),
        _ => {
            let initial = match initial_of(spec) {
                InitialImage::Fbp => Some(analytic_run(
                    &FbpParams::default(),
                    views,
                    data.view(),
                    grid,
                    ctl,
                )?),
                InitialImage::Zero => None,
            };
            iterative::solve(
                spec,
                views,
                data,
                grid,
                initial.as_ref().map(|a| a.view()),
                limits,
                ctl,
            )
        }
    }
}

fn initial_of(spec: &AlgorithmSpec) -> InitialImage {
    match spec {
        AlgorithmSpec::Art(p) => p.initial,
        AlgorithmSpec::Sart(p) | AlgorithmSpec::OsSart(p) => p.initial,
        AlgorithmSpec::Sirt(p) => p.initial,
        AlgorithmSpec::Cgls(p) => p.initial,
        AlgorithmSpec::Tv(p) => p.initial,
        AlgorithmSpec::Mlem(_) | AlgorithmSpec::Fbp(_) | AlgorithmSpec::Fdk(_) => {
            InitialImage::Zero
        }
    }
}

fn analytic_run(
    params: &FbpParams,
    views: &Views,
    data: ArrayViewD<'_, f32>,
    grid: &OutputGrid,
    ctl: Control<'_>,
) -> Result<ArrayD<f32>, ReconError> {
    params.validate()?;
    // A data array of the wrong rank is a fault of the data, not of a parameter.
    let got = data.shape().to_vec();
    let shape_err = |_: ndarray::ShapeError| ReconError::ShapeMismatch {
        expected: views.data_shape(),
        got: got.clone(),
    };
    match (views, grid) {
        (Views::D2(v), OutputGrid::Image(g)) => {
            let sino = data.into_dimensionality::<Ix2>().map_err(shape_err)?;
            Ok(analytic::fbp_2d(v, sino, g, params, ctl)?.into_dyn())
        }
        (Views::D3(v), OutputGrid::Volume(g)) => {
            let proj = data.into_dimensionality::<Ix3>().map_err(shape_err)?;
            Ok(analytic::fdk(v, proj, g, params, ctl)?.into_dyn())
        }
        (Views::Slices(_), _) => Err(ReconError::param(
            "geometry",
            "a 3D parallel beam is reconstructed slice by slice (recon::algorithm::reconstruct)",
        )),
        _ => Err(ReconError::param(
            "grid",
            "grid and geometry dimensionality differ",
        )),
    }
}

#[cfg(test)]
mod tests {
    use ndarray::ArrayD;

    use super::*;
    use crate::recon::control::unattended;
    use crate::recon::geometry::Geometry;
    use crate::recon::grid::ImageGrid;

    #[test]
    fn data_of_the_wrong_rank_is_a_shape_mismatch_not_a_bad_parameter() {
        let geometry: Geometry = serde_json::from_str(
            r#"{"type": "parallel", "angles": {"count": 4}, "det_count": 8, "det_spacing_mm": 1.0}"#,
        )
        .unwrap();
        let views = geometry.to_views().unwrap();
        let data = ArrayD::<f32>::zeros(vec![4, 1, 8]);
        let grid = OutputGrid::Image(ImageGrid::square(8, 1.0));
        let r = analytic_run(
            &FbpParams::default(),
            &views,
            data.view(),
            &grid,
            unattended(),
        );
        assert_eq!(
            r.unwrap_err(),
            ReconError::ShapeMismatch {
                expected: vec![4, 8],
                got: vec![4, 1, 8],
            }
        );
    }
}
