//! Zeiss Xradia scans (Versa, Context, Ultra): one OLE compound file, `.txrm` (a tomography) or `.xrm` (one
//! image), read stream by stream ([`super::ole`]). View `n` (from 1) is the stream `ImageData<k>/Image<n>`
//! with `k = ⌈n/100⌉`, `ImageWidth × ImageHeight` little-endian samples of `ImageInfo/DataType` (5 uint16,
//! 10 float32), rows stored one after the other; the views are `ImageInfo/ImagesTaken` (else `NoOfImages`),
//! each with its angle in degrees in `ImageInfo/Angles`. `ReferenceData/Image` (open beam, its own
//! `DataType`) is the flat: the views are raw counts divided by it. Every count and length is checked
//! against the streams' sizes and the limits before anything is allocated, and the views are read one at a
//! time.
//!
//! Geometry, following CIL's `ZEISSDataReader` (cone beam, source at `(0, −|StoRADistance|, 0)`, panel
//! centre at `(0, |DtoRADistance|, 0)`, rotation axis along z through the origin, panel origin bottom-left:
//! image column 0 towards −x and image row 0 at the bottom, CIL angle `θ = Angles` in degrees) and CIL's
//! conversion to vectors (the system turns by `−θ` about z):
//! - the image is used as stored ([`Orientation::AS_STORED`]): columns along ctrecon's u, row 0 at the
//!   bottom (txrm2tiff likewise says the stored images are upside down to how XRM Data Explorer shows them);
//! - ctrecon's view angle is `β = −θ` (the Zeiss angle increasing = ctrecon's source turning clockwise seen
//!   from +z);
//! - `dso = |StoRADistance|`, `dsd = |StoRADistance| + |DtoRADistance|` (mm; the first view's values: the
//!   magnitudes are taken, as CIL does, whatever the sign the file gives them);
//! - the detector pixel is `PixelSize · dsd / dso` (`PixelSize` is the pixel at the object, µm), square;
//! - no offsets: the file states no calibrated centre of rotation (it is found on import).
//!
//! `Alignment/X-Shifts` and `Y-Shifts` (per view, pixels) are Zeiss's motion correction; CIL,
//! xrmreader and txrm2tiff apply them, and so does ctrecon ([`super::ViewSource::shift`]): each view, divided by
//! the reference, is moved by `(Y-Shift, X-Shift)` (its value at `(r, c)` becomes the one at
//! `(r − y, c − x)`, interpolated linearly as xrmreader does). Stage positions, optical and X-ray
//! magnifications, the camera pixel, `ReconSettings/CenterShift` and a reference exposure that differs from
//! the views' are listed in [`Scan::notes`], not applied.

use std::path::Path;

use super::ole::OleFile;
pub use super::xradia_views::{Sample, image_stream};
use super::xradia_views::{XradiaViews, decode};
use super::{Format, Intensity, MAX_VIEW_PIXELS, Orientation, Scan, ScanError};
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::geometry::{Angles, ConeBeam, Geometry, Panel};
use crate::recon::grid::MAX_AXIS;

/// The numbers of an Xradia file that ctrecon uses, as read.
#[derive(Debug, Clone, PartialEq)]
pub struct Xradia {
    /// Views: `ImagesTaken`, else `NoOfImages`.
    pub views: usize,
    pub width: usize,
    pub height: usize,
    pub sample: Sample,
    /// `ImageInfo/Angles` of the views, degrees.
    pub angles_deg: Vec<f64>,
    /// `|StoRADistance|` of the first view, mm.
    pub source_to_axis_mm: f64,
    /// `|DtoRADistance|` of the first view, mm.
    pub detector_to_axis_mm: f64,
    /// `PixelSize`: the pixel at the object, µm.
    pub pixel_um: f64,
    /// `[Y-Shift, X-Shift]` of each view (pixels), when the file has them.
    pub shifts: Option<Vec<[f64; 2]>>,
    /// The sample type of `ReferenceData/Image`, when the file has one.
    pub reference: Option<Sample>,
    pub notes: Vec<String>,
}

