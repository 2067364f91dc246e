//! Nikon XT H / Inspect-X scans: a `.xtekct` file (section `[XTekCT]`), projections `<Name>_0001.tif`, … in
//! `InputFolderName` (or beside the `.xtekct`), angles from `<Name>_ctdata.txt` or `<Name>.ang` when present,
//! else `InitialAngle + i·AngularStep`. The TIFFs are flat-corrected: `value / WhiteLevel` is the
//! transmission.
//!
//! Geometry, following CIL's `NikonDataReader` (source at `(0, −SrcToObject)`, rotation axis at
//! `(−ObjectOffsetX, 0)`, detector centre at `(−DetectorOffsetX, SrcToDetector − SrcToObject,
//! DetectorOffsetY)`, image column 0 at the panel's right and row 0 at its top, CIL angle
//! `θ = −(angle) + 180°` where `angle = InitialAngle + i·AngularStep`) and CIL's conversion to vectors (the
//! system turns by `−θ` about z):
//! - the image is turned by 180° ([`Orientation::TURNED`]) so that ctrecon's u runs along CIL's panel x and
//!   v along +z;
//! - ctrecon's view angle is `β = angle − 180°` (Nikon's angle increasing = ctrecon's source turning
//!   counter-clockwise seen from +z);
//! - `offset_u = ObjectOffsetX · SrcToDetector / SrcToObject − DetectorOffsetX` (the centre of the panel
//!   relative to where the rotation axis projects), `offset_v = DetectorOffsetY`. Without `ObjectOffsetX`
//!   (older files) it is `(CentreOfRotationTop + CentreOfRotationBottom)/2 · SrcToObject / SrcToDetector`.
//!
//! ctrecon's cone beam puts the source on the line through the axis perpendicular to the panel; Nikon's
//! source sits `ObjectOffsetX` beside that line. The mapping is exact up to a rigid turn of the volume by
//! `atan(ObjectOffsetX / SrcToObject)` and a panel tilt of the same angle (negligible for offsets of a few
//! pixels). Object tilt/roll and a centre of rotation that differs top to bottom are listed in
//! [`Scan::notes`], not applied.

use std::path::{Path, PathBuf};

use super::ini::Ini;
use super::tiff_views::TiffFiles;
use super::{
    Format, Intensity, MAX_VIEW_PIXELS, Orientation, Provenance, Scan, ScanError, ViewSource,
    read_text, tiffs_in,
};
use crate::recon::geometry::angles::MAX_VIEWS;
use crate::recon::geometry::{Angles, ConeBeam, Geometry, Panel};
use crate::recon::grid::MAX_AXIS;

const SECTION: &str = "XTekCT";

/// The numbers of a `.xtekct` that ctrecon uses, as read.
#[derive(Debug, Clone, PartialEq)]
pub struct Xtek {
    pub name: String,
    pub input_folder: Option<String>,
    pub projections: usize,
    pub pixels_x: usize,
    pub pixels_y: usize,
    pub pixel_x_mm: f64,
    pub pixel_y_mm: f64,
    pub src_to_object_mm: f64,
    pub src_to_detector_mm: f64,
    pub initial_angle_deg: f64,
    pub angular_step_deg: f64,
    /// `ObjectOffsetX`, or the one derived from `CentreOfRotationTop/Bottom`.
    pub object_offset_x_mm: f64,
    pub detector_offset_x_mm: f64,
    pub detector_offset_y_mm: f64,
    pub white_level: f64,
    pub notes: Vec<String>,
}

