//! NeXus NXtomo scans (HDF5), as ESRF's `nxtomo` package and tomoscan write them, read with the pure-Rust
//! `hdf5-pure` (chunked, deflate-compressed and contiguous datasets; virtual datasets are refused).
//!
//! What is read, under the first root group whose `definition` is `NXtomo` (`/entry` below):
//! - `/entry/instrument/detector/data`: `[frames][rows][cols]`, any integer or float type of up to 64 bits,
//!   read one frame at a time (never whole);
//! - `/entry/instrument/detector/image_key` (0 projection, 1 flat, 2 dark, 3 invalid) and, where present,
//!   `image_key_control` (the same, and −1 for alignment frames, which are left out);
//! - `/entry/sample/rotation_angle` (`@units` degree or rad; default degree): one angle per frame;
//! - the pixel size: `/entry/sample/x_pixel_size` / `y_pixel_size` (the pixel at the sample) where present,
//!   else `/entry/instrument/detector/x_pixel_size` / `y_pixel_size`; `@units` m (default), mm, um, nm;
//! - `/entry/instrument/detector/distance`: noted, not used (a parallel beam has no magnification).
//!
//! Conventions (documented assumptions, tested by an off-centre point): the beam is parallel
//! ([`crate::recon::geometry::Parallel3d`]); the sample turns by `rotation_angle` counter-clockwise seen from
//! above, so ctrecon's view angle is β = −θ; image row 0 is the detector's top ([`Orientation::ROWS_UP`]);
//! columns run along +u. Projections keep the order of their frames, each with its own angle. The dark is
//! the mean of every dark frame; flats come in series (runs of consecutive flat frames), each averaged, and
//! the flat of a projection is interpolated linearly by frame index between the series before and after it
//! (the nearest series outside them), DESIGN.md §11.
//!
//! The centre of rotation is not read from the file (no key of it is taken, e.g. nxtomo's
//! `x_rotation_axis_pixel_position`): the panel's `offset_u_mm` is 0 and the import finds it from the views
//! (`scans::calibrate_parallel`). The mapping is tested by an off-centre point (`nxtomo_tests`).

use std::path::Path;

use hdf5_pure::{DType, Dataset, File as H5File};

use super::nxtomo_views::NxViews;
use super::{Format, Intensity, MAX_VIEW_PIXELS, Orientation, Provenance, Scan, ScanError};
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::geometry::{Angles, Geometry, Panel, Parallel3d};

/// Most frames (projections, flats, darks, alignment) a file may hold.
pub const MAX_FRAMES: usize = 4 * MAX_VIEWS;
/// Most flat series kept in memory (each one view of `f32`).
pub const MAX_FLAT_SERIES: usize = 16;

/// The detector data types read (converted to `f32` frame by frame).
const NUMERIC: [DType; 10] = [
    DType::U8,
    DType::U16,
    DType::U32,
    DType::U64,
    DType::I8,
    DType::I16,
    DType::I32,
    DType::I64,
    DType::F32,
    DType::F64,
];

/// Whether `path` is an HDF5 file with an NXtomo entry.
pub fn is_nxtomo(path: &Path) -> bool {
    open_file(path).and_then(|f| entry(path, &f)).is_ok()
}

pub(super) fn h5_error(file: &Path, key: &str, e: impl std::fmt::Display) -> ScanError {
    ScanError::invalid(file, key, "", format!("unreadable HDF5: {e}"))
}

fn open_file(path: &Path) -> Result<H5File, ScanError> {
    match hdf5_pure::is_hdf5(path) {
        Ok(true) => {}
        Ok(false) => {
            return Err(ScanError::NotAScan {
                path: path.to_path_buf(),
                why: "not an HDF5 file (no HDF5 signature)".into(),
            });
        }
        Err(e) => return Err(ScanError::io(path, e)),
    }
    H5File::open_streaming(path).map_err(|e| h5_error(path, "/", e))
}

/// Most elements a dataset read as a scalar may declare: checked before it is read, so that a hostile file
/// cannot make a scalar read allocate without bound.
const MAX_SCALAR_ELEMENTS: u64 = 16;

/// Whether `ds` declares at most [`MAX_SCALAR_ELEMENTS`] elements.
fn small(ds: &Dataset) -> bool {
    ds.shape().is_ok_and(|s| {
        s.iter()
            .try_fold(1u64, |a, &d| a.checked_mul(d))
            .is_some_and(|n| n <= MAX_SCALAR_ELEMENTS)
    })
}

