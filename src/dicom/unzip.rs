//! Uploads on disk: a ZIP archive is inflated member by member into files of a scratch directory (never whole in
//! memory, through one 64 KiB buffer), each member checked against a per-member cap, what is left of a
//! per-archive cap and a compression-ratio cap; then the files are decoded in parallel, one file's bytes in
//! memory per worker at a time.
//!
//! A member that breaks a limit or cannot be inflated is refused on its own (listed with its reason) and the
//! others go on; only an archive that cannot be opened at all, or that has too many members, is refused
//! whole. Member names are labels for messages: the files are named `m<index>` in the scratch directory.

use std::fs::File;
use std::io::{self, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use rayon::prelude::*;

use super::error::DicomError;
use super::read::{Instance, ReadLimits, read_bytes};
use super::upload::{Rejected, Upload, ZipLimits, group_series};
use crate::recon::control::Control;

/// One file of an upload on disk: the client's name (for messages only) and where the bytes are.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UploadFile {
    pub label: String,
    pub path: PathBuf,
}

/// Files ready to decode and the members refused while unpacking.
#[derive(Debug, Default)]
pub struct Unpacked {
    pub files: Vec<UploadFile>,
    pub rejected: Vec<Rejected>,
    /// Bytes inflated so far (all archives of the upload), counted against [`ZipLimits::max_total_bytes`].
    pub inflated_bytes: u64,
}

fn clean_label(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_control() { '?' } else { c })
        .take(200)
        .collect()
}