/// Read the `[XTekCT]` keys ctrecon needs from a parsed `.xtekct`.
pub fn parse(ini: &mut Ini) -> Result<Xtek, ScanError> {
    let file = ini.file.clone();
    if !ini.has_section(SECTION) {
        return Err(ScanError::NotAScan {
            path: file,
            why: "no [XTekCT] section".into(),
        });
    }
    let s = SECTION;
    if let Some(units) = ini.text(s, "Units")
        && !units.eq_ignore_ascii_case("mm")
    {
        return Err(ScanError::invalid(
            &file,
            "Units",
            &units,
            "only mm is read",
        ));
    }
    let name = ini.text(s, "Name").ok_or_else(|| ini.missing("Name"))?;
    if name.is_empty() || name.contains(['/', '\\']) {
        return Err(ScanError::invalid(
            &file,
            "Name",
            &name,
            "not a file name prefix",
        ));
    }
    let input_folder = ini.text(s, "InputFolderName").filter(|f| !f.is_empty());
    let projections = ini.count(s, "Projections", MAX_VIEWS)?;
    let pixels_x = ini.count(s, "DetectorPixelsX", MAX_AXIS)?;
    let pixels_y = ini.count(s, "DetectorPixelsY", MAX_AXIS)?;
    if pixels_x * pixels_y > MAX_VIEW_PIXELS {
        return Err(ScanError::Limit {
            file,
            what: format!("DetectorPixelsX × DetectorPixelsY = {pixels_x} × {pixels_y}"),
        });
    }
    let pixel_x_mm = ini.positive(s, "DetectorPixelSizeX")?;
    let pixel_y_mm = ini.positive(s, "DetectorPixelSizeY")?;
    let src_to_object_mm = ini.positive(s, "SrcToObject")?;
    let src_to_detector_mm = ini.positive(s, "SrcToDetector")?;
    if src_to_detector_mm <= src_to_object_mm {
        return Err(ScanError::invalid(
            &file,
            "SrcToDetector",
            &src_to_detector_mm.to_string(),
            format!("must exceed SrcToObject ({src_to_object_mm})"),
        ));
    }
    let initial_angle_deg = ini.number(s, "InitialAngle")?.unwrap_or(0.0);
    let angular_step_deg = ini.required(s, "AngularStep")?;
    let white_level = ini.positive(s, "WhiteLevel")?;
    let detector_offset_x_mm = ini.number(s, "DetectorOffsetX")?.unwrap_or(0.0);
    let detector_offset_y_mm = ini.number(s, "DetectorOffsetY")?.unwrap_or(0.0);
    let mut notes = Vec::new();
    let cor_top = ini.number(s, "CentreOfRotationTop")?;
    let cor_bottom = ini.number(s, "CentreOfRotationBottom")?;
    let object_offset_x_mm = match ini.number(s, "ObjectOffsetX")? {
        Some(x) => x,
        None => {
            let (t, b) = (cor_top.unwrap_or(0.0), cor_bottom.unwrap_or(0.0));
            (t + b) / 2.0 * src_to_object_mm / src_to_detector_mm
        }
    };
    if let (Some(t), Some(b)) = (cor_top, cor_bottom)
        && t != b
    {
        notes.push(format!(
            "CentreOfRotationTop {t} ≠ CentreOfRotationBottom {b}: the axis tilt is not applied"
        ));
    }
    for key in ["ObjectTilt", "ObjectRoll", "ObjectOffsetY"] {
        if let Some(x) = ini.number(s, key)?
            && x != 0.0
        {
            notes.push(format!("{key} = {x} is not applied"));
        }
    }
    Ok(Xtek {
        name,
        input_folder,
        projections,
        pixels_x,
        pixels_y,
        pixel_x_mm,
        pixel_y_mm,
        src_to_object_mm,
        src_to_detector_mm,
        initial_angle_deg,
        angular_step_deg,
        object_offset_x_mm,
        detector_offset_x_mm,
        detector_offset_y_mm,
        white_level,
        notes,
    })
}

/// `(projection number, angle in degrees)` rows of a `_ctdata.txt` (tab-separated columns: projection,
/// angle, …) or `.ang` (`Projection N: angle`) file: every line whose first number is a whole number
/// followed by a number. Header lines have no such pair.
pub fn parse_angle_rows(text: &str) -> Vec<(u64, f64)> {
    text.lines()
        .filter_map(|line| {
            let line = line.replace(':', " ");
            let mut tokens = line
                .split_whitespace()
                .skip_while(|t| t.parse::<u64>().is_err());
            let n = tokens.next()?.parse::<u64>().ok()?;
            let a = tokens
                .next()?
                .parse::<f64>()
                .ok()
                .filter(|a| a.is_finite())?;
            Some((n, a))
        })
        .collect()
}

