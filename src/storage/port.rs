//! The blob-store port, shaped after the `object_store` crate so that an S3 adapter is a drop-in: objects
//! under `/`-separated keys, a streamed put that is complete or absent, ranged gets, remove, list by prefix,
//! and metadata with a strong ETag, size and last-modified time. The data directory ([`BlobStore`]) is the
//! first adapter; [`conformance`] is the suite every adapter passes.
//!
//! Numeric kernels that need a local file (memory-mapped or `.npy` reads) ask [`Blobs::local_path`]: the
//! directory adapter answers its own file, an object-store adapter fetches the object to a temporary file.

use std::io;
use std::ops::Range;
use std::path::{Path, PathBuf};

use futures_util::FutureExt;
use futures_util::future::BoxFuture;
use futures_util::stream::{BoxStream, StreamExt};
use tokio::io::{AsyncReadExt, AsyncSeekExt, AsyncWriteExt};

use super::BlobStore;

/// A validated object key: `/`-separated segments of `[A-Za-z0-9._-]`, none empty, `.` or `..`.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct BlobKey(String);

impl BlobKey {
    pub fn parse(key: &str) -> io::Result<Self> {
        let ok = !key.is_empty()
            && key.split('/').all(|s| {
                !s.is_empty()
                    && s != "."
                    && s != ".."
                    && s.chars()
                        .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
            });
        if ok {
            Ok(Self(key.to_string()))
        } else {
            Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("invalid blob key {key:?}"),
            ))
        }
    }
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// What a store knows of an object.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlobMeta {
    pub key: BlobKey,
    pub size: u64,
    /// Strong validator (unquoted), the same from `put`, `head` and `list` while the object is unchanged
    /// (the directory adapter derives it from size and modification time, as S3 servers derive theirs).
    pub e_tag: String,
    /// Microseconds since the Unix epoch.
    pub last_modified_us: i64,
}

/// A stream of chunks, as a put takes it and a get gives it.
pub type ByteStream = BoxStream<'static, io::Result<Vec<u8>>>;

/// The blob-store port.
pub trait Blobs: Send + Sync {
    /// Store the whole stream under `key`: afterwards the object is complete, or (on any error, including
    /// one from the stream) absent and any earlier object under `key` unchanged.
    fn put(&self, key: &BlobKey, body: ByteStream) -> BoxFuture<'_, io::Result<BlobMeta>>;
    /// The object's bytes in `range` (all of them for `None`); `NotFound` when absent, `InvalidInput` when
    /// the range starts past the end.
    fn get(
        &self,
        key: &BlobKey,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'_, io::Result<ByteStream>>;
    fn head(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<BlobMeta>>;
    /// Remove the object; removing an absent one is not an error.
    fn delete(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<()>>;
    /// Every object whose key starts with `prefix` followed by `/` (or equals it), sorted by key.
    fn list(&self, prefix: &BlobKey) -> BoxFuture<'_, io::Result<Vec<BlobMeta>>>;
    /// A local file holding the object, for kernels that map or seek files.
    fn local_path(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<PathBuf>>;
    /// The store can be used now: reachable, and the credentials allowed to read (`/readyz`). A local
    /// directory always is.
    fn check(&self) -> BoxFuture<'_, io::Result<()>> {
        async { Ok(()) }.boxed()
    }
}

fn meta_of(key: BlobKey, md: &std::fs::Metadata) -> BlobMeta {
    let modified_us = md
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_micros() as i64);
    BlobMeta {
        key,
        size: md.len(),
        e_tag: format!("{:x}-{:x}", md.len(), modified_us),
        last_modified_us: modified_us,
    }
}

impl BlobStore {
    fn object_path(&self, key: &BlobKey) -> PathBuf {
        key.0
            .split('/')
            .fold(self.root().to_path_buf(), |p, s| p.join(s))
    }

    async fn put_stream(&self, key: &BlobKey, mut body: ByteStream) -> io::Result<BlobMeta> {
        let temp = self.temp();
        let written: io::Result<()> = async {
            let mut f = tokio::fs::File::create(temp.path()).await?;
            while let Some(chunk) = body.next().await {
                f.write_all(&chunk?).await?;
            }
            f.sync_all().await
        }
        .await;
        if let Err(e) = written {
            temp.discard().await;
            return Err(e);
        }
        let dest = self.object_path(key);
        self.commit_async(temp, dest.clone()).await?;
        let md = tokio::fs::metadata(&dest).await?;
        Ok(meta_of(key.clone(), &md))
    }

    async fn get_range(&self, key: &BlobKey, range: Option<Range<u64>>) -> io::Result<ByteStream> {
        let mut f = tokio::fs::File::open(self.object_path(key)).await?;
        let len = f.metadata().await?.len();
        let r = range.unwrap_or(0..len);
        if r.start > len || r.start > r.end {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                format!("range {r:?} outside an object of {len} bytes"),
            ));
        }
        f.seek(io::SeekFrom::Start(r.start)).await?;
        let take = r.end.min(len) - r.start;
        let reader = f.take(take);
        // Pieces of up to 1 MiB: each is one read on the blocking pool (4 KiB pieces took ~50 ms a MiB).
        Ok(tokio_util::io::ReaderStream::with_capacity(reader, 1 << 20)
            .map(|c| c.map(|b| b.to_vec()))
            .boxed())
    }

