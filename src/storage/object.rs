//! The object-storage adapter of the blob-store port: S3 and S3-compatible servers (AWS, MinIO, Garage,
//! Ceph) through the `object_store` crate, selected by `storage.url = "s3://bucket/prefix"`.
//!
//! - **Complete or absent.** A body up to [`SINGLE_PUT_MAX`] is sent as one `PutObject`; a larger one as
//!   a multipart upload whose parts are sent while the stream is read (never the whole object in memory).
//!   S3 makes neither visible before it completes, and an upload whose stream fails is aborted, so an
//!   earlier object under the key stays as it was.
//! - **Strong ETags** are the server's (quotes removed), the same from `put`, `head` and `list`.
//! - **Ranged gets** ask the server for exactly the bytes wanted; a range past the end is refused before
//!   any request for the body, and one running past the end is cut to the object's size.
//! - **Local files** for kernels that map or seek: the object is fetched once into a cache directory,
//!   named by the key and its ETag, written to a temporary file and renamed, so a reader never sees a
//!   part of it.

use std::io;
use std::ops::Range;
use std::path::{Path as FsPath, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use futures_util::FutureExt;
use futures_util::future::BoxFuture;
use futures_util::stream::{StreamExt, TryStreamExt};
use object_store::aws::AmazonS3Builder;
use object_store::path::Path;
use object_store::{
    ClientOptions, GetOptions, GetRange, ObjectMeta, ObjectStore, ObjectStoreExt, PutPayload,
    RetryConfig, WriteMultipart,
};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use super::port::{BlobKey, BlobMeta, Blobs, ByteStream};

/// Bodies up to this size go as one `PutObject`; larger ones as a multipart upload.
pub const SINGLE_PUT_MAX: usize = 8 << 20;
/// Size of a multipart upload's parts (S3 wants at least 5 MiB for all but the last).
pub const PART_SIZE: usize = 8 << 20;
/// Parts in flight at once during a multipart upload.
const PARTS_IN_FLIGHT: usize = 4;
/// How long a request is retried against a server that fails or does not answer.
pub const GIVE_UP: Duration = Duration::from_secs(15);
/// How long connecting to the server may take.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);

/// The `AWS_*` variables the S3 adapter reads (a deployment's environment names only these).
pub const AWS_VARIABLES: &[&str] = &[
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN",
    "AWS_REGION",
    "AWS_DEFAULT_REGION",
    "AWS_ENDPOINT_URL",
    "AWS_ENDPOINT",
    "AWS_ALLOW_HTTP",
];

/// Where and how to reach an S3-compatible server.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct S3Location {
    pub bucket: String,
    /// Key prefix inside the bucket (no leading or trailing `/`; empty for the bucket's root).
    pub prefix: String,
    /// Endpoint for self-hosted servers (`http://127.0.0.1:9000`); requests are then path-style.
    pub endpoint: Option<String>,
    pub region: Option<String>,
    /// Credentials; absent = the usual `AWS_*` variables (and, on AWS, instance metadata).
    pub access_key_id: Option<String>,
    pub secret_access_key: Option<String>,
}

impl S3Location {
    /// Parse `s3://bucket[/prefix]`.
    pub fn parse(url: &str) -> Result<Self, String> {
        let rest = url
            .strip_prefix("s3://")
            .ok_or_else(|| format!("storage URL {url:?} must start with s3://"))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let bucket_ok = (3..=63).contains(&bucket.len())
            && bucket
                .chars()
                .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.');
        if !bucket_ok {
            return Err(format!(
                "bucket name {bucket:?} is not a valid S3 bucket name (3–63 of a-z, 0-9, '-', '.')"
            ));
        }
        let prefix = prefix.trim_matches('/').to_string();
        if !prefix.is_empty() && BlobKey::parse(&prefix).is_err() {
            return Err(format!(
                "key prefix {prefix:?} must be '/'-separated segments of [A-Za-z0-9._-]"
            ));
        }
        Ok(Self {
            bucket: bucket.to_string(),
            prefix,
            endpoint: None,
            region: None,
            access_key_id: None,
            secret_access_key: None,
        })
    }
}

