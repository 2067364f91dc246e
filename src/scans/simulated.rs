//! A simulated scan written as a Nikon XT H scanner writes one: `<name>.xtekct` and `<name>_0001.tif`, …
//! (16-bit, flat-corrected: `WhiteLevel · e^(−line integral)`), with the angles in `<name>_ctdata.txt` when
//! they are not equally spaced. It is the exact inverse of [`super::nikon`]'s mapping: images turned by
//! 180°, Nikon angle = ctrecon's β + 180°, `DetectorOffsetY` = the panel's v offset.
//!
//! The panel's u offset is deliberately not written: a scan whose axis does not project onto the panel's
//! centre column, with no calibrated centre in its file, is what the import's centre search is for.

use std::io::BufWriter;
use std::path::{Path, PathBuf};

use ndarray::ArrayView3;
use tiff::encoder::{TiffEncoder, colortype::Gray16};

use super::{Orientation, ScanError};
use crate::recon::geometry::{Angles, Geometry};

/// The white level written (`value / WhiteLevel` is the transmission).
pub const WHITE_LEVEL: f64 = 60_000.0;

/// What [`write_nikon`] wrote.
#[derive(Debug, Clone)]
pub struct Written {
    pub xtekct: PathBuf,
    pub tiffs: usize,
    /// Pixels whose intensity was clipped to the 16-bit range (0 is never reached for finite data).
    pub clipped: usize,
}

fn err(file: &Path, what: impl Into<String>) -> ScanError {
    ScanError::Unsupported {
        file: file.to_path_buf(),
        what: what.into(),
    }
}

/// Write `projections` (`[view][v][u]` line integrals measured with `geometry`, a cone beam) as a Nikon XT H
/// scan named by `xtekct` (`…/<name>.xtekct`; the TIFFs go beside it).
pub fn write_nikon(
    xtekct: &Path,
    geometry: &Geometry,
    projections: ArrayView3<'_, f32>,
) -> Result<Written, ScanError> {
    let Geometry::Cone(cone) = geometry else {
        return Err(err(
            xtekct,
            "a Nikon scan is a circular cone beam: give a geometry of type cone",
        ));
    };
    let name = xtekct
        .file_stem()
        .and_then(|s| s.to_str())
        .filter(|s| !s.is_empty())
        .ok_or_else(|| err(xtekct, "the .xtekct needs a file name"))?
        .to_string();
    let dir = xtekct.parent().unwrap_or(Path::new(".")).to_path_buf();
    let p = &cone.detector;
    let (n, nv, nu) = projections.dim();
    if (nv, nu) != (p.nv, p.nu) {
        return Err(ScanError::mismatch(
            xtekct,
            "detector",
            format!("projections are {nv} × {nu}, the panel {} × {}", p.nv, p.nu),
        ));
    }
    let (initial, step, listed) = match &cone.angles {
        Angles::Uniform {
            count,
            start_deg,
            range_deg,
            short_scan: false,
        } => {
            let range = range_deg.unwrap_or(360.0);
            (start_deg + 180.0, range / *count as f64, None)
        }
        Angles::List { degrees } => {
            let step = if degrees.len() > 1 {
                (degrees[degrees.len() - 1] - degrees[0]) / (degrees.len() - 1) as f64
            } else {
                0.0
            };
            (degrees[0] + 180.0, step, Some(degrees.clone()))
        }
        Angles::Uniform { .. } => {
            return Err(err(
                xtekct,
                "a short scan's angles: list them ({\"degrees\": […]})",
            ));
        }
    };
    std::fs::create_dir_all(&dir).map_err(|e| ScanError::io(&dir, e))?;
    let text = format!(
        "[XTekCT]\r\nName={name}\r\nInputFolderName=\r\nUnits=mm\r\nProjections={n}\r\nDetectorPixelsX={nu}\r\n\
         DetectorPixelsY={nv}\r\nDetectorPixelSizeX={}\r\nDetectorPixelSizeY={}\r\nSrcToObject={}\r\n\
         SrcToDetector={}\r\nInitialAngle={initial}\r\nAngularStep={step}\r\nDetectorOffsetX=0\r\n\
         DetectorOffsetY={}\r\nWhiteLevel={WHITE_LEVEL}\r\n",
        p.du_mm, p.dv_mm, cone.dso_mm, cone.dsd_mm, p.offset_v_mm
    );
    std::fs::write(xtekct, text).map_err(|e| ScanError::io(xtekct, e))?;
    if let Some(degrees) = listed {
        let file = dir.join(format!("{name}_ctdata.txt"));
        let mut rows = String::from("Projection\tAngle(deg)\r\n");
        for (k, b) in degrees.iter().enumerate() {
            rows.push_str(&format!("{}\t{}\r\n", k + 1, b + 180.0));
        }
        std::fs::write(&file, rows).map_err(|e| ScanError::io(&file, e))?;
    }
    let mut clipped = 0;
    let mut image = vec![0.0f32; nv * nu];
    let mut pixels = vec![0u16; nv * nu];
    for (k, view) in projections.outer_iter().enumerate() {
        let flat: Vec<f32> = view.iter().copied().collect();
        // The turn by 180° is its own inverse.
        Orientation::TURNED.apply(&flat, nv, nu, &mut image);
        for (px, &p) in pixels.iter_mut().zip(&image) {
            let i = (WHITE_LEVEL * (-f64::from(p)).exp()).round();
            if !(0.0..=65535.0).contains(&i) {
                clipped += 1;
            }
            *px = i.clamp(0.0, 65535.0) as u16;
        }
        let file = dir.join(format!("{name}_{:04}.tif", k + 1));
        let out = std::fs::File::create(&file).map_err(|e| ScanError::io(&file, e))?;
        let tiff_err = |e: tiff::TiffError| ScanError::Tiff {
            file: file.clone(),
            message: e.to_string(),
        };
        TiffEncoder::new(BufWriter::new(out))
            .map_err(tiff_err)?
            .write_image::<Gray16>(nu as u32, nv as u32, &pixels)
            .map_err(tiff_err)?;
    }
    Ok(Written {
        xtekct: xtekct.to_path_buf(),
        tiffs: n,
        clipped,
    })
}
