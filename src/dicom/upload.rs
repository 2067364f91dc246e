//! Uploads: ZIP unpacking in memory with limits (the library's easy path; the service unpacks to disk with
//! [`super::unzip`]), parallel decoding, splitting by series, per-series reports and assembly.

use std::collections::BTreeMap;
use std::io::{Cursor, Read};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;
use serde::Serialize;

use super::error::DicomError;
use super::read::{Instance, ReadLimits, read_bytes};
use crate::recon::control::Control;
use crate::series::{Assembled, AssemblyOptions, Warning, assemble};

/// Limits on a ZIP upload, checked on the bytes actually inflated (declared sizes are not trusted).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ZipLimits {
    pub max_entries: usize,
    /// Total inflated bytes (of all the archives of one upload).
    pub max_total_bytes: u64,
    /// Largest inflated/compressed ratio of one entry (entries under 1 MiB are exempt).
    pub max_ratio: u64,
    /// Largest inflated entry.
    pub max_member_bytes: u64,
}

impl Default for ZipLimits {
    fn default() -> Self {
        Self {
            max_entries: 20_000,
            max_total_bytes: 4 << 30,
            max_ratio: 200,
            max_member_bytes: 1 << 30,
        }
    }
}

/// Split an upload body into named files: a ZIP archive's regular entries (names are labels only; folders,
/// `__MACOSX` resource forks and nested archives are skipped), or the body itself.
pub fn unpack(
    name: &str,
    body: Vec<u8>,
    limits: &ZipLimits,
) -> Result<Vec<(String, Vec<u8>)>, DicomError> {
    if !body.starts_with(b"PK\x03\x04") && !body.starts_with(b"PK\x05\x06") {
        return Ok(vec![(name.to_string(), body)]);
    }
    let zerr = |e: zip::result::ZipError| DicomError::Zip {
        reason: e.to_string(),
    };
    let bomb = |reason: String| DicomError::ZipBomb { reason };
    let mut archive = zip::ZipArchive::new(Cursor::new(body.as_slice())).map_err(zerr)?;
    if archive.len() > limits.max_entries {
        return Err(bomb(format!(
            "{} entries, limit {}",
            archive.len(),
            limits.max_entries
        )));
    }
    let mut out = Vec::new();
    let mut total: u64 = 0;
    for i in 0..archive.len() {
        let mut entry = archive.by_index(i).map_err(zerr)?;
        if entry.is_dir() {
            continue;
        }
        let label: String = entry
            .name()
            .chars()
            .map(|c| if c.is_control() { '?' } else { c })
            .take(200)
            .collect();
        if label.starts_with("__MACOSX/")
            || label
                .rsplit('/')
                .next()
                .is_some_and(|b| b.starts_with("._"))
        {
            continue;
        }
        let compressed = entry.compressed_size().max(1);
        // Allow what is left of the total, and the ratio limit (with 1 MiB of slack for tiny entries).
        let allowed = (limits.max_total_bytes.saturating_sub(total))
            .min(compressed.saturating_mul(limits.max_ratio).max(1 << 20))
            .min(limits.max_member_bytes);
        let mut buf = Vec::new();
        (&mut entry)
            .take(allowed + 1)
            .read_to_end(&mut buf)
            .map_err(|e| DicomError::Zip {
                reason: format!("{label}: {e}"),
            })?;
        if buf.len() as u64 > allowed {
            return Err(bomb(
                if allowed < limits.max_total_bytes.saturating_sub(total) {
                    format!(
                        "entry {label} inflates more than {}× its compressed size",
                        limits.max_ratio
                    )
                } else {
                    format!("more than {} bytes once inflated", limits.max_total_bytes)
                },
            ));
        }
        total += buf.len() as u64;
        if buf.starts_with(b"PK\x03\x04") {
            continue;
        }
        out.push((label, buf));
    }
    Ok(out)
}

