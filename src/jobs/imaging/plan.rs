//! Planning a volume job at submission: defaults resolved, parameters checked and the memory estimated from
//! the input's shape and frame alone.

use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::*;
use crate::jobs::render_products::plan_render;
use crate::jobs::views::volume_problem;
use crate::mesh::MeshOptions;
use crate::volume::{
    Axis, DisplayGrid, Frame, MAX_SIDE, Plane, ProjectionKind, Slab, isotropic_grid, series_count,
    whole_ceil,
};

/// Shape and placement of a volume, known before any data is read.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VolumeShape {
    /// `[nz, ny, nx]`.
    pub dim: (usize, usize, usize),
    pub frame: Frame,
    /// No value of the volume exceeds this, when known (the stored maximum of a series or result; after a
    /// step, at least 0, which covers the fill of resampling and the borders of smoothing).
    pub max_value: Option<f32>,
}

impl VolumeShape {
    fn voxels(&self) -> u64 {
        (self.dim.0 as u64) * (self.dim.1 as u64) * (self.dim.2 as u64)
    }
    fn smallest_spacing(&self) -> f64 {
        self.frame
            .spacing_mm
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min)
    }
    /// Patient positions of the eight corner voxels.
    fn corners(&self) -> [[f64; 3]; 8] {
        self.frame.corners(self.dim)
    }
    pub(super) fn centre(&self) -> [f64; 3] {
        let c = self.corners();
        std::array::from_fn(|a| c.iter().map(|p| p[a]).sum::<f64>() / 8.0)
    }
    /// Half the extent of the volume along unit vector `d`, seen from `centre`.
    fn half_extent(&self, centre: [f64; 3], d: [f64; 3]) -> f64 {
        self.corners()
            .iter()
            .map(|p| {
                ((p[0] - centre[0]) * d[0] + (p[1] - centre[1]) * d[1] + (p[2] - centre[2]) * d[2])
                    .abs()
            })
            .fold(0.0, f64::max)
    }
}

/// A product with its defaults resolved.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Planned {
    Projection {
        axis: Axis,
        kind: ProjectionKind,
        slab: Option<std::ops::Range<usize>>,
    },
    Mpr {
        plane: Plane,
        slab: Option<Slab>,
        /// `(spacing, extent)` of a series.
        series: Option<(f64, f64)>,
    },
    Curved {
        points: Vec<[f64; 3]>,
        down: Option<[f64; 3]>,
        height: usize,
        pixel_mm: f64,
    },
    Rotating {
        angles: Vec<f64>,
        kind: ProjectionKind,
    },
    Mesh(MeshOptions),
    Render(RenderSpec),
}

/// A checked volume job: the shape after the steps, the products with defaults resolved, the memory needed.
#[derive(Debug, Clone, PartialEq)]
pub struct VolumePlan {
    pub output: VolumeShape,
    pub(super) products: Vec<Planned>,
    pub estimate_bytes: u64,
}

fn invalid(detail: impl Into<String>) -> Problem {
    Problem::new(ErrorCode::InvalidParameter, detail)
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|c| c.is_finite())
}

fn principal_normal(axis: Axis) -> [f64; 3] {
    match axis {
        Axis::Axial => [0.0, 0.0, 1.0],
        Axis::Coronal => [0.0, 1.0, 0.0],
        // Columns then run anterior → posterior (anterior on the left, as radiographers read sagittal images).
        Axis::Sagittal => [-1.0, 0.0, 0.0],
    }
}

