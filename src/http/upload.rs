//! Streaming `.npy` uploads to a temporary file: each chunk is validated (header, limits, expected shape,
//! finiteness, exact length) and hashed before it is written; nothing is kept unless the whole upload is
//! accepted.

use tokio::io::AsyncWriteExt;

use super::problem::{ApiError, ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::storage::npy::{NpyError, NpyHeader, NpyStream, StreamError, StreamLimits};
use crate::storage::{BlobStore, TempBlob};

/// The catalogue problem of a refused upload.
pub fn stream_error(e: StreamError) -> ApiError {
    let code = match &e {
        StreamError::Npy(NpyError::UnsupportedDtype(_) | NpyError::FortranOrder) => {
            ErrorCode::UnsupportedDtype
        }
        StreamError::Npy(_) | StreamError::TrailingBytes { .. } => ErrorCode::MalformedNpy,
        StreamError::ShapeMismatch { .. } => ErrorCode::ShapeMismatch,
        StreamError::TooLarge { .. } => ErrorCode::ArrayTooLarge,
        StreamError::Truncated { .. } => ErrorCode::TruncatedUpload,
        StreamError::NonFinite { .. } => ErrorCode::NonFiniteData,
    };
    api_error(code, e.to_string())
}

/// A completed, validated upload still in `tmp/`.
pub struct Uploaded {
    pub temp: TempBlob,
    pub header: NpyHeader,
    pub bytes: u64,
    pub sha256: String,
}

/// An upload in progress.
pub struct UploadSink {
    stream: NpyStream,
    file: tokio::fs::File,
    temp: TempBlob,
}

impl UploadSink {
    pub async fn create(
        store: &BlobStore,
        limits: StreamLimits,
        expected_shape: Option<Vec<usize>>,
    ) -> ApiResult<Self> {
        let temp = store.temp();
        let file = tokio::fs::File::create(temp.path()).await?;
        Ok(Self {
            stream: NpyStream::new(limits, expected_shape),
            file,
            temp,
        })
    }

    pub async fn write(&mut self, chunk: &[u8]) -> ApiResult<()> {
        self.stream.feed(chunk).map_err(stream_error)?;
        self.file.write_all(chunk).await?;
        Ok(())
    }

    pub async fn finish(mut self) -> ApiResult<Uploaded> {
        let (header, bytes, sha256) = self.stream.finish().map_err(stream_error)?;
        self.file.flush().await?;
        self.file.sync_all().await?;
        Ok(Uploaded {
            temp: self.temp,
            header,
            bytes,
            sha256,
        })
    }
}
