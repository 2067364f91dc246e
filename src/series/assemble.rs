//! [`assemble`] in its stages: the layout every slice must share, the order along the normal with exact
//! duplicates dropped, the stack's spacing and tilt, the output grid (even, or resampled under the policy),
//! and the conversion to HU. Each stage refuses what it cannot place, naming the slices.

use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};

use super::{
    Assembled, AssemblyOptions, MAX_BRIDGED_GAP, PADDING_HU, SeriesError, Slice,
    TILT_TOLERANCE_DEG, UnevenPolicy, Warning,
};
use crate::recon::control::Control;
use crate::volume::{Frame, Volume, to_closest_canonical};

type V3 = [f64; 3];

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Row direction, column direction and normal of a validated orientation.
fn axes(label: &str, o: [f64; 6]) -> Result<[V3; 3], SeriesError> {
    let bad = |reason: String| SeriesError::InvalidAttribute {
        label: label.to_string(),
        reason,
    };
    if o.iter().any(|v| !v.is_finite()) {
        return Err(bad("image orientation is not finite".into()));
    }
    let r = [o[0], o[1], o[2]];
    let c = [o[3], o[4], o[5]];
    let (nr, nc) = (norm(r), norm(c));
    if (nr - 1.0).abs() > 1e-3 || (nc - 1.0).abs() > 1e-3 {
        return Err(bad(format!(
            "image orientation vectors are not unit length ({nr:.4}, {nc:.4})"
        )));
    }
    let (r, c) = (scale(r, 1.0 / nr), scale(c, 1.0 / nc));
    if dot(r, c).abs() > 1e-3 {
        return Err(bad("image orientation vectors are not orthogonal".into()));
    }
    let n = cross(r, c);
    Ok([r, c, scale(n, 1.0 / norm(n))])
}

/// What every slice of the series shares.
struct Layout {
    rows: usize,
    columns: usize,
    /// Row direction, column direction, unit normal.
    axes: [V3; 3],
    /// Between rows, then between columns (mm).
    pixel_spacing: [f64; 2],
}

/// The first slice's size, orientation and spacing, checked against every other slice; a lone slice may lack
/// its placement (assumed, with a warning).
fn check_layout(slices: &[Slice], warnings: &mut Vec<Warning>) -> Result<Layout, SeriesError> {
    let first = slices.first().ok_or(SeriesError::Empty)?;
    let (rows, columns) = (first.rows, first.columns);
    if rows == 0 || columns == 0 {
        return Err(SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: "the image has no pixels".into(),
        });
    }
    let single = slices.len() == 1;
    let orientation = match first.orientation {
        Some(o) => o,
        None if single => [1.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        None => {
            return Err(SeriesError::MissingAttribute {
                label: first.label.clone(),
                what: "image orientation (0020,0037)",
            });
        }
    };
    if single && first.orientation.is_none() {
        warnings.push(Warning {
            code: "orientation_assumed",
            message: format!(
                "slice {} has no image orientation (0020,0037): axial (rows along +x, columns along +y) assumed",
                first.label
            ),
        });
    }
    if single && first.position_mm.is_none() {
        warnings.push(Warning {
            code: "position_assumed",
            message: format!(
                "slice {} has no image position (0020,0032): its first pixel is placed at the origin",
                first.label
            ),
        });
    }
    if single
        && first
            .slice_thickness_mm
            .is_none_or(|t| !(t.is_finite() && t > 0.0))
    {
        warnings.push(Warning {
            code: "slice_thickness_assumed",
            message: format!(
                "slice {} has no slice thickness (0018,0050): 1 mm assumed for the volume's third axis",
                first.label
            ),
        });
    }
    let axes = axes(&first.label, orientation)?;
    let pixel_spacing = match first.pixel_spacing_mm {
        Some(ps) => ps,
        None => {
            warnings.push(Warning {
                code: "pixel_spacing_assumed",
                message: "no pixel spacing: 1 mm assumed".into(),
            });
            [1.0, 1.0]
        }
    };
    if pixel_spacing.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
        return Err(SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: format!("pixel spacing {pixel_spacing:?} is not positive"),
        });
    }
    for s in slices {
        check_slice(s, rows, columns)?;
        if !single {
            check_same_plane(first, s, orientation, pixel_spacing)?;
        }
    }
    Ok(Layout {
        rows,
        columns,
        axes,
        pixel_spacing,
    })
}