/// Warning codes of [`read_bytes`] that every file of a series may carry; a report keeps the first of each.
const PER_FILE_NOTES: &[&str] = &[
    "monochrome1",
    "rescale_assumed",
    "series_uid_missing",
    "transfer_syntax_guessed",
    "trailing_bytes_ignored",
];

/// A file that was not accepted, and why.
#[derive(Debug, Clone, PartialEq)]
pub struct Rejected {
    pub label: String,
    pub error: DicomError,
}

/// The instances of one SeriesInstanceUID.
#[derive(Debug, Clone, PartialEq)]
pub struct SeriesGroup {
    pub series_uid: String,
    pub study_uid: Option<String>,
    pub modality: Option<String>,
    pub instances: Vec<Instance>,
    pub warnings: Vec<Warning>,
}

/// A summary of one series for the client.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct SeriesReport {
    pub series_uid: String,
    pub study_uid: Option<String>,
    pub modality: Option<String>,
    pub description: Option<String>,
    pub instances: usize,
    pub frames: usize,
    pub rows: usize,
    pub columns: usize,
    /// Pixel spacing (row, column) of the first frame (mm).
    pub pixel_spacing_mm: Option<[f64; 2]>,
    pub slice_thickness_mm: Option<f64>,
    pub size_bytes: usize,
    pub transfer_syntaxes: Vec<String>,
    pub warnings: Vec<Warning>,
    /// Body Part Examined of the first instance (for processing rules; not part of the API document).
    #[serde(skip)]
    pub body_part: Option<String>,
    /// Image Type values of the first instance (for processing rules; not part of the API document).
    #[serde(skip)]
    pub image_type: Vec<String>,
}

/// Decoded upload: series and the files refused.
#[derive(Debug, Clone, PartialEq)]
pub struct Upload {
    pub series: Vec<SeriesGroup>,
    pub rejected: Vec<Rejected>,
}

/// Decode `files` in parallel and split them by SeriesInstanceUID (series in order of UID). Files that fail are
/// listed in [`Upload::rejected`]; the cancel flag is checked before each file and progress reported after it.
pub fn read_upload(
    files: &[(String, Vec<u8>)],
    limits: &ReadLimits,
    ctl: Control<'_>,
) -> Result<Upload, DicomError> {
    let done = AtomicUsize::new(0);
    let total = files.len().max(1) as f64;
    let results: Vec<Option<Result<Instance, Rejected>>> = files
        .par_iter()
        .map(|(label, bytes)| {
            if ctl.cancel.is_canceled() {
                return None;
            }
            let r = read_bytes(label, bytes, limits).map_err(|error| Rejected {
                label: label.clone(),
                error,
            });
            let n = done.fetch_add(1, Ordering::Relaxed) + 1;
            ctl.step("decode", n as f64 / total);
            Some(r)
        })
        .collect();
    if ctl.cancel.is_canceled() {
        return Err(DicomError::Canceled);
    }
    let mut instances = Vec::new();
    let mut rejected = Vec::new();
    for r in results.into_iter().flatten() {
        match r {
            Ok(i) => instances.push(i),
            Err(r) => rejected.push(r),
        }
    }
    Ok(Upload {
        series: group_series(instances),
        rejected,
    })
}

/// Split instances by SeriesInstanceUID; repeated SOP Instance UIDs are dropped with a warning.
pub fn group_series(instances: Vec<Instance>) -> Vec<SeriesGroup> {
    let mut by_uid: BTreeMap<String, SeriesGroup> = BTreeMap::new();
    for inst in instances {
        let g = by_uid
            .entry(inst.series_uid.clone())
            .or_insert_with(|| SeriesGroup {
                series_uid: inst.series_uid.clone(),
                study_uid: inst.study_uid.clone(),
                modality: inst.modality.clone(),
                instances: Vec::new(),
                warnings: Vec::new(),
            });
        if !inst.sop_instance_uid.is_empty()
            && g.instances
                .iter()
                .any(|o| o.sop_instance_uid == inst.sop_instance_uid)
        {
            g.warnings.push(Warning {
                code: "duplicate_instance_dropped",
                message: format!(
                    "{}: SOP Instance UID {} was already received",
                    inst.label, inst.sop_instance_uid
                ),
            });
            continue;
        }
        if g.modality != inst.modality {
            g.warnings.push(Warning {
                code: "mixed_modality",
                message: format!(
                    "{}: modality {:?} differs from the series' {:?}",
                    inst.label, inst.modality, g.modality
                ),
            });
        }
        g.instances.push(inst);
    }
    by_uid.into_values().collect()
}