fn starts_with_zip_magic(path: &Path) -> io::Result<bool> {
    let mut head = [0u8; 4];
    let mut f = File::open(path)?;
    let mut n = 0;
    while n < 4 {
        match f.read(&mut head[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n == 4 && (&head == b"PK\x03\x04" || &head == b"PK\x05\x06"))
}

/// The entry count an archive's end-of-central-directory record declares (ZIP64 included), read from its last
/// 64 KiB before the ZIP reader allocates anything per entry; `None` when there is no such record (the reader
/// then refuses the archive).
fn declared_entries(f: &mut File) -> io::Result<Option<u64>> {
    let len = f.metadata()?.len();
    let tail_len = len.min(65_535 + 22);
    f.seek(SeekFrom::Start(len - tail_len))?;
    let mut tail = vec![0u8; tail_len as usize];
    f.read_exact(&mut tail)?;
    let Some(at) = (0..tail.len().saturating_sub(21))
        .rev()
        .find(|&i| tail[i..i + 4] == *b"PK\x05\x06")
    else {
        return Ok(None);
    };
    let count = u16::from_le_bytes([tail[at + 10], tail[at + 11]]);
    if count != 0xFFFF {
        return Ok(Some(u64::from(count)));
    }
    // ZIP64: the locator (20 bytes) sits just before the record and points at the ZIP64 end record.
    if at < 20 || tail[at - 20..at - 16] != *b"PK\x06\x07" {
        return Ok(None);
    }
    let mut offset = [0u8; 8];
    offset.copy_from_slice(&tail[at - 12..at - 4]);
    let offset = u64::from_le_bytes(offset);
    if offset.saturating_add(56) > len {
        return Ok(None);
    }
    f.seek(SeekFrom::Start(offset))?;
    let mut record = [0u8; 56];
    f.read_exact(&mut record)?;
    if record[..4] != *b"PK\x06\x06" {
        return Ok(None);
    }
    let mut total = [0u8; 8];
    total.copy_from_slice(&record[32..40]);
    Ok(Some(u64::from_le_bytes(total)))
}

fn io_error(label: &str, e: io::Error) -> DicomError {
    // Our own scratch files failing is the server's problem, not the client's.
    DicomError::Write(format!("scratch file for {label}: {e}"))
}

/// Add `file` to `out`: a ZIP archive's members, inflated into `scratch`, or the file itself. Errors are only
/// the server's (I/O on the scratch directory); everything the client sent that breaks a rule is in
/// `out.rejected`.
pub fn unpack_file(
    file: UploadFile,
    limits: &ZipLimits,
    scratch: &Path,
    out: &mut Unpacked,
) -> Result<(), DicomError> {
    if !starts_with_zip_magic(&file.path).map_err(|e| io_error(&file.label, e))? {
        out.files.push(file);
        return Ok(());
    }
    let refuse = |out: &mut Unpacked, label: String, error: DicomError| {
        out.rejected.push(Rejected { label, error });
    };
    let mut f = File::open(&file.path).map_err(|e| io_error(&file.label, e))?;
    let declared = declared_entries(&mut f).map_err(|e| io_error(&file.label, e))?;
    if let Some(n) = declared.filter(|&n| n > limits.max_entries as u64) {
        let reason = format!("{n} entries declared, limit {}", limits.max_entries);
        refuse(out, file.label, DicomError::ZipBomb { reason });
        return Ok(());
    }
    f.seek(SeekFrom::Start(0))
        .map_err(|e| io_error(&file.label, e))?;
    let mut archive = match zip::ZipArchive::new(f) {
        Ok(a) => a,
        Err(e) => {
            refuse(
                out,
                file.label,
                DicomError::Zip {
                    reason: e.to_string(),
                },
            );
            return Ok(());
        }
    };
    if archive.len() > limits.max_entries {
        let reason = format!("{} entries, limit {}", archive.len(), limits.max_entries);
        refuse(out, file.label, DicomError::ZipBomb { reason });
        return Ok(());
    }
    let count = archive.len();
    let mut buf = vec![0u8; 64 << 10];
    for i in 0..count {
        let mut entry = match archive.by_index(i) {
            Ok(e) => e,
            Err(e) => {
                let label = format!("{}#{}", file.label, i + 1);
                let reason = e.to_string();
                refuse(out, label, DicomError::Zip { reason });
                continue;
            }
        };
        if entry.is_dir() {
            continue;
        }
        let label = clean_label(entry.name());
        if label.starts_with("__MACOSX/")
            || label
                .rsplit('/')
                .next()
                .is_some_and(|b| b.starts_with("._"))
        {
            continue;
        }
        let left = limits.max_total_bytes.saturating_sub(out.inflated_bytes);
        let compressed = entry.compressed_size().max(1);
        let by_ratio = compressed.saturating_mul(limits.max_ratio).max(1 << 20);
        let bomb = |reason: String| DicomError::ZipBomb { reason };
        // Declared sizes refuse the honest bombs before inflating a byte; the count below catches liars.
        let declared = entry.size();
        if declared > by_ratio {
            let reason = format!(
                "entry {label} inflates more than {}× its compressed size",
                limits.max_ratio
            );
            refuse(out, label, bomb(reason));
            continue;
        }
        if declared > limits.max_member_bytes {
            let reason = format!(
                "entry {label} declares {declared} bytes, over the limit of one entry ({})",
                limits.max_member_bytes
            );
            refuse(out, label, bomb(reason));
            continue;
        }
        // A member inflates no further than it declares: one that lies about its size is refused at that
        // size, not at the ratio cap.
        let allowed = limits
            .max_member_bytes
            .min(by_ratio)
            .min(left)
            .min(declared);
        let path = scratch.join(format!("m{}", out.files.len()));
        let mut dest = File::create(&path).map_err(|e| io_error(&label, e))?;
        let mut written: u64 = 0;
        let mut head = [0u8; 4];
        let outcome: Result<(), DicomError> = loop {
            let n = match entry.read(&mut buf) {
                Ok(0) => break Ok(()),
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    break Err(DicomError::Zip {
                        reason: format!("{label}: {e}"),
                    });
                }
            };
            if written < 4 {
                let k = (4 - written as usize).min(n);
                head[written as usize..written as usize + k].copy_from_slice(&buf[..k]);
            }
            written += n as u64;
            if written > allowed {
                break Err(bomb(
                    if declared < left.min(by_ratio).min(limits.max_member_bytes) {
                        format!("entry {label} inflates past the {declared} bytes it declares")
                    } else if left <= by_ratio && left <= limits.max_member_bytes {
                        format!("more than {} bytes once inflated", limits.max_total_bytes)
                    } else if limits.max_member_bytes <= by_ratio {
                        format!(
                            "entry {label} inflates to more than {} bytes, over the limit of one entry",
                            limits.max_member_bytes
                        )
                    } else {
                        format!(
                            "entry {label} inflates more than {}× its compressed size",
                            limits.max_ratio
                        )
                    },
                ));
            }
            if let Err(e) = dest.write_all(&buf[..n]) {
                return Err(io_error(&label, e));
            }
        };
        drop(dest);
        out.inflated_bytes += written.min(allowed);
        let total_spent = out.inflated_bytes >= limits.max_total_bytes;
        match outcome {
            Err(error) => {
                let _ = std::fs::remove_file(&path);
                refuse(out, label, error);
                if total_spent {
                    // Nothing more can be inflated: say so once for the rest of the archive.
                    let reason = format!(
                        "more than {} bytes once inflated; the entries after {} were not read",
                        limits.max_total_bytes,
                        i + 1
                    );
                    if i + 1 < count {
                        refuse(out, file.label.clone(), bomb(reason));
                    }
                    break;
                }
            }
            // Nested archives are not unpacked.
            Ok(()) if &head == b"PK\x03\x04" => {
                let _ = std::fs::remove_file(&path);
            }
            Ok(()) => out.files.push(UploadFile { label, path }),
        }
    }
    Ok(())
}

/// What a file that is not a ZIP archive starts like, from its first bytes (at least 132 for DICOM): a
/// few formats sent by mistake, for a message that says what was sent.
pub fn starts_like(head: &[u8]) -> Option<&'static str> {
    const SIGNATURES: &[(&[u8], &str)] = &[
        (b"\x89PNG\r\n\x1a\n", "a PNG image"),
        (b"\xFF\xD8\xFF", "a JPEG image"),
        (b"GIF8", "a GIF image"),
        (b"%PDF", "a PDF document"),
        (b"\x1F\x8B", "a gzip file"),
        (b"II*\0", "a TIFF image"),
        (b"MM\0*", "a TIFF image"),
        (b"\x93NUMPY", "a NumPy .npy array"),
        (b"Rar!", "a RAR archive"),
        (b"7z\xBC\xAF", "a 7-Zip archive"),
    ];
    if may_be_dicom(head, head.len() as u64) {
        return Some("a DICOM file");
    }
    SIGNATURES
        .iter()
        .find(|(magic, _)| head.starts_with(magic))
        .map(|(_, what)| *what)
}

