//! Serving immutable result files: strong ETags, `Cache-Control: immutable`, conditional GETs
//! (`If-None-Match`), and single byte ranges (`Range`, `If-Range`).

use std::path::PathBuf;

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::Response;
use tokio::io::{AsyncReadExt, AsyncSeekExt};
use tokio_util::io::ReaderStream;

use super::problem::{ApiResult, api_error};
use crate::error_code::ErrorCode;
use crate::storage::BlobStore;

/// A file to serve and how to describe it.
pub struct FileMeta {
    pub path: PathBuf,
    /// Strong validator (without quotes): a content hash, or the hash of the parameters that fix it.
    pub etag: String,
    pub content_type: &'static str,
    pub filename: Option<String>,
}

/// A requested byte range, inclusive.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ByteRange {
    Full,
    Part(u64, u64),
    Unsatisfiable,
}

/// Parse one `Range: bytes=…` header against a file of `len` bytes. Multiple ranges and other units are
/// ignored (the whole file is sent), as RFC 9110 allows.
pub fn parse_range(value: Option<&str>, len: u64) -> ByteRange {
    let Some(spec) = value.and_then(|v| v.trim().strip_prefix("bytes=")) else {
        return ByteRange::Full;
    };
    if spec.contains(',') {
        return ByteRange::Full;
    }
    let Some((a, b)) = spec.split_once('-') else {
        return ByteRange::Full;
    };
    let (a, b) = (a.trim(), b.trim());
    if a.is_empty() {
        return match b.parse::<u64>() {
            Ok(0) => ByteRange::Unsatisfiable,
            Ok(_) if len == 0 => ByteRange::Unsatisfiable,
            Ok(n) => ByteRange::Part(len.saturating_sub(n), len - 1),
            Err(_) => ByteRange::Full,
        };
    }
    let Ok(start) = a.parse::<u64>() else {
        return ByteRange::Full;
    };
    let end = if b.is_empty() {
        len.saturating_sub(1)
    } else {
        match b.parse::<u64>() {
            Ok(e) if e >= start => e.min(len.saturating_sub(1)),
            _ => return ByteRange::Full,
        }
    };
    if start >= len {
        ByteRange::Unsatisfiable
    } else {
        ByteRange::Part(start, end)
    }
}

fn etag_matches(list: &str, quoted: &str) -> bool {
    list.split(',')
        .map(str::trim)
        .any(|t| t == "*" || t == quoted || t.strip_prefix("W/") == Some(quoted))
}

fn hv(s: &str) -> HeaderValue {
    HeaderValue::from_str(s).unwrap_or_else(|_| HeaderValue::from_static(""))
}

/// The start of a response for an immutable representation with strong validator `quoted`: its `ETag`
/// and `Cache-Control`, and `Err` with the whole `304 Not Modified` answer when `If-None-Match` matches.
/// The one place conditional GETs are decided.
fn conditional(
    req: &HeaderMap,
    quoted: &str,
) -> ApiResult<Result<axum::http::response::Builder, Response>> {
    let builder = Response::builder()
        .header(header::ETAG, hv(quoted))
        .header(header::CACHE_CONTROL, "public, max-age=31536000, immutable");
    if let Some(inm) = req.get(header::IF_NONE_MATCH).and_then(|v| v.to_str().ok())
        && etag_matches(inm, quoted)
    {
        return builder
            .status(StatusCode::NOT_MODIFIED)
            .body(Body::empty())
            .map(Err)
            .map_err(|_| api_error(ErrorCode::Internal, "building a response"));
    }
    Ok(Ok(builder))
}

/// Serve a small immutable body held in memory, with strong ETag `etag` (without quotes) and conditional
/// GETs answered as [`serve_file`] answers them.
pub fn serve_bytes(
    req: &HeaderMap,
    etag: &str,
    content_type: &'static str,
    body: Vec<u8>,
) -> ApiResult<Response> {
    let builder = match conditional(req, &format!("\"{etag}\""))? {
        Ok(b) => b,
        Err(not_modified) => return Ok(not_modified),
    };
    builder
        .status(StatusCode::OK)
        .header(header::CONTENT_TYPE, content_type)
        .body(Body::from(body))
        .map_err(|_| api_error(ErrorCode::Internal, "building a response"))
}

/// Serve `meta` answering the conditional and range headers of `req`.
pub async fn serve_file(req: &HeaderMap, meta: FileMeta) -> ApiResult<Response> {
    serve_from(req, meta, None).await
}

