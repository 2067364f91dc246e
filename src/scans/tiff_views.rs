//! Projection TIFFs through the `tiff` crate: one file per view ([`TiffFiles`]) or one multi-page file
//! ([`TiffPages`]). Grey images of 8/16/32-bit integers or 16/32/64-bit floats, either byte order,
//! uncompressed. Before a page is decoded its declared size is checked against the expected view shape,
//! [`MAX_VIEW_PIXELS`] and the file's length, so a lying header allocates nothing.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::tags::Tag;
use tiff::{ColorType, TiffError};

use super::{MAX_VIEW_PIXELS, ScanError, ViewSource};

type TiffDecoder = Decoder<BufReader<File>>;

fn tiff_error(file: &Path, e: TiffError) -> ScanError {
    let message = match e {
        TiffError::IoError(ref io) if io.kind() == std::io::ErrorKind::UnexpectedEof => {
            "truncated: the file ends before its pixel data".to_string()
        }
        e => e.to_string(),
    };
    ScanError::Tiff {
        file: file.to_path_buf(),
        message,
    }
}

fn open_decoder(file: &Path) -> Result<(TiffDecoder, u64), ScanError> {
    let f = File::open(file).map_err(|e| ScanError::io(file, e))?;
    let len = f.metadata().map_err(|e| ScanError::io(file, e))?.len();
    let mut limits = Limits::default();
    limits.decoding_buffer_size = MAX_VIEW_PIXELS * 8;
    let decoder = Decoder::new(BufReader::new(f))
        .map_err(|e| tiff_error(file, e))?
        .with_limits(limits);
    Ok((decoder, len))
}

/// `(rows, columns, bytes per sample)` of the decoder's current page, checked: grey, uncompressed, within
/// [`MAX_VIEW_PIXELS`].
fn page_layout(d: &mut TiffDecoder, file: &Path) -> Result<(usize, usize, usize), ScanError> {
    let (w, h) = d.dimensions().map_err(|e| tiff_error(file, e))?;
    let bits = match d.colortype().map_err(|e| tiff_error(file, e))? {
        ColorType::Gray(b) if matches!(b, 8 | 16 | 32 | 64) => b as usize,
        other => {
            return Err(ScanError::Unsupported {
                file: file.to_path_buf(),
                what: format!(
                    "{other:?} pixels (projections are one grey sample of 8/16/32/64 bits)"
                ),
            });
        }
    };
    let compression = d
        .find_tag_unsigned::<u32>(Tag::Compression)
        .map_err(|e| tiff_error(file, e))?
        .unwrap_or(1);
    if compression != 1 {
        return Err(ScanError::Unsupported {
            file: file.to_path_buf(),
            what: format!(
                "TIFF compression {compression} (only uncompressed projections are read)"
            ),
        });
    }
    let (rows, cols) = (h as usize, w as usize);
    if rows.saturating_mul(cols) > MAX_VIEW_PIXELS {
        return Err(ScanError::Limit {
            file: file.to_path_buf(),
            what: format!("a {cols} × {rows} image (at most {MAX_VIEW_PIXELS} pixels a view)"),
        });
    }
    Ok((rows, cols, bits / 8))
}

fn check_shape(file: &Path, got: (usize, usize), want: (usize, usize)) -> Result<(), ScanError> {
    if got != want {
        return Err(ScanError::Tiff {
            file: file.to_path_buf(),
            message: format!(
                "image is {} × {} (columns × rows), the scan's views are {} × {}",
                got.1, got.0, want.1, want.0
            ),
        });
    }
    Ok(())
}

fn check_length(
    file: &Path,
    len: u64,
    pages: usize,
    pixels: usize,
    bytes: usize,
) -> Result<(), ScanError> {
    let need = (pages as u64)
        .saturating_mul(pixels as u64)
        .saturating_mul(bytes as u64);
    if need > len {
        return Err(ScanError::Tiff {
            file: file.to_path_buf(),
            message: format!(
                "truncated: declares {need} bytes of pixels, the file has {len} bytes"
            ),
        });
    }
    Ok(())
}

/// Decode the decoder's current page into `out` as `f32`.
fn decode_page(d: &mut TiffDecoder, file: &Path, out: &mut [f32]) -> Result<(), ScanError> {
    let image = d.read_image().map_err(|e| tiff_error(file, e))?;
    fn copy<T: Copy>(src: &[T], out: &mut [f32], f: impl Fn(T) -> f32) -> bool {
        if src.len() != out.len() {
            return false;
        }
        for (o, &s) in out.iter_mut().zip(src) {
            *o = f(s);
        }
        true
    }
    let ok = match &image {
        DecodingResult::U8(v) => copy(v, out, f32::from),
        DecodingResult::U16(v) => copy(v, out, f32::from),
        DecodingResult::U32(v) => copy(v, out, |x| x as f32),
        DecodingResult::U64(v) => copy(v, out, |x| x as f32),
        DecodingResult::I8(v) => copy(v, out, f32::from),
        DecodingResult::I16(v) => copy(v, out, f32::from),
        DecodingResult::I32(v) => copy(v, out, |x| x as f32),
        DecodingResult::I64(v) => copy(v, out, |x| x as f32),
        DecodingResult::F16(v) => copy(v, out, f32::from),
        DecodingResult::F32(v) => copy(v, out, |x| x),
        DecodingResult::F64(v) => copy(v, out, |x| x as f32),
    };
    if !ok {
        return Err(ScanError::Tiff {
            file: file.to_path_buf(),
            message: format!(
                "decoded a page of the wrong size (expected {} values)",
                out.len()
            ),
        });
    }
    Ok(())
}

