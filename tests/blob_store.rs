//! The blob-store conformance suite, run against the data-directory adapter (an S3 adapter adds one line).

mod directory {
    use ctrecon::storage::BlobStore;

    async fn fresh() -> BlobStore {
        let dir = tempfile::tempdir().expect("temp dir").keep();
        BlobStore::open(&dir).expect("blob store")
    }

    ctrecon::blob_store_conformance!(fresh());
}