impl Xradia {
    /// ctrecon's detector pixel (mm): `PixelSize` magnified onto the panel.
    pub fn detector_pixel_mm(&self) -> f64 {
        self.pixel_um / 1000.0 * (self.source_to_axis_mm + self.detector_to_axis_mm)
            / self.source_to_axis_mm
    }
}

fn data_type(ole: &mut OleFile, stream: &str) -> Result<Option<Sample>, ScanError> {
    Ok(match ole.int(stream)? {
        None => None,
        Some(5) => Some(Sample::U16),
        Some(10) => Some(Sample::F32),
        Some(code) => {
            let known = [
                "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
                "float32", "float64", "string",
            ];
            let name = usize::try_from(code - 2)
                .ok()
                .and_then(|k| known.get(k))
                .map_or("an unknown type".to_string(), |n| n.to_string());
            return Err(ScanError::Unsupported {
                file: ole.file.clone(),
                what: format!(
                    "{stream} = {code} ({name}): ctrecon reads Xradia images of uint16 (5) or float32 (10)"
                ),
            });
        }
    })
}

/// The first view's magnitude of a required per-view distance, noting a distance that changes.
fn distance(
    ole: &mut OleFile,
    stream: &str,
    n: usize,
    max: usize,
    count_key: &str,
    notes: &mut Vec<String>,
) -> Result<f64, ScanError> {
    let v = ole
        .floats(stream, n, max, count_key)?
        .ok_or_else(|| ole.missing(stream))?;
    ole.record_array(stream, &v, " mm");
    let d = v[0].abs();
    if d == 0.0 {
        return Err(ScanError::invalid(
            &ole.file,
            stream,
            "0",
            "must not be zero",
        ));
    }
    let (lo, hi) = v.iter().fold((f64::MAX, f64::MIN), |(lo, hi), x| {
        (lo.min(x.abs()), hi.max(x.abs()))
    });
    if hi - lo > 1e-6 * d {
        notes.push(format!(
            "{stream} changes from {lo} to {hi} mm over the views: the first view's {d} mm is used"
        ));
    }
    Ok(d)
}

