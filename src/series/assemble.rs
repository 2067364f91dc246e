//! [`assemble`] in its stages: the layout every slice must share, the order along the normal with exact
//! duplicates dropped, the stack's spacing and tilt, the output grid (even, or resampled under the policy),
//! and the conversion to HU. Each stage refuses what it cannot place, naming the slices.

use super::hu::fill_hu;
use super::layout::check_layout;
use super::stack::{measure_stack, needs_resample, positions, sort_unique};
use super::{Assembled, AssemblyOptions, PADDING_HU, SeriesError, Slice, Warning};
use crate::recon::control::Control;
use crate::volume::{Frame, Volume, to_closest_canonical};

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
