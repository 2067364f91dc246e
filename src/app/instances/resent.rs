//! Instances sent again. The index holds one received copy per SOP Instance UID, whichever door brought it
//! (C-STORE, STOW-RS, an HTTP upload), and each copy's SHA-256:
//!
//! - a copy whose SOP Instance UID is indexed with the same SHA-256 is *recognised*: the sender is answered
//!   as for a new one, and nothing is kept (no file, no row);
//! - a copy whose SOP Instance UID is indexed with other content (or with no hash, indexed before hashes
//!   were kept) *replaces* it: the row of the earlier copy goes in the transaction that writes the new one,
//!   and its file after.
//!
//! What a series does about it is the door's (`app::recognised`): C-STORE and STOW-RS assemble nothing for an
//! arrival that brought only recognised copies.

use std::collections::{HashMap, HashSet};
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use super::{indexed, storage};
use crate::app::{App, AppResult};
use crate::dicom::{DicomError, InstanceHeader, header_of, read_bounded};
use crate::jobs::model::{IndexedInstance, ReplacedCopy, StoredInstance};
use crate::storage::InstanceOwner;
use crate::storage::npy::hex;

/// A received instance read for indexing: its file, its index row and the SHA-256 of the file (hex).
#[derive(Debug, Clone)]
pub struct Arrived {
    pub path: PathBuf,
    pub instance: IndexedInstance,
    pub sha256: String,
}

/// Received instances sorted against the index.
#[derive(Debug, Default)]
pub struct Sorted {
    /// New SOP Instance UIDs, and known ones with other content (each replaces the copy indexed before).
    pub fresh: Vec<Arrived>,
    /// Copies of what the index holds already, byte for byte, each with the row that holds it.
    pub recognised: Vec<(Arrived, StoredInstance)>,
    /// Copies of a SOP Instance UID that came twice in one batch (the first is kept).
    pub repeated: Vec<Arrived>,
}

/// Read the header and SHA-256 of the file at `path` (blocking; files over `max_bytes` are refused unread).
pub fn read_arrived_at(
    path: &Path,
    max_bytes: u64,
) -> Result<(InstanceHeader, String), DicomError> {
    let (label, bytes) = read_bounded(path, max_bytes)?;
    let header = header_of(&label, &bytes)?;
    Ok((header, hex(&Sha256::digest(&bytes))))
}

/// Sort `arrived` against `known` (the received copies of their SOP Instance UIDs, newest first).
fn sort(arrived: Vec<Arrived>, known: &[StoredInstance]) -> Sorted {
    let mut newest: HashMap<&str, &StoredInstance> = HashMap::new();
    for k in known {
        newest
            .entry(k.instance.sop_instance_uid.as_str())
            .or_insert(k);
    }
    let mut seen = HashSet::new();
    let mut out = Sorted::default();
    for a in arrived {
        if !seen.insert(a.instance.sop_instance_uid.clone()) {
            out.repeated.push(a);
            continue;
        }
        match newest.get(a.instance.sop_instance_uid.as_str()) {
            Some(k) if k.sha256.as_deref() == Some(a.sha256.as_str()) => {
                out.recognised.push((a, (*k).clone()))
            }
            _ => out.fresh.push(a),
        }
    }
    out
}

impl App {
    /// The largest received instance read back (the DICOM node's instance limit and room for its prefix).
    pub(crate) fn max_received_bytes(&self) -> u64 {
        self.settings
            .dicom
            .max_instance_bytes
            .saturating_add(64 << 10)
    }

    /// Read the received files `files` for indexing (off the async threads); a file whose header cannot be
    /// read is logged and left out (and left where it is).
    pub(crate) async fn read_arrived(&self, files: Vec<PathBuf>) -> AppResult<Vec<Arrived>> {
        let max = self.max_received_bytes();
        tokio::task::spawn_blocking(move || {
            files
                .into_iter()
                .filter_map(|path| match read_arrived_at(&path, max) {
                    Ok((h, sha256)) => {
                        let bytes = std::fs::metadata(&path).map(|m| m.len()).ok()?;
                        Some(Arrived {
                            path,
                            instance: indexed(&h, bytes),
                            sha256,
                        })
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "a received instance is not indexed");
                        None
                    }
                })
                .collect()
        })
        .await
        .map_err(|e| storage("reading received headers failed", std::io::Error::other(e)).into())
    }

    /// Sort received instances against the index: fresh, recognised, or repeated within `arrived`.
    pub(crate) async fn sort_arrived(&self, arrived: Vec<Arrived>) -> AppResult<Sorted> {
        let uids: Vec<String> = arrived
            .iter()
            .map(|a| a.instance.sop_instance_uid.clone())
            .collect::<HashSet<_>>()
            .into_iter()
            .collect();
        let known = self.db.received_copies(&uids).await?;
        Ok(sort(arrived, &known))
    }

    /// Remove the files of received copies that newer ones replaced (a failure is logged: the file is then
    /// an orphan of a folder that other rows keep).
    pub(crate) async fn remove_replaced(&self, replaced: Vec<ReplacedCopy>) {
        if replaced.is_empty() {
            return;
        }
        let store = self.store.clone();
        let n = replaced.len();
        let removed = tokio::task::spawn_blocking(move || {
            for r in replaced {
                let path = store.instance_path(InstanceOwner::Upload(r.upload), r.id);
                if let Err(e) = std::fs::remove_file(&path)
                    && e.kind() != std::io::ErrorKind::NotFound
                {
                    tracing::warn!(error = %e, instance_id = %r.id, "a replaced instance's file was not removed");
                }
            }
        })
        .await;
        if removed.is_ok() {
            tracing::info!(instances = n, "received copies replaced by newer ones");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::{InstanceId, UploadId};

    fn arrived(sop: &str, sha: &str) -> Arrived {
        Arrived {
            path: PathBuf::from(format!("{sop}.dcm")),
            instance: IndexedInstance {
                sop_instance_uid: sop.into(),
                ..IndexedInstance::default()
            },
            sha256: sha.into(),
        }
    }

    fn stored(sop: &str, sha: Option<&str>) -> StoredInstance {
        StoredInstance {
            id: InstanceId::generate(),
            owner: InstanceOwner::Upload(UploadId::generate()),
            series_id: None,
            created_us: 0,
            instance: IndexedInstance {
                sop_instance_uid: sop.into(),
                ..IndexedInstance::default()
            },
            sha256: sha.map(str::to_string),
        }
    }

    #[test]
    fn the_same_bytes_are_recognised_and_other_bytes_or_no_hash_replace() {
        let known = [
            stored("1.1", Some("aa")),
            stored("1.2", Some("bb")),
            stored("1.3", None),
        ];
        let s = sort(
            vec![
                arrived("1.1", "aa"),
                arrived("1.2", "cc"),
                arrived("1.3", "dd"),
                arrived("1.4", "ee"),
                arrived("1.1", "ff"),
            ],
            &known,
        );
        let uids = |v: &[Arrived]| {
            v.iter()
                .map(|a| a.instance.sop_instance_uid.clone())
                .collect::<Vec<_>>()
        };
        assert_eq!(uids(&s.fresh), ["1.2", "1.3", "1.4"]);
        assert_eq!(s.recognised.len(), 1);
        assert_eq!(s.recognised[0].1.id, known[0].id);
        assert_eq!(uids(&s.repeated), ["1.1"]);
    }
}