fn plan_mpr(s: &MprSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let normal = match (s.plane, s.normal) {
        (Some(a), None) => principal_normal(a),
        (None, Some(n)) if finite3(&n) => n,
        (None, Some(_)) => return Err(invalid(format!("products[{i}]: `normal` must be finite"))),
        _ => {
            return Err(invalid(format!(
                "products[{i}]: give exactly one of `plane` (axial, coronal, sagittal) and `normal`"
            )));
        }
    };
    let centre = match s.centre_mm {
        Some(c) if finite3(&c) => c,
        Some(_) => {
            return Err(invalid(format!(
                "products[{i}]: `centre_mm` must be finite"
            )));
        }
        None => shape.centre(),
    };
    let pixel = s.pixel_mm.unwrap_or_else(|| shape.smallest_spacing());
    // Orientation first (a 1×1 plane), then the size that covers the volume.
    let probe = Plane::oblique(centre, normal, [1, 1], pixel)
        .map_err(|e| invalid(format!("products[{i}]: {e}")))?;
    let size = match s.size {
        Some(sz) => sz,
        None => {
            let side = |d: [f64; 3]| {
                let n = whole_ceil(2.0 * shape.half_extent(centre, d) / pixel) + 1.0;
                n.clamp(1.0, MAX_SIDE as f64) as usize
            };
            [side(probe.u), side(probe.v)]
        }
    };
    let plane = Plane { size, ..probe };
    plane
        .validate()
        .map_err(|e| invalid(format!("products[{i}]: {e}")))?;
    if let Some(slab) = s.slab
        && !(slab.thickness_mm.is_finite() && slab.thickness_mm >= 0.0)
    {
        return Err(invalid(format!(
            "products[{i}]: slab `thickness_mm` must be finite and non-negative"
        )));
    }
    let series = match (s.spacing_mm, s.extent_mm) {
        (None, None) => None,
        (None, Some(_)) => {
            return Err(invalid(format!(
                "products[{i}]: `extent_mm` needs `spacing_mm`"
            )));
        }
        (Some(sp), ext) => {
            let ext = ext.unwrap_or_else(|| shape.half_extent(centre, plane.normal()));
            if !(sp.is_finite() && sp > 0.0 && ext.is_finite() && ext >= 0.0) {
                return Err(invalid(format!(
                    "products[{i}]: `spacing_mm` must be positive and `extent_mm` non-negative"
                )));
            }
            if 2.0 * ext / sp + 1.0 > MAX_SIDE as f64 {
                return Err(invalid(format!("products[{i}]: too many planes")));
            }
            Some((sp, ext))
        }
    };
    let count = series.map_or(1, |(sp, ext)| series_count(sp, ext) as u64);
    let bytes = count * (size[0] as u64) * (size[1] as u64) * 4;
    Ok((
        Planned::Mpr {
            plane,
            slab: s.slab,
            series,
        },
        bytes,
    ))
}

