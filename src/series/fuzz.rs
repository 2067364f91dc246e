//! The series-assembly fuzz target's entry point (and its regression replay's): slices whose placement is read
//! from arbitrary bytes — positions, orientations, spacings and rescales that may be NaN, infinite, huge,
//! parallel or repeated — assembled under both uneven-spacing policies. Every outcome but a panic or an
//! allocation sized by the input is fine.

use super::{AssemblyOptions, Slice, UnevenPolicy, assemble};
use crate::recon::control::unattended;

/// Reads fields from the fuzz input; past its end every read is zero.
struct Fields<'a>(&'a [u8]);

impl Fields<'_> {
    fn byte(&mut self) -> u8 {
        match self.0.split_first() {
            Some((&b, rest)) => {
                self.0 = rest;
                b
            }
            None => 0,
        }
    }
    /// A small round number most of the time (where assembly branches), any bit pattern otherwise.
    fn number(&mut self) -> f64 {
        match self.byte() % 4 {
            0 => {
                let mut b = [0u8; 8];
                b.iter_mut().for_each(|x| *x = self.byte());
                f64::from_le_bytes(b)
            }
            1 => f64::from(self.byte() as i8) / 64.0,
            _ => f64::from(self.byte() as i8) / 4.0,
        }
    }
    fn numbers<const N: usize>(&mut self) -> Option<[f64; N]> {
        (!self.byte().is_multiple_of(8)).then(|| std::array::from_fn(|_| self.number()))
    }
}

#[doc(hidden)]
pub fn fuzz_entry(data: &[u8]) {
    let (slices, opts) = fuzz_slices(data);
    let _ = assemble(slices, &opts, unattended());
}

/// The slices and options a fuzz input stands for: a count, the policy and tolerance, then per slice its size,
/// pixels, rescale and placement (each optional field behind a presence byte).
#[doc(hidden)]
pub fn fuzz_slices(data: &[u8]) -> (Vec<Slice>, AssemblyOptions) {
    let mut f = Fields(data);
    let count = 1 + usize::from(f.byte() % 12);
    let uneven = if f.byte() % 2 == 0 {
        UnevenPolicy::Refuse
    } else {
        UnevenPolicy::Resample
    };
    let opts = AssemblyOptions {
        uneven,
        spacing_tolerance: f.number(),
        // Small enough that a volume the checks let through cannot exhaust the fuzzer's memory limit.
        max_voxels: 1 << 22,
    };
    let slices = (0..count)
        .map(|k| {
            let rows = 1 + usize::from(f.byte() % 6);
            let columns = 1 + usize::from(f.byte() % 6);
            Slice {
                rows,
                columns,
                stored: (0..rows * columns)
                    .map(|_| f32::from(f.byte()) * 16.0 - 1024.0)
                    .collect(),
                rescale_slope: f.number(),
                rescale_intercept: f.number(),
                position_mm: f.numbers(),
                orientation: f.numbers(),
                pixel_spacing_mm: f.numbers(),
                slice_thickness_mm: f.numbers::<1>().map(|[t]| t),
                padding: f.numbers::<2>().map(|[a, b]| (a, b)),
                label: format!("slice {k}"),
            }
        })
        .collect();
    (slices, opts)
}
