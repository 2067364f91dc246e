//! Blob storage for uploaded datasets and results (local files; ids, never client strings, name paths).
//!
//! Layout under the data directory:
//! - `datasets/<dataset id>.npy`: uploaded or simulated projections, exactly as accepted;
//! - `results/<job id>/<name>`: a job's results (`volume.npy`, `metrics.json`, and cached derived files
//!   named by the SHA-256 of their parameters);
//! - `series/<series id>.npy`: assembled CT series (HU volumes);
//! - `uploads/<upload id>/<sha256>.dcm`: instances of an open upload;
//! - `instances/<upload id>/<instance id>.dcm`: received instances kept in the instance index (a job's
//!   indexed DICOM results are `results/<job id>/instances/<instance id>.dcm`);
//! - `tmp/`: uploads, unpacked archives and results being written. Every write goes to a temporary file, is
//!   flushed to disk and then renamed into place, so a file under `datasets/` or `results/` is always
//!   complete. A blob that has a database row is renamed into place only after its row is committed.
//!   `tmp/` is emptied at start (in a directory shared by several processes, of what lay idle for an hour).
//!
//! With object storage (`storage.url = "s3://…"`, see [`mirror`]) the durable copy of `datasets/`, `series/`,
//! `results/` and `uploads/` is the object under the same key, put before the local rename; the data
//! directory is then a cache that readers fill on a miss ([`BlobStore::local`], [`BlobStore::fetch`]).

pub mod ids;
pub mod mirror;
pub mod npy;
#[cfg(feature = "s3")]
pub mod object;
pub mod port;
pub mod sweep;

use std::fs;
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

pub use ids::{AnyId, BadId, DatasetId, InstanceId, JobId, SeriesId, UploadId};

/// Names of the files a job's result directory holds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ResultName {
    /// The reconstructed volume, float32 `[z][y][x]`.
    Volume,
    /// Quality metrics against the phantom, JSON.
    Metrics,
    /// A derived file (slice, projection, mesh) keyed by the hex SHA-256 of its parameters.
    Derived { key_hex: String, ext: &'static str },
    /// The `index`-th product of a volume job (an image stack `.npy` or a mesh `.stl`).
    Product { index: usize, ext: &'static str },
}

impl ResultName {
    fn file_name(&self) -> String {
        match self {
            ResultName::Volume => "volume.npy".into(),
            ResultName::Metrics => "metrics.json".into(),
            ResultName::Derived { key_hex, ext } => format!("derived-{key_hex}.{ext}"),
            ResultName::Product { index, ext } => format!("product-{index}.{ext}"),
        }
    }
}

/// Who an indexed instance belongs to: the upload that received it, or the job that made it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum InstanceOwner {
    Upload(UploadId),
    Job(JobId),
}

/// The local blob store rooted at the data directory, with the object store that holds the durable copies
/// of its blobs when one is configured.
#[derive(Debug, Clone)]
pub struct BlobStore {
    root: PathBuf,
    mirror: Option<mirror::Mirror>,
}

/// A file being written under `tmp/`; removed on drop unless committed.
#[derive(Debug)]
pub struct TempBlob {
    path: PathBuf,
    committed: bool,
}

impl TempBlob {
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl TempBlob {
    /// Flush the file's data to disk (before it is kept by a rename).
    pub async fn sync(&self) -> io::Result<()> {
        tokio::fs::File::open(&self.path).await?.sync_all().await
    }

    /// Remove the file now, without blocking the async runtime (dropping removes it too, synchronously).
    pub async fn discard(mut self) {
        let _ = tokio::fs::remove_file(&self.path).await;
        self.committed = true;
    }
}

impl Drop for TempBlob {
    fn drop(&mut self) {
        if !self.committed {
            let _ = fs::remove_file(&self.path);
        }
    }
}

/// A directory under `tmp/` (the members of an archive being unpacked); removed with its files on drop.
#[derive(Debug)]
pub struct ScratchDir {
    path: PathBuf,
}

impl ScratchDir {
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.path);
    }
}

/// How long a file in a data directory shared by several processes must lie untouched before a start-up sweep
/// may take it for abandoned (an upload in progress in another process is written to all the time).
pub const SHARED_IDLE: Duration = Duration::from_secs(3600);

/// Whether nothing under `path` was modified within `idle` (a directory counts its entries, one level down:
/// the members of an archive being unpacked). Unreadable metadata counts as recent.
pub fn idle_for(path: &Path, idle: Duration) -> bool {
    let recent = |p: &Path| {
        fs::symlink_metadata(p)
            .and_then(|m| m.modified())
            .map(|t| t.elapsed().map_or(true, |age| age < idle))
            .unwrap_or(true)
    };
    if recent(path) {
        return false;
    }
    match fs::read_dir(path) {
        Ok(entries) => !entries.flatten().any(|e| recent(&e.path())),
        Err(_) => true,
    }
}