/// ctrecon's geometry for a `.xtekct`, with `listed` angles (degrees, Nikon's) when an angle file gave them.
pub fn geometry(x: &Xtek, listed: Option<&[f64]>) -> Geometry {
    let angles = match listed {
        Some(a) => Angles::List {
            degrees: a.iter().map(|d| d - 180.0).collect(),
        },
        None => Angles::Uniform {
            count: x.projections,
            start_deg: x.initial_angle_deg - 180.0,
            range_deg: Some(x.angular_step_deg * x.projections as f64),
            short_scan: false,
        },
    };
    let magnification = x.src_to_detector_mm / x.src_to_object_mm;
    Geometry::Cone(ConeBeam {
        angles,
        dso_mm: x.src_to_object_mm,
        dsd_mm: x.src_to_detector_mm,
        detector: Panel {
            nu: x.pixels_x,
            nv: x.pixels_y,
            du_mm: x.pixel_x_mm,
            dv_mm: x.pixel_y_mm,
            offset_u_mm: x.object_offset_x_mm * magnification - x.detector_offset_x_mm,
            offset_v_mm: x.detector_offset_y_mm,
        },
    })
}

/// The angle file beside the `.xtekct`: `<Name>_ctdata.txt`, else `<Name>.ang`.
fn angle_file(dir: &Path, name: &str) -> Option<PathBuf> {
    [format!("{name}_ctdata.txt"), format!("{name}.ang")]
        .into_iter()
        .map(|f| dir.join(f))
        .find(|p| p.is_file())
}

/// Read the angle list of `file`, checked against `Projections`.
fn listed_angles(file: &Path, x: &Xtek) -> Result<Vec<f64>, ScanError> {
    let rows = parse_angle_rows(&read_text(file)?);
    if rows.len() != x.projections {
        return Err(ScanError::mismatch(
            file,
            "Projections",
            format!(
                "{} angles listed, the .xtekct has Projections={}",
                rows.len(),
                x.projections
            ),
        ));
    }
    if rows.windows(2).any(|w| w[1].0 <= w[0].0) {
        return Err(ScanError::invalid(
            file,
            "projection number",
            "",
            "projection numbers must increase line by line",
        ));
    }
    Ok(rows.into_iter().map(|(_, a)| a).collect())
}

/// Open a Nikon scan from its `.xtekct` file.
pub fn open(xtekct: &Path) -> Result<Scan, ScanError> {
    let mut ini = Ini::parse(xtekct, &read_text(xtekct)?);
    let mut x = parse(&mut ini)?;
    let dir = xtekct.parent().unwrap_or(Path::new(".")).to_path_buf();
    // Inspect-X writes the acquisition machine's absolute folder; the TIFFs usually travel beside the file.
    let folder = match &x.input_folder {
        Some(f) if dir.join(f).is_dir() => dir.join(f),
        Some(f) => {
            x.notes.push(format!(
                "InputFolderName {f:?} not found: projections read beside the .xtekct"
            ));
            dir.clone()
        }
        None => dir.clone(),
    };
    let mut provenance = std::mem::take(&mut ini.taken);
    let listed = match angle_file(&dir, &x.name) {
        Some(f) => {
            let a = listed_angles(&f, &x)?;
            provenance.push(Provenance {
                key: "angles".into(),
                value: format!("{} angles, {} … {}°", a.len(), a[0], a[a.len() - 1]),
                origin: f
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            });
            Some(a)
        }
        None => None,
    };
    let files = tiffs_in(&folder, &format!("{}_", x.name))?;
    if files.len() != x.projections {
        return Err(ScanError::mismatch(
            xtekct,
            "Projections",
            format!(
                "Projections={} but {} files {}_*.tif in {}",
                x.projections,
                files.len(),
                x.name,
                folder.display()
            ),
        ));
    }
    let views = TiffFiles::open(files)?;
    let (rows, cols) = views.shape();
    if cols != x.pixels_x {
        return Err(ScanError::mismatch(
            xtekct,
            "DetectorPixelsX",
            format!(
                "DetectorPixelsX={} but the images are {cols} wide",
                x.pixels_x
            ),
        ));
    }
    if rows != x.pixels_y {
        return Err(ScanError::mismatch(
            xtekct,
            "DetectorPixelsY",
            format!(
                "DetectorPixelsY={} but the images are {rows} high",
                x.pixels_y
            ),
        ));
    }
    let geometry = geometry(&x, listed.as_deref());
    Ok(Scan {
        format: Format::NikonXtek,
        source: xtekct.to_path_buf(),
        geometry,
        views: Box::new(views),
        orientation: Orientation::TURNED,
        intensity: Intensity::FlatCorrected {
            white_level: x.white_level,
        },
        dark: None,
        flat: None,
        provenance,
        notes: x.notes,
    })
}