/// Serve a stored blob (a result, a series volume): the local file, or, where this host has no copy of it
/// and object storage holds it, the object with the range asked for read straight from the store.
pub async fn serve_stored(
    req: &HeaderMap,
    store: &BlobStore,
    meta: FileMeta,
) -> ApiResult<Response> {
    serve_from(req, meta, Some(store)).await
}

/// Where the bytes come from: an open local file, or the object behind the path.
enum Source<'a> {
    File(tokio::fs::File),
    Object(&'a BlobStore),
}

async fn serve_from(
    req: &HeaderMap,
    meta: FileMeta,
    store: Option<&BlobStore>,
) -> ApiResult<Response> {
    let quoted = format!("\"{}\"", meta.etag);
    let mut builder = match conditional(req, &quoted)? {
        Ok(b) => b.header(header::ACCEPT_RANGES, "bytes"),
        Err(not_modified) => return Ok(not_modified),
    };
    let object = match store {
        Some(s) => s.object_meta(&meta.path).await?.map(|m| (s, m.size)),
        None => None,
    };
    let (source, len) = match object {
        Some((s, size)) => (Source::Object(s), size),
        None => {
            let file = tokio::fs::File::open(&meta.path).await?;
            let len = file.metadata().await?.len();
            (Source::File(file), len)
        }
    };
    let if_range_ok = req
        .get(header::IF_RANGE)
        .and_then(|v| v.to_str().ok())
        .is_none_or(|v| v.trim() == quoted);
    let range = if if_range_ok {
        parse_range(req.get(header::RANGE).and_then(|v| v.to_str().ok()), len)
    } else {
        ByteRange::Full
    };
    builder = builder.header(header::CONTENT_TYPE, meta.content_type);
    if let Some(name) = &meta.filename {
        builder = builder.header(
            header::CONTENT_DISPOSITION,
            hv(&format!("inline; filename=\"{name}\"")),
        );
    }
    let response = match range {
        ByteRange::Unsatisfiable => {
            let mut r = axum::response::IntoResponse::into_response(api_error(
                ErrorCode::RangeNotSatisfiable,
                format!("the file has {len} bytes"),
            ));
            r.headers_mut()
                .insert(header::CONTENT_RANGE, hv(&format!("bytes */{len}")));
            return Ok(r);
        }
        ByteRange::Full => {
            let body = match source {
                Source::File(file) => Body::from_stream(ReaderStream::new(file)),
                Source::Object(s) => Body::from_stream(s.object_get(&meta.path, None).await?),
            };
            builder
                .status(StatusCode::OK)
                .header(header::CONTENT_LENGTH, len)
                .body(body)
        }
        ByteRange::Part(start, end) => {
            let n = end - start + 1;
            let body = match source {
                Source::File(mut file) => {
                    file.seek(std::io::SeekFrom::Start(start)).await?;
                    Body::from_stream(ReaderStream::new(file.take(n)))
                }
                Source::Object(s) => {
                    Body::from_stream(s.object_get(&meta.path, Some(start..end + 1)).await?)
                }
            };
            builder
                .status(StatusCode::PARTIAL_CONTENT)
                .header(header::CONTENT_LENGTH, n)
                .header(
                    header::CONTENT_RANGE,
                    hv(&format!("bytes {start}-{end}/{len}")),
                )
                .body(body)
        }
    };
    response.map_err(|_| api_error(ErrorCode::Internal, "building a response"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_ranges_follow_rfc_9110() {
        assert_eq!(parse_range(None, 100), ByteRange::Full);
        assert_eq!(parse_range(Some("bytes=0-9"), 100), ByteRange::Part(0, 9));
        assert_eq!(parse_range(Some("bytes=90-"), 100), ByteRange::Part(90, 99));
        assert_eq!(parse_range(Some("bytes=-10"), 100), ByteRange::Part(90, 99));
        assert_eq!(
            parse_range(Some("bytes=50-500"), 100),
            ByteRange::Part(50, 99)
        );
        assert_eq!(
            parse_range(Some("bytes=100-"), 100),
            ByteRange::Unsatisfiable
        );
        assert_eq!(parse_range(Some("bytes=-0"), 100), ByteRange::Unsatisfiable);
        assert_eq!(parse_range(Some("bytes=0-1,5-6"), 100), ByteRange::Full);
        assert_eq!(parse_range(Some("items=0-1"), 100), ByteRange::Full);
        assert_eq!(parse_range(Some("bytes=9-3"), 100), ByteRange::Full);
    }
}
