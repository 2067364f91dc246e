//! The blob-store conformance suite, run against the data-directory adapter and against the object-storage
//! adapter talking to a real S3 server that checks SigV4 signatures (s3s-fs, started here on a port of its
//! own; `scripts/install-peers.sh s3` builds it into `.peers/s3s/`). Without s3s-fs the S3 tests print one
//! skip line, unless `CTRECON_REQUIRE_PEERS=1` (as in CI), when they fail.

mod directory {
    use ctrecon::storage::BlobStore;

    async fn fresh() -> BlobStore {
        let dir = tempfile::tempdir().expect("temp dir").keep();
        BlobStore::open(&dir).expect("blob store")
    }

    ctrecon::blob_store_conformance!(fresh());
}

#[cfg(feature = "s3")]
use crate::s3 as s3server;

#[cfg(feature = "s3")]
mod s3 {
    use std::io;

    use ctrecon::storage::object::{ObjectBlobs, PART_SIZE, S3Location, SINGLE_PUT_MAX};
    use ctrecon::storage::port::{BlobKey, Blobs, ByteStream};
    use futures_util::StreamExt;

    use super::s3server::{ACCESS_KEY, BUCKET, S3Server, SECRET_KEY};

    /// s3s-fs with one bucket (`tests/common/s3.rs`), or `None` after one skip line.
    fn start() -> Option<S3Server> {
        super::s3server::s3("blob store conformance")
    }

    fn location(server: &S3Server, prefix: &str, secret: &str, bucket: &str) -> S3Location {
        let mut l = S3Location::parse(&format!("s3://{bucket}/{prefix}")).expect("s3 URL");
        l.endpoint = Some(server.endpoint.clone());
        l.region = Some("us-east-1".into());
        l.access_key_id = Some(ACCESS_KEY.into());
        l.secret_access_key = Some(secret.into());
        l
    }

    pub async fn fresh() -> Option<(ObjectBlobs, (S3Server, tempfile::TempDir))> {
        let server = start()?;
        let cache = tempfile::tempdir().expect("cache dir");
        let store = ObjectBlobs::s3(
            &location(&server, "site/a", SECRET_KEY, BUCKET),
            cache.path(),
        )
        .expect("adapter");
        store.check().await.expect("bucket reachable");
        Some((store, (server, cache)))
    }

    ctrecon::blob_store_conformance!(maybe: fresh());

    fn key(k: &str) -> BlobKey {
        BlobKey::parse(k).expect("key")
    }

    /// `n` bytes of a pattern that differs at every offset within a part, sent in chunks of `chunk`.
    fn pattern(n: usize) -> Vec<u8> {
        (0..n)
            .map(|i| (i % 251) as u8 ^ (i / 65_536) as u8)
            .collect()
    }

    fn chunked(bytes: &[u8], chunk: usize, fail_after: Option<usize>) -> ByteStream {
        let mut parts: Vec<io::Result<Vec<u8>>> =
            bytes.chunks(chunk).map(|c| Ok(c.to_vec())).collect();
        if let Some(n) = fail_after {
            parts.truncate(n);
            parts.push(Err(io::Error::other("the client went away")));
        }
        futures_util::stream::iter(parts).boxed()
    }

    async fn read(s: &ObjectBlobs, k: &BlobKey, r: Option<std::ops::Range<u64>>) -> Vec<u8> {
        let mut st = s.get(k, r).await.expect("get");
        let mut out = Vec::new();
        while let Some(c) = st.next().await {
            out.extend(c.expect("chunk"));
        }
        out
    }

