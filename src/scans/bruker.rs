//! Bruker SkyScan scans: a `.log` file (sections `[System]`, `[Acquisition]`, `[Reconstruction]`) and
//! projections `<Filename Prefix>00000000.tif`, … beside it (flat-field corrected by the scanner when
//! `Flat Field Correction=ON`; `value / 2^Depth (bits)` is the transmission, as TIGRE's `BrukerDataLoader`
//! reads them).
//!
//! Geometry (after TIGRE's `BrukerDataLoader`; the rotation sense and column order are not documented by the
//! vendor and are taken as Nikon's, see [`super::nikon`]):
//! - view `i` at `β = i · Rotation Step (deg)`, `Number of Files` views;
//! - detector pixel `Image Pixel Size (um) · Camera to Source / Object to Source` (the pixel at the object
//!   magnified back to the detector: binning and resizing included), else `Camera Pixel Size (um)`;
//! - the image turned by 180° ([`Orientation::TURNED`]);
//! - `Optical Axis (line)` (image row of the central ray) gives `offset_v = (line − (rows−1)/2) · dv`;
//! - `[Reconstruction] Post alignment` (a centre correction found by NRecon) is listed in the notes, not
//!   applied: the centre of rotation is left to calibration.

use std::path::Path;

use super::ini::Ini;
use super::tiff_views::TiffFiles;
use super::{
    Format, Intensity, MAX_VIEW_PIXELS, Orientation, Scan, ScanError, ViewSource, read_text,
    tiffs_in,
};
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::geometry::{Angles, ConeBeam, Geometry, Panel};
use crate::recon::grid::MAX_AXIS;

const ACQ: &str = "Acquisition";
const SYS: &str = "System";

/// The numbers of a SkyScan `.log` that ctrecon uses, as read.
#[derive(Debug, Clone, PartialEq)]
pub struct SkyscanLog {
    pub prefix: Option<String>,
    pub files: usize,
    pub rows: usize,
    pub columns: usize,
    pub object_to_source_mm: f64,
    pub camera_to_source_mm: f64,
    pub detector_pixel_mm: f64,
    pub rotation_step_deg: f64,
    pub optical_axis_line: Option<f64>,
    pub depth_bits: u32,
    pub flat_field_corrected: bool,
    pub notes: Vec<String>,
}

/// Read the keys ctrecon needs from a parsed SkyScan `.log`.
pub fn parse(ini: &mut Ini) -> Result<SkyscanLog, ScanError> {
    let file = ini.file.clone();
    if !ini.has_section(ACQ) {
        return Err(ScanError::NotAScan {
            path: file,
            why: "no [Acquisition] section".into(),
        });
    }
    let prefix = ini.text(ACQ, "Filename Prefix").filter(|p| !p.is_empty());
    if let Some(p) = &prefix
        && p.contains(['/', '\\'])
    {
        return Err(ScanError::invalid(
            &file,
            "Filename Prefix",
            p,
            "not a file name prefix",
        ));
    }
    let files = ini.count(ACQ, "Number of Files", MAX_VIEWS)?;
    let rows = ini.count(ACQ, "Number of Rows", MAX_AXIS)?;
    let columns = ini.count(ACQ, "Number of Columns", MAX_AXIS)?;
    if rows * columns > MAX_VIEW_PIXELS {
        return Err(ScanError::Limit {
            file,
            what: format!("Number of Columns × Number of Rows = {columns} × {rows}"),
        });
    }
    let object_to_source_mm = ini.positive(ACQ, "Object to Source (mm)")?;
    let camera_to_source_mm = ini.positive(ACQ, "Camera to Source (mm)")?;
    if camera_to_source_mm <= object_to_source_mm {
        return Err(ScanError::invalid(
            &file,
            "Camera to Source (mm)",
            &camera_to_source_mm.to_string(),
            format!("must exceed Object to Source (mm) ({object_to_source_mm})"),
        ));
    }
    let magnification = camera_to_source_mm / object_to_source_mm;
    let detector_pixel_mm = match ini.number(ACQ, "Image Pixel Size (um)")? {
        Some(p) if p > 0.0 => p / 1000.0 * magnification,
        Some(p) => {
            return Err(ScanError::invalid(
                &file,
                "Image Pixel Size (um)",
                &p.to_string(),
                "must be positive",
            ));
        }
        None => ini.positive(SYS, "Camera Pixel Size (um)")? / 1000.0,
    };
    let rotation_step_deg = ini.required(ACQ, "Rotation Step (deg)")?;
    if rotation_step_deg == 0.0 {
        return Err(ScanError::invalid(
            &file,
            "Rotation Step (deg)",
            "0",
            "must not be zero",
        ));
    }
    let optical_axis_line = ini.number(ACQ, "Optical Axis (line)")?;
    let depth_bits = match ini.number(ACQ, "Depth (bits)")? {
        None => 16,
        Some(d) if (1.0..=32.0).contains(&d) && d.fract() == 0.0 => d as u32,
        Some(d) => {
            return Err(ScanError::invalid(
                &file,
                "Depth (bits)",
                &d.to_string(),
                "must be 1 to 32",
            ));
        }
    };
    let flat_field_corrected = ini
        .text(ACQ, "Flat Field Correction")
        .is_none_or(|v| v.eq_ignore_ascii_case("ON"));
    let mut notes = Vec::new();
    if let Some(v) = ini.text("Reconstruction", "Post alignment") {
        notes.push(format!(
            "[Reconstruction] Post alignment = {v} is not applied"
        ));
    }
    if let Some(v) = ini.text(ACQ, "Use 360 Rotation") {
        let range = rotation_step_deg.abs() * files as f64;
        notes.push(format!(
            "Use 360 Rotation = {v}; {files} files cover {range:.3}°"
        ));
    }
    Ok(SkyscanLog {
        prefix,
        files,
        rows,
        columns,
        object_to_source_mm,
        camera_to_source_mm,
        detector_pixel_mm,
        rotation_step_deg,
        optical_axis_line,
        depth_bits,
        flat_field_corrected,
        notes,
    })
}