/// Blobs kept in an object store.
#[derive(Debug, Clone)]
pub struct ObjectBlobs {
    store: Arc<dyn ObjectStore>,
    prefix: String,
    cache: PathBuf,
}

fn to_io(e: object_store::Error) -> io::Error {
    match e {
        object_store::Error::NotFound { .. } => io::Error::new(io::ErrorKind::NotFound, e),
        object_store::Error::InvalidPath { .. } => io::Error::new(io::ErrorKind::InvalidInput, e),
        object_store::Error::PermissionDenied { .. }
        | object_store::Error::Unauthenticated { .. } => {
            io::Error::new(io::ErrorKind::PermissionDenied, e)
        }
        other => io::Error::other(other),
    }
}

fn unquote(e_tag: &str) -> String {
    e_tag.trim_matches('"').to_string()
}

impl ObjectBlobs {
    /// An adapter over any object store; `cache` is a local directory for [`Blobs::local_path`].
    pub fn new(store: Arc<dyn ObjectStore>, prefix: &str, cache: &FsPath) -> io::Result<Self> {
        std::fs::create_dir_all(cache)?;
        Ok(Self {
            store,
            prefix: prefix.trim_matches('/').to_string(),
            cache: cache.to_path_buf(),
        })
    }

    /// An adapter over an S3-compatible server. What `location` leaves out comes from the `AWS_*`
    /// variables (`AWS_ENDPOINT_URL`, `AWS_REGION`, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, …). A
    /// server that does not answer fails a request within about [`GIVE_UP`], not after minutes of retries.
    pub fn s3(location: &S3Location, cache: &FsPath) -> io::Result<Self> {
        let mut builder = AmazonS3Builder::from_env()
            .with_bucket_name(&location.bucket)
            .with_retry(RetryConfig {
                max_retries: 3,
                retry_timeout: GIVE_UP,
                ..RetryConfig::default()
            })
            .with_client_options(ClientOptions::new().with_connect_timeout(CONNECT_TIMEOUT));
        let endpoint = location.endpoint.clone().or_else(|| {
            ["AWS_ENDPOINT_URL", "AWS_ENDPOINT"]
                .iter()
                .find_map(|v| std::env::var(v).ok().filter(|e| !e.is_empty()))
        });
        if let Some(endpoint) = &endpoint {
            builder = builder
                .with_endpoint(endpoint)
                .with_allow_http(endpoint.starts_with("http://"))
                .with_virtual_hosted_style_request(false);
        }
        if let Some(region) = &location.region {
            builder = builder.with_region(region);
        }
        if let Some(id) = &location.access_key_id {
            builder = builder.with_access_key_id(id);
        }
        if let Some(secret) = &location.secret_access_key {
            builder = builder.with_secret_access_key(secret);
        }
        let store = builder.build().map_err(|e| {
            io::Error::new(io::ErrorKind::InvalidInput, format!("object storage: {e}"))
        })?;
        Self::new(Arc::new(store), &location.prefix, cache)
    }

    fn path(&self, key: &BlobKey) -> Path {
        if self.prefix.is_empty() {
            Path::from(key.as_str())
        } else {
            Path::from(format!("{}/{}", self.prefix, key.as_str()))
        }
    }

    fn meta(&self, m: ObjectMeta) -> Option<BlobMeta> {
        let full = m.location.as_ref();
        let rel = if self.prefix.is_empty() {
            full
        } else {
            full.strip_prefix(self.prefix.as_str())?.strip_prefix('/')?
        };
        Some(BlobMeta {
            key: BlobKey::parse(rel).ok()?,
            size: m.size,
            e_tag: m.e_tag.as_deref().map(unquote).unwrap_or_default(),
            last_modified_us: m.last_modified.timestamp_micros(),
        })
    }