/// Whether the file at `path` starts like a ZIP archive (a local file header or an empty archive's end).
pub fn is_zip(path: &Path) -> io::Result<bool> {
    starts_with_zip_magic(path)
}

/// Whether `head` (the first bytes of a file) can start DICOM: a Part 10 file (`DICM` after the preamble or
/// first), or a raw data set whose first element is in the file meta (0002) or identification (0008) group,
/// little or big endian (what the reader's framing accepts).
pub(super) fn may_be_dicom(head: &[u8], len: u64) -> bool {
    let group = |b: &[u8]| {
        [
            u16::from_le_bytes([b[0], b[1]]),
            u16::from_be_bytes([b[0], b[1]]),
        ]
    };
    (len >= 132 && head.len() >= 132 && &head[128..132] == b"DICM")
        || (head.len() >= 4 && &head[..4] == b"DICM")
        || (head.len() >= 8 && group(head).iter().any(|g| matches!(g, 0x0002 | 0x0008)))
}

/// Read and decode one file from disk; a file that cannot start DICOM is refused from its first 132 bytes
/// (never read whole).
pub fn read_upload_file(file: &UploadFile, limits: &ReadLimits) -> Result<Instance, DicomError> {
    let mut f = File::open(&file.path).map_err(|e| io_error(&file.label, e))?;
    let len = f.metadata().map_err(|e| io_error(&file.label, e))?.len();
    let mut head = Vec::with_capacity(132);
    (&mut f)
        .take(132)
        .read_to_end(&mut head)
        .map_err(|e| io_error(&file.label, e))?;
    if !may_be_dicom(&head, len) {
        return Err(DicomError::NotDicom {
            label: file.label.clone(),
        });
    }
    let mut bytes = head;
    bytes.reserve_exact(usize::try_from(len).unwrap_or(0).saturating_sub(132));
    f.read_to_end(&mut bytes)
        .map_err(|e| io_error(&file.label, e))?;
    read_bytes(&file.label, &bytes, limits)
}

/// Decode `files` from disk in parallel and split them by SeriesInstanceUID, like
/// [`read_upload`](super::read_upload); `rejected` (refused while unpacking) comes first in the result.
pub fn read_upload_files(
    files: &[UploadFile],
    mut rejected: Vec<Rejected>,
    limits: &ReadLimits,
    ctl: Control<'_>,
) -> Result<Upload, DicomError> {
    let done = AtomicUsize::new(0);
    let total = files.len().max(1) as f64;
    let results: Vec<Option<Result<Instance, DicomError>>> = files
        .par_iter()
        .map(|file| {
            if ctl.cancel.is_canceled() {
                return None;
            }
            let r = read_upload_file(file, limits);
            let n = done.fetch_add(1, Ordering::Relaxed) + 1;
            ctl.step("decode", n as f64 / total);
            Some(r)
        })
        .collect();
    if ctl.cancel.is_canceled() {
        return Err(DicomError::Canceled);
    }
    let mut instances = Vec::new();
    for (file, r) in files.iter().zip(results) {
        match r {
            Some(Ok(i)) => instances.push(i),
            Some(Err(e)) if !e.is_client_error() => return Err(e),
            Some(Err(error)) => rejected.push(Rejected {
                label: file.label.clone(),
                error,
            }),
            None => {}
        }
    }
    Ok(Upload {
        series: group_series(instances),
        rejected,
    })
}