/// Read the streams ctrecon needs from an Xradia file and check the images against them.
pub fn parse(ole: &mut OleFile) -> Result<Xradia, ScanError> {
    if !ole.has_storage("ImageInfo") {
        return Err(ScanError::NotAScan {
            path: ole.file.clone(),
            why: "an OLE file without an ImageInfo storage: not a Zeiss Xradia file".into(),
        });
    }
    let file = ole.file.clone();
    if let Some(mode) = ole.int("ImageInfo/AcquisitionMode")?
        && mode != 0
    {
        return Err(ScanError::Unsupported {
            file,
            what: format!(
                "ImageInfo/AcquisitionMode = {mode}: a reconstructed volume (.txm), not projections"
            ),
        });
    }
    if let Some(g) = ole.int("ImageInfo/XrayGeometry")?
        && g != 1
    {
        return Err(ScanError::Unsupported {
            file,
            what: format!(
                "ImageInfo/XrayGeometry = {g}: a parallel beam (ctrecon reads Xradia cone beams, 1)"
            ),
        });
    }
    let width = ole.count("ImageInfo/ImageWidth", MAX_AXIS)?;
    let height = ole.count("ImageInfo/ImageHeight", MAX_AXIS)?;
    if width * height > MAX_VIEW_PIXELS {
        return Err(ScanError::Limit {
            file,
            what: format!("ImageWidth × ImageHeight = {width} × {height}"),
        });
    }
    let sample =
        data_type(ole, "ImageInfo/DataType")?.ok_or_else(|| ole.missing("ImageInfo/DataType"))?;
    let planned = match ole.len("ImageInfo/NoOfImages") {
        Some(_) => Some(ole.count("ImageInfo/NoOfImages", MAX_VIEWS)?),
        None => None,
    };
    let (views, count_key) = match ole.len("ImageInfo/ImagesTaken") {
        Some(_) => (
            ole.count("ImageInfo/ImagesTaken", MAX_VIEWS)?,
            "ImageInfo/ImagesTaken",
        ),
        None => (
            planned.ok_or_else(|| ole.missing("ImageInfo/ImagesTaken"))?,
            "ImageInfo/NoOfImages",
        ),
    };
    if let Some(p) = planned
        && views > p
    {
        return Err(ScanError::mismatch(
            &file,
            count_key,
            format!("ImagesTaken = {views} exceeds NoOfImages = {p}"),
        ));
    }
    let max = planned.unwrap_or(views);
    check_images(ole, views, width * height * sample.bytes(), count_key)?;
    let mut notes = Vec::new();
    let angles_deg = ole
        .floats("ImageInfo/Angles", views, max, count_key)?
        .ok_or_else(|| ole.missing("ImageInfo/Angles"))?;
    ole.record_array("ImageInfo/Angles", &angles_deg, "°");
    let a = &angles_deg;
    let up = a.len() > 1 && a[1] > a[0];
    if let Some(k) = (1..a.len()).find(|&k| {
        let step = a[k] - a[k - 1];
        step == 0.0 || (step > 0.0) != up
    }) {
        return Err(ScanError::invalid(
            &file,
            "ImageInfo/Angles",
            &a[k].to_string(),
            format!(
                "the angles must increase (or decrease) view by view; view {} does not",
                k + 1
            ),
        ));
    }
    let source_to_axis_mm = distance(
        ole,
        "ImageInfo/StoRADistance",
        views,
        max,
        count_key,
        &mut notes,
    )?;
    let detector_to_axis_mm = distance(
        ole,
        "ImageInfo/DtoRADistance",
        views,
        max,
        count_key,
        &mut notes,
    )?;
    let pixel_um = ole
        .float("ImageInfo/PixelSize")?
        .ok_or_else(|| ole.missing("ImageInfo/PixelSize"))?;
    if pixel_um <= 0.0 {
        return Err(ScanError::invalid(
            &file,
            "ImageInfo/PixelSize",
            &pixel_um.to_string(),
            "must be positive",
        ));
    }
    let shifts = read_shifts(ole, views, max, count_key)?;
    let reference = match ole.len("ReferenceData/Image") {
        None => {
            notes.push(if ole.has_storage("MultiReferenceData") {
                "MultiReferenceData is not read and there is no ReferenceData/Image: no flat".into()
            } else {
                "no ReferenceData/Image: no flat".into()
            });
            None
        }
        Some(len) => {
            let s = match data_type(ole, "ReferenceData/DataType")? {
                Some(s) => s,
                None => sample,
            };
            let want = (width * height * s.bytes()) as u64;
            if len != want {
                return Err(ScanError::invalid(
                    &file,
                    "ReferenceData/Image",
                    &format!("{len} bytes"),
                    format!("a {width} × {height} image of {} is {want} bytes", s.name()),
                ));
            }
            Some(s)
        }
    };
    notes.extend(unapplied(ole)?);
    Ok(Xradia {
        views,
        width,
        height,
        sample,
        angles_deg,
        source_to_axis_mm,
        detector_to_axis_mm,
        pixel_um,
        shifts,
        reference,
        notes,
    })
}

/// Every view's stream exists with `bytes` bytes, and there is none beyond the last.
fn check_images(
    ole: &OleFile,
    views: usize,
    bytes: usize,
    count_key: &str,
) -> Result<(), ScanError> {
    for i in 0..views {
        let stream = image_stream(i);
        match ole.len(&stream) {
            None => {
                return Err(ScanError::mismatch(
                    &ole.file,
                    count_key,
                    format!("{count_key} = {views}, but there is no stream {stream}"),
                ));
            }
            Some(len) if len != bytes as u64 => {
                return Err(ScanError::invalid(
                    &ole.file,
                    &stream,
                    &format!("{len} bytes"),
                    format!("an image is {bytes} bytes (ImageWidth × ImageHeight × DataType)"),
                ));
            }
            Some(_) => {}
        }
    }
    let beyond = image_stream(views);
    if ole.len(&beyond).is_some() {
        return Err(ScanError::mismatch(
            &ole.file,
            count_key,
            format!("{count_key} = {views}, but the file has a further image {beyond}"),
        ));
    }
    Ok(())
}

