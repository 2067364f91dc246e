//! WADO-RS retrieval of a study, series or instance as `multipart/related; type="application/dicom"`,
//! streamed from the stored files (one part per instance, each with its Content-Type, Content-Length and
//! Content-Location). The transfer syntax asked for in `Accept` decides which instances are re-encoded
//! (`app::wado::RetrieveSyntax`): explicit VR little endian unless `transfer-syntax=*` asks for the stored
//! one.

use axum::body::{Body, Bytes};
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::Response;

use super::super::super::AppState;
use super::super::super::problem::{ApiResult, api_error};
use super::negotiation::{accepted, base_url, not_acceptable, param};
use crate::app::dicomweb::resource_path;
use crate::app::wado::RetrieveSyntax;
use crate::dicom::EXPLICIT_LE;
use crate::error_code::ErrorCode;
use crate::http::files::{CHUNK, Chunks};
use crate::jobs::model::StoredInstance;

/// The syntax a retrieval's `Accept` asks for, or 406.
fn retrieve_syntax(headers: &HeaderMap) -> ApiResult<RetrieveSyntax> {
    for (t, p) in accepted(headers) {
        let dicom = match t.as_str() {
            "*/*" | "multipart/*" => true,
            "multipart/related" => param(&p, "type").is_none_or(|ty| ty == "application/dicom"),
            _ => false,
        };
        if !dicom {
            continue;
        }
        // PS3.18 §8.7.3.5.2: without a transfer-syntax parameter, application/dicom is explicit VR
        // little endian.
        return match param(&p, "transfer-syntax") {
            None => Ok(RetrieveSyntax::ExplicitLe),
            Some("*") => Ok(RetrieveSyntax::Stored),
            Some(EXPLICIT_LE) => Ok(RetrieveSyntax::ExplicitLe),
            Some(other) => Err(api_error(
                ErrorCode::NotAcceptable,
                format!("transfer syntax {other} is not offered: ask for * or {EXPLICIT_LE}"),
            )),
        };
    }
    Err(not_acceptable(
        "multipart/related; type=\"application/dicom\"",
    ))
}

/// Send one part of a body whose instance is the file at `path`: its header (made by `head` from the
/// file's length), the file in pieces of up to [`CHUNK`] bytes, and the line break that ends the part. The
/// header rides with the first piece and the line break with the last, so a part is one piece up to a
/// MiB, all read on the calling (blocking) thread. False when the response is gone or the file cannot be
/// read whole (the error is sent, which cuts the body off).
fn send_part(path: &std::path::Path, head: impl FnOnce(u64) -> String, tx: &Chunks) -> bool {
    use std::io::Read;
    let sent = (|| -> std::io::Result<bool> {
        let file = std::fs::File::open(path)?;
        let len = file.metadata()?.len();
        let mut buf = head(len).into_bytes();
        buf.reserve(len.min(CHUNK as u64) as usize + 2);
        let mut rest = file.take(len);
        let mut left = len;
        loop {
            let piece = left.min(CHUNK as u64);
            let before = buf.len();
            (&mut rest).take(piece).read_to_end(&mut buf)?;
            if ((buf.len() - before) as u64) < piece {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    "an instance file ended before its length",
                ));
            }
            left -= piece;
            if left == 0 {
                buf.extend_from_slice(b"\r\n");
            }
            if tx.blocking_send(Ok(Bytes::from(buf))).is_err() {
                return Ok(false);
            }
            if left == 0 {
                return Ok(true);
            }
            buf = Vec::with_capacity(left.min(CHUNK as u64) as usize + 2);
        }
    })();
    sent.unwrap_or_else(|e| {
        let _ = tx.blocking_send(Err(e));
        false
    })
}

