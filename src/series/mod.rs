//! Pure series-to-volume assembly: sort slices along the normal, check spacing, tilt and gaps, rescale to HU,
//! patient coordinates.
//!
//! Input is a list of decoded 2D slices with the attributes that place them in patient space (LPS, mm):
//! image position, image orientation, pixel spacing, and the rescale to Hounsfield units. [`assemble`] sorts
//! them by their position along the slice normal, drops exact duplicates, detects missing slices and uneven
//! spacing (refused or resampled onto a uniform grid, with a warning), measures gantry tilt (kept as a
//! non-orthogonal slice axis in the [`Frame`]) and returns a [`Volume`] in HU in the closest canonical order
//! (patient left, posterior, superior along the array axes x, y, z).
//!
//! This module knows nothing about file formats: the reader that fills [`Slice`] lives elsewhere.

use rayon::prelude::*;
use serde::Serialize;

use crate::recon::control::Control;
use crate::recon::error::ReconError;
use crate::volume::{Frame, Volume, to_closest_canonical};

/// HU given to pixels marked as padding (outside the scanned field).
pub const PADDING_HU: f32 = -1024.0;

/// Tilt below which the angle between the slice axis and the image normal is rounding noise in the stored
/// positions (degrees): not reported as gantry tilt. Real gantry tilts are whole degrees (commonly 5–30°).
pub const TILT_TOLERANCE_DEG: f64 = 0.1;

/// Widest gap, in nominal slice spacings, that resampling may bridge (four missing slices). A wider gap is
/// two stacks or a lost part of the series and is refused under every [`UnevenPolicy`].
pub const MAX_BRIDGED_GAP: f64 = 5.0;

/// Whether a warning of [`assemble`] describes the assembled grid itself, so that an isotropic resample onto an
/// orthogonal grid makes it stale: gantry tilt (the sheared slice axis is gone after the resample).
pub fn stale_after_resample(code: &str) -> bool {
    code == "gantry_tilt"
}

/// One decoded image plane with its placement.
#[derive(Debug, Clone, PartialEq)]
pub struct Slice {
    /// Rows (y, index `j`) and columns (x, index `i`).
    pub rows: usize,
    pub columns: usize,
    /// Stored pixel values, row-major (`rows × columns`), before the rescale.
    pub stored: Vec<f32>,
    /// HU = stored · slope + intercept.
    pub rescale_slope: f64,
    pub rescale_intercept: f64,
    /// Patient position of the first pixel (mm, LPS).
    pub position_mm: Option<[f64; 3]>,
    /// Direction cosines of a row (increasing column index) then of a column (increasing row index).
    pub orientation: Option<[f64; 6]>,
    /// Spacing between rows, then between columns (mm).
    pub pixel_spacing_mm: Option<[f64; 2]>,
    pub slice_thickness_mm: Option<f64>,
    /// Stored values in `[padding.0, padding.1]` are padding (a single value when both are equal).
    pub padding: Option<(f64, f64)>,
    /// Where the slice came from (file name and frame), for messages only.
    pub label: String,
}

/// What to do when slices are not evenly spaced (including missing slices).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnevenPolicy {
    /// Refuse the series.
    #[default]
    Refuse,
    /// Interpolate linearly onto a uniform grid at the most common spacing.
    Resample,
}

/// Options of [`assemble`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AssemblyOptions {
    pub uneven: UnevenPolicy,
    /// Relative tolerance on slice spacing (fraction of the most common spacing).
    pub spacing_tolerance: f64,
    /// Largest volume accepted (voxels).
    pub max_voxels: usize,
}

impl Default for AssemblyOptions {
    fn default() -> Self {
        Self {
            uneven: UnevenPolicy::Refuse,
            spacing_tolerance: 0.02,
            max_voxels: 1 << 30,
        }
    }
}

/// Something worth telling the user that did not stop the assembly.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Warning {
    /// Stable snake_case code.
    pub code: &'static str,
    pub message: String,
}

/// An assembled series.
#[derive(Debug, Clone, PartialEq)]
pub struct Assembled {
    /// HU, `[z][y][x]` in the closest canonical order (see [`crate::volume::to_closest_canonical`]): the
    /// column axis runs as nearly as it can to the patient's left, the row axis posterior, the slice axis
    /// superior, whatever the acquisition's orientation and the order of its rows, columns and slices.
    pub volume: Volume,
    pub warnings: Vec<Warning>,
    /// Angle between the slice axis and the image normal (degrees); 0 for an untilted series.
    pub tilt_deg: f64,
    /// Slice spacing measured along the normal (mm).
    pub normal_spacing_mm: f64,
}