/// ctrecon's geometry for a SkyScan `.log`.
pub fn geometry(l: &SkyscanLog) -> Geometry {
    let d = l.detector_pixel_mm;
    let offset_v_mm = l
        .optical_axis_line
        .map_or(0.0, |line| (line - (l.rows as f64 - 1.0) / 2.0) * d);
    Geometry::Cone(ConeBeam {
        angles: Angles::Uniform {
            count: l.files,
            start_deg: 0.0,
            range_deg: Some(l.rotation_step_deg * l.files as f64),
            short_scan: false,
        },
        dso_mm: l.object_to_source_mm,
        dsd_mm: l.camera_to_source_mm,
        detector: Panel {
            nu: l.columns,
            nv: l.rows,
            du_mm: d,
            dv_mm: d,
            offset_u_mm: 0.0,
            offset_v_mm,
        },
    })
}

/// Open a SkyScan scan from its `.log` file.
pub fn open(log: &Path) -> Result<Scan, ScanError> {
    let mut ini = Ini::parse(log, &read_text(log)?);
    let l = parse(&mut ini)?;
    let dir = log.parent().unwrap_or(Path::new("."));
    let prefix = match &l.prefix {
        Some(p) => p.clone(),
        None => log
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default(),
    };
    let files = tiffs_in(dir, &prefix)?;
    if files.len() != l.files {
        return Err(ScanError::mismatch(
            log,
            "Number of Files",
            format!(
                "Number of Files={} but {} files {prefix}*.tif in {}",
                l.files,
                files.len(),
                dir.display()
            ),
        ));
    }
    let views = TiffFiles::open(files)?;
    let (rows, cols) = views.shape();
    if cols != l.columns {
        return Err(ScanError::mismatch(
            log,
            "Number of Columns",
            format!(
                "Number of Columns={} but the images are {cols} wide",
                l.columns
            ),
        ));
    }
    if rows != l.rows {
        return Err(ScanError::mismatch(
            log,
            "Number of Rows",
            format!("Number of Rows={} but the images are {rows} high", l.rows),
        ));
    }
    let white_level = 2f64.powi(l.depth_bits as i32);
    let intensity = if l.flat_field_corrected {
        Intensity::FlatCorrected { white_level }
    } else {
        Intensity::Raw { white_level }
    };
    Ok(Scan {
        format: Format::BrukerSkyscan,
        source: log.to_path_buf(),
        geometry: geometry(&l),
        views: Box::new(views),
        orientation: Orientation::TURNED,
        intensity,
        dark: None,
        flat: None,
        provenance: std::mem::take(&mut ini.taken),
        notes: l.notes,
    })
}
