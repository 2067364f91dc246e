//! The views of a Zeiss Xradia file ([`super::zeiss`]), read one `ImageData<k>/Image<n>` stream at a time
//! into a buffer of one view, its length checked before it is read; the alignment shift of each view as
//! [`ViewSource::shift`].

use super::ole::OleFile;
use super::{ScanError, ViewSource};

/// The sample types of Xradia images ctrecon reads (`DataType` codes of Xradia's `XrmDataTypes`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sample {
    /// Code 5.
    U16,
    /// Code 10.
    F32,
}

impl Sample {
    pub fn bytes(self) -> usize {
        match self {
            Sample::U16 => 2,
            Sample::F32 => 4,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Sample::U16 => "uint16",
            Sample::F32 => "float32",
        }
    }
}

/// The stream of view `i` (from 0): `ImageData<⌈(i+1)/100⌉>/Image<i+1>`.
pub fn image_stream(i: usize) -> String {
    let n = i + 1;
    format!("ImageData{}/Image{n}", n.div_ceil(100))
}

/// The views of an Xradia file, read one stream at a time.
pub struct XradiaViews {
    ole: OleFile,
    views: usize,
    shape: (usize, usize),
    sample: Sample,
    shifts: Option<Vec<[f64; 2]>>,
    bytes: Vec<u8>,
}

impl XradiaViews {
    /// `views` views of `shape` (`(rows, columns)`) of `sample`s in `ole`, checked by `zeiss::parse`.
    pub fn new(
        ole: OleFile,
        views: usize,
        shape: (usize, usize),
        sample: Sample,
        shifts: Option<Vec<[f64; 2]>>,
    ) -> Self {
        Self {
            ole,
            views,
            shape,
            sample,
            shifts,
            bytes: Vec::new(),
        }
    }
}

/// Decode little-endian `sample`s into `out` (`bytes.len() = out.len() · sample bytes`).
pub fn decode(sample: Sample, bytes: &[u8], out: &mut [f32]) {
    match sample {
        Sample::U16 => {
            for (o, b) in out.iter_mut().zip(bytes.chunks_exact(2)) {
                *o = f32::from(u16::from_le_bytes([b[0], b[1]]));
            }
        }
        Sample::F32 => {
            for (o, b) in out.iter_mut().zip(bytes.chunks_exact(4)) {
                *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
    }
}

impl ViewSource for XradiaViews {
    fn view_count(&self) -> usize {
        self.views
    }
    fn shape(&self) -> (usize, usize) {
        self.shape
    }
    fn read_view(&mut self, i: usize, out: &mut [f32]) -> Result<(), ScanError> {
        if i >= self.views {
            return Err(ScanError::NoSuchView {
                file: self.ole.file.clone(),
                index: i,
                count: self.views,
            });
        }
        let pixels = self.shape.0 * self.shape.1;
        let stream = image_stream(i);
        let want = pixels * self.sample.bytes();
        match self.ole.len(&stream) {
            Some(len) if len == want as u64 && out.len() == pixels => {}
            len => {
                return Err(ScanError::invalid(
                    &self.ole.file,
                    &stream,
                    &format!("{} bytes", len.unwrap_or(0)),
                    format!("an image is {want} bytes"),
                ));
            }
        }
        self.bytes.resize(want, 0);
        self.ole.read_into(&stream, &mut self.bytes)?;
        decode(self.sample, &self.bytes, out);
        Ok(())
    }
    fn shift(&self, i: usize) -> Option<[f64; 2]> {
        self.shifts.as_ref().and_then(|s| s.get(i).copied())
    }
}