    /// Reachable and allowed: a list of the prefix (read access) that must not fail. Used at start so
    /// that wrong credentials or a missing bucket stop the process with a message instead of failing jobs.
    pub async fn check(&self) -> io::Result<()> {
        let prefix = (!self.prefix.is_empty()).then(|| Path::from(self.prefix.as_str()));
        self.store
            .list_with_delimiter(prefix.as_ref())
            .await
            .map(|_| ())
            .map_err(|e| {
                // Servers answer these as plain 403/404 statuses, which the client reports as generic.
                let text = e.to_string();
                let any = |codes: &[&str]| codes.iter().any(|c| text.contains(c));
                let kind = if any(&[
                    "SignatureDoesNotMatch",
                    "InvalidAccessKeyId",
                    "AccessDenied",
                    "403 Forbidden",
                ]) {
                    io::ErrorKind::PermissionDenied
                } else if any(&["NoSuchBucket", "404 Not Found"]) {
                    io::ErrorKind::NotFound
                } else {
                    to_io(e).kind()
                };
                io::Error::new(kind, text)
            })
    }

    async fn put_stream(&self, key: &BlobKey, mut body: ByteStream) -> io::Result<BlobMeta> {
        let path = self.path(key);
        // Read up to SINGLE_PUT_MAX; a body that ends by then is one PutObject.
        let mut head: Vec<Vec<u8>> = Vec::new();
        let mut buffered = 0usize;
        let mut ended = false;
        while buffered <= SINGLE_PUT_MAX {
            match body.next().await {
                Some(chunk) => {
                    let chunk = chunk?;
                    buffered += chunk.len();
                    head.push(chunk);
                }
                None => {
                    ended = true;
                    break;
                }
            }
        }
        let result = if ended {
            let payload: PutPayload = head.into_iter().map(bytes::Bytes::from).collect();
            self.store
                .put_opts(&path, payload, Default::default())
                .await
                .map_err(to_io)?
        } else {
            let upload = self
                .store
                .put_multipart_opts(&path, Default::default())
                .await
                .map_err(to_io)?;
            let mut writer = WriteMultipart::new_with_chunk_size(upload, PART_SIZE);
            for chunk in head {
                writer.put(bytes::Bytes::from(chunk));
            }
            let streamed: io::Result<()> = async {
                while let Some(chunk) = body.next().await {
                    let chunk = chunk?;
                    writer
                        .wait_for_capacity(PARTS_IN_FLIGHT)
                        .await
                        .map_err(to_io)?;
                    writer.put(bytes::Bytes::from(chunk));
                }
                Ok(())
            }
            .await;
            if let Err(e) = streamed {
                if let Err(abort) = writer.abort().await {
                    tracing::warn!(key = key.as_str(), error = %abort, "aborting a multipart upload failed; the server expires it");
                }
                return Err(e);
            }
            writer.finish().await.map_err(to_io)?
        };
        match result.e_tag {
            Some(tag) => {
                // Size and time from the server, so put, head and list agree.
                let mut meta = self.head_meta(key).await?;
                meta.e_tag = unquote(&tag);
                Ok(meta)
            }
            None => self.head_meta(key).await,
        }
    }

    async fn head_meta(&self, key: &BlobKey) -> io::Result<BlobMeta> {
        let m = self.store.head(&self.path(key)).await.map_err(to_io)?;
        self.meta(m)
            .ok_or_else(|| io::Error::other("the server answered for another key"))
    }

