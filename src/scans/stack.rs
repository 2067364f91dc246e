//! TIFF stacks with a ctrecon geometry: one multi-page file (`scan.tif` + `scan.json`) or a folder of one
//! file per view (sorted by the number in their names) with `geometry.json`. In a folder, files whose names
//! start with `dark` or `flat` (any case) are the dark and flat images, averaged.
//!
//! The geometry JSON is ctrecon's (`{"type": "cone", …}`, DESIGN.md §2) for the stored image with its rows
//! reversed ([`Orientation::ROWS_UP`]: image row 0 is the detector's top, ctrecon's row 0 its bottom);
//! columns are ctrecon's u as stored. Integer images are raw counts (white level `2^bits − 1` without a flat);
//! float images are transmissions.

use std::path::{Path, PathBuf};

use super::tiff_views::{TiffFiles, TiffPages, sample_kind};
use super::{
    Format, Intensity, Orientation, Provenance, Scan, ScanError, ViewSource, read_text, tiffs_in,
};
use crate::recon::geometry::Geometry;

/// The geometry JSON of a stack: `<stem>.json` beside a multi-page file, `geometry.json` in a folder.
pub fn geometry_file(path: &Path) -> PathBuf {
    if path.is_dir() {
        path.join("geometry.json")
    } else {
        path.with_extension("json")
    }
}

fn read_geometry(file: &Path) -> Result<Geometry, ScanError> {
    if !file.is_file() {
        return Err(ScanError::Missing {
            file: file.to_path_buf(),
            key: "geometry (a ctrecon geometry JSON beside the TIFFs)".into(),
        });
    }
    let text = read_text(file)?;
    let geometry: Geometry = serde_json::from_str(&text).map_err(|e| {
        ScanError::invalid(file, "geometry", "", format!("not a ctrecon geometry: {e}"))
    })?;
    if !geometry.is_3d() {
        return Err(ScanError::invalid(
            file,
            "type",
            "",
            "a TIFF stack needs a cone-beam geometry",
        ));
    }
    Ok(geometry)
}

/// Check `geometry` against the views' count and shape.
fn check(file: &Path, geometry: &Geometry, views: &dyn ViewSource) -> Result<(), ScanError> {
    let Geometry::Cone(g) = geometry else {
        return Err(ScanError::invalid(
            file,
            "type",
            "",
            "a TIFF stack needs a cone-beam geometry",
        ));
    };
    let (rows, cols) = views.shape();
    if g.angles.count() != views.view_count() {
        return Err(ScanError::mismatch(
            file,
            "angles",
            format!(
                "{} angles for {} views",
                g.angles.count(),
                views.view_count()
            ),
        ));
    }
    if g.detector.nu != cols {
        return Err(ScanError::mismatch(
            file,
            "detector.nu",
            format!("nu = {} but the images are {cols} wide", g.detector.nu),
        ));
    }
    if g.detector.nv != rows {
        return Err(ScanError::mismatch(
            file,
            "detector.nv",
            format!("nv = {} but the images are {rows} high", g.detector.nv),
        ));
    }
    Ok(())
}

/// The mean of the images in `files` (each `rows × cols`, every page of each).
fn mean_image(files: &[PathBuf], shape: (usize, usize)) -> Result<Option<Vec<f32>>, ScanError> {
    if files.is_empty() {
        return Ok(None);
    }
    let n = shape.0 * shape.1;
    let mut sum = vec![0f64; n];
    let mut buf = vec![0f32; n];
    let mut count = 0usize;
    for f in files {
        let mut pages = TiffPages::open(f)?;
        if pages.shape() != shape {
            return Err(ScanError::mismatch(
                f,
                "image size",
                "a dark or flat differs in size from the projections",
            ));
        }
        for p in 0..pages.view_count() {
            pages.read_view(p, &mut buf)?;
            for (s, &b) in sum.iter_mut().zip(&buf) {
                *s += f64::from(b);
            }
            count += 1;
        }
    }
    Ok(Some(
        sum.iter().map(|s| (s / count as f64) as f32).collect(),
    ))
}

fn is_reference(path: &Path, what: &str) -> bool {
    path.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.to_ascii_lowercase().starts_with(what))
}

/// Open a TIFF stack: a multi-page `.tif` file or a folder of TIFFs, with its geometry JSON.
pub fn open(path: &Path) -> Result<Scan, ScanError> {
    let gfile = geometry_file(path);
    let geometry = read_geometry(&gfile)?;
    let (views, first, dark, flat): (Box<dyn ViewSource>, PathBuf, _, _) = if path.is_dir() {
        let all = tiffs_in(path, "")?;
        let (refs, projections): (Vec<PathBuf>, Vec<PathBuf>) = all
            .into_iter()
            .partition(|p| is_reference(p, "dark") || is_reference(p, "flat"));
        let Some(first) = projections.first().cloned() else {
            return Err(ScanError::NotAScan {
                path: path.to_path_buf(),
                why: "no projection TIFFs in the folder".into(),
            });
        };
        let views = TiffFiles::open(projections)?;
        let shape = views.shape();
        let darks: Vec<PathBuf> = refs
            .iter()
            .filter(|p| is_reference(p, "dark"))
            .cloned()
            .collect();
        let flats: Vec<PathBuf> = refs
            .iter()
            .filter(|p| is_reference(p, "flat"))
            .cloned()
            .collect();
        (
            Box::new(views) as Box<dyn ViewSource>,
            first,
            mean_image(&darks, shape)?,
            mean_image(&flats, shape)?,
        )
    } else {
        (
            Box::new(TiffPages::open(path)?) as Box<dyn ViewSource>,
            path.to_path_buf(),
            None,
            None,
        )
    };
    check(&gfile, &geometry, views.as_ref())?;
    let (bits, float) = sample_kind(&first)?;
    let intensity = if float {
        Intensity::Transmission
    } else {
        Intensity::Raw {
            white_level: 2f64.powi(bits as i32) - 1.0,
        }
    };
    let provenance = vec![Provenance {
        key: "geometry".into(),
        value: serde_json::to_string(&geometry).unwrap_or_default(),
        origin: gfile
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
    }];
    Ok(Scan {
        format: Format::TiffStack,
        source: path.to_path_buf(),
        geometry,
        views,
        orientation: Orientation::ROWS_UP,
        intensity,
        dark,
        flat,
        provenance,
        notes: Vec::new(),
    })
}
