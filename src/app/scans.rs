//! Importing a scan as the scanner wrote it (`POST /v1/scans`): the received files (ZIPs inflated member by
//! member under the ZIP caps, names sanitised) are laid out in a scratch folder under the data directory,
//! opened by [`crate::scans::open`] (the format detected as the CLI does), and converted view by view into a
//! float32 `.npy` (`[view][v][u]`, line integrals in ctrecon's detector order) written as a stream: the header
//! with the known shape, then each view as it is converted. At most two views are held at once (the one read
//! and converted in place, the one oriented for writing) besides the scan's dark and flat. Nothing is left
//! behind on failure: the scratch folder and the partial file are removed.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde_json::json;
use sha2::{Digest, Sha256};

use super::App;
use super::uploads::ReceivedFile;
use crate::dicom::{Unpacked, UploadFile, ZipLimits, is_zip, unpack_file};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::{ScanRecord, ScanValue};
use crate::recon::geometry::Geometry;
use crate::recon::prep::PrepPlan;
use crate::scans::calibrate::{CentrePolicy, NpyViews, calibrate};
use crate::scans::{
    Normalisation, Scan, ScanError, TRANSMISSION_FLOOR, ViewConverter, convert::Normalisation as N,
};
use crate::storage::npy::hex;
use crate::storage::{BlobStore, TempBlob};

/// Most files one scan may have once unpacked.
pub const MAX_SCAN_FILES: usize = 20_000;

/// A scan converted to a dataset file still in `tmp/`, with what its dataset row records.
#[derive(Debug)]
pub struct ImportedScan {
    pub temp: TempBlob,
    pub bytes: u64,
    pub sha256: String,
    pub shape: Vec<usize>,
    pub geometry: Geometry,
    pub record: ScanRecord,
}

fn invalid(detail: impl Into<String>) -> Problem {
    Problem::new(ErrorCode::ScanInvalid, detail)
}

/// The relative path a client's file name is laid out at: `/` and `\` separate folders, empty and `.`
/// components are dropped, control characters replaced; `None` for a name with a `..` component or nothing
/// left (never an absolute path: a leading `/` or drive is dropped with the empty component).
pub fn sanitise(name: &str) -> Option<PathBuf> {
    let mut out = PathBuf::new();
    for part in name.split(['/', '\\']) {
        let part: String = part
            .chars()
            .map(|c| if c.is_control() || c == ':' { '_' } else { c })
            .take(200)
            .collect();
        match part.as_str() {
            "" | "." => {}
            ".." => return None,
            p => out.push(p),
        }
    }
    (!out.as_os_str().is_empty()).then_some(out)
}

/// Move `from` to `root/<sanitised label>`, refusing unsafe or repeated names.
fn place(root: &Path, label: &str, from: &Path) -> Result<(), Problem> {
    let rel = sanitise(label)
        .ok_or_else(|| invalid(format!("{label:?}: not a file name a scan may use")))?;
    let dest = root.join(&rel);
    if dest.exists() {
        return Err(invalid(format!(
            "{label:?}: the upload has this file twice"
        )));
    }
    if let Some(parent) = dest.parent() {
        std::fs::create_dir_all(parent).map_err(|e| {
            // A component that is already a file: the client's names collide.
            invalid(format!("{label:?}: cannot be laid out ({e})"))
        })?;
    }
    std::fs::rename(from, &dest).map_err(|e| {
        tracing::error!(error = %e, "moving a scan file into its scratch folder failed");
        Problem::internal()
    })
}

/// The folder to open: `root`, or the one folder it holds when it holds nothing else (a ZIP of a folder).
fn scan_root(mut root: PathBuf) -> PathBuf {
    loop {
        let Ok(entries) = std::fs::read_dir(&root) else {
            return root;
        };
        let entries: Vec<PathBuf> = entries.filter_map(|e| e.ok().map(|e| e.path())).collect();
        match entries.as_slice() {
            [only] if only.is_dir() => root = only.clone(),
            _ => return root,
        }
    }
}

/// Whether `root` holds a file a scan reader starts from (`.xtekct`, `.txrm`, `.xrm`, `.nx`, `.nxs`, `.h5`,
/// `.hdf5`, `.log`, `.tif`, `.tiff`).
fn recognisable(root: &Path) -> bool {
    std::fs::read_dir(root).is_ok_and(|entries| {
        entries
            .filter_map(Result::ok)
            .any(|e| crate::scans::detect::is_scan_file(&e.path()))
    })
}

