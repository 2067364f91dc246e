//! Object storage behind the data directory (`storage.url = "s3://…"`): several hosts, each with a data
//! directory of its own, share datasets, assembled series, job results and the instances of open uploads.
//!
//! - **Durable in the object store.** A blob under `datasets/`, `series/`, `results/` (renderings cached as
//!   `derived-*` excepted: any host makes them again) or `uploads/<upload>/` is put to the object of the
//!   same key *before* its temporary file is renamed into place ([`BlobStore::commit`]), and every caller
//!   commits before it records the blob as there (a dataset's 201, a series' answer, a job's `succeeded`,
//!   an instance's acknowledgement, so that an upload can be completed through any API host). A put is
//!   complete or absent (one `PutObject`, or a multipart upload that is aborted when the file cannot be
//!   read), streamed from the synced temporary file, never whole in memory.
//! - **The data directory is a cache.** A reader asks for a local path ([`BlobStore::local`] on the
//!   worker pool, [`BlobStore::fetch`] on the runtime): a file that is not there is fetched from its object
//!   into `tmp/`, synced and renamed, so a reader never sees a part of it. Results are served to clients
//!   straight from the object with ranged GETs when the API host has no copy ([`BlobStore::object_meta`]).
//! - **Deletion** removes the object too ([`BlobStore::remove_blob`], [`BlobStore::delete_results`],
//!   [`BlobStore::remove_upload`]); the start-up removal of an unfinished job's partial files stays local,
//!   since on a shared job database another host may be running that job.

use std::fmt;
use std::future::Future;
use std::io;
use std::ops::Range;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use futures_util::StreamExt;
use tokio::io::AsyncWriteExt;
use tokio::runtime::{Handle, RuntimeFlavor};

use super::port::{BlobKey, BlobMeta, Blobs, ByteStream};
use super::{BlobStore, JobId, UploadId};

/// The top-level folders of the data directory whose files live in the object store.
const DURABLE: [&str; 4] = ["datasets", "series", "results", "uploads"];
/// How long `/readyz` waits for the object store to answer.
const CHECK_WITHIN: std::time::Duration = std::time::Duration::from_secs(3);
/// Read size when a file is streamed to the object store.
const CHUNK: usize = 1 << 20;

/// The object store that holds the durable copy of a data directory's blobs.
#[derive(Clone)]
pub struct Mirror {
    blobs: Arc<dyn Blobs>,
    handle: Handle,
    name: String,
}

impl fmt::Debug for Mirror {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Mirror").field("name", &self.name).finish()
    }
}

