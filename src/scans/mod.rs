//! Measured scans as the scanner wrote them: TIFF stacks (with a ctrecon geometry JSON), Nikon XT H
//! (`.xtekct`), Bruker SkyScan (`.log`), Zeiss Xradia (`.txrm`/`.xrm`) and NeXus NXtomo (HDF5: `.nx`,
//! `.nxs`, `.h5`, `.hdf5`), read into one format-independent [`Scan`].
//!
//! An adapter: it reads files (`std::fs`), never the network, a clock or the environment, and imports no
//! async runtime, HTTP, database or DICOM crate. The text parsers work on `&str`, the Zeiss compound files
//! are read stream by stream (`ole`); the projections are read view by view through [`ViewSource`] and
//! never held whole.
//!
//! Conventions (DESIGN.md §2, §11):
//! - [`ViewSource::read_view`] gives the image as stored: row 0 is the image's first row (its top in a
//!   TIFF), column 0 its first column. [`Orientation`] says how that image maps onto ctrecon's detector
//!   (`[v][u]`, row 0 at the most negative v, v along +z), and [`Scan::geometry`] is ctrecon's geometry for
//!   the image so oriented.
//! - Values are raw detector values as `f32`; [`Intensity`] says what a value of "no attenuation" is.
//! - Every value taken from a vendor file is listed in [`Scan::provenance`] with the file and key it came
//!   from; values read but not used are listed in [`Scan::notes`].
//! - A scanner's per-view alignment (Zeiss `Alignment/X-Shifts`) is given by [`ViewSource::shift`] and
//!   applied to the normalised view, before the minus log (`convert`).

pub mod bruker;
pub mod calibrate;
pub mod calibrate_parallel;
pub mod convert;
pub mod detect;
pub mod ini;
pub mod nikon;
pub mod nxtomo;
pub mod nxtomo_views;
pub mod ole;
pub mod simulated;
pub mod simulated_nxtomo;
pub mod stack;
pub mod tiff_views;
pub mod xradia_views;
pub mod zeiss;

#[cfg(test)]
mod nxtomo_tests;
#[cfg(test)]
mod tests;

use std::fmt;
use std::path::{Path, PathBuf};

use crate::recon::geometry::Geometry;

pub use convert::{
    LineIntegrals, Normalisation, TRANSMISSION_FLOOR, ViewConverter, line_integrals,
};
pub use detect::open;
pub use tiff_views::{TiffFiles, TiffPages};

/// Most pixels one view may have (8192 × 8192): checked before a view buffer is allocated.
pub const MAX_VIEW_PIXELS: usize = 1 << 26;
/// Largest metadata file read whole (`.xtekct`, `.log`, `_ctdata.txt`, `.ang`, geometry JSON).
pub const MAX_METADATA_BYTES: u64 = 16 << 20;

/// The scanner format a scan was read from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// TIFF files (one per view, or one multi-page file) with a ctrecon geometry JSON.
    TiffStack,
    /// Nikon XT H / Inspect-X: `.xtekct` + TIFFs.
    NikonXtek,
    /// Bruker SkyScan: `.log` + TIFFs.
    BrukerSkyscan,
    /// Zeiss Xradia (Versa, Context, Ultra): one OLE compound file, `.txrm` (or `.xrm`).
    ZeissXradia,
    /// NeXus NXtomo (the synchrotron standard): one HDF5 file, `.nx`/`.nxs`/`.h5`/`.hdf5`.
    NxTomo,
}

impl fmt::Display for Format {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Format::TiffStack => "tiff_stack",
            Format::NikonXtek => "nikon_xtek",
            Format::BrukerSkyscan => "bruker_skyscan",
            Format::ZeissXradia => "zeiss_xradia",
            Format::NxTomo => "nxtomo",
        })
    }
}

/// A scan could not be read. Every variant names the file; those about metadata also name the key.
#[derive(Debug, thiserror::Error)]
pub enum ScanError {
    #[error("{}: {source}", file.display())]
    Io {
        file: PathBuf,
        source: std::io::Error,
    },
    #[error("{}: not a readable TIFF: {message}", file.display())]
    Tiff { file: PathBuf, message: String },
    #[error("{}: required key `{key}` is missing", file.display())]
    Missing { file: PathBuf, key: String },
    #[error("{}: key `{key}` has value {value:?}: {why}", file.display())]
    Invalid {
        file: PathBuf,
        key: String,
        value: String,
        why: String,
    },
    #[error("{}: `{key}` contradicts the images: {why}", file.display())]
    Mismatch {
        file: PathBuf,
        key: String,
        why: String,
    },
    #[error("{}: unsupported: {what}", file.display())]
    Unsupported { file: PathBuf, what: String },
    #[error("{}: over a limit: {what}", file.display())]
    Limit { file: PathBuf, what: String },
    #[error("{}: not a scan ctrecon reads: {why}", path.display())]
    NotAScan { path: PathBuf, why: String },
    #[error("{}: view {index} requested, the scan has {count}", file.display())]
    NoSuchView {
        file: PathBuf,
        index: usize,
        count: usize,
    },
}