/// The problem of a scan that cannot be read, its paths given relative to the uploaded folder.
fn scan_problem(e: &ScanError, root: &Path) -> Problem {
    let code = match e {
        ScanError::NotAScan { .. } => ErrorCode::ScanNotRecognised,
        ScanError::Unsupported { .. } => ErrorCode::ScanUnsupported,
        ScanError::Limit { .. } => ErrorCode::ArrayTooLarge,
        _ => ErrorCode::ScanInvalid,
    };
    let text = e.to_string();
    let prefix = format!("{}{}", root.display(), std::path::MAIN_SEPARATOR);
    let text = text
        .replace(&prefix, "")
        .replace(&root.display().to_string(), "the upload");
    Problem::new(code, text)
}

fn normalise_step(n: Normalisation) -> serde_json::Value {
    match n {
        N::DarkFlat => json!({"step": "normalise", "dark": true, "flat": true}),
        N::Flat => json!({"step": "normalise", "dark": false, "flat": true}),
        N::WhiteLevel(w) => json!({"step": "normalise", "white_level": w}),
    }
}

/// Lay `files` out in `folder`: ZIPs inflated (under `limits`), other files moved as they are.
fn lay_out(
    files: Vec<ReceivedFile>,
    folder: &Path,
    scratch: &Path,
    limits: &ZipLimits,
) -> Result<(), Problem> {
    let internal = |e: &dyn std::fmt::Display| {
        tracing::error!(error = %e, "unpacking a scan failed");
        Problem::internal()
    };
    let mut unpacked = Unpacked::default();
    for f in files {
        let zip = is_zip(f.temp.path()).map_err(|e| internal(&e))?;
        if !zip {
            place(folder, &f.label, f.temp.path())?;
            continue;
        }
        let file = UploadFile {
            label: f.label.clone(),
            path: f.temp.path().to_path_buf(),
        };
        let first = unpacked.files.len();
        unpack_file(file, limits, scratch, &mut unpacked).map_err(|e| internal(&e))?;
        if let Some(r) = unpacked.rejected.first() {
            return Err(Problem::new(
                ErrorCode::from(&r.error),
                format!("{}: {}", r.label, r.error),
            ));
        }
        if unpacked.files.len() > MAX_SCAN_FILES {
            return Err(invalid(format!(
                "more than {MAX_SCAN_FILES} files in the upload"
            )));
        }
        for m in &unpacked.files[first..] {
            place(folder, &m.label, &m.path)?;
        }
    }
    Ok(())
}

impl App {
    /// Import the scan in `files` (on disk; ZIPs or the scan's own files) as a float32 dataset file in
    /// `tmp/`, on the compute pool. Bad input is a 4xx problem naming the file (and key).
    pub async fn import_scan(
        &self,
        files: Vec<ReceivedFile>,
        centre: CentrePolicy,
        plan: PrepPlan,
    ) -> Result<ImportedScan, Problem> {
        let store = self.store.clone();
        let s = &self.settings;
        let limits = ZipLimits {
            max_total_bytes: s.zip_max_total_bytes,
            max_ratio: s.zip_max_ratio,
            max_member_bytes: s.zip_max_member_bytes,
            max_entries: MAX_SCAN_FILES,
        };
        let max_values = super::limits::max_array_values(s).min(s.max_upload_bytes / 4);
        self.engine
            .compute(move || import(&store, files, &limits, max_values, centre, &plan))
            .await
    }
}

