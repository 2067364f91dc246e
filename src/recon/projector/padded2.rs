//! A 2D image held as the lines of both of its axes, each line padded with one value at either end, as
//! the fast Joseph kernels read (forward) and write (back) it.
//!
//! A ray whose dominant axis is y samples image rows: it reads [`Layouts2::rows`] (line `y`, value
//! `x + 1` = pixel `[y][x]`). A ray whose dominant axis is x samples image columns: it reads
//! [`Layouts2::cols`] (line `x`, value `y + 1` = pixel `[y][x]`). Both neighbours of a sample then sit
//! side by side, and a sample that falls half outside the grid reads (forward) a zero border value or
//! writes (back) one that is discarded, which is what "pixels outside the grid count zero" means: no
//! branch per sample.

use std::cell::RefCell;

use rayon::prelude::*;

/// Largest buffer (values) kept for reuse, and how many a thread keeps: single-view updates (SART)
/// project thousands of times per pass, and fresh buffers of this size cost page faults each time.
const POOL_MAX_LEN: usize = 1 << 19;
const POOL_SLOTS: usize = 2;

thread_local! {
    static POOL: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
}

/// `len` zeros, in a buffer from this thread's pool when one is large enough.
fn zeroed(len: usize) -> Vec<f32> {
    if len <= POOL_MAX_LEN {
        let reused = POOL.with(|p| {
            let mut p = p.borrow_mut();
            let i = p.iter().position(|v| v.capacity() >= len)?;
            Some(p.swap_remove(i))
        });
        if let Some(mut v) = reused {
            v.clear();
            v.resize(len, 0.0);
            return v;
        }
    }
    vec![0.0; len]
}

/// Give `v` back to this thread's pool (or free it).
fn recycle(v: Vec<f32>) {
    if v.capacity() > 0 && v.capacity() <= POOL_MAX_LEN {
        POOL.with(|p| {
            let mut p = p.borrow_mut();
            if p.len() < POOL_SLOTS {
                p.push(v);
            }
        });
    }
}

/// `count` lines of `width = len + 2` values; value `j + 1` of a line is its pixel `j`, values `0` and
/// `len + 1` are the border.
#[derive(Debug, Clone, PartialEq)]
pub struct Lines {
    pub count: usize,
    pub width: usize,
    pub data: Vec<f32>,
}

impl Lines {
    /// `count` zero lines of `len` pixels; without values (no line may be used) unless `used`.
    pub fn zeros(count: usize, len: usize, used: bool) -> Self {
        let width = len + 2;
        Self {
            count,
            width,
            data: if used {
                zeroed(count * width)
            } else {
                Vec::new()
            },
        }
    }

    /// True when the lines hold values.
    pub fn is_used(&self) -> bool {
        !self.data.is_empty()
    }
}

impl Drop for Lines {
    fn drop(&mut self) {
        recycle(std::mem::take(&mut self.data));
    }
}

/// Which layouts a projection uses: `cols` for rays whose dominant axis is x, `rows` for the others.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Needs {
    pub rows: bool,
    pub cols: bool,
}

impl Needs {
    pub const BOTH: Self = Self {
        rows: true,
        cols: true,
    };
}

/// Lines handled per parallel task when copying between an image and its layouts.
const LINES_PER_TASK: usize = 16;

/// The line layouts of an `nx × ny` image (flat `[y][x]`); a layout that no ray of a projection uses
/// may be left without values (see [`Needs`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Layouts2 {
    /// `ny` lines of `nx` pixels: image rows.
    pub rows: Lines,
    /// `nx` lines of `ny` pixels: image columns.
    pub cols: Lines,
}

impl Layouts2 {
    /// Zero layouts (back-projection accumulators), those in `needs`.
    pub fn zeros(nx: usize, ny: usize, needs: Needs) -> Self {
        Self {
            rows: Lines::zeros(ny, nx, needs.rows),
            cols: Lines::zeros(nx, ny, needs.cols),
        }
    }