/// `(rows, columns)` and page count of a TIFF file, every page checked to have the first page's layout and
/// the file long enough for all of them.
pub fn probe(file: &Path) -> Result<(usize, usize, usize), ScanError> {
    let (mut d, len) = open_decoder(file)?;
    let (rows, cols, bytes) = page_layout(&mut d, file)?;
    let mut pages = 1usize;
    while d.more_images() {
        d.next_image().map_err(|e| tiff_error(file, e))?;
        let (r, c, b) = page_layout(&mut d, file)?;
        if (r, c, b) != (rows, cols, bytes) {
            return Err(ScanError::Tiff {
                file: file.to_path_buf(),
                message: format!(
                    "page {pages} is {c} × {r} of {} bits, page 0 is {cols} × {rows} of {} bits",
                    b * 8,
                    bytes * 8
                ),
            });
        }
        pages += 1;
        if pages > crate::recon::geometry::angles::MAX_VIEWS {
            return Err(ScanError::Limit {
                file: file.to_path_buf(),
                what: format!(
                    "more than {} pages",
                    crate::recon::geometry::angles::MAX_VIEWS
                ),
            });
        }
    }
    check_length(file, len, pages, rows * cols, bytes)?;
    Ok((rows, cols, pages))
}

/// `(bits per sample, whether samples are floats)` of a TIFF's first page.
pub fn sample_kind(file: &Path) -> Result<(u32, bool), ScanError> {
    let (mut d, _) = open_decoder(file)?;
    let (_, _, bytes) = page_layout(&mut d, file)?;
    let format = d
        .find_tag_unsigned::<u16>(Tag::SampleFormat)
        .ok()
        .flatten()
        .unwrap_or(1);
    Ok(((bytes * 8) as u32, format == 3))
}

/// One TIFF file per view, in the given order.
pub struct TiffFiles {
    files: Vec<PathBuf>,
    shape: (usize, usize),
}

impl TiffFiles {
    /// The views are `files`; the shape is the first file's (each view is checked when read).
    pub fn open(files: Vec<PathBuf>) -> Result<Self, ScanError> {
        let Some(first) = files.first() else {
            return Err(ScanError::NotAScan {
                path: PathBuf::new(),
                why: "no TIFF files".into(),
            });
        };
        let (rows, cols, _) = probe_first_page(first)?;
        Ok(Self {
            files,
            shape: (rows, cols),
        })
    }
    pub fn files(&self) -> &[PathBuf] {
        &self.files
    }
}

fn probe_first_page(file: &Path) -> Result<(usize, usize, usize), ScanError> {
    let (mut d, len) = open_decoder(file)?;
    let (rows, cols, bytes) = page_layout(&mut d, file)?;
    check_length(file, len, 1, rows * cols, bytes)?;
    Ok((rows, cols, bytes))
}

impl ViewSource for TiffFiles {
    fn view_count(&self) -> usize {
        self.files.len()
    }
    fn shape(&self) -> (usize, usize) {
        self.shape
    }
    fn read_view(&mut self, i: usize, out: &mut [f32]) -> Result<(), ScanError> {
        let Some(file) = self.files.get(i) else {
            return Err(ScanError::NoSuchView {
                file: self.files.first().cloned().unwrap_or_default(),
                index: i,
                count: self.files.len(),
            });
        };
        let (mut d, len) = open_decoder(file)?;
        let (rows, cols, bytes) = page_layout(&mut d, file)?;
        check_shape(file, (rows, cols), self.shape)?;
        check_length(file, len, 1, rows * cols, bytes)?;
        decode_page(&mut d, file, out)
    }
}

/// One multi-page TIFF file, a view per page.
pub struct TiffPages {
    file: PathBuf,
    decoder: TiffDecoder,
    pages: usize,
    shape: (usize, usize),
}

impl TiffPages {
    pub fn open(file: &Path) -> Result<Self, ScanError> {
        let (rows, cols, pages) = probe(file)?;
        let (decoder, _) = open_decoder(file)?;
        Ok(Self {
            file: file.to_path_buf(),
            decoder,
            pages,
            shape: (rows, cols),
        })
    }
}

impl ViewSource for TiffPages {
    fn view_count(&self) -> usize {
        self.pages
    }
    fn shape(&self) -> (usize, usize) {
        self.shape
    }
    fn read_view(&mut self, i: usize, out: &mut [f32]) -> Result<(), ScanError> {
        if i >= self.pages {
            return Err(ScanError::NoSuchView {
                file: self.file.clone(),
                index: i,
                count: self.pages,
            });
        }
        let file = &self.file;
        self.decoder
            .seek_to_image(i)
            .map_err(|e| tiff_error(file, e))?;
        let (rows, cols, _) = page_layout(&mut self.decoder, file)?;
        check_shape(file, (rows, cols), self.shape)?;
        decode_page(&mut self.decoder, file, out)
    }
}