/// [`App::import_scan`], blocking.
pub fn import(
    store: &BlobStore,
    files: Vec<ReceivedFile>,
    limits: &ZipLimits,
    max_values: u64,
    centre: CentrePolicy,
    plan: &PrepPlan,
) -> Result<ImportedScan, Problem> {
    let internal = |e: std::io::Error| {
        tracing::error!(error = %e, "importing a scan failed");
        Problem::internal()
    };
    let scratch = store.scratch().map_err(internal)?;
    let folder = scratch.path().join("scan");
    let members = scratch.path().join("zip");
    std::fs::create_dir(&folder).map_err(internal)?;
    std::fs::create_dir(&members).map_err(internal)?;
    lay_out(files, &folder, &members, limits)?;
    let root = scan_root(folder.clone());
    if !recognisable(&root) {
        return Err(Problem::new(
            ErrorCode::ScanNotRecognised,
            "no .xtekct (Nikon), .txrm/.xrm (Zeiss), .nx/.nxs/.h5/.hdf5 (NXtomo), .log (SkyScan) or \
             .tif/.tiff file in the upload's folder",
        ));
    }
    let mut scan = crate::scans::open(&root).map_err(|e| scan_problem(&e, &folder))?;
    let (nv, nu) = scan.views.shape();
    let n = scan.views.view_count();
    let values = (n as u64)
        .saturating_mul(nv as u64)
        .saturating_mul(nu as u64);
    if values > max_values {
        return Err(Problem::new(
            ErrorCode::ArrayTooLarge,
            format!("{n} views of {nu} × {nv} are {values} values, the limit is {max_values}"),
        ));
    }
    let shape = vec![n, nv, nu];
    let expected = scan
        .geometry
        .to_views()
        .map(|v| v.data_shape())
        .map_err(|e| invalid(format!("the scan's geometry: {e}")))?;
    if expected != shape {
        return Err(invalid(format!(
            "the geometry expects projections {expected:?}, the images are {shape:?}"
        )));
    }
    let asked = |e: crate::recon::ReconError| {
        Problem::new(ErrorCode::InvalidParameter, format!("preprocessing: {e}"))
    };
    plan.check(n, nv, nu).map_err(asked)?;
    let kept = plan.kept_views(n).map_err(asked)?;
    let (pv, pu) = plan.view_shape(nv, nu).map_err(asked)?;
    let scan_geometry = plan.geometry(&scan.geometry).map_err(asked)?;
    let shape = vec![kept.len(), pv, pu];
    let temp = store.temp();
    let (bytes, sha256, counts, normalisation) =
        write_views(&mut scan, temp.path(), &kept, [nv, nu], &shape, plan).map_err(
            |e| match e {
                Written::Scan(e) => scan_problem(&e, &folder),
                Written::Io(e) => internal(e),
                Written::Prep(e) => asked(e),
            },
        )?;
    // The centre of rotation, from the views just written (read back one at a time where needed).
    let views = std::fs::File::open(temp.path()).map_err(internal)?;
    let header = crate::storage::npy::f32_header(&shape).len() as u64;
    let source = NpyViews::new(views, header, [shape[0], shape[1], shape[2]]);
    let mut geometry = scan_geometry;
    let calibration = calibrate(&mut geometry, &source, &scan.provenance, centre)
        .map_err(|e| invalid(format!("calibrating the centre of rotation: {e}")))?;
    let record = ScanRecord {
        format: scan.format.to_string(),
        provenance: scan
            .provenance
            .iter()
            .map(|p| ScanValue {
                key: p.key.clone(),
                value: p.value.clone(),
                origin: p.origin.clone(),
            })
            .collect(),
        notes: scan.notes.clone(),
        preprocessing: [
            Some(normalise_step(normalisation)),
            // The scanner's motion correction (Zeiss alignment shifts), on the transmissions.
            (counts.shifted_views > 0)
                .then(|| json!({"step": "align", "shifted_views": counts.shifted_views})),
            Some(
                json!({"step": "minus_log", "floor": TRANSMISSION_FLOOR, "clamped_pixels": counts.clamped}),
            ),
            Some(json!({"step": "orient", "flip_rows": scan.orientation.flip_rows,
                   "flip_cols": scan.orientation.flip_cols})),
        ]
        .into_iter()
        .flatten()
        .chain(plan.steps(n, kept.len()))
        .collect(),
        calibration: Some(calibration),
    };
    Ok(ImportedScan {
        temp,
        bytes,
        sha256,
        shape,
        geometry,
        record,
    })
}

enum Written {
    Scan(ScanError),
    Io(std::io::Error),
    Prep(crate::recon::ReconError),
}

/// Pixels clamped and views moved by the scanner's alignment while converting.
struct Counts {
    clamped: u64,
    shifted_views: u64,
}