/// One slice's size, pixel count and rescale.
fn check_slice(s: &Slice, rows: usize, columns: usize) -> Result<(), SeriesError> {
    if (s.rows, s.columns) != (rows, columns) {
        return Err(SeriesError::SizeMismatch {
            label: s.label.clone(),
            rows: s.rows,
            columns: s.columns,
            want_rows: rows,
            want_columns: columns,
        });
    }
    if s.stored.len() != rows * columns {
        return Err(SeriesError::InvalidAttribute {
            label: s.label.clone(),
            reason: format!(
                "{} pixel values for a {rows}×{columns} image",
                s.stored.len()
            ),
        });
    }
    if !(s.rescale_slope.is_finite() && s.rescale_intercept.is_finite()) || s.rescale_slope == 0.0 {
        return Err(SeriesError::InvalidAttribute {
            label: s.label.clone(),
            reason: "rescale slope/intercept invalid".into(),
        });
    }
    Ok(())
}

/// A slice of a stack has the first slice's orientation and pixel spacing.
fn check_same_plane(
    first: &Slice,
    s: &Slice,
    orientation: [f64; 6],
    pixel_spacing: [f64; 2],
) -> Result<(), SeriesError> {
    let o = s.orientation.ok_or_else(|| SeriesError::MissingAttribute {
        label: s.label.clone(),
        what: "image orientation (0020,0037)",
    })?;
    if o.iter().zip(orientation).any(|(a, b)| (a - b).abs() > 1e-4) {
        return Err(SeriesError::OrientationMismatch {
            a: first.label.clone(),
            b: s.label.clone(),
        });
    }
    let ps = s.pixel_spacing_mm.unwrap_or([1.0, 1.0]);
    if ps
        .iter()
        .zip(pixel_spacing)
        .any(|(a, b)| (a - b).abs() > 1e-4 * b.max(1.0))
    {
        return Err(SeriesError::SpacingMismatch {
            a: first.label.clone(),
            b: s.label.clone(),
        });
    }
    Ok(())
}