/// Text of a scalar string dataset (fixed or variable length).
fn text(ds: &Dataset) -> Option<String> {
    if !small(ds) {
        return None;
    }
    if let Ok(v) = ds.read_string() {
        return v.into_iter().next();
    }
    ds.read_vlen_strings(Default::default())
        .ok()
        .and_then(|v| v.into_iter().next())
}

/// The path of the NXtomo entry: the first root group whose `definition` reads `NXtomo`.
fn entry(path: &Path, f: &H5File) -> Result<String, ScanError> {
    let groups = f.root().groups().map_err(|e| h5_error(path, "/", e))?;
    for g in groups {
        let name = format!("/{}", g.trim_start_matches('/'));
        if let Ok(ds) = f.dataset(&format!("{name}/definition"))
            && text(&ds).is_some_and(|t| t.trim() == "NXtomo")
        {
            return Ok(name);
        }
    }
    Err(ScanError::NotAScan {
        path: path.to_path_buf(),
        why: "an HDF5 file without an NXtomo entry (no root group with definition = NXtomo)".into(),
    })
}

/// The reading context: the file, its path, and the provenance gathered so far.
struct Reader<'a> {
    path: &'a Path,
    file: H5File,
    taken: Vec<Provenance>,
}

impl Reader<'_> {
    fn dataset(&self, key: &str) -> Result<Dataset, ScanError> {
        self.file.dataset(key).map_err(|_| ScanError::Missing {
            file: self.path.to_path_buf(),
            key: key.to_string(),
        })
    }
    fn units(&self, ds: &Dataset) -> Option<String> {
        let attrs = ds.attrs().ok()?;
        use hdf5_pure::AttrValue as A;
        match attrs.get("units")? {
            A::String(s)
            | A::AsciiString(s)
            | A::VarLenString(s)
            | A::VarLenAsciiString(s)
            | A::StringSized { value: s, .. }
            | A::AsciiStringSized { value: s, .. } => Some(s.clone()),
            A::StringArray(v)
            | A::AsciiStringArray(v)
            | A::VarLenStringArray(v)
            | A::VarLenAsciiStringArray(v) => v.first().cloned(),
            other => Some(format!("{other:?}")),
        }
    }
    /// A 1D numeric dataset of exactly `n` values.
    fn vector(&self, key: &str, n: usize) -> Result<Vec<f64>, ScanError> {
        let ds = self.dataset(key)?;
        let shape = ds.shape().map_err(|e| h5_error(self.path, key, e))?;
        if shape.len() != 1 || shape[0] != n as u64 {
            return Err(ScanError::mismatch(
                self.path,
                key,
                format!("shape {shape:?}, the detector data have {n} frames"),
            ));
        }
        ds.read_f64().map_err(|e| h5_error(self.path, key, e))
    }
    /// A scalar length in mm from a dataset with `@units` (default metres); `None` when absent.
    fn length_mm(&mut self, key: &str) -> Result<Option<f64>, ScanError> {
        let Ok(ds) = self.file.dataset(key) else {
            return Ok(None);
        };
        if !small(&ds) {
            return Err(ScanError::invalid(
                self.path,
                key,
                "",
                format!(
                    "a length, but the dataset declares more than {MAX_SCALAR_ELEMENTS} values"
                ),
            ));
        }
        let v = ds.read_f64().map_err(|e| h5_error(self.path, key, e))?;
        let Some(&x) = v.first() else {
            return Err(ScanError::invalid(self.path, key, "", "empty"));
        };
        let units = self.units(&ds).unwrap_or_else(|| "m".into());
        let scale = match units.trim() {
            "m" | "meter" | "metre" | "meters" | "metres" => 1e3,
            "mm" | "millimeter" | "millimetre" => 1.0,
            "um" | "µm" | "μm" | "micron" | "micrometer" | "micrometre" => 1e-3,
            "nm" | "nanometer" | "nanometre" => 1e-6,
            other => {
                return Err(ScanError::invalid(
                    self.path,
                    &format!("{key}@units"),
                    other,
                    "a length unit ctrecon does not know (m, mm, um, nm)",
                ));
            }
        };
        let mm = x * scale;
        self.taken.push(Provenance {
            key: key.to_string(),
            value: format!("{x} {units} = {mm} mm"),
            origin: format!("{} {key}", self.path.display()),
        });
        Ok(Some(mm))
    }
}