/// Stream the `kept` views of `scan` (`nv × nu` each), converted and put through `plan`, as a float32
/// `.npy` of `shape` to `path` (synced); then the plan's stripe pass, a block of detector rows at a time.
/// Answers the file's size, SHA-256, the clamped pixels and shifted views, and the normalisation used.
fn write_views(
    scan: &mut Scan,
    path: &Path,
    kept: &[usize],
    [nv, nu]: [usize; 2],
    shape: &[usize],
    plan: &PrepPlan,
) -> Result<(u64, String, Counts, Normalisation), Written> {
    let io = Written::Io;
    // Read and write: the stripe pass reads the views back.
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(true)
        .open(path)
        .map_err(io)?;
    let mut out = std::io::BufWriter::with_capacity(64 << 10, file);
    let header = crate::storage::npy::f32_header(shape);
    out.write_all(&header).map_err(io)?;
    let mut conv = ViewConverter::new(scan);
    let mut view = vec![0f32; nv * nu];
    let mut bytes = Vec::with_capacity(64 << 10);
    for &i in kept {
        conv.convert(scan, i, &mut view).map_err(Written::Scan)?;
        let raw = ndarray::ArrayView2::from_shape((nv, nu), &view)
            .map_err(|e| Written::Io(std::io::Error::other(e)))?;
        let done = if plan.is_empty() {
            None
        } else {
            Some(plan.apply_view(raw).map_err(Written::Prep)?)
        };
        let values: Vec<f32>;
        let slice: &[f32] = match &done {
            None => &view,
            Some(a) => match a.as_slice() {
                Some(s) => s,
                None => {
                    values = a.iter().copied().collect();
                    &values
                }
            },
        };
        for chunk in slice.chunks(16 << 10) {
            bytes.clear();
            for v in chunk {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            out.write_all(&bytes).map_err(io)?;
        }
    }
    let file = out.into_inner().map_err(|e| Written::Io(e.into_error()))?;
    if plan.stripes.is_some() {
        stripe_pass(&file, header.len() as u64, shape, plan)?;
    }
    file.sync_all().map_err(io)?;
    drop(file);
    let (written, sha256) = hash_file(path).map_err(io)?;
    Ok((
        written,
        sha256,
        Counts {
            clamped: conv.clamped,
            shifted_views: conv.shifted_views,
        },
        conv.normalisation(),
    ))
}

/// The plan's stripe suppression on the float32 `[view][v][u]` values after `header` bytes of `file`, in
/// place: blocks of detector rows of every view ([`PrepPlan::stripe_rows`]), read, filtered and written
/// back.
fn stripe_pass(
    file: &std::fs::File,
    header: u64,
    shape: &[usize],
    plan: &PrepPlan,
) -> Result<(), Written> {
    use std::os::unix::fs::FileExt;
    let [n, nv, nu] = [shape[0], shape[1], shape[2]];
    let rows = PrepPlan::stripe_rows(n, nu).min(nv);
    let mut bytes = Vec::new();
    let mut v0 = 0;
    while v0 < nv {
        let r = rows.min(nv - v0);
        let mut block = ndarray::Array3::<f32>::zeros((n, r, nu));
        bytes.resize(r * nu * 4, 0);
        for k in 0..n {
            let at = header + ((k * nv + v0) * nu * 4) as u64;
            file.read_exact_at(&mut bytes, at).map_err(Written::Io)?;
            for (d, b) in block
                .index_axis_mut(ndarray::Axis(0), k)
                .iter_mut()
                .zip(bytes.chunks_exact(4))
            {
                *d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
        plan.apply_stripes(block.view_mut())
            .map_err(Written::Prep)?;
        for k in 0..n {
            bytes.clear();
            for v in block.index_axis(ndarray::Axis(0), k) {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            let at = header + ((k * nv + v0) * nu * 4) as u64;
            file.write_all_at(&bytes, at).map_err(Written::Io)?;
        }
        v0 += r;
    }
    Ok(())
}

/// Size and SHA-256 (hex) of a file, read in 1 MiB pieces.
fn hash_file(path: &Path) -> std::io::Result<(u64, String)> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    let mut hash = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    let mut total = 0u64;
    loop {
        let got = f.read(&mut buf)?;
        if got == 0 {
            break;
        }
        hash.update(&buf[..got]);
        total += got as u64;
    }
    Ok((total, hex(&hash.finalize())))
}