    /// The layouts in `needs` of `image` (flat `[y][x]`, `nx·ny` values) with zero borders.
    ///
    /// # Panics
    /// If `image.len() != nx·ny`.
    pub fn from_image(image: &[f32], nx: usize, ny: usize, needs: Needs) -> Self {
        assert_eq!(image.len(), nx * ny, "image must hold nx·ny values");
        let mut out = Self::zeros(nx, ny, needs);
        if nx == 0 || ny == 0 {
            return out;
        }
        let (wr, wc) = (out.rows.width, out.cols.width);
        out.rows
            .data
            .par_chunks_mut(wr)
            .zip(image.par_chunks(nx))
            .for_each(|(line, src)| line[1..=nx].copy_from_slice(src));
        out.cols
            .data
            .par_chunks_mut(wc * LINES_PER_TASK)
            .enumerate()
            .for_each(|(task, block)| {
                let x0 = task * LINES_PER_TASK;
                for y in 0..ny {
                    let src = &image[y * nx..(y + 1) * nx];
                    for (k, line) in block.chunks_exact_mut(wc).enumerate() {
                        line[y + 1] = src[x0 + k];
                    }
                }
            });
        out
    }

    /// The lines a ray samples: columns when its dominant axis is x, rows otherwise.
    pub fn lines(&self, along_x: bool) -> &Lines {
        if along_x { &self.cols } else { &self.rows }
    }

    /// `image[y][x] = rows[y][x + 1] + cols[x][y + 1]`: the sum of the accumulators without their
    /// borders (overwrites `image`); a layout without values counts zero.
    ///
    /// # Panics
    /// If `image.len()` is not the pixel count of the layouts.
    pub fn sum_into(&self, image: &mut [f32]) {
        let (nx, ny) = (self.cols.count, self.rows.count);
        assert_eq!(image.len(), nx * ny, "image must hold nx·ny values");
        if nx == 0 || ny == 0 {
            return;
        }
        let (wr, wc) = (self.rows.width, self.cols.width);
        image
            .par_chunks_mut(nx * LINES_PER_TASK)
            .enumerate()
            .for_each(|(task, block)| {
                let y0 = task * LINES_PER_TASK;
                for (k, out) in block.chunks_exact_mut(nx).enumerate() {
                    let y = y0 + k;
                    if self.rows.is_used() {
                        out.copy_from_slice(&self.rows.data[y * wr + 1..y * wr + 1 + nx]);
                    } else {
                        out.fill(0.0);
                    }
                }
                if !self.cols.is_used() {
                    return;
                }
                for x in 0..nx {
                    let col = &self.cols.data[x * wc + 1 + y0..];
                    for (k, out) in block.chunks_exact_mut(nx).enumerate() {
                        out[x] += col[k];
                    }
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layouts_hold_the_image_with_zero_borders_and_sum_back() {
        let (nx, ny) = (37, 21);
        let image: Vec<f32> = (0..nx * ny).map(|k| k as f32 + 0.5).collect();
        let l = Layouts2::from_image(&image, nx, ny, Needs::BOTH);
        for y in 0..ny {
            for x in 0..nx {
                let v = image[y * nx + x];
                assert_eq!(l.rows.data[y * (nx + 2) + x + 1], v);
                assert_eq!(l.cols.data[x * (ny + 2) + y + 1], v);
            }
            assert_eq!(l.rows.data[y * (nx + 2)], 0.0);
            assert_eq!(l.rows.data[y * (nx + 2) + nx + 1], 0.0);
        }
        for x in 0..nx {
            assert_eq!(l.cols.data[x * (ny + 2)], 0.0);
            assert_eq!(l.cols.data[x * (ny + 2) + ny + 1], 0.0);
        }
        let mut sum = vec![f32::NAN; nx * ny];
        l.sum_into(&mut sum);
        for (s, v) in sum.iter().zip(&image) {
            assert_eq!(*s, 2.0 * v);
        }
        for (rows, cols) in [(true, false), (false, true)] {
            let one = Layouts2::from_image(&image, nx, ny, Needs { rows, cols });
            assert_eq!((one.rows.is_used(), one.cols.is_used()), (rows, cols));
            one.sum_into(&mut sum);
            assert_eq!(sum, image);
        }
    }
}
