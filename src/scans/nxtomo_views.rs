//! The projections of an NXtomo file (`super::nxtomo`) as a [`ViewSource`]: one frame of the detector data
//! read at a time, and the flat of each view interpolated between the flat series around it.

use std::path::PathBuf;

use hdf5_pure::Dataset;

use super::nxtomo::h5_error;
use super::{ScanError, ViewSource};

/// The projections of an NXtomo file, read frame by frame; flats interpolated per view.
pub struct NxViews {
    pub(super) path: PathBuf,
    pub(super) key: String,
    pub(super) data: Dataset,
    pub(super) frames: Vec<usize>,
    pub(super) rows: usize,
    pub(super) cols: usize,
    /// Flat series: (mean frame index, mean image).
    pub(super) flats: Vec<(f64, Vec<f32>)>,
}

impl NxViews {
    fn read_frame(&self, frame: usize, out: &mut [f32]) -> Result<(), ScanError> {
        let v = self
            .data
            .read_f32_rows(frame as u64, 1)
            .map_err(|e| h5_error(&self.path, &self.key, format!("frame {frame}: {e}")))?;
        if v.len() != out.len() {
            return Err(ScanError::mismatch(
                &self.path,
                &self.key,
                format!("frame {frame} has {} values, not {}", v.len(), out.len()),
            ));
        }
        out.copy_from_slice(&v);
        Ok(())
    }
    pub(super) fn mean(&self, frames: &[usize]) -> Result<Vec<f32>, ScanError> {
        let mut acc = vec![0f64; self.rows * self.cols];
        let mut one = vec![0f32; self.rows * self.cols];
        for &f in frames {
            self.read_frame(f, &mut one)?;
            acc.iter_mut()
                .zip(&one)
                .for_each(|(a, &v)| *a += f64::from(v));
        }
        let n = frames.len().max(1) as f64;
        Ok(acc.iter().map(|a| (a / n) as f32).collect())
    }
}

impl ViewSource for NxViews {
    fn view_count(&self) -> usize {
        self.frames.len()
    }
    fn shape(&self) -> (usize, usize) {
        (self.rows, self.cols)
    }
    fn read_view(&mut self, i: usize, out: &mut [f32]) -> Result<(), ScanError> {
        let Some(&frame) = self.frames.get(i) else {
            return Err(ScanError::NoSuchView {
                file: self.path.clone(),
                index: i,
                count: self.frames.len(),
            });
        };
        self.read_frame(frame, out)
    }
    fn view_flat(&self, i: usize, out: &mut [f32]) -> bool {
        let (Some(&frame), Some(first), Some(last)) =
            (self.frames.get(i), self.flats.first(), self.flats.last())
        else {
            return false;
        };
        let at = frame as f64;
        let after = self.flats.iter().position(|(k, _)| *k >= at);
        let (a, b, w) = match after {
            None => (last, last, 0.0),
            Some(0) => (first, first, 0.0),
            Some(j) => {
                let (a, b) = (&self.flats[j - 1], &self.flats[j]);
                (a, b, ((at - a.0) / (b.0 - a.0)) as f32)
            }
        };
        for ((o, &x), &y) in out.iter_mut().zip(&a.1).zip(&b.1) {
            *o = x + w * (y - x);
        }
        true
    }
}
