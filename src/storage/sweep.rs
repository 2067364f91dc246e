//! The blob files of one kind as found on disk, for the start-up sweep that pairs them with database rows.

use std::fs;
use std::io;
use std::path::PathBuf;

use super::BlobStore;
use super::ids::AnyId;

/// A kind of blob that has a database row per file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlobKind {
    /// `series/<id>.npy`.
    Series,
    /// `datasets/<id>.npy`.
    Dataset,
    /// `uploads/<id>/` (the instances of an open upload).
    Upload,
    /// `results/<job>/` (the files a job wrote; the job's row owns them).
    Results,
}

impl BlobKind {
    pub const ALL: [BlobKind; 4] = [
        BlobKind::Series,
        BlobKind::Dataset,
        BlobKind::Upload,
        BlobKind::Results,
    ];

    /// Whether every row of this kind has its file, so a row without one is marked missing (an upload's
    /// folder or a job's results folder may rightly not exist yet).
    pub fn row_needs_file(self) -> bool {
        matches!(self, BlobKind::Series | BlobKind::Dataset)
    }

    /// The label of metrics and logs.
    pub fn as_str(self) -> &'static str {
        match self {
            BlobKind::Series => "series",
            BlobKind::Dataset => "dataset",
            BlobKind::Upload => "upload",
            BlobKind::Results => "results",
        }
    }

    fn dir(self) -> &'static str {
        match self {
            BlobKind::Series => "series",
            BlobKind::Dataset => "datasets",
            BlobKind::Upload => "uploads",
            BlobKind::Results => "results",
        }
    }
}

/// An entry of a blob directory: its path and, when its name is `<canonical id>.npy` (a directory named by
/// the id for uploads and results), the id. An entry without an id is never the service's own.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlobEntry {
    pub path: PathBuf,
    pub id: Option<String>,
}

impl BlobStore {
    /// Every entry of `kind`'s directory (blocking; run at start-up).
    pub fn list_blobs(&self, kind: BlobKind) -> io::Result<Vec<BlobEntry>> {
        let mut out = Vec::new();
        for entry in fs::read_dir(self.root().join(kind.dir()))? {
            let entry = entry?;
            let name = entry.file_name();
            let name = name.to_string_lossy();
            let stem = match kind {
                BlobKind::Upload | BlobKind::Results => Some(name.as_ref()),
                _ => name.strip_suffix(".npy"),
            };
            let id = stem.filter(|s| AnyId::parse(s).is_ok()).map(str::to_string);
            out.push(BlobEntry {
                path: entry.path(),
                id,
            });
        }
        out.sort_by(|a, b| a.path.cmp(&b.path));
        Ok(out)
    }

    /// Remove a blob entry, file or directory (missing is fine).
    pub fn remove_entry(&self, entry: &BlobEntry) -> io::Result<()> {
        let r = if entry.path.is_dir() {
            fs::remove_dir_all(&entry.path)
        } else {
            fs::remove_file(&entry.path)
        };
        match r {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::SeriesId;

    #[test]
    fn entries_named_by_an_id_carry_it_and_others_do_not() {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::open(dir.path()).unwrap();
        let id = SeriesId::generate();
        fs::write(store.series_path(id), b"x").unwrap();
        fs::write(dir.path().join("series").join("stray.npy"), b"x").unwrap();
        let listed = store.list_blobs(BlobKind::Series).unwrap();
        let ids: Vec<Option<String>> = listed.iter().map(|e| e.id.clone()).collect();
        assert_eq!(ids.len(), 2);
        assert!(ids.contains(&Some(id.to_string())) && ids.contains(&None));
        for e in &listed {
            store.remove_entry(e).unwrap();
        }
        assert!(store.list_blobs(BlobKind::Series).unwrap().is_empty());
    }
}