impl ScanError {
    pub(crate) fn io(file: &Path, source: std::io::Error) -> Self {
        ScanError::Io {
            file: file.to_path_buf(),
            source,
        }
    }
    pub(crate) fn invalid(file: &Path, key: &str, value: &str, why: impl Into<String>) -> Self {
        ScanError::Invalid {
            file: file.to_path_buf(),
            key: key.to_string(),
            value: value.to_string(),
            why: why.into(),
        }
    }
    pub(crate) fn mismatch(file: &Path, key: &str, why: impl Into<String>) -> Self {
        ScanError::Mismatch {
            file: file.to_path_buf(),
            key: key.to_string(),
            why: why.into(),
        }
    }
}

/// Projections read one view at a time.
pub trait ViewSource: Send {
    /// Number of views.
    fn view_count(&self) -> usize;
    /// `(rows, columns)` of every view: `(nv, nu)`.
    fn shape(&self) -> (usize, usize);
    /// Read view `i` into `out` (`nv · nu` values, row-major, row 0 = the image's first row), as raw
    /// detector values converted to `f32`.
    fn read_view(&mut self, i: usize, out: &mut [f32]) -> Result<(), ScanError>;
    /// The scanner's alignment of view `i` (motion correction): `[rows, columns]`, in pixels of the stored
    /// image, by which the view is moved once normalised to transmissions (its value at `(r, c)` becomes
    /// the one at `(r − rows, c − columns)`, linearly interpolated, the edge value beyond the image).
    /// `None` (the default): not moved.
    fn shift(&self, _i: usize) -> Option<[f64; 2]> {
        None
    }
    /// The flat (open beam) image of view `i` (as stored, `nv · nu` values) where the scan's flat varies
    /// from view to view (NXtomo flats taken before and after, interpolated): writes it to `out` and says
    /// `true`. `false` (the default): the scan's one [`Scan::flat`] applies.
    fn view_flat(&self, _i: usize, _out: &mut [f32]) -> bool {
        false
    }
}

/// How a stored image maps onto ctrecon's detector: ctrecon's `[r][c]` is the image's
/// `[flip_rows ? nv−1−r : r][flip_cols ? nu−1−c : c]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Orientation {
    pub flip_rows: bool,
    pub flip_cols: bool,
}

impl Orientation {
    /// The image as stored: row 0 at the detector's bottom (ctrecon's row 0), column 0 at its most
    /// negative u.
    pub const AS_STORED: Orientation = Orientation {
        flip_rows: false,
        flip_cols: false,
    };
    /// Image row 0 is the detector's top (+z): rows reversed, columns as stored.
    pub const ROWS_UP: Orientation = Orientation {
        flip_rows: true,
        flip_cols: false,
    };
    /// The image turned by 180° (rows and columns reversed): a radiograph seen from behind the detector.
    pub const TURNED: Orientation = Orientation {
        flip_rows: true,
        flip_cols: true,
    };

    /// Copy `image` (`nv × nu`, as stored) into `out` in ctrecon's detector order.
    pub fn apply(&self, image: &[f32], nv: usize, nu: usize, out: &mut [f32]) {
        for r in 0..nv {
            let src_r = if self.flip_rows { nv - 1 - r } else { r };
            let src = &image[src_r * nu..(src_r + 1) * nu];
            let dst = &mut out[r * nu..(r + 1) * nu];
            if self.flip_cols {
                for (d, s) in dst.iter_mut().zip(src.iter().rev()) {
                    *d = *s;
                }
            } else {
                dst.copy_from_slice(src);
            }
        }
    }
    /// The image index `(row, column)` of ctrecon's detector element `(r, c)` (and back: it is its own
    /// inverse).
    pub fn image_index(&self, r: usize, c: usize, nv: usize, nu: usize) -> (usize, usize) {
        (
            if self.flip_rows { nv - 1 - r } else { r },
            if self.flip_cols { nu - 1 - c } else { c },
        )
    }
}