/// Why slices could not be assembled into a volume. Messages say which slices.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SeriesError {
    #[error("the series has no image slices")]
    Empty,
    #[error("slice {label} is {rows}×{columns} but the series is {want_rows}×{want_columns}")]
    SizeMismatch {
        label: String,
        rows: usize,
        columns: usize,
        want_rows: usize,
        want_columns: usize,
    },
    #[error("slice {label} lacks {what}, needed to place it in patient space")]
    MissingAttribute { label: String, what: &'static str },
    #[error("slice {label}: {reason}")]
    InvalidAttribute { label: String, reason: String },
    #[error("slices {a} and {b} have different orientations")]
    OrientationMismatch { a: String, b: String },
    #[error("slices {a} and {b} have different pixel spacings")]
    SpacingMismatch { a: String, b: String },
    #[error("slices {a} and {b} are at the same position with different pixels")]
    DuplicatePosition { a: String, b: String },
    #[error("slice positions do not lie on a line (slice {label} is {offset_mm:.3} mm off)")]
    NotCollinear { label: String, offset_mm: f64 },
    #[error(
        "{missing} slice(s) missing: gap of {gap_mm:.3} mm between {a} and {b}, expected {spacing_mm:.3} mm; resample to accept"
    )]
    MissingSlices {
        missing: usize,
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
    },
    #[error(
        "uneven slice spacing: {gap_mm:.3} mm between {a} and {b}, expected {spacing_mm:.3} mm; resample to accept"
    )]
    UnevenSpacing {
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
    },
    #[error(
        "gap of {gap_mm:.3} mm between {a} and {b}, {slices:.1}× the {spacing_mm:.3} mm slice spacing: \
         two stacks or a large part of the series missing, too wide to interpolate; upload the stacks as separate series"
    )]
    SpacingJump {
        a: String,
        b: String,
        gap_mm: f64,
        spacing_mm: f64,
        slices: f64,
    },
    #[error("the volume would have {voxels} voxels, more than the limit of {limit}")]
    TooLarge { voxels: usize, limit: usize },
    #[error("canceled")]
    Canceled,
}

impl SeriesError {
    /// Stable code for the API error catalogue.
    pub fn code(&self) -> &'static str {
        match self {
            SeriesError::Empty => "series_empty",
            SeriesError::SizeMismatch { .. } => "series_size_mismatch",
            SeriesError::MissingAttribute { .. } => "series_missing_attribute",
            SeriesError::InvalidAttribute { .. } => "series_invalid_attribute",
            SeriesError::OrientationMismatch { .. } => "series_orientation_mismatch",
            SeriesError::SpacingMismatch { .. } => "series_spacing_mismatch",
            SeriesError::DuplicatePosition { .. } => "series_duplicate_position",
            SeriesError::NotCollinear { .. } => "series_not_collinear",
            SeriesError::MissingSlices { .. } => "series_missing_slices",
            SeriesError::UnevenSpacing { .. } => "series_uneven_spacing",
            SeriesError::SpacingJump { .. } => "series_spacing_jump",
            SeriesError::TooLarge { .. } => "series_too_large",
            SeriesError::Canceled => "canceled",
        }
    }
}