impl Mirror {
    /// `blobs` named `name` in logs (the storage URL); blocking callers run its requests on `handle`.
    pub fn new(blobs: Arc<dyn Blobs>, handle: Handle, name: impl Into<String>) -> Self {
        Self {
            blobs,
            handle,
            name: name.into(),
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Run `fut` to its end from blocking code: a worker-pool thread, a blocking task, or a runtime worker
    /// (through `block_in_place`, so the runtime keeps serving).
    fn wait<T: Send>(&self, fut: impl Future<Output = io::Result<T>> + Send) -> io::Result<T> {
        match Handle::try_current() {
            Ok(h) if h.runtime_flavor() == RuntimeFlavor::CurrentThread => {
                std::thread::scope(|s| {
                    s.spawn(|| self.handle.block_on(fut))
                        .join()
                        .unwrap_or_else(|_| Err(io::Error::other("an object-store call panicked")))
                })
            }
            Ok(_) => tokio::task::block_in_place(|| self.handle.block_on(fut)),
            Err(_) => self.handle.block_on(fut),
        }
    }

    async fn put_file_async(&self, key: &BlobKey, path: &Path) -> io::Result<BlobMeta> {
        let file = tokio::fs::File::open(path).await?;
        let body = tokio_util::io::ReaderStream::with_capacity(file, CHUNK)
            .map(|c| c.map(|b| b.to_vec()))
            .boxed();
        let meta = self.blobs.put(key, body).await?;
        tracing::debug!(key = key.as_str(), bytes = meta.size, store = %self.name, "blob stored");
        Ok(meta)
    }

    /// Put the file at `path` to `key` (blocking).
    pub(super) fn put_file(&self, key: &BlobKey, path: &Path) -> io::Result<BlobMeta> {
        self.wait(self.put_file_async(key, path))
    }

    /// The object store answers and lets this process read (a listing), within a few seconds.
    pub async fn check(&self) -> io::Result<()> {
        match tokio::time::timeout(CHECK_WITHIN, self.blobs.check()).await {
            Ok(r) => r,
            Err(_) => Err(io::Error::new(
                io::ErrorKind::TimedOut,
                format!("no answer within {CHECK_WITHIN:?}"),
            )),
        }
    }

    /// Remove every object under `prefix` (blocking).
    fn remove_under(&self, prefix: &str) -> io::Result<()> {
        let prefix = BlobKey::parse(prefix)?;
        self.wait(async {
            for m in self.blobs.list(&prefix).await? {
                self.blobs.delete(&m.key).await?;
            }
            Ok(())
        })
    }
}

impl BlobStore {
    /// Keep the durable copy of datasets, series and results in `mirror` (the data directory becomes a cache).
    pub fn with_mirror(mut self, mirror: Mirror) -> Self {
        self.mirror = Some(mirror);
        self
    }

    pub fn mirror(&self) -> Option<&Mirror> {
        self.mirror.as_ref()
    }

    /// The object key of a durable blob at `path` in the data directory: its path below the root.
    fn key_of(&self, path: &Path) -> Option<BlobKey> {
        let rel = path.strip_prefix(self.root()).ok()?;
        let mut parts = Vec::new();
        for c in rel.components() {
            match c {
                Component::Normal(s) => parts.push(s.to_str()?),
                _ => return None,
            }
        }
        let first = *parts.first()?;
        let name = *parts.last()?;
        if parts.len() < 2 || !DURABLE.contains(&first) || name.starts_with("derived-") {
            return None;
        }
        // An upload's instances, not its folder.
        if first == "uploads" && parts.len() != 3 {
            return None;
        }
        BlobKey::parse(&parts.join("/")).ok()
    }

    /// The object store and key of `path`, when it is a durable blob and object storage is configured.
    pub(super) fn mirrored(&self, path: &Path) -> Option<(&Mirror, BlobKey)> {
        let mirror = self.mirror.as_ref()?;
        Some((mirror, self.key_of(path)?))
    }

    /// Fetch `key` into `path`: a temporary file, synced, then renamed.
    async fn fetch_into(&self, mirror: &Mirror, key: &BlobKey, path: &Path) -> io::Result<PathBuf> {
        let temp = self.temp();
        let written: io::Result<u64> = async {
            let mut body = mirror.blobs.get(key, None).await?;
            let mut f = tokio::fs::File::create(temp.path()).await?;
            let mut n = 0u64;
            while let Some(chunk) = body.next().await {
                let chunk = chunk?;
                n += chunk.len() as u64;
                f.write_all(&chunk).await?;
            }
            f.sync_all().await?;
            Ok(n)
        }
        .await;
        let bytes = match written {
            Ok(n) => n,
            Err(e) => {
                temp.discard().await;
                return Err(e);
            }
        };
        let store = self.clone();
        let dest = path.to_path_buf();
        tokio::task::spawn_blocking(move || store.commit_local(temp, &dest))
            .await
            .map_err(io::Error::other)??;
        tracing::debug!(key = key.as_str(), bytes, store = %mirror.name, "blob fetched into the cache");
        Ok(path.to_path_buf())
    }

    /// `path` as a local file: as it is, or (a durable blob this host has no copy of) fetched from its
    /// object first. Blocking: for the worker pool and blocking tasks.
    pub fn local(&self, path: &Path) -> io::Result<PathBuf> {
        match self.mirrored(path) {
            Some((mirror, key)) if !path.is_file() => {
                mirror.wait(self.fetch_into(mirror, &key, path))
            }
            _ => Ok(path.to_path_buf()),
        }
    }

    /// [`local`](Self::local) on the async runtime.
    pub async fn fetch(&self, path: &Path) -> io::Result<PathBuf> {
        match self.mirrored(path) {
            Some((mirror, key)) if !tokio::fs::try_exists(path).await.unwrap_or(false) => {
                self.fetch_into(mirror, &key, path).await
            }
            _ => Ok(path.to_path_buf()),
        }
    }

    /// Whether the blob at `path` exists here or in the object store.
    pub async fn exists(&self, path: &Path) -> io::Result<bool> {
        if tokio::fs::try_exists(path).await? {
            return Ok(true);
        }
        match self.mirrored(path) {
            None => Ok(false),
            Some((mirror, key)) => match mirror.blobs.head(&key).await {
                Ok(_) => Ok(true),
                Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(false),
                Err(e) => Err(e),
            },
        }
    }

    /// What the object store knows of the blob at `path` when this host has no copy of it (`None`: serve
    /// the local file, or there is no object storage).
    pub async fn object_meta(&self, path: &Path) -> io::Result<Option<BlobMeta>> {
        let Some((mirror, key)) = self.mirrored(path) else {
            return Ok(None);
        };
        if tokio::fs::try_exists(path).await.unwrap_or(false) {
            return Ok(None);
        }
        mirror.blobs.head(&key).await.map(Some)
    }

    /// The bytes in `range` (all for `None`) of the object behind `path`.
    pub async fn object_get(
        &self,
        path: &Path,
        range: Option<Range<u64>>,
    ) -> io::Result<ByteStream> {
        let (mirror, key) = self.mirrored(path).ok_or_else(|| {
            io::Error::new(io::ErrorKind::NotFound, "not a blob kept in object storage")
        })?;
        mirror.blobs.get(&key, range).await
    }

    /// Remove the blob at `path` here and its object (missing is fine). Blocking.
    pub fn remove_blob(&self, path: &Path) -> io::Result<()> {
        if let Some((mirror, key)) = self.mirrored(path) {
            mirror.wait(mirror.blobs.delete(&key))?;
        }
        match std::fs::remove_file(path) {
            Err(e) if e.kind() != io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }

    /// [`remove_blob`](Self::remove_blob) on the async runtime.
    pub async fn remove_blob_async(&self, path: &Path) -> io::Result<()> {
        if let Some((mirror, key)) = self.mirrored(path) {
            mirror.blobs.delete(&key).await?;
        }
        BlobStore::remove_file(path).await
    }

    /// Remove a job's results here and their objects (missing is fine). Blocking.
    pub fn delete_results(&self, id: JobId) -> io::Result<()> {
        if let Some(mirror) = &self.mirror {
            mirror.remove_under(&format!("results/{id}"))?;
        }
        self.remove_results(id)
    }

    /// Remove the instances of an upload here and their objects (missing is fine): once it is completed,
    /// deleted or retired. Another host's copies of them go with that host's start-up sweep. Blocking.
    pub fn remove_upload(&self, id: UploadId) -> io::Result<()> {
        if let Some(mirror) = &self.mirror {
            mirror.remove_under(&format!("uploads/{id}"))?;
        }
        self.remove_upload_here(id)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::storage::{DatasetId, ResultName, SeriesId};

    #[test]
    fn durable_blobs_map_to_their_path_below_the_root_and_caches_stay_local() {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::open(dir.path()).unwrap();
        let job = JobId::generate();
        let key = |p: PathBuf| store.key_of(&p).map(|k| k.as_str().to_string());
        assert_eq!(
            key(store.result_path(job, &ResultName::Volume)),
            Some(format!("results/{job}/volume.npy"))
        );
        let d = DatasetId::generate();
        assert_eq!(
            key(store.dataset_path(d)),
            Some(format!("datasets/{d}.npy"))
        );
        let s = SeriesId::generate();
        assert_eq!(key(store.series_path(s)), Some(format!("series/{s}.npy")));
        let derived = ResultName::Derived {
            key_hex: "ab".into(),
            ext: "png",
        };
        assert_eq!(key(store.result_path(job, &derived)), None);
        // An upload's instances are kept too (any API host may complete it), its folder is no blob.
        let u = UploadId::generate();
        let sha = "ab".repeat(32);
        assert_eq!(
            key(store.upload_file(u, &sha)),
            Some(format!("uploads/{u}/{sha}.dcm"))
        );
        assert_eq!(key(store.upload_dir(u)), None);
        assert_eq!(key(dir.path().join("tmp").join("x.part")), None);
        assert_eq!(key(PathBuf::from("/elsewhere/results/x")), None);
        // Without object storage nothing is mirrored and local paths are answered as they are.
        let p = store.dataset_path(d);
        assert!(store.mirrored(&p).is_none());
        assert_eq!(store.local(&p).unwrap(), p);
    }
}