    async fn get_range(&self, key: &BlobKey, range: Option<Range<u64>>) -> io::Result<ByteStream> {
        let path = self.path(key);
        let options = match range {
            None => GetOptions::default(),
            Some(r) => {
                let size = self.head_meta(key).await?.size;
                if r.start > size || r.start > r.end {
                    return Err(io::Error::new(
                        io::ErrorKind::InvalidInput,
                        format!("range {r:?} outside an object of {size} bytes"),
                    ));
                }
                let end = r.end.min(size);
                if r.start == end {
                    return Ok(futures_util::stream::empty().boxed());
                }
                GetOptions::default().with_range(Some(GetRange::Bounded(r.start..end)))
            }
        };
        let got = self.store.get_opts(&path, options).await.map_err(to_io)?;
        Ok(got
            .into_stream()
            .map_ok(|b| b.to_vec())
            .map_err(to_io)
            .boxed())
    }

    async fn list_under(&self, prefix: &BlobKey) -> io::Result<Vec<BlobMeta>> {
        let path = self.path(prefix);
        let mut out: Vec<BlobMeta> = self
            .store
            .list(Some(&path))
            .map_err(to_io)
            .try_filter_map(|m| futures_util::future::ready(Ok(self.meta(m))))
            .try_collect()
            .await?;
        // An object named exactly like the prefix belongs to it too.
        if let Ok(m) = self.head_meta(prefix).await
            && !out.iter().any(|o| o.key == m.key)
        {
            out.push(m);
        }
        out.sort_by(|a, b| a.key.cmp(&b.key));
        Ok(out)
    }

    async fn fetch_to_cache(&self, key: &BlobKey) -> io::Result<PathBuf> {
        let meta = self.head_meta(key).await?;
        let digest = Sha256::digest(format!("{}\n{}", key.as_str(), meta.e_tag).as_bytes());
        let name: String = digest.iter().map(|b| format!("{b:02x}")).collect();
        let dest = self.cache.join(&name);
        if tokio::fs::metadata(&dest)
            .await
            .is_ok_and(|m| m.len() == meta.size)
        {
            return Ok(dest);
        }
        let temp = self
            .cache
            .join(format!("{name}.{}.part", uuid::Uuid::new_v4().simple()));
        let written: io::Result<()> = async {
            let mut f = tokio::fs::File::create(&temp).await?;
            let mut body = self.get_range(key, None).await?;
            while let Some(chunk) = body.next().await {
                f.write_all(&chunk?).await?;
            }
            f.sync_all().await
        }
        .await;
        if let Err(e) = written {
            let _ = tokio::fs::remove_file(&temp).await;
            return Err(e);
        }
        tokio::fs::rename(&temp, &dest).await?;
        Ok(dest)
    }
}

impl Blobs for ObjectBlobs {
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
        async move { self.head_meta(&key).await }.boxed()
    }

    fn delete(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<()>> {
        let path = self.path(key);
        async move {
            match self.store.delete(&path).await {
                Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                Err(e) => Err(to_io(e)),
            }
        }
        .boxed()
    }

    fn list(&self, prefix: &BlobKey) -> BoxFuture<'_, io::Result<Vec<BlobMeta>>> {
        let prefix = prefix.clone();
        async move { self.list_under(&prefix).await }.boxed()
    }

    fn local_path(&self, key: &BlobKey) -> BoxFuture<'_, io::Result<PathBuf>> {
        let key = key.clone();
        async move { self.fetch_to_cache(&key).await }.boxed()
    }

    fn check(&self) -> BoxFuture<'_, io::Result<()>> {
        async move { ObjectBlobs::check(self).await }.boxed()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_name_a_bucket_and_a_clean_prefix() {
        let l = S3Location::parse("s3://ct-results/site-a/ctrecon/").unwrap();
        assert_eq!(l.bucket, "ct-results");
        assert_eq!(l.prefix, "site-a/ctrecon");
        assert_eq!(S3Location::parse("s3://bucket").unwrap().prefix, "");
        for bad in [
            "http://bucket/x",
            "s3://",
            "s3://ab",
            "s3://Upper",
            "s3://b_u_c",
            "s3://bucket/a/../b",
            "s3://bucket/a b",
        ] {
            assert!(S3Location::parse(bad).is_err(), "{bad}");
        }
    }
}