/// Frames of one kind, in frame order.
#[derive(Debug, Default)]
struct Frames {
    projections: Vec<usize>,
    flats: Vec<usize>,
    darks: Vec<usize>,
    alignment: usize,
    invalid: usize,
}

fn classify(keys: &[f64], control: Option<&[f64]>) -> Frames {
    let mut f = Frames::default();
    for (i, &k) in keys.iter().enumerate() {
        let c = control.map_or(k, |c| c[i]);
        match (c as i64, k as i64) {
            (-1, _) => f.alignment += 1,
            (_, 0) => f.projections.push(i),
            (_, 1) => f.flats.push(i),
            (_, 2) => f.darks.push(i),
            _ => f.invalid += 1,
        }
    }
    f
}

/// Runs of consecutive frame indices.
fn series(frames: &[usize]) -> Vec<Vec<usize>> {
    let mut out: Vec<Vec<usize>> = Vec::new();
    for &i in frames {
        match out.last_mut() {
            Some(s) if s.last().is_some_and(|&l| l + 1 == i) => s.push(i),
            _ => out.push(vec![i]),
        }
    }
    out
}

/// Open an NXtomo scan from its HDF5 file (`.nx`, `.nxs`, `.h5`, `.hdf5`).
pub fn open(path: &Path) -> Result<Scan, ScanError> {
    let file = open_file(path)?;
    let e = entry(path, &file)?;
    let mut r = Reader {
        path,
        file,
        taken: Vec::new(),
    };
    let key = format!("{e}/instrument/detector/data");
    let data = r.dataset(&key)?;
    if let Ok(hdf5_pure::Layout::Virtual) = data.layout() {
        return Err(ScanError::Unsupported {
            file: path.to_path_buf(),
            what: format!("{key} is a virtual dataset (copy it into the file first)"),
        });
    }
    let dtype = data.dtype().map_err(|err| h5_error(path, &key, err))?;
    if !NUMERIC.contains(&dtype) {
        return Err(ScanError::Unsupported {
            file: path.to_path_buf(),
            what: format!("{key} has type {dtype:?} (ctrecon reads integers and floats)"),
        });
    }
    let shape = data.shape().map_err(|err| h5_error(path, &key, err))?;
    let [n, rows, cols] = match shape.as_slice() {
        &[n, rows, cols] => [n, rows, cols].map(|x| usize::try_from(x).unwrap_or(usize::MAX)),
        other => {
            return Err(ScanError::invalid(
                path,
                &key,
                &format!("{other:?}"),
                "the detector data must be [frames][rows][cols]",
            ));
        }
    };
    if n == 0 || n > MAX_FRAMES {
        return Err(ScanError::Limit {
            file: path.to_path_buf(),
            what: format!("{key}: {n} frames (1 to {MAX_FRAMES})"),
        });
    }
    if rows == 0 || cols == 0 || rows.saturating_mul(cols) > MAX_VIEW_PIXELS {
        return Err(ScanError::Limit {
            file: path.to_path_buf(),
            what: format!("{key}: frames of {cols} × {rows} (at most {MAX_VIEW_PIXELS} pixels)"),
        });
    }
    let keys = r.vector(&format!("{e}/instrument/detector/image_key"), n)?;
    let control_key = format!("{e}/instrument/detector/image_key_control");
    let control = match r.file.dataset(&control_key) {
        Ok(_) => Some(r.vector(&control_key, n)?),
        Err(_) => None,
    };
    let frames = classify(&keys, control.as_deref());
    let angle_key = format!("{e}/sample/rotation_angle");
    let angles = r.vector(&angle_key, n)?;
    let angle_ds = r.dataset(&angle_key)?;
    let angle_units = r.units(&angle_ds).unwrap_or_else(|| "degree".into());
    let to_deg = match angle_units.trim() {
        "degree" | "degrees" | "deg" | "°" => 1.0,
        "rad" | "radian" | "radians" => 180.0 / std::f64::consts::PI,
        other => {
            return Err(ScanError::invalid(
                path,
                &format!("{angle_key}@units"),
                other,
                "an angle unit ctrecon does not know (degree, rad)",
            ));
        }
    };
    if frames.projections.is_empty() {
        return Err(ScanError::invalid(
            path,
            &format!("{e}/instrument/detector/image_key"),
            "",
            "no projection frames (image_key 0)",
        ));
    }
    let mut degrees = Vec::with_capacity(frames.projections.len());
    for &f in &frames.projections {
        let a = angles[f] * to_deg;
        if !a.is_finite() {
            return Err(ScanError::invalid(
                path,
                &angle_key,
                &angles[f].to_string(),
                format!("frame {f}: not a finite angle"),
            ));
        }
        // β = −θ: the sample turns counter-clockwise seen from above (module docs).
        degrees.push(-a + 0.0);
    }
    r.taken.push(Provenance {
        key: angle_key.clone(),
        value: format!(
            "{} projection angles, {} … {} {angle_units}",
            degrees.len(),
            angles[frames.projections[0]],
            angles[frames.projections[frames.projections.len() - 1]]
        ),
        origin: format!("{} {angle_key}", path.display()),
    });
    r.taken.push(Provenance {
        key: format!("{e}/instrument/detector/image_key"),
        value: format!(
            "{} projections, {} flats, {} darks, {} alignment frames left out, {} invalid frames left out",
            frames.projections.len(),
            frames.flats.len(),
            frames.darks.len(),
            frames.alignment,
            frames.invalid
        ),
        origin: format!("{} {e}/instrument/detector/image_key", path.display()),
    });
    let (du, dv) = pixel_size(&mut r, &e)?;
    let mut notes = Vec::new();
    if let Some(d) = r.length_mm(&format!("{e}/instrument/detector/distance"))? {
        notes.push(format!(
            "{e}/instrument/detector/distance = {d} mm: not used (a parallel beam)"
        ));
    }
    let flat_series = series(&frames.flats);
    if flat_series.len() > MAX_FLAT_SERIES {
        return Err(ScanError::Limit {
            file: path.to_path_buf(),
            what: format!(
                "{} flat series (at most {MAX_FLAT_SERIES})",
                flat_series.len()
            ),
        });
    }
    let mut views = NxViews {
        path: path.to_path_buf(),
        key: key.clone(),
        data,
        frames: frames.projections.clone(),
        rows,
        cols,
        flats: Vec::new(),
    };
    let dark = if frames.darks.is_empty() {
        None
    } else {
        Some(views.mean(&frames.darks)?)
    };
    let mut flats = Vec::with_capacity(flat_series.len());
    for s in &flat_series {
        let at = s.iter().sum::<usize>() as f64 / s.len() as f64;
        flats.push((at, views.mean(s)?));
    }
    let flat = if frames.flats.is_empty() {
        None
    } else {
        Some(views.mean(&frames.flats)?)
    };
    views.flats = flats;
    let geometry = Geometry::Parallel3d(Parallel3d {
        angles: Angles::List { degrees },
        detector: Panel {
            nu: cols,
            nv: rows,
            du_mm: du,
            dv_mm: dv,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    });
    Ok(Scan {
        format: Format::NxTomo,
        source: path.to_path_buf(),
        geometry,
        views: Box::new(views),
        orientation: Orientation::ROWS_UP,
        intensity: Intensity::Raw { white_level: 1.0 },
        dark,
        flat,
        provenance: r.taken,
        notes,
    })
}

/// The pixel size (du, dv) in mm: the sample's where given, else the detector's.
fn pixel_size(r: &mut Reader<'_>, e: &str) -> Result<(f64, f64), ScanError> {
    for group in ["sample", "instrument/detector"] {
        let x = r.length_mm(&format!("{e}/{group}/x_pixel_size"))?;
        let y = r.length_mm(&format!("{e}/{group}/y_pixel_size"))?;
        if let Some(x) = x {
            let y = y.unwrap_or(x);
            for (k, v) in [("x_pixel_size", x), ("y_pixel_size", y)] {
                if !(v.is_finite() && v > 0.0) {
                    return Err(ScanError::invalid(
                        r.path,
                        &format!("{e}/{group}/{k}"),
                        &v.to_string(),
                        "must be a positive length",
                    ));
                }
            }
            return Ok((x, y));
        }
    }
    Err(ScanError::Missing {
        file: r.path.to_path_buf(),
        key: format!("{e}/instrument/detector/x_pixel_size"),
    })
}
