//! Uploads stream to temporary files under the data directory, chunk by chunk, so memory stays flat in the
//! upload size: [`spool`] for any body or multipart field (hashed, the size limit enforced while streaming);
//! [`UploadSink`] for `.npy` uploads, where each chunk is also validated (header, limits, expected shape,
//! finiteness, exact length) before it is written. Nothing is kept unless the whole upload is accepted.

use std::pin::Pin;
use std::task::{Context, Poll};

use axum::body::{Body, Bytes};
use axum::extract::Request;
use futures_util::{Stream, StreamExt};
use sha2::{Digest, Sha256};
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

/// A body (or multipart field) written to `tmp/` (not synced: most are read once and removed; see
/// [`TempBlob::sync`] before keeping one).
pub struct Spooled {
    pub temp: TempBlob,
    pub bytes: u64,
    pub sha256: [u8; 32],
}

/// The 413 problem of an upload over `limit` bytes.
pub fn too_large(limit: u64) -> ApiError {
    api_error(
        ErrorCode::BodyTooLarge,
        format!("the upload exceeds the limit of {limit} bytes"),
    )
}

/// The `Content-Length` a request declares, if any.
pub fn declared_length(headers: &axum::http::HeaderMap) -> Option<u64> {
    headers
        .get(axum::http::header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
}

/// Write `stream` to a temporary file chunk by chunk; `spent` counts the bytes of the whole request and the
/// upload is refused (413, the file removed) as soon as it passes `limit`. A stream error is a truncated upload.
pub async fn spool<S, B, E>(
    store: &BlobStore,
    mut stream: S,
    spent: &mut u64,
    limit: u64,
) -> ApiResult<Spooled>
where
    S: Stream<Item = Result<B, E>> + Unpin,
    B: Into<Bytes>,
    E: std::fmt::Display,
{
    let temp = store.temp();
    let mut file = tokio::fs::File::create(temp.path()).await?;
    let mut hash = Sha256::new();
    let mut bytes = 0u64;
    let failed = loop {
        let chunk: Bytes = match stream.next().await {
            None => break None,
            Some(Ok(c)) => c.into(),
            Some(Err(e)) => break Some(api_error(ErrorCode::TruncatedUpload, e.to_string())),
        };
        *spent = spent.saturating_add(chunk.len() as u64);
        if *spent > limit {
            break Some(too_large(limit));
        }
        hash.update(&chunk);
        bytes += chunk.len() as u64;
        if let Err(e) = file.write_all(&chunk).await {
            break Some(e.into());
        }
    };
    let failed = match failed {
        None => file.flush().await.err().map(ApiError::from),
        Some(e) => Some(e),
    };
    drop(file);
    if let Some(e) = failed {
        temp.discard().await;
        return Err(e);
    }
    Ok(Spooled {
        temp,
        bytes,
        sha256: hash.finalize().into(),
    })
}

/// A body stream that yields one chunk per poll and then reports `Pending` (waking its task at once), so that a
/// reader which drains everything ready (the multipart parser does) holds about one chunk at a time rather than
/// whatever the connection has buffered.
struct OneChunkPerPoll<S> {
    inner: S,
    yielded: bool,
}

impl<S: Stream + Unpin> Stream for OneChunkPerPoll<S> {
    type Item = S::Item;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<S::Item>> {
        if self.yielded {
            self.yielded = false;
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        let next = Pin::new(&mut self.inner).poll_next(cx);
        if matches!(next, Poll::Ready(Some(_))) {
            self.yielded = true;
        }
        next
    }
}

/// The request with its body paced one chunk per poll (for multipart forms: see [`OneChunkPerPoll`]).
pub fn paced(req: Request) -> Request {
    let (parts, body) = req.into_parts();
    let body = Body::from_stream(OneChunkPerPoll {
        inner: body.into_data_stream(),
        yielded: false,
    });
    Request::from_parts(parts, body)
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

/// Boundary of the multipart bodies the upload fuzz target sends.
#[doc(hidden)]
pub const FUZZ_BOUNDARY: &str = "ctrecon-fuzz-boundary";

/// How the upload fuzz target (and its regression replay) frames an input as a `POST /v1/series`: the first
/// byte picks the media type — mostly a multipart form with [`FUZZ_BOUNDARY`], sometimes one without a
/// boundary, a ZIP body or a single instance — and the rest is the body.
#[doc(hidden)]
pub fn fuzz_upload_request(data: &[u8]) -> (&'static str, &[u8]) {
    let (first, body) = data.split_first().map_or((0, data), |(f, b)| (*f, b));
    let media_type = match first % 8 {
        5 => "multipart/form-data",
        6 => "application/zip",
        7 => "application/dicom",
        _ => "multipart/form-data; boundary=ctrecon-fuzz-boundary",
    };
    (media_type, body)
}