    fn list_under(&self, prefix: &BlobKey) -> io::Result<Vec<BlobMeta>> {
        fn walk(dir: &Path, key: &str, out: &mut Vec<BlobMeta>) -> io::Result<()> {
            let md = match std::fs::metadata(dir) {
                Ok(md) => md,
                Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(()),
                Err(e) => return Err(e),
            };
            if md.is_file() {
                if let Ok(k) = BlobKey::parse(key) {
                    out.push(meta_of(k, &md));
                }
                return Ok(());
            }
            for entry in std::fs::read_dir(dir)? {
                let entry = entry?;
                let name = entry.file_name().to_string_lossy().into_owned();
                walk(&entry.path(), &format!("{key}/{name}"), out)?;
            }
            Ok(())
        }
        let mut out = Vec::new();
        walk(&self.object_path(prefix), prefix.as_str(), &mut out)?;
        out.sort_by(|a, b| a.key.cmp(&b.key));
        Ok(out)
    }
}

impl Blobs for BlobStore {
    fn put(&self, key: &BlobKey, body: ByteStream) -> BoxFuture<'_, io::Result<BlobMeta>> {
        let key = key.clone();
        async move { self.put_stream(&key, body).await }.boxed()
    }

    fn get(
        &self,
        key: &BlobKey,
        range: Option<Range<u64>>,
    ) -> BoxFuture<'_, io::Result<ByteStream>> {
        let key = key.clone();
        async move { self.get_range(&key, range).await }.boxed()
    }

    fn head(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<BlobMeta>> {
        let key = key.clone();
        async move {
            let md = tokio::fs::metadata(self.object_path(&key)).await?;
            if !md.is_file() {
                return Err(io::Error::new(io::ErrorKind::NotFound, "not an object"));
            }
            Ok(meta_of(key, &md))
        }
        .boxed()
    }

    fn delete(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<()>> {
        let path = self.object_path(key);
        async move { BlobStore::remove_file(&path).await }.boxed()
    }

    fn list(&self, prefix: &BlobKey) -> BoxFuture<'_, io::Result<Vec<BlobMeta>>> {
        let store = self.clone();
        let prefix = prefix.clone();
        async move {
            tokio::task::spawn_blocking(move || store.list_under(&prefix))
                .await
                .map_err(io::Error::other)?
        }
        .boxed()
    }

    fn local_path(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<PathBuf>> {
        let path = self.object_path(key);
        async move {
            tokio::fs::metadata(&path).await?;
            Ok(path)
        }
        .boxed()
    }
}

pub mod conformance {
    //! What every [`Blobs`] adapter must do, as async checks that panic on a violation; instantiate them
    //! all for an adapter with `ctrecon::blob_store_conformance!(make_store())`.

    use super::*;

    fn key(k: &str) -> BlobKey {
        BlobKey::parse(k).expect("a valid key")
    }

    fn body(chunks: Vec<io::Result<Vec<u8>>>) -> ByteStream {
        futures_util::stream::iter(chunks).boxed()
    }

    async fn read(s: &dyn Blobs, k: &BlobKey, r: Option<Range<u64>>) -> Vec<u8> {
        let mut st = s.get(k, r).await.expect("get");
        let mut out = Vec::new();
        while let Some(c) = st.next().await {
            out.extend(c.expect("chunk"));
        }
        out
    }

    /// A streamed put is read back whole and in ranges, with its size and a strong ETag.
    pub async fn put_then_get_whole_and_ranges(s: &dyn Blobs) {
        let k = key("results/a/volume.npy");
        let m = s
            .put(
                &k,
                body(vec![Ok(b"hello ".to_vec()), Ok(b"world".to_vec())]),
            )
            .await
            .expect("put");
        assert_eq!(m.size, 11);
        assert!(!m.e_tag.is_empty());
        assert_eq!(read(s, &k, None).await, b"hello world");
        assert_eq!(read(s, &k, Some(6..11)).await, b"world");
        assert_eq!(read(s, &k, Some(6..100)).await, b"world");
        assert_eq!(s.head(&k).await.expect("head").size, 11);
        assert!(s.local_path(&k).await.is_ok());
    }

    /// A put whose stream fails leaves nothing, and an earlier object under the key unchanged.
    pub async fn a_failed_put_leaves_the_object_complete_or_absent(s: &dyn Blobs) {
        let k = key("datasets/b.npy");
        let failing = || {
            body(vec![
                Ok(b"part".to_vec()),
                Err(io::Error::other("client went away")),
            ])
        };
        assert!(s.put(&k, failing()).await.is_err());
        assert_eq!(
            s.head(&k).await.map_err(|e| e.kind()).err(),
            Some(io::ErrorKind::NotFound)
        );
        s.put(&k, body(vec![Ok(b"v1".to_vec())]))
            .await
            .expect("put");
        assert!(s.put(&k, failing()).await.is_err());
        assert_eq!(read(s, &k, None).await, b"v1");
    }

    /// Remove is idempotent; absent objects answer `NotFound`.
    pub async fn remove_is_idempotent_and_absent_objects_are_not_found(s: &dyn Blobs) {
        let k = key("series/c.npy");
        s.put(&k, body(vec![Ok(vec![1, 2, 3])])).await.expect("put");
        s.delete(&k).await.expect("delete");
        s.delete(&k).await.expect("delete again");
        assert_eq!(
            s.get(&k, None).await.err().map(|e| e.kind()),
            Some(io::ErrorKind::NotFound)
        );
    }

    /// List by prefix finds exactly the objects under it, sorted.
    pub async fn list_by_prefix(s: &dyn Blobs) {
        for k in [
            "results/j1/volume.npy",
            "results/j1/product-0.npy",
            "results/j2/volume.npy",
        ] {
            s.put(&key(k), body(vec![Ok(vec![0])])).await.expect("put");
        }
        let keys: Vec<String> = s
            .list(&key("results/j1"))
            .await
            .expect("list")
            .into_iter()
            .map(|m| m.key.as_str().to_string())
            .collect();
        assert_eq!(
            keys,
            vec!["results/j1/product-0.npy", "results/j1/volume.npy"]
        );
        assert!(s.list(&key("results/none")).await.expect("list").is_empty());
    }

    /// Keys that could escape the store are refused before any adapter sees them.
    pub async fn keys_cannot_escape(_: &dyn Blobs) {
        for bad in ["", "/abs", "a/../b", "a//b", "a/./b", "a\\b", "a b"] {
            assert!(BlobKey::parse(bad).is_err(), "{bad:?}");
        }
    }

    /// Instantiate every check as a `#[tokio::test]` for the store `$make` (a future of a fresh store).
    /// `maybe: $make` takes a future of `Option<(store, guard)>` instead, for adapters whose server may be
    /// missing: `None` ends the test (the fixture has said why), and the guard lives until the check ends.
    #[macro_export]
    macro_rules! blob_store_conformance {
        (maybe: $make:expr) => {
            $crate::blob_store_conformance!(@maybe $make; @all);
        };
        ($make:expr) => {
            $crate::blob_store_conformance!(@always $make; @all);
        };
        (@$how:ident $make:expr; @all) => {
            $crate::blob_store_conformance!(@$how $make;
                put_then_get_whole_and_ranges,
                a_failed_put_leaves_the_object_complete_or_absent,
                remove_is_idempotent_and_absent_objects_are_not_found,
                list_by_prefix,
                keys_cannot_escape,
            );
        };
        (@always $make:expr; $($case:ident),* $(,)?) => {
            $(
                #[tokio::test]
                async fn $case() {
                    let store = $make.await;
                    $crate::storage::port::conformance::$case(&store).await;
                }
            )*
        };
        (@maybe $make:expr; $($case:ident),* $(,)?) => {
            $(
                #[tokio::test]
                async fn $case() {
                    let Some((store, _guard)) = $make.await else { return };
                    $crate::storage::port::conformance::$case(&store).await;
                }
            )*
        };
    }
}