impl SeriesGroup {
    pub fn report(&self) -> SeriesReport {
        let first = self.instances.first();
        let slice = first.and_then(|i| i.slices.first());
        let mut ts: Vec<String> = self
            .instances
            .iter()
            .map(|i| i.transfer_syntax.clone())
            .collect();
        ts.sort();
        ts.dedup();
        let mut warnings = self.warnings.clone();
        for i in &self.instances {
            warnings.extend(i.warnings.iter().cloned());
        }
        // Per-file notes repeat on every file of a series: keep the first of each.
        let mut seen = std::collections::HashSet::new();
        warnings.retain(|w| !PER_FILE_NOTES.contains(&w.code) || seen.insert(w.code));
        SeriesReport {
            series_uid: self.series_uid.clone(),
            study_uid: self.study_uid.clone(),
            modality: self.modality.clone(),
            description: first.and_then(|i| i.series_description.clone()),
            instances: self.instances.len(),
            frames: self.instances.iter().map(|i| i.slices.len()).sum(),
            rows: slice.map_or(0, |s| s.rows),
            columns: slice.map_or(0, |s| s.columns),
            pixel_spacing_mm: slice.and_then(|s| s.pixel_spacing_mm),
            slice_thickness_mm: slice.and_then(|s| s.slice_thickness_mm),
            size_bytes: self.instances.iter().map(|i| i.size_bytes).sum(),
            transfer_syntaxes: ts,
            warnings,
            body_part: first.and_then(|i| i.body_part.clone()),
            image_type: first.map(|i| i.image_type.clone()).unwrap_or_default(),
        }
    }

    /// Assemble the series into an HU volume (consumes the decoded pixels; take the report first). With `require_ct`, a modality other than CT is refused.
    pub fn assemble(
        self,
        opts: &AssemblyOptions,
        require_ct: bool,
        ctl: Control<'_>,
    ) -> Result<Assembled, DicomError> {
        let modality = self.modality.clone().unwrap_or_default();
        if require_ct && modality != "CT" {
            return Err(DicomError::NotCt {
                series_uid: self.series_uid.clone(),
                modality: if modality.is_empty() {
                    "unknown".into()
                } else {
                    modality
                },
            });
        }
        // Colour (RGB, YBR) and palette indices are not grey values: refused rather than read as HU.
        if let Some(i) = self
            .instances
            .iter()
            .find(|i| i.samples_per_pixel == 1 && !i.photometric.starts_with("MONOCHROME"))
        {
            return Err(DicomError::UnsupportedPhotometric {
                label: i.label.clone(),
                photometric: i.photometric.clone(),
                hint: " (palette indices are not intensities)",
            });
        }
        if let Some(i) = self.instances.iter().find(|i| i.samples_per_pixel != 1) {
            return Err(DicomError::UnsupportedPhotometric {
                label: i.label.clone(),
                photometric: i.photometric.clone(),
                hint: " (a colour image has several samples per pixel)",
            });
        }
        let mut w = self.report().warnings;
        let series_uid = self.series_uid;
        let slices = self.instances.into_iter().flat_map(|i| i.slices).collect();
        let mut a = assemble(slices, opts, ctl)
            .map_err(|source| DicomError::Series { series_uid, source })?;
        w.append(&mut a.warnings);
        a.warnings = w;
        Ok(a)
    }
}