impl From<ReconError> for SeriesError {
    fn from(_: ReconError) -> Self {
        SeriesError::Canceled
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}
fn scale(a: [f64; 3], s: f64) -> [f64; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Row direction, column direction and normal of a validated orientation.
fn axes(label: &str, o: [f64; 6]) -> Result<[[f64; 3]; 3], SeriesError> {
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

/// Assemble `slices` (in any order) into an HU volume. Checks the cancel flag once per slice.
pub fn assemble(
    slices: Vec<Slice>,
    opts: &AssemblyOptions,
    ctl: Control<'_>,
) -> Result<Assembled, SeriesError> {
    let first = slices.first().ok_or(SeriesError::Empty)?;
    let (rows, columns) = (first.rows, first.columns);
    if rows == 0 || columns == 0 {
        return Err(SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: "the image has no pixels".into(),
        });
    }
    let mut warnings = Vec::new();
    // Consistency of size, orientation and spacing; a lone slice may lack its placement.
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
    let [row_dir, col_dir, normal] = axes(&first.label, orientation)?;
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
    for s in &slices {
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
        if !(s.rescale_slope.is_finite() && s.rescale_intercept.is_finite())
            || s.rescale_slope == 0.0
        {
            return Err(SeriesError::InvalidAttribute {
                label: s.label.clone(),
                reason: "rescale slope/intercept invalid".into(),
            });
        }
        if !single {
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
        }
    }
    let positions: Vec<[f64; 3]> = slices
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
        .collect::<Result<_, _>>()?;

    // Sort along the normal; drop exact duplicates.
    let mut order: Vec<(f64, usize)> = positions
        .iter()
        .enumerate()
        .map(|(i, p)| (dot(*p, normal), i))
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    let same_place_mm = 1e-3 * pixel_spacing[0].min(pixel_spacing[1]).max(1e-3);
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
    let nz = kept.len();

    // Spacing along the normal, gaps, tilt.
    let mut gaps: Vec<f64> = kept.windows(2).map(|w| w[1].0 - w[0].0).collect();
    let (spacing_n, step) = if nz < 2 {
        let t = first
            .slice_thickness_mm
            .filter(|t| t.is_finite() && *t > 0.0)
            .unwrap_or(1.0);
        (t, scale(normal, t))
    } else {
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
        for &(d, i) in &kept {
            let want = [
                p0[0] + per_mm[0] * (d - kept[0].0),
                p0[1] + per_mm[1] * (d - kept[0].0),
                p0[2] + per_mm[2] * (d - kept[0].0),
            ];
            let off = norm(sub(positions[i], want));
            if off > 0.05 * pixel_spacing[0].max(pixel_spacing[1]).max(0.1) {
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

    // A gap too wide to bridge is refused whatever the policy.
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

    // Uneven spacing / missing slices.
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
    let resample = match (uneven, opts.uneven) {
        (None, _) => false,
        (Some(e), UnevenPolicy::Refuse) => return Err(e),
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
            true
        }
    };
    let out_nz = if resample {
        let span = kept[nz - 1].0 - kept[0].0;
        (span / spacing_n).round() as usize + 1
    } else {
        nz
    };
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

    // Rescale to HU.
    let plane = rows * columns;
    let mut data = vec![0f32; voxels];
    let padded = std::sync::atomic::AtomicUsize::new(0);
    let hu_of = |s: &Slice, out: &mut [f32]| {
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
        padded.fetch_add(n, std::sync::atomic::Ordering::Relaxed);
    };
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
                hu_of(&slices[ia], &mut hu_a);
                hu_of(&slices[ib], &mut hu_b);
                loaded = (ia, ib);
            }
            for ((o, a), b) in out.iter_mut().zip(&hu_a).zip(&hu_b) {
                *o = a + t * (b - a);
            }
        }
    } else {
        // Slices convert independently: one task per slice on the caller's pool.
        let done = std::sync::atomic::AtomicUsize::new(0);
        data.par_chunks_exact_mut(plane).enumerate().try_for_each(
            |(k, out)| -> Result<(), SeriesError> {
                ctl.check()?;
                hu_of(&slices[kept[k].1], out);
                let n = done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
                if n.is_multiple_of(16) {
                    ctl.step("assemble", n as f64 / out_nz as f64);
                }
                Ok(())
            },
        )?;
    }
    ctl.step("assemble", 1.0);
    if padded.load(std::sync::atomic::Ordering::Relaxed) > 0 && !resample {
        warnings.push(Warning {
            code: "pixel_padding_replaced",
            message: format!(
                "{} pixels equal to the Pixel Padding Value (0028,0120) were set to {PADDING_HU} HU",
                padded.load(std::sync::atomic::Ordering::Relaxed)
            ),
        });
    } else if padded.load(std::sync::atomic::Ordering::Relaxed) > 0 {
        warnings.push(Warning {
            code: "pixel_padding_replaced",
            message: format!(
                "pixels equal to the Pixel Padding Value (0028,0120) were set to {PADDING_HU} HU before resampling"
            ),
        });
    }
    let data = ndarray::Array3::from_shape_vec((out_nz, rows, columns), data).map_err(|e| {
        SeriesError::InvalidAttribute {
            label: first.label.clone(),
            reason: e.to_string(),
        }
    })?;
    let frame = Frame {
        spacing_mm: [pixel_spacing[1], pixel_spacing[0], step_len],
        origin_mm: positions[kept[0].1],
        direction: [row_dir, col_dir, slice_dir],
    };
    Ok(Assembled {
        // Closest canonical order (x left, y posterior, z superior) by exact flips and permutations, so every
        // acquisition of the same patient becomes the same array.
        volume: to_closest_canonical(Volume { data, frame }),
        warnings,
        tilt_deg,
        normal_spacing_mm: spacing_n,
    })
}

mod fuzz;
#[doc(hidden)]
pub use fuzz::{fuzz_entry, fuzz_slices};

#[cfg(test)]
mod tests;
