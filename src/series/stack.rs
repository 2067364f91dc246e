//! The slices along the normal: their positions, their order with exact duplicates dropped, the stack's
//! nominal spacing, collinearity and gantry tilt, and whether uneven spacing or missing slices are refused or
//! resampled under the [`UnevenPolicy`].

use super::layout::Layout;
use super::vector::{V3, dot, norm, scale, sub};
use super::{
    AssemblyOptions, MAX_BRIDGED_GAP, SeriesError, Slice, TILT_TOLERANCE_DEG, UnevenPolicy, Warning,
};

/// Each slice's image position (the origin for a lone slice without one).
pub(super) fn positions(slices: &[Slice]) -> Result<Vec<V3>, SeriesError> {
    let single = slices.len() == 1;
    slices
        .iter()
        .map(|s| match s.position_mm {
            Some(p) if p.iter().all(|v| v.is_finite()) => Ok(p),
            Some(_) => Err(SeriesError::InvalidAttribute {
                label: s.label.clone(),
                reason: "image position is not finite".into(),
            }),
            None if single => Ok([0.0; 3]),
            None => Err(SeriesError::MissingAttribute {
                label: s.label.clone(),
                what: "image position (0020,0032)",
            }),
        })
        .collect()
}

/// `(distance along the normal, slice index)` sorted by distance, exact duplicates dropped (with a warning); two
/// different slices at one place are refused.
pub(super) fn sort_unique(
    slices: &[Slice],
    positions: &[V3],
    layout: &Layout,
    warnings: &mut Vec<Warning>,
) -> Result<Vec<(f64, usize)>, SeriesError> {
    let normal = layout.axes[2];
    let mut order: Vec<(f64, usize)> = positions
        .iter()
        .enumerate()
        .map(|(i, p)| (dot(*p, normal), i))
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let [ps_r, ps_c] = layout.pixel_spacing;
    let same_place_mm = 1e-3 * ps_r.min(ps_c).max(1e-3);
    let mut kept: Vec<(f64, usize)> = Vec::with_capacity(order.len());
    for (d, i) in order {
        if let Some(&(dp, ip)) = kept.last()
            && (d - dp).abs() <= same_place_mm
            && norm(sub(positions[i], positions[ip])) <= 10.0 * same_place_mm
        {
            let (a, b) = (&slices[ip], &slices[i]);
            let same = a.stored == b.stored
                && a.rescale_slope == b.rescale_slope
                && a.rescale_intercept == b.rescale_intercept;
            if !same {
                return Err(SeriesError::DuplicatePosition {
                    a: a.label.clone(),
                    b: b.label.clone(),
                });
            }
            warnings.push(Warning {
                code: "duplicate_slice_dropped",
                message: format!("slice {} duplicates {} and was dropped", b.label, a.label),
            });
            continue;
        }
        kept.push((d, i));
    }
    Ok(kept)
}

/// The stack's nominal spacing and slice axis.
pub(super) struct Stack {
    /// Nominal spacing along the normal (mm): the median gap.
    pub(super) spacing_n: f64,
    /// Unit slice axis (off the normal by the gantry tilt).
    pub(super) slice_dir: V3,
    /// Length of one slice step along the slice axis (mm).
    pub(super) step_len: f64,
    pub(super) tilt_deg: f64,
}