    /// A body larger than one PutObject goes as a multipart upload: read back whole and in a range that
    /// crosses a part boundary, with the server's multipart ETag (`…-N`).
    #[tokio::test]
    async fn a_large_body_goes_as_a_multipart_upload() {
        let Some((store, _guard)) = fresh().await else {
            return;
        };
        let n = SINGLE_PUT_MAX + 2 * PART_SIZE + 12_345;
        let data = pattern(n);
        let k = key("results/big/volume.npy");
        let meta = store
            .put(&k, chunked(&data, 1 << 20, None))
            .await
            .expect("multipart put");
        assert_eq!(meta.size, n as u64);
        assert!(
            meta.e_tag.contains('-'),
            "multipart ETag, got {}",
            meta.e_tag
        );
        assert_eq!(store.head(&k).await.expect("head").e_tag, meta.e_tag);
        let got = read(&store, &k, None).await;
        assert!(got == data, "whole object differs");
        let cross = (PART_SIZE as u64 - 100)..(PART_SIZE as u64 + 100);
        assert_eq!(
            read(&store, &k, Some(cross.clone())).await,
            &data[cross.start as usize..cross.end as usize]
        );
        let local = store.local_path(&k).await.expect("local copy");
        assert!(std::fs::read(&local).expect("read local") == data);
        // A second ask reuses the cached copy.
        assert_eq!(store.local_path(&k).await.expect("again"), local);
    }

    /// A multipart upload whose stream fails is aborted: nothing new appears and the earlier object stays.
    #[tokio::test]
    async fn a_failed_multipart_upload_leaves_the_earlier_object() {
        let Some((store, _guard)) = fresh().await else {
            return;
        };
        let k = key("datasets/d.npy");
        let big = pattern(SINGLE_PUT_MAX + PART_SIZE + 1);
        let fails = || chunked(&big, 1 << 20, Some((SINGLE_PUT_MAX >> 20) + 4));
        assert!(store.put(&k, fails()).await.is_err());
        assert_eq!(
            store.head(&k).await.err().map(|e| e.kind()),
            Some(io::ErrorKind::NotFound)
        );
        store
            .put(&k, chunked(b"version one", 4, None))
            .await
            .expect("small put");
        assert!(store.put(&k, fails()).await.is_err());
        assert_eq!(read(&store, &k, None).await, b"version one");
        assert_eq!(
            store.list(&key("datasets")).await.expect("list").len(),
            1,
            "no stray object"
        );
    }

    /// A range starting past the end is refused; objects outside the store's prefix are not listed.
    #[tokio::test]
    async fn ranges_and_prefixes_are_exact() {
        let Some((store, guard)) = fresh().await else {
            return;
        };
        let k = key("results/r/metrics.json");
        store
            .put(&k, chunked(b"0123456789", 3, None))
            .await
            .expect("put");
        assert_eq!(
            store.get(&k, Some(11..20)).await.err().map(|e| e.kind()),
            Some(io::ErrorKind::InvalidInput)
        );
        assert_eq!(read(&store, &k, Some(10..20)).await, b"");
        // Another ctrecon (another prefix) in the same bucket sees none of it.
        let cache = tempfile::tempdir().expect("cache");
        let other = ObjectBlobs::s3(
            &location(&guard.0, "site/b", SECRET_KEY, BUCKET),
            cache.path(),
        )
        .expect("adapter");
        assert!(other.list(&key("results")).await.expect("list").is_empty());
        assert_eq!(
            other.head(&k).await.err().map(|e| e.kind()),
            Some(io::ErrorKind::NotFound)
        );
    }

    /// The server checks signatures: a wrong secret and a missing bucket are found by the start-up check.
    #[tokio::test]
    async fn wrong_credentials_and_missing_buckets_fail_the_check() {
        let Some(server) = start() else {
            return;
        };
        let cache = tempfile::tempdir().expect("cache");
        let wrong = ObjectBlobs::s3(
            &location(&server, "", "not-the-secret", BUCKET),
            cache.path(),
        )
        .expect("adapter");
        let e = wrong.check().await.expect_err("a wrong secret is refused");
        assert!(
            e.to_string().contains("SignatureDoesNotMatch")
                || e.kind() == io::ErrorKind::PermissionDenied,
            "{e}"
        );
        let missing = ObjectBlobs::s3(
            &location(&server, "", SECRET_KEY, "no-such-bucket"),
            cache.path(),
        )
        .expect("adapter");
        let e = missing
            .check()
            .await
            .expect_err("a missing bucket is found");
        assert!(e.to_string().contains("NoSuchBucket"), "{e}");
    }
}