/// `[Y-Shift, X-Shift]` per view from `Alignment/`, when the file has either (a missing one is 0).
fn read_shifts(
    ole: &mut OleFile,
    views: usize,
    max: usize,
    count_key: &str,
) -> Result<Option<Vec<[f64; 2]>>, ScanError> {
    let x = ole.floats("Alignment/X-Shifts", views, max, count_key)?;
    let y = ole.floats("Alignment/Y-Shifts", views, max, count_key)?;
    if x.is_none() && y.is_none() {
        return Ok(None);
    }
    for (stream, v) in [("Alignment/X-Shifts", &x), ("Alignment/Y-Shifts", &y)] {
        if let Some(v) = v {
            ole.record_array(stream, v, " px");
        }
    }
    let at = |v: &Option<Vec<f64>>, i: usize| v.as_ref().map_or(0.0, |v| v[i]);
    Ok(Some((0..views).map(|i| [at(&y, i), at(&x, i)]).collect()))
}

/// Values read but not applied, as notes.
fn unapplied(ole: &mut OleFile) -> Result<Vec<String>, ScanError> {
    let mut notes = Vec::new();
    for (stream, unit) in [
        ("ImageInfo/CamPixelSize", " µm"),
        ("ImageInfo/OpticalMagnification", ""),
        ("ImageInfo/XrayMagnification", ""),
        ("ImageInfo/XPosition", " µm"),
        ("ImageInfo/YPosition", " µm"),
        ("ImageInfo/ZPosition", " µm"),
        ("ImageInfo/CameraOffset", ""),
        ("ReconSettings/CenterShift", " px"),
    ] {
        if let Some(v) = ole.float(stream)? {
            notes.push(format!(
                "{stream} = {v}{unit} (the first view's) is not applied"
            ));
        }
    }
    let views = ole.float("ImageInfo/ExpTimes")?;
    if let (Some(r), Some(v)) = (ole.float("ReferenceData/ExpTime")?, views)
        && r != v
    {
        notes.push(format!(
            "ReferenceData/ExpTime = {r} s differs from the first view's ImageInfo/ExpTimes = {v} s: \
             the reference is not scaled"
        ));
    }
    Ok(notes)
}

/// ctrecon's geometry for an Xradia file.
pub fn geometry(x: &Xradia) -> Geometry {
    let d = x.detector_pixel_mm();
    Geometry::Cone(ConeBeam {
        angles: Angles::List {
            degrees: x.angles_deg.iter().map(|a| -a).collect(),
        },
        dso_mm: x.source_to_axis_mm,
        dsd_mm: x.source_to_axis_mm + x.detector_to_axis_mm,
        detector: Panel {
            nu: x.width,
            nv: x.height,
            du_mm: d,
            dv_mm: d,
            offset_u_mm: 0.0,
            offset_v_mm: 0.0,
        },
    })
}

/// Open a Zeiss Xradia scan from its `.txrm` / `.xrm` file.
pub fn open(path: &Path) -> Result<Scan, ScanError> {
    let mut ole = OleFile::open(path)?;
    let x = parse(&mut ole)?;
    let flat = match x.reference {
        Some(s) => {
            let mut bytes = vec![0u8; x.width * x.height * s.bytes()];
            ole.read_into("ReferenceData/Image", &mut bytes)?;
            let mut image = vec![0f32; x.width * x.height];
            decode(s, &bytes, &mut image);
            ole.record(
                "ReferenceData/Image",
                format!("{} × {} {} (the flat)", x.width, x.height, s.name()),
            );
            Some(image)
        }
        None => None,
    };
    let white_level = match x.sample {
        Sample::U16 => f64::from(u16::MAX),
        Sample::F32 => 1.0,
    };
    let provenance = std::mem::take(&mut ole.taken);
    let views = XradiaViews::new(
        ole,
        x.views,
        (x.height, x.width),
        x.sample,
        x.shifts.clone(),
    );
    Ok(Scan {
        format: Format::ZeissXradia,
        source: path.to_path_buf(),
        geometry: geometry(&x),
        views: Box::new(views),
        orientation: Orientation::AS_STORED,
        intensity: Intensity::Raw { white_level },
        dark: None,
        flat,
        provenance,
        notes: x.notes.clone(),
    })
}
