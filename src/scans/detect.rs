//! Format detection: a path (a metadata file, a TIFF, or a folder holding one) to the right reader.

use std::path::{Path, PathBuf};

use super::{Scan, ScanError, bruker, nikon, nxtomo, stack, zeiss};

/// The extensions of the files a scan is opened from (lower case).
pub const EXTENSIONS: [&str; 10] = [
    "xtekct", "log", "txrm", "xrm", "nx", "nxs", "h5", "hdf5", "tif", "tiff",
];

/// Whether `path` names a file a scan is opened from, by its extension (any case).
pub fn is_scan_file(path: &Path) -> bool {
    EXTENSIONS.contains(&extension(path).as_str())
}

/// The extensions of NeXus (HDF5) files, opened as NXtomo.
const NEXUS: [&str; 4] = ["nx", "nxs", "h5", "hdf5"];

fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// Files of `dir` with extension `ext` (lower case), sorted by name (shortest first: SkyScan folders hold
/// the scan's `.log` and longer-named logs of reconstructions).
fn with_extension(dir: &Path, ext: &str) -> Result<Vec<PathBuf>, ScanError> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| ScanError::io(dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && extension(p) == ext)
        .collect();
    out.sort_by_key(|p| (p.as_os_str().len(), p.clone()));
    Ok(out)
}

/// Open a scan: `.xtekct` (Nikon), `.txrm`/`.xrm` (Zeiss Xradia), `.nx`/`.nxs`/`.h5`/`.hdf5` (NeXus
/// NXtomo), `.log` (Bruker SkyScan), `.tif`/`.tiff` (a multi-page stack with `<stem>.json`), or a folder
/// holding one of these, looked for in that order (else a folder of TIFFs with `geometry.json`). A folder's `.txrm` comes before its `.xrm` files (a
/// tomography beside single images such as a separate reference).
pub fn open(path: &Path) -> Result<Scan, ScanError> {
    if path.is_dir() {
        if let Some(x) = with_extension(path, "xtekct")?.first() {
            return nikon::open(x);
        }
        for ext in ["txrm", "xrm"] {
            if let Some(z) = with_extension(path, ext)?.first() {
                return zeiss::open(z);
            }
        }
        for ext in NEXUS {
            if let Some(n) = with_extension(path, ext)?.first() {
                return nxtomo::open(n);
            }
        }
        if let Some(l) = with_extension(path, "log")?.first() {
            return bruker::open(l);
        }
        return stack::open(path);
    }
    match extension(path).as_str() {
        "xtekct" => nikon::open(path),
        "log" => bruker::open(path),
        "txrm" | "xrm" => zeiss::open(path),
        "nx" | "nxs" | "h5" | "hdf5" => nxtomo::open(path),
        "tif" | "tiff" => stack::open(path),
        _ if !path.exists() => Err(ScanError::NotAScan {
            path: path.to_path_buf(),
            why: "no such file or folder".into(),
        }),
        other => Err(ScanError::NotAScan {
            path: path.to_path_buf(),
            why: format!(
                "unknown extension {other:?} (ctrecon reads .xtekct, Zeiss .txrm/.xrm, NXtomo \
                 .nx/.nxs/.h5/.hdf5, SkyScan .log, .tif/.tiff or a folder of them)"
            ),
        }),
    }
}