fn sync_dir(dir: &Path) {
    // Best effort: makes the rename durable on file systems that support syncing directories.
    if let Ok(d) = fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

impl BlobStore {
    /// Create the layout under `root` and empty `tmp/`: the data directory of one process.
    pub fn open(root: &Path) -> io::Result<Self> {
        Self::open_shared(root, Duration::ZERO)
    }

    /// Create the layout under `root` and remove what `tmp/` holds untouched for at least `idle`. Several
    /// processes may share the directory (API processes and workers on one job database): another one's
    /// upload in progress is written to all the time, so only what was abandoned goes.
    pub fn open_shared(root: &Path, idle: Duration) -> io::Result<Self> {
        for sub in [
            "datasets",
            "results",
            "series",
            "uploads",
            "instances",
            "tmp",
        ] {
            fs::create_dir_all(root.join(sub))?;
        }
        for entry in fs::read_dir(root.join("tmp"))? {
            let entry = entry?;
            if !idle.is_zero() && !idle_for(&entry.path(), idle) {
                continue;
            }
            let gone = if entry.file_type()?.is_dir() {
                fs::remove_dir_all(entry.path())
            } else {
                fs::remove_file(entry.path())
            };
            match gone {
                // Another process sharing the directory may have removed it first.
                Err(e) if e.kind() != io::ErrorKind::NotFound => return Err(e),
                _ => {}
            }
        }
        Ok(Self {
            root: root.to_path_buf(),
            mirror: None,
        })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn dataset_path(&self, id: DatasetId) -> PathBuf {
        self.root.join("datasets").join(format!("{id}.npy"))
    }

    pub fn series_path(&self, id: SeriesId) -> PathBuf {
        self.root.join("series").join(format!("{id}.npy"))
    }

    pub fn upload_dir(&self, id: UploadId) -> PathBuf {
        self.root.join("uploads").join(id.to_string())
    }

    /// An instance of an open upload, named by the hex SHA-256 of its bytes (computed here, never sent).
    pub fn upload_file(&self, id: UploadId, sha256_hex: &str) -> PathBuf {
        self.upload_dir(id).join(format!("{sha256_hex}.dcm"))
    }

    /// Remove an upload's instances from the data directory only (missing is fine); see
    /// [`remove_upload`](Self::remove_upload).
    pub fn remove_upload_here(&self, id: UploadId) -> io::Result<()> {
        match fs::remove_dir_all(self.upload_dir(id)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// The file of an indexed instance: received ones under their upload, derived ones under their job.
    pub fn instance_path(&self, owner: InstanceOwner, id: InstanceId) -> PathBuf {
        match owner {
            InstanceOwner::Upload(u) => self.instance_dir(u).join(format!("{id}.dcm")),
            InstanceOwner::Job(j) => self
                .result_dir(j)
                .join("instances")
                .join(format!("{id}.dcm")),
        }
    }

    /// The folder of the indexed instances an upload received.
    pub fn instance_dir(&self, upload: UploadId) -> PathBuf {
        self.root.join("instances").join(upload.to_string())
    }

    /// Remove the indexed instances an upload received (missing is fine).
    pub fn remove_instances(&self, upload: UploadId) -> io::Result<()> {
        match fs::remove_dir_all(self.instance_dir(upload)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    pub fn result_dir(&self, id: JobId) -> PathBuf {
        self.root.join("results").join(id.to_string())
    }

    pub fn result_path(&self, id: JobId, name: &ResultName) -> PathBuf {
        self.result_dir(id).join(name.file_name())
    }

    /// A fresh temporary file name under `tmp/` (the file is not created).
    pub fn temp(&self) -> TempBlob {
        TempBlob {
            path: self
                .root
                .join("tmp")
                .join(format!("{}.part", uuid::Uuid::new_v4())),
            committed: false,
        }
    }

    /// A fresh, empty scratch directory under `tmp/`.
    pub fn scratch(&self) -> io::Result<ScratchDir> {
        let path = self
            .root
            .join("tmp")
            .join(format!("{}.d", uuid::Uuid::new_v4()));
        fs::create_dir(&path)?;
        Ok(ScratchDir { path })
    }

    /// Write `bytes` to a temporary file and sync it; [`commit`](Self::commit) moves it into place once its
    /// database row exists (so a crash leaves a row without a file, never a file without a row).
    pub fn write_temp(&self, bytes: &[u8]) -> io::Result<TempBlob> {
        self.write_temp_with(|f| f.write_all(bytes))
            .map(|(temp, ())| temp)
    }

    /// [`write_temp`](Self::write_temp) of what `write` writes through a 64 KiB buffer (the file is removed
    /// when it fails).
    pub fn write_temp_with<T>(
        &self,
        write: impl FnOnce(&mut io::BufWriter<fs::File>) -> io::Result<T>,
    ) -> io::Result<(TempBlob, T)> {
        let temp = self.temp();
        let mut f = io::BufWriter::with_capacity(64 << 10, fs::File::create(temp.path())?);
        let out = write(&mut f)?;
        f.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        Ok((temp, out))
    }

    /// [`commit`](Self::commit) off the async runtime.
    pub async fn commit_async(&self, temp: TempBlob, dest: PathBuf) -> io::Result<()> {
        let store = self.clone();
        tokio::task::spawn_blocking(move || store.commit(temp, &dest))
            .await
            .map_err(io::Error::other)?
    }

    /// Remove a file off the async runtime (missing is fine).
    pub async fn remove_file(path: &Path) -> io::Result<()> {
        match tokio::fs::remove_file(path).await {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// Move a fully written and synced temporary file to `dest` (atomic on one file system). With object
    /// storage a durable blob is first put to its object (complete or absent there too), so a local file
    /// always has its object; blocking, so call it off the async runtime ([`commit_async`](Self::commit_async)).
    pub fn commit(&self, temp: TempBlob, dest: &Path) -> io::Result<()> {
        if let Some((mirror, key)) = self.mirrored(dest) {
            mirror.put_file(&key, temp.path())?;
        }
        self.commit_local(temp, dest)
    }

    /// Move a temporary file to `dest` in the data directory only.
    fn commit_local(&self, mut temp: TempBlob, dest: &Path) -> io::Result<()> {
        if let Some(parent) = dest.parent() {
            fs::create_dir_all(parent)?;
        }
        fs::rename(&temp.path, dest)?;
        temp.committed = true;
        if let Some(parent) = dest.parent() {
            sync_dir(parent);
        }
        Ok(())
    }

    /// Write `bytes` to `dest` atomically: temporary file, fsync, rename.
    pub fn write_atomic(&self, dest: &Path, bytes: &[u8]) -> io::Result<()> {
        let temp = self.write_temp(bytes)?;
        self.commit(temp, dest)
    }

    /// Remove a job's results from the data directory (missing is fine); the objects stay (see
    /// [`delete_results`](Self::delete_results)).
    pub fn remove_results(&self, id: JobId) -> io::Result<()> {
        match fs::remove_dir_all(self.result_dir(id)) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// The store is usable: a probe file can be written, read back and removed.
    pub fn probe(&self) -> bool {
        let temp = self.temp();
        fs::write(temp.path(), b"ok").is_ok() && fs::read(temp.path()).is_ok_and(|b| b == b"ok")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_shared_directory_keeps_scratch_in_use_and_removes_what_was_abandoned() {
        let dir = tempfile::tempdir().unwrap();
        let tmp = dir.path().join("tmp");
        fs::create_dir_all(tmp.join("unpacking")).unwrap();
        fs::write(tmp.join("live.part"), b"x").unwrap();
        fs::write(tmp.join("unpacking").join("member"), b"x").unwrap();
        fs::write(tmp.join("old.part"), b"x").unwrap();
        fs::create_dir_all(tmp.join("old-dir")).unwrap();
        fs::write(tmp.join("old-dir").join("member"), b"x").unwrap();
        let two_hours_ago = std::time::SystemTime::now() - Duration::from_secs(7200);
        let age = |p: &Path| {
            let f = fs::File::options()
                .write(true)
                .open(p)
                .or_else(|_| fs::File::open(p));
            f.unwrap().set_modified(two_hours_ago).unwrap();
        };
        age(&tmp.join("old.part"));
        age(&tmp.join("old-dir").join("member"));
        age(&tmp.join("old-dir"));
        BlobStore::open_shared(dir.path(), SHARED_IDLE).unwrap();
        let mut left: Vec<String> = fs::read_dir(&tmp)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(left, ["live.part", "unpacking"]);
        // One process alone empties it.
        BlobStore::open(dir.path()).unwrap();
        assert_eq!(fs::read_dir(&tmp).unwrap().count(), 0);
    }

    #[test]
    fn atomic_writes_leave_no_temporary_files_and_paths_come_from_ids() {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::open(dir.path()).unwrap();
        let job = JobId::generate();
        let dest = store.result_path(job, &ResultName::Volume);
        assert!(dest.starts_with(dir.path().join("results")));
        store.write_atomic(&dest, b"abc").unwrap();
        assert_eq!(fs::read(&dest).unwrap(), b"abc");
        assert_eq!(fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0);
        assert!(store.probe());
        store.remove_results(job).unwrap();
        assert!(!dest.exists());
        store.remove_results(job).unwrap();
    }
}
