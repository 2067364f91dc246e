//! Serving immutable result files: strong ETags, `Cache-Control: immutable`, conditional GETs
//! (`If-None-Match`), and single byte ranges (`Range`, `If-Range`).

use std::path::PathBuf;

use axum::body::Body;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::Response;
use bytes::Bytes;

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

/// Largest piece of a file read at once for a response body.
pub(crate) const CHUNK: usize = 1 << 20;

/// Pieces of a response body, read off the async runtime.
pub(crate) type Chunks = tokio::sync::mpsc::Sender<Result<Bytes, std::io::Error>>;

/// Hand `n` bytes of `file` from `start` to `tx` in pieces of up to [`CHUNK`] bytes, read on the calling
/// (blocking) thread: one blocking task per file rather than one per piece. False when the response is gone
/// or the file could not be read (the error is sent, which cuts the body off).
pub(crate) fn send_file_range(mut file: std::fs::File, start: u64, n: u64, tx: &Chunks) -> bool {
    use std::io::{Read, Seek};
    if let Err(e) = file.seek(std::io::SeekFrom::Start(start)) {
        let _ = tx.blocking_send(Err(e));
        return false;
    }
    let mut left = file.take(n);
    loop {
        let mut buf = Vec::with_capacity(CHUNK);
        match (&mut left).take(CHUNK as u64).read_to_end(&mut buf) {
            Ok(0) => return true,
            Ok(_) => {
                if tx.blocking_send(Ok(Bytes::from(buf))).is_err() {
                    return false;
                }
            }
            Err(e) => {
                let _ = tx.blocking_send(Err(e));
                return false;
            }
        }
    }
}

/// A body of `n` bytes of `file` from `start`, read by one blocking task through a channel of four pieces
/// (memory stays within a few MiB whatever the file's size).
fn file_body(file: std::fs::File, start: u64, n: u64) -> Body {
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    tokio::task::spawn_blocking(move || send_file_range(file, start, n, &tx));
    Body::from_stream(futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|c| (c, rx))
    }))
}

/// Where the bytes come from: an open local file, or the object behind the path.
enum Source<'a> {
    File(std::fs::File),
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
            (Source::File(file.into_std().await), len)
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
                Source::File(file) => file_body(file, 0, len),
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
                Source::File(file) => file_body(file, start, n),
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
    fn a_range_across_pieces_comes_back_byte_for_byte() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("blob");
        let bytes: Vec<u8> = (0..(3 * CHUNK + 12345))
            .map(|i| (i * 7 % 251) as u8)
            .collect();
        std::fs::write(&path, &bytes).expect("write");
        for (start, n) in [
            (0, bytes.len()),
            (1000, 2 * CHUNK + 5),
            (CHUNK - 1, 2),
            (17, 0),
        ] {
            let (tx, mut rx) = tokio::sync::mpsc::channel(64);
            let file = std::fs::File::open(&path).expect("open");
            assert!(send_file_range(file, start as u64, n as u64, &tx));
            drop(tx);
            let mut got = Vec::new();
            let mut pieces = 0;
            while let Ok(piece) = rx.try_recv() {
                let piece = piece.expect("read");
                assert!(piece.len() <= CHUNK);
                got.extend_from_slice(&piece);
                pieces += 1;
            }
            assert_eq!(got.len(), n, "{start}+{n}");
            assert!(got == bytes[start..start + n], "{start}+{n}");
            assert_eq!(pieces, n.div_ceil(CHUNK), "{start}+{n}");
        }
    }

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