/// Stream `instances` as one `multipart/related` body: the parts are produced one at a time by a task,
/// files read in chunks of up to 1 MiB through a channel of four, so memory stays flat in the retrieval's
/// size.
async fn retrieve(
    state: AppState,
    headers: HeaderMap,
    instances: Vec<StoredInstance>,
) -> ApiResult<Response> {
    let syntax = retrieve_syntax(&headers)?;
    syntax.check(&instances)?;
    let boundary = uuid::Uuid::new_v4().simple().to_string();
    let base = base_url(&headers);
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(4);
    let app = state.app.clone();
    let b = boundary.clone();
    // The first instance is made ready before the answer starts, so that one that cannot be sent in the
    // syntax asked for (a single-instance retrieval above all) is a problem, not a cut-off body.
    let mut first = match instances.first() {
        Some(i) => Some(state.retrieved_instance(i, syntax).await?),
        None => None,
    };
    tokio::spawn(async move {
        for i in instances {
            let ready = match first.take() {
                Some(v) => Ok(v),
                None => app.retrieved_instance(&i, syntax).await,
            };
            let (bytes, ts) = match ready {
                Ok(v) => v,
                Err(e) => {
                    tracing::error!(error = %e, "an instance cannot be sent");
                    let _ = tx
                        .send(Err(std::io::Error::other("instance unreadable")))
                        .await;
                    return;
                }
            };
            let h = &i.instance;
            let location = format!(
                "{base}{}",
                resource_path(&h.study_uid, Some(&h.series_uid), Some(&h.sop_instance_uid))
            );
            let b2 = b.clone();
            let head = move |len: u64| {
                format!(
                    "--{b2}\r\nContent-Type: application/dicom; transfer-syntax={ts}\r\nContent-Length: {len}\r\nContent-Location: {location}\r\n\r\n"
                )
            };
            match bytes {
                Some(v) => {
                    let mut part = head(v.len() as u64).into_bytes();
                    part.extend_from_slice(&v);
                    part.extend_from_slice(b"\r\n");
                    if tx.send(Ok(Bytes::from(part))).await.is_err() {
                        return;
                    }
                }
                None => {
                    let (path, tx) = (app.instance_file(&i), tx.clone());
                    let sent =
                        tokio::task::spawn_blocking(move || send_part(&path, head, &tx)).await;
                    if !matches!(sent, Ok(true)) {
                        return;
                    }
                }
            }
        }
        let _ = tx.send(Ok(Bytes::from(format!("--{b}--\r\n")))).await;
    });
    let stream =
        futures_util::stream::unfold(rx, |mut rx| async move { rx.recv().await.map(|c| (c, rx)) });
    let mut r = Response::new(Body::from_stream(stream));
    let ct = format!("multipart/related; type=\"application/dicom\"; boundary={boundary}");
    if let Ok(v) = HeaderValue::from_str(&ct) {
        r.headers_mut().insert(header::CONTENT_TYPE, v);
    }
    Ok(r)
}

#[tracing::instrument(skip_all, fields(study = %study))]
pub async fn retrieve_study(
    State(state): State<AppState>,
    Path(study): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state.wado_instances(&study, None, None).await?;
    retrieve(state, headers, found).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series))]
pub async fn retrieve_series(
    State(state): State<AppState>,
    Path((study, series)): Path<(String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state.wado_instances(&study, Some(&series), None).await?;
    retrieve(state, headers, found).await
}

#[tracing::instrument(skip_all, fields(study = %study, series = %series, instance = %instance))]
pub async fn retrieve_instance(
    State(state): State<AppState>,
    Path((study, series, instance)): Path<(String, String, String)>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    retrieve_syntax(&headers)?;
    let found = state
        .wado_instances(&study, Some(&series), Some(&instance))
        .await?;
    retrieve(state, headers, found).await
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pieces `send_part` sends for a file of `len` bytes, or the error that cut them off.
    fn pieces(len: usize) -> (Vec<u8>, Vec<Result<Vec<u8>, std::io::ErrorKind>>) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("i.dcm");
        let bytes: Vec<u8> = (0..len).map(|k| (k % 251) as u8).collect();
        std::fs::write(&path, &bytes).unwrap();
        let (tx, mut rx) = tokio::sync::mpsc::channel(64);
        let ok = std::thread::spawn(move || send_part(&path, |n| format!("H{n}|"), &tx))
            .join()
            .unwrap();
        assert!(ok);
        let mut out = Vec::new();
        while let Ok(p) = rx.try_recv() {
            out.push(p.map(|b| b.to_vec()).map_err(|e| e.kind()));
        }
        (bytes, out)
    }

    #[test]
    fn a_part_carries_its_header_with_the_first_piece_and_its_line_break_with_the_last() {
        // Smaller than a piece: one piece, header + file + CRLF.
        let (bytes, out) = pieces(1000);
        let mut want = b"H1000|".to_vec();
        want.extend_from_slice(&bytes);
        want.extend_from_slice(b"\r\n");
        assert_eq!(out, vec![Ok(want)]);

        // An empty file: the header and the line break.
        let (_, out) = pieces(0);
        assert_eq!(out, vec![Ok(b"H0|\r\n".to_vec())]);

        // Two pieces and a bit: every byte once, in order, the header first and the CRLF last.
        let len = 2 * CHUNK + 7;
        let (bytes, out) = pieces(len);
        let sizes: Vec<usize> = out.iter().map(|p| p.as_ref().unwrap().len()).collect();
        let head = format!("H{len}|");
        assert_eq!(sizes, vec![head.len() + CHUNK, CHUNK, 7 + 2]);
        let joined: Vec<u8> = out.into_iter().flat_map(|p| p.unwrap()).collect();
        assert_eq!(&joined[..head.len()], head.as_bytes());
        assert!(joined[head.len()..head.len() + len] == bytes[..]);
        assert_eq!(&joined[head.len() + len..], b"\r\n");
    }

    #[test]
    fn a_missing_file_cuts_the_body_off_with_its_error() {
        let (tx, mut rx) = tokio::sync::mpsc::channel(4);
        let sent = std::thread::spawn(move || {
            send_part(
                std::path::Path::new("/nonexistent/i.dcm"),
                |_| String::new(),
                &tx,
            )
        })
        .join()
        .unwrap();
        assert!(!sent);
        let e = rx.try_recv().unwrap().unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::NotFound);
        assert!(rx.try_recv().is_err());
    }
}
