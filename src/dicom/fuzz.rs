//! The ZIP-ingest fuzz target's entry point (and its regression replay's): an upload body as the service
//! receives it — written to a file, unpacked member by member into a scratch directory under bomb limits,
//! every member decoded, the series assembled. Every outcome but a panic, an allocation sized by the input or
//! a file left behind is fine.

use std::path::PathBuf;

use super::{
    DicomError, ReadLimits, Unpacked, UploadFile, ZipLimits, read_upload_files, unpack_file,
};
use crate::recon::control::unattended;
use crate::series::AssemblyOptions;

#[doc(hidden)]
pub fn fuzz_zip_entry(data: &[u8]) {
    // One scratch directory per process and thread: the replay test runs entries in parallel.
    let dir = std::env::temp_dir().join(format!(
        "ctrecon-fuzz-zip-{}-{:?}",
        std::process::id(),
        std::thread::current().id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    if std::fs::create_dir_all(dir.join("scratch")).is_err() {
        return;
    }
    let _ = ingest(data, dir.join("upload"), &dir);
    let _ = std::fs::remove_dir_all(&dir);
}

fn ingest(data: &[u8], path: PathBuf, dir: &std::path::Path) -> Result<(), DicomError> {
    std::fs::write(&path, data).map_err(|e| DicomError::Write(e.to_string()))?;
    let limits = ZipLimits {
        max_entries: 256,
        max_total_bytes: 64 << 20,
        max_ratio: 200,
        max_member_bytes: 16 << 20,
    };
    let mut out = Unpacked::default();
    let file = UploadFile {
        label: "upload.zip".into(),
        path,
    };
    unpack_file(file, &limits, &dir.join("scratch"), &mut out)?;
    let read = ReadLimits {
        max_pixel_bytes: 16 << 20,
        ..ReadLimits::default()
    };
    let upload = read_upload_files(&out.files, out.rejected, &read, unattended())?;
    let opts = AssemblyOptions {
        max_voxels: 1 << 22,
        ..AssemblyOptions::default()
    };
    for group in upload.series {
        let _ = group.assemble(&opts, false, unattended());
    }
    Ok(())
}