/// Each slice's image position (the origin for a lone slice without one).
fn positions(slices: &[Slice]) -> Result<Vec<V3>, SeriesError> {
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
fn sort_unique(
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
struct Stack {
    /// Nominal spacing along the normal (mm): the median gap.
    spacing_n: f64,
    /// Unit slice axis (off the normal by the gantry tilt).
    slice_dir: V3,
    /// Length of one slice step along the slice axis (mm).
    step_len: f64,
    tilt_deg: f64,
}

/// Spacing, collinearity and tilt of the sorted slices.
fn measure_stack(
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
fn needs_resample(
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

/// Stored values to HU (padding to [`PADDING_HU`]), counting padded pixels.
fn hu_of(s: &Slice, out: &mut [f32], padded: &AtomicUsize) {
    let (m, b) = (s.rescale_slope, s.rescale_intercept);
    let mut n = 0usize;
    for (o, &v) in out.iter_mut().zip(&s.stored) {
        let pad = s
            .padding
            .is_some_and(|(lo, hi)| (v as f64) >= lo.min(hi) && (v as f64) <= lo.max(hi));
        n += pad as usize;
        *o = if pad {
            PADDING_HU
        } else {
            (v as f64 * m + b) as f32
        };
    }
    padded.fetch_add(n, Ordering::Relaxed);
}

/// The output planes in HU: each kept slice converted (in parallel), or planes every `spacing_n` interpolated
/// linearly between their neighbours. Returns the number of padded pixels.
fn fill_hu(
    data: &mut [f32],
    plane: usize,
    slices: &[Slice],
    kept: &[(f64, usize)],
    resample: bool,
    spacing_n: f64,
    ctl: Control<'_>,
) -> Result<usize, SeriesError> {
    let padded = AtomicUsize::new(0);
    let (nz, out_nz) = (kept.len(), data.len() / plane);
    if resample {
        let d0 = kept[0].0;
        let mut hu_a = vec![0f32; plane];
        let mut hu_b = vec![0f32; plane];
        let mut loaded = (usize::MAX, usize::MAX);
        let mut seg = 0usize;
        for (k, out) in data.chunks_exact_mut(plane).enumerate() {
            ctl.check()?;
            ctl.step("assemble", k as f64 / out_nz as f64);
            let d = d0 + k as f64 * spacing_n;
            while seg + 2 < nz && kept[seg + 1].0 < d - 1e-9 {
                seg += 1;
            }
            let (da, db) = (kept[seg].0, kept[(seg + 1).min(nz - 1)].0);
            let t = if db > da {
                ((d - da) / (db - da)).clamp(0.0, 1.0)
            } else {
                0.0
            } as f32;
            let (ia, ib) = (kept[seg].1, kept[(seg + 1).min(nz - 1)].1);
            if loaded != (ia, ib) {
                hu_of(&slices[ia], &mut hu_a, &padded);
                hu_of(&slices[ib], &mut hu_b, &padded);
                loaded = (ia, ib);
            }
            for ((o, a), b) in out.iter_mut().zip(&hu_a).zip(&hu_b) {
                *o = a + t * (b - a);
            }
        }
    } else {
        // Slices convert independently: one task per slice on the caller's pool.
        let done = AtomicUsize::new(0);
        data.par_chunks_exact_mut(plane).enumerate().try_for_each(
            |(k, out)| -> Result<(), SeriesError> {
                ctl.check()?;
                hu_of(&slices[kept[k].1], out, &padded);
                let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_multiple_of(16) {
                    ctl.step("assemble", n as f64 / out_nz as f64);
                }
                Ok(())
            },
        )?;
    }
    ctl.step("assemble", 1.0);
    Ok(padded.load(Ordering::Relaxed))
}

/// Assemble `slices` (in any order) into an HU volume. Checks the cancel flag once per slice.
pub fn assemble(
    slices: Vec<Slice>,
    opts: &AssemblyOptions,
    ctl: Control<'_>,
) -> Result<Assembled, SeriesError> {
    let mut warnings = Vec::new();
    let layout = check_layout(&slices, &mut warnings)?;
    let positions = positions(&slices)?;
    let kept = sort_unique(&slices, &positions, &layout, &mut warnings)?;
    let stack = measure_stack(&slices, &positions, &kept, &layout, &mut warnings)?;
    let spacing_n = stack.spacing_n;
    let resample = needs_resample(&slices, &kept, spacing_n, opts, &mut warnings)?;
    let nz = kept.len();
    let out_nz = if resample {
        let span = kept[nz - 1].0 - kept[0].0;
        (span / spacing_n).round() as usize + 1
    } else {
        nz
    };
    let (rows, columns) = (layout.rows, layout.columns);
    let voxels = out_nz
        .checked_mul(rows)
        .and_then(|v| v.checked_mul(columns))
        .unwrap_or(usize::MAX);
    if voxels > opts.max_voxels {
        return Err(SeriesError::TooLarge {
            voxels,
            limit: opts.max_voxels,
        });
    }

    let mut data = vec![0f32; voxels];
    let padded = fill_hu(
        &mut data,
        rows * columns,
        &slices,
        &kept,
        resample,
        spacing_n,
        ctl,
    )?;
    if padded > 0 {
        warnings.push(Warning {
            code: "pixel_padding_replaced",
            message: if resample {
                format!(
                    "pixels equal to the Pixel Padding Value (0028,0120) were set to {PADDING_HU} HU before resampling"
                )
            } else {
                format!(
                    "{padded} pixels equal to the Pixel Padding Value (0028,0120) were set to {PADDING_HU} HU"
                )
            },
        });
    }
    let label = &slices[0].label;
    let data = ndarray::Array3::from_shape_vec((out_nz, rows, columns), data).map_err(|e| {
        SeriesError::InvalidAttribute {
            label: label.clone(),
            reason: e.to_string(),
        }
    })?;
    let [row_dir, col_dir, _] = layout.axes;
    let [ps_r, ps_c] = layout.pixel_spacing;
    let frame = Frame {
        spacing_mm: [ps_c, ps_r, stack.step_len],
        origin_mm: positions[kept[0].1],
        direction: [row_dir, col_dir, stack.slice_dir],
    };
    Ok(Assembled {
        // Closest canonical order (x left, y posterior, z superior) by exact flips and permutations, so every
        // acquisition of the same patient becomes the same array.
        volume: to_closest_canonical(Volume { data, frame }),
        warnings,
        tilt_deg: stack.tilt_deg,
        normal_spacing_mm: spacing_n,
    })
}