/// What the detector values mean.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Intensity {
    /// Flat-corrected intensities: `value / white_level` is the transmission (Nikon `WhiteLevel`).
    FlatCorrected { white_level: f64 },
    /// Raw counts, to be normalised with the scan's dark and flat ([`Scan::dark`], [`Scan::flat`]); without
    /// them, `value / white_level` is taken as the transmission.
    Raw { white_level: f64 },
    /// Already transmissions (float TIFFs in [0, 1]).
    Transmission,
}

/// One value a reader took from a file: what it is, the value, and where it came from (`file [section]
/// key`).
#[derive(Debug, Clone, PartialEq)]
pub struct Provenance {
    pub key: String,
    pub value: String,
    pub origin: String,
}

/// A scan as read from its files: geometry in ctrecon's form, the projections as a view source, and what
/// came from where.
pub struct Scan {
    pub format: Format,
    /// The file the scan was opened from (metadata file, TIFF or folder).
    pub source: PathBuf,
    /// ctrecon's geometry of the views once oriented by [`Scan::orientation`] (a cone beam).
    pub geometry: Geometry,
    pub views: Box<dyn ViewSource>,
    pub orientation: Orientation,
    pub intensity: Intensity,
    /// Mean dark image (as stored, `nv × nu`), when the scan has one.
    pub dark: Option<Vec<f32>>,
    /// Mean flat (open beam) image (as stored, `nv × nu`), when the scan has one.
    pub flat: Option<Vec<f32>>,
    pub provenance: Vec<Provenance>,
    /// Values read but not applied (tilts, reconstruction hints), each with its origin.
    pub notes: Vec<String>,
}

impl fmt::Debug for Scan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scan")
            .field("format", &self.format)
            .field("source", &self.source)
            .field("geometry", &self.geometry)
            .field("views", &self.views.view_count())
            .field("shape", &self.views.shape())
            .field("orientation", &self.orientation)
            .field("intensity", &self.intensity)
            .field("provenance", &self.provenance)
            .field("notes", &self.notes)
            .finish_non_exhaustive()
    }
}

/// Read a metadata file whole, refusing one over [`MAX_METADATA_BYTES`] or not UTF-8 (Latin-1 bytes are
/// taken as such: vendor files write `µ` and `°` that way).
pub(crate) fn read_text(file: &Path) -> Result<String, ScanError> {
    let len = std::fs::metadata(file)
        .map_err(|e| ScanError::io(file, e))?
        .len();
    if len > MAX_METADATA_BYTES {
        return Err(ScanError::Limit {
            file: file.to_path_buf(),
            what: format!("{len} bytes of metadata (at most {MAX_METADATA_BYTES})"),
        });
    }
    let bytes = std::fs::read(file).map_err(|e| ScanError::io(file, e))?;
    Ok(match String::from_utf8(bytes) {
        Ok(s) => s,
        Err(e) => e.into_bytes().iter().map(|&b| b as char).collect(),
    })
}

/// The last run of ASCII digits in a file name's stem, for natural ordering (`p_2` before `p_10`).
pub(crate) fn view_number(name: &str) -> Option<u64> {
    let stem = name.rsplit_once('.').map_or(name, |(s, _)| s);
    let end = stem.rfind(|c: char| c.is_ascii_digit())? + 1;
    let start = stem[..end]
        .rfind(|c: char| !c.is_ascii_digit())
        .map_or(0, |i| i + 1);
    stem[start..end].parse().ok()
}

/// Sort files naturally by the number in their names (then by name).
pub(crate) fn sort_naturally(files: &mut [PathBuf]) {
    files.sort_by(|a, b| {
        let name = |p: &PathBuf| {
            p.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        };
        let (na, nb) = (name(a), name(b));
        (view_number(&na), &na).cmp(&(view_number(&nb), &nb))
    });
}

/// The TIFF files in `dir` whose names start with `prefix` (case-sensitive) and that end in `.tif`/`.tiff`,
/// sorted naturally.
pub(crate) fn tiffs_in(dir: &Path, prefix: &str) -> Result<Vec<PathBuf>, ScanError> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(|e| ScanError::io(dir, e))? {
        let path = entry.map_err(|e| ScanError::io(dir, e))?.path();
        let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        let lower = name.to_ascii_lowercase();
        if name.starts_with(prefix)
            && (lower.ends_with(".tif") || lower.ends_with(".tiff"))
            && path.is_file()
        {
            out.push(path);
        }
    }
    sort_naturally(&mut out);
    Ok(out)
}