fn plan_product(p: &ProductSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let (nz, ny, nx) = shape.dim;
    match p {
        ProductSpec::Projection(s) => {
            // Slabs count images of the display grid: the volume's own slices when it is axis-aligned.
            let grid = DisplayGrid::of(&shape.frame, shape.dim).map_err(|e| volume_problem(&e))?;
            let n = grid.len(s.axis);
            let (gz, gy, gx) = grid.dim;
            let slab = match s.slab {
                None => None,
                Some([a, b]) if a < b && b <= n => Some(a..b),
                Some([a, b]) => {
                    return Err(Problem::new(
                        ErrorCode::InvalidSlab,
                        format!("products[{i}]: slab {a}..{b} is empty or outside 0..{n}"),
                    ));
                }
            };
            let pixels = (gz * gy * gx / n.max(1)) as u64;
            Ok((
                Planned::Projection {
                    axis: s.axis,
                    kind: s.kind,
                    slab,
                },
                pixels * 4,
            ))
        }
        ProductSpec::Mpr(s) => plan_mpr(s, shape, i),
        ProductSpec::Curved(s) => {
            if s.points_mm.len() < 2 || s.points_mm.len() > MAX_CURVE_POINTS {
                return Err(invalid(format!(
                    "products[{i}]: a curve needs 2 to {MAX_CURVE_POINTS} points"
                )));
            }
            if !s.points_mm.iter().all(finite3) || s.down.is_some_and(|d| !finite3(&d)) {
                return Err(invalid(format!("products[{i}]: points must be finite")));
            }
            let pixel = s.pixel_mm.unwrap_or_else(|| shape.smallest_spacing());
            if !(pixel.is_finite() && pixel > 0.0) || s.height == 0 || s.height > MAX_SIDE {
                return Err(invalid(format!(
                    "products[{i}]: `pixel_mm` must be positive and `height` within 1..={MAX_SIDE}"
                )));
            }
            let length: f64 = s
                .points_mm
                .windows(2)
                .map(|w| {
                    (0..3)
                        .map(|c| (w[1][c] - w[0][c]).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .sum();
            let cols = (length / pixel).floor() + 1.0;
            if cols > MAX_SIDE as f64 {
                return Err(invalid(format!(
                    "products[{i}]: the curve is longer than {MAX_SIDE} pixels"
                )));
            }
            Ok((
                Planned::Curved {
                    points: s.points_mm.clone(),
                    down: s.down,
                    height: s.height,
                    pixel_mm: pixel,
                },
                cols as u64 * s.height as u64 * 4,
            ))
        }
        ProductSpec::Rotating(s) => {
            if s.frames == 0 || s.frames > MAX_ROTATING_FRAMES {
                return Err(invalid(format!(
                    "products[{i}]: `frames` must be in 1..={MAX_ROTATING_FRAMES}"
                ))
                .at(format!("/products/{i}/frames")));
            }
            let angles = (0..s.frames)
                .map(|k| 360.0 * k as f64 / s.frames as f64)
                .collect();
            // Frames are about (volume diagonal in the axial plane) × (height) at the finest spacing.
            let px = shape.smallest_spacing().max(0.5);
            let sp = shape.frame.spacing_mm;
            let w = whole_ceil((nx as f64 * sp[0]).hypot(ny as f64 * sp[1]) / px) + 2.0;
            let h = whole_ceil(nz as f64 * sp[2] / px) + 1.0;
            Ok((
                Planned::Rotating {
                    angles,
                    kind: s.kind,
                },
                (s.frames as f64 * w.min(MAX_SIDE as f64) * h.min(MAX_SIDE as f64) * 4.0) as u64,
            ))
        }
        ProductSpec::Mesh(m) => {
            m.validate()
                .map_err(|e| Problem::new(ErrorCode::from(&e), format!("products[{i}]: {e}")))?;
            if let Some(max) = shape.max_value.filter(|&max| m.iso > max) {
                return Err(Problem::new(
                    ErrorCode::IsoOutOfRange,
                    format!(
                        "products[{i}]: {}",
                        crate::jobs::iso_range::above_every_value("iso", m.iso, max)
                    ),
                )
                .at(format!("/products/{i}/iso")));
            }
            // Marching cubes keeps a vertex index over two slices plus the mesh; bound it by the volume.
            Ok((Planned::Mesh(m.clone()), shape.voxels() * 4))
        }
        ProductSpec::VolumeRender(s) => render_plan(RenderSpec::Volume(s.clone()), shape, i),
        ProductSpec::SurfaceRender(s) => render_plan(RenderSpec::Surface(s.clone()), shape, i),
    }
}

fn render_plan(spec: RenderSpec, shape: &VolumeShape, i: usize) -> Result<(Planned, u64), Problem> {
    let bytes = plan_render(&spec, shape.dim, &shape.frame, i)?;
    Ok((Planned::Render(spec), bytes))
}

/// Check a volume job against its input's shape and the memory budget.
pub fn plan(
    req: &VolumeJobRequest,
    input: VolumeShape,
    budget_bytes: u64,
) -> Result<VolumePlan, Problem> {
    if req.steps.len() > MAX_ITEMS || req.products.len() > MAX_ITEMS {
        let at = if req.steps.len() > MAX_ITEMS {
            "/steps"
        } else {
            "/products"
        };
        return Err(invalid(format!(
            "at most {MAX_ITEMS} steps and {MAX_ITEMS} products"
        ))
        .at(at));
    }
    let max_voxels = budget_bytes / 4;
    let mut shape = input;
    let mut peak = 2 * shape.voxels() * 4;
    for (i, step) in req.steps.iter().enumerate() {
        match *step {
            Step::Resample { spacing_mm } => {
                let (n, frame) = isotropic_grid(&shape.frame, shape.dim, spacing_mm, max_voxels)
                    .map_err(|e| {
                        invalid(format!("steps[{i}]: {e}")).at(format!("/steps/{i}/spacing_mm"))
                    })?;
                let before = shape.voxels();
                shape = VolumeShape {
                    dim: (n[2], n[1], n[0]),
                    frame,
                    max_value: shape.max_value,
                };
                peak = peak.max((before + shape.voxels()) * 4);
            }
            Step::Gaussian { sigma_mm } => {
                if !(sigma_mm.is_finite() && (0.0..=MAX_SIGMA_MM).contains(&sigma_mm)) {
                    return Err(invalid(format!(
                        "steps[{i}]: `sigma_mm` must be in [0, {MAX_SIGMA_MM}], got {sigma_mm}"
                    ))
                    .at(format!("/steps/{i}/sigma_mm")));
                }
                peak = peak.max(3 * shape.voxels() * 4);
            }
            Step::Median => peak = peak.max(2 * shape.voxels() * 4),
        }
        shape.max_value = shape.max_value.map(|m| m.max(0.0));
    }
    let mut products = Vec::with_capacity(req.products.len());
    let mut product_bytes = 0u64;
    for (i, p) in req.products.iter().enumerate() {
        // A product's problem names its field, or at least the product.
        let (planned, bytes) = plan_product(p, &shape, i).map_err(|e| {
            if e.errors.is_empty() {
                e.at(format!("/products/{i}"))
            } else {
                e
            }
        })?;
        products.push(planned);
        product_bytes = product_bytes.max(bytes);
    }
    let estimate = peak.max(shape.voxels() * 4 + 2 * product_bytes);
    if estimate > budget_bytes {
        return Err(Problem::new(
            ErrorCode::JobTooLarge,
            format!(
                "the job needs about {estimate} bytes, more than the whole memory budget of {budget_bytes} bytes: \
                 resample to coarser voxels or ask for smaller products, or raise the service's memory_budget_bytes"
            ),
        ));
    }
    Ok(VolumePlan {
        output: shape,
        products,
        estimate_bytes: estimate,
    })
}