/// Spacing, collinearity and tilt of the sorted slices.
pub(super) fn measure_stack(
    slices: &[Slice],
    positions: &[V3],
    kept: &[(f64, usize)],
    layout: &Layout,
    warnings: &mut Vec<Warning>,
) -> Result<Stack, SeriesError> {
    let normal = layout.axes[2];
    let nz = kept.len();
    let (spacing_n, step) = if nz < 2 {
        let t = slices[0]
            .slice_thickness_mm
            .filter(|t| t.is_finite() && *t > 0.0)
            .unwrap_or(1.0);
        (t, scale(normal, t))
    } else {
        let mut gaps: Vec<f64> = kept.windows(2).map(|w| w[1].0 - w[0].0).collect();
        gaps.sort_by(f64::total_cmp);
        // The median gap is the nominal spacing, robust when a few slices are missing.
        let nominal = gaps[gaps.len() / 2];
        let (p0, plast) = (positions[kept[0].1], positions[kept[nz - 1].1]);
        let span = kept[nz - 1].0 - kept[0].0;
        // Step per unit of normal distance: includes the in-plane shift of a tilted series.
        let per_mm = scale(sub(plast, p0), 1.0 / span);
        (nominal, scale(per_mm, nominal))
    };
    // Collinearity: every slice must sit on the line through the first along `step`.
    if nz >= 2 {
        let p0 = positions[kept[0].1];
        let per_mm = scale(step, 1.0 / spacing_n);
        let [ps_r, ps_c] = layout.pixel_spacing;
        for &(d, i) in kept {
            let want = [
                p0[0] + per_mm[0] * (d - kept[0].0),
                p0[1] + per_mm[1] * (d - kept[0].0),
                p0[2] + per_mm[2] * (d - kept[0].0),
            ];
            let off = norm(sub(positions[i], want));
            if off > 0.05 * ps_r.max(ps_c).max(0.1) {
                return Err(SeriesError::NotCollinear {
                    label: slices[i].label.clone(),
                    offset_mm: off,
                });
            }
        }
    }
    let step_len = norm(step);
    let slice_dir = scale(step, 1.0 / step_len);
    let tilt_deg = dot(slice_dir, normal).clamp(-1.0, 1.0).acos().to_degrees();
    if tilt_deg > TILT_TOLERANCE_DEG {
        warnings.push(Warning {
            code: "gantry_tilt",
            message: format!(
                "gantry tilt of {tilt_deg:.2}°: the slice axis is not orthogonal to the image plane; \
                 the volume keeps the sheared geometry"
            ),
        });
    }
    Ok(Stack {
        spacing_n,
        slice_dir,
        step_len,
        tilt_deg,
    })
}

/// Whether the sorted slices are resampled onto a uniform grid: a gap too wide to bridge is refused whatever
/// the policy; uneven spacing or missing slices are refused or resampled (with a warning) by the policy.
pub(super) fn needs_resample(
    slices: &[Slice],
    kept: &[(f64, usize)],
    spacing_n: f64,
    opts: &AssemblyOptions,
    warnings: &mut Vec<Warning>,
) -> Result<bool, SeriesError> {
    if let Some(w) = kept
        .windows(2)
        .find(|w| w[1].0 - w[0].0 > MAX_BRIDGED_GAP * spacing_n * (1.0 + opts.spacing_tolerance))
    {
        let gap = w[1].0 - w[0].0;
        return Err(SeriesError::SpacingJump {
            a: slices[w[0].1].label.clone(),
            b: slices[w[1].1].label.clone(),
            gap_mm: gap,
            spacing_mm: spacing_n,
            slices: gap / spacing_n,
        });
    }
    let tol = opts.spacing_tolerance * spacing_n;
    let mut uneven = None;
    let mut missing_total = 0usize;
    for w in kept.windows(2) {
        let gap = w[1].0 - w[0].0;
        if (gap - spacing_n).abs() > tol {
            let ratio = gap / spacing_n;
            let whole = ratio.round();
            let (a, b) = (slices[w[0].1].label.clone(), slices[w[1].1].label.clone());
            if whole >= 2.0 && (ratio - whole).abs() * spacing_n <= tol {
                missing_total += whole as usize - 1;
                if uneven.is_none() {
                    uneven = Some(SeriesError::MissingSlices {
                        missing: whole as usize - 1,
                        a,
                        b,
                        gap_mm: gap,
                        spacing_mm: spacing_n,
                    });
                }
            } else if uneven.is_none() || matches!(uneven, Some(SeriesError::MissingSlices { .. }))
            {
                uneven = Some(SeriesError::UnevenSpacing {
                    a,
                    b,
                    gap_mm: gap,
                    spacing_mm: spacing_n,
                });
            }
        }
    }
    match (uneven, opts.uneven) {
        (None, _) => Ok(false),
        (Some(e), UnevenPolicy::Refuse) => Err(e),
        (Some(e), UnevenPolicy::Resample) => {
            warnings.push(Warning {
                code: match e {
                    SeriesError::MissingSlices { .. } => "missing_slices_interpolated",
                    _ => "uneven_spacing_resampled",
                },
                message: format!(
                    "{e}; resampled linearly onto a uniform {spacing_n:.3} mm grid ({missing_total} slice(s) missing)"
                )
                .replace("; resample to accept", ""),
            });
            Ok(true)
        }
    }
}
