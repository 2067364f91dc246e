//! ctrecon as a DICOMweb client: deliveries to a DICOMweb origin (`dicom.web_peers`) by STOW-RS.
//!
//! A delivery's files go as `POST {url}/studies` with a `multipart/related; type="application/dicom"` body
//! streamed from the exported files (never all in memory; its `Content-Length` is known beforehand), in
//! batches of at most `batch_instances`. What became of each instance is read from the PS3.18 answer
//! (§10.5.3, the Store Instances Response Module): in the Referenced SOP Sequence → `succeeded` (status 0,
//! or its Warning Reason), in the Failed SOP Sequence → `failed` with its Failure Reason as the status.
//! A peer that cannot be reached, times out or answers 408, 429 or 5xx without a PS3.18 body is tried
//! again with the DIMSE deliveries' backoff; any other refusal (401, 403, 413, 415, …) fails the
//! instances of the batch with the HTTP status in their detail, and the delivery is `failed`.
//!
//! The framing and the answer's reading are plain functions (tested here); the HTTP client is the
//! `dicomweb-client` cargo feature.

use std::collections::HashMap;

use serde_json::Value;

/// Referenced SOP Sequence (0008,1199).
const REFERENCED_SOP_SEQUENCE: &str = "00081199";
/// Failed SOP Sequence (0008,1198).
const FAILED_SOP_SEQUENCE: &str = "00081198";
/// Referenced SOP Instance UID (0008,1155).
const REFERENCED_SOP_INSTANCE_UID: &str = "00081155";
/// Failure Reason (0008,1197).
const FAILURE_REASON: &str = "00081197";
/// Warning Reason (0008,1196).
const WARNING_REASON: &str = "00081196";

/// What a STOW-RS answer says about one instance.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acknowledged {
    /// Stored: 0, or the Warning Reason (e.g. 0xB000 coercion of data elements).
    Stored(u16),
    /// Not stored: the Failure Reason (e.g. 0x0110 processing failure, 0xA700 out of resources).
    Failed(u16),
}

/// The first value of attribute `tag` of a DICOM JSON object.
fn first<'a>(item: &'a Value, tag: &str) -> Option<&'a Value> {
    item.get(tag)?.get("Value")?.as_array()?.first()
}

fn items<'a>(body: &'a Value, tag: &str) -> impl Iterator<Item = &'a Value> {
    body.get(tag)
        .and_then(|a| a.get("Value"))
        .and_then(Value::as_array)
        .into_iter()
        .flatten()
}

/// The instances a STOW-RS answer (`application/dicom+json`: one object, or an array of one) names, by SOP
/// Instance UID; `None` when `body` is no Store Instances Response (neither sequence present).
pub fn read_stow_response(body: &[u8]) -> Option<HashMap<String, Acknowledged>> {
    let v: Value = serde_json::from_slice(body).ok()?;
    let v = match v {
        Value::Array(mut a) if a.len() == 1 => a.remove(0),
        v => v,
    };
    if v.get(REFERENCED_SOP_SEQUENCE).is_none() && v.get(FAILED_SOP_SEQUENCE).is_none() {
        return None;
    }
    let code = |item: &Value, tag: &str| {
        first(item, tag)
            .and_then(|c| {
                c.as_u64()
                    .or_else(|| c.as_str().and_then(|s| s.trim().parse().ok()))
            })
            .and_then(|c| u16::try_from(c).ok())
    };
    let mut out = HashMap::new();
    for item in items(&v, REFERENCED_SOP_SEQUENCE) {
        if let Some(uid) = first(item, REFERENCED_SOP_INSTANCE_UID).and_then(Value::as_str) {
            let warning = code(item, WARNING_REASON).unwrap_or(0);
            out.insert(uid.to_string(), Acknowledged::Stored(warning));
        }
    }
    for item in items(&v, FAILED_SOP_SEQUENCE) {
        if let Some(uid) = first(item, REFERENCED_SOP_INSTANCE_UID).and_then(Value::as_str) {
            // 0xC000 (cannot understand) when the origin gave no reason.
            let reason = code(item, FAILURE_REASON).unwrap_or(0xC000);
            out.insert(uid.to_string(), Acknowledged::Failed(reason));
        }
    }
    Some(out)
}

/// The `multipart/related` framing of a STOW-RS body: a boundary of its own, a head before each part and
/// the delimiters.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Framing {
    pub boundary: String,
}

impl Framing {
    pub fn new() -> Self {
        Self {
            boundary: format!("ctrecon-{}", uuid::Uuid::new_v4().simple()),
        }
    }

    /// The request's `Content-Type`.
    pub fn content_type(&self) -> String {
        format!(
            "multipart/related; type=\"application/dicom\"; boundary={}",
            self.boundary
        )
    }

    /// What precedes a part of `len` bytes.
    pub fn head(&self, len: u64) -> String {
        format!(
            "--{}\r\nContent-Type: application/dicom\r\nContent-Length: {len}\r\n\r\n",
            self.boundary
        )
    }

    /// What follows each part.
    pub const TAIL: &'static str = "\r\n";

    /// The close delimiter.
    pub fn close(&self) -> String {
        format!("--{}--\r\n", self.boundary)
    }

    /// The body's length for parts of `sizes` bytes.
    pub fn body_length(&self, sizes: &[u64]) -> u64 {
        sizes
            .iter()
            .map(|&n| self.head(n).len() as u64 + n + Self::TAIL.len() as u64)
            .sum::<u64>()
            + self.close().len() as u64
    }
}

impl Default for Framing {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(feature = "dicomweb-client")]
pub use client::{StowClient, StowError};

#[cfg(feature = "dicomweb-client")]
mod client {
    use std::path::PathBuf;
    use std::time::Duration;

    use bytes::Bytes;
    use futures_util::StreamExt as _;

    use super::{Acknowledged, Framing, read_stow_response};
    use crate::app::App;
    use crate::app::dicom_caller::SentInstance;
    use crate::config::dicom::WebPeer;
    use crate::jobs::deliveries::{Delivery, DeliveryState, InstanceState};
    use crate::jobs::export::export_dir;

    /// Most bytes of a STOW-RS answer read.
    const MAX_ANSWER_BYTES: usize = 16 << 20;

    /// Why a STOW-RS request did not give per-instance outcomes.
    #[derive(Debug, Clone, PartialEq, Eq)]
    pub enum StowError {
        /// Worth trying again later: no connection, a timeout, 408, 429 or a server error.
        Unreachable(String),
        /// The origin refused the request as a whole (e.g. 401 with wrong credentials): every instance of
        /// it failed, with this HTTP status and detail.
        Refused { status: u16, detail: String },
    }

    /// The HTTP client of STOW-RS deliveries.
    #[derive(Debug, Clone)]
    pub struct StowClient {
        http: reqwest::Client,
    }

    enum Piece {
        Bytes(Bytes),
        File(PathBuf),
    }

    impl StowClient {
        pub fn new() -> Result<Self, String> {
            reqwest::Client::builder()
                .connect_timeout(Duration::from_secs(10))
                .tcp_nodelay(true)
                .user_agent(concat!("ctrecon/", env!("CARGO_PKG_VERSION")))
                .build()
                .map(|http| Self { http })
                .map_err(|e| format!("cannot make the DICOMweb client: {e}"))
        }

        /// STOW-RS `files` (path and SOP Instance UID each) to `peer` in one request: one outcome per
        /// file, in order.
        pub async fn store(
            &self,
            peer: &WebPeer,
            files: &[(PathBuf, String)],
        ) -> Result<Vec<SentInstance>, StowError> {
            let framing = Framing::new();
            let mut sizes = Vec::with_capacity(files.len());
            for (path, _) in files {
                let len = tokio::fs::metadata(path).await.map_err(|e| {
                    tracing::error!(error = %e, "an exported instance cannot be read");
                    StowError::Unreachable("an exported instance cannot be read".into())
                })?;
                sizes.push(len.len());
            }
            let mut pieces = Vec::with_capacity(files.len() * 3 + 1);
            for ((path, _), &n) in files.iter().zip(&sizes) {
                pieces.push(Piece::Bytes(Bytes::from(framing.head(n))));
                pieces.push(Piece::File(path.clone()));
                pieces.push(Piece::Bytes(Bytes::from_static(Framing::TAIL.as_bytes())));
            }
            pieces.push(Piece::Bytes(Bytes::from(framing.close())));
            let body = futures_util::stream::iter(pieces)
                .then(|p| async move {
                    match p {
                        Piece::Bytes(b) => {
                            futures_util::stream::once(async move { Ok::<_, std::io::Error>(b) })
                                .boxed()
                        }
                        Piece::File(path) => match tokio::fs::File::open(&path).await {
                            Ok(f) => {
                                tokio_util::io::ReaderStream::with_capacity(f, 256 << 10).boxed()
                            }
                            Err(e) => futures_util::stream::once(async move { Err(e) }).boxed(),
                        },
                    }
                })
                .flatten();
            let mut req = self
                .http
                .post(peer.studies_url())
                .timeout(peer.timeout())
                .header(reqwest::header::CONTENT_TYPE, framing.content_type())
                .header(reqwest::header::ACCEPT, "application/dicom+json")
                .header(reqwest::header::CONTENT_LENGTH, framing.body_length(&sizes))
                .body(reqwest::Body::wrap_stream(body));
            if let Some(t) = &peer.bearer_token {
                req = req.bearer_auth(t);
            } else if let Some(u) = &peer.username {
                req = req.basic_auth(u, peer.password.as_deref());
            }
            let resp = req.send().await.map_err(|e| {
                StowError::Unreachable(format!("STOW-RS to {}: {}", peer.name, error_chain(&e)))
            })?;
            let status = resp.status();
            let answer = read_limited(resp).await.map_err(|e| {
                StowError::Unreachable(format!(
                    "STOW-RS to {}: reading the answer: {}",
                    peer.name,
                    error_chain(&e)
                ))
            })?;
            let http = format!(
                "HTTP {} {}",
                status.as_u16(),
                status.canonical_reason().unwrap_or("")
            )
            .trim_end()
            .to_string();
            let Some(acks) = read_stow_response(&answer) else {
                let code = status.as_u16();
                let detail = format!("{http} from {}{}", peer.name, snippet(&answer));
                return if status.is_success() {
                    Err(StowError::Refused {
                        status: code,
                        detail: format!("{detail} (no PS3.18 Store Instances Response)"),
                    })
                } else if status.is_server_error() || code == 408 || code == 429 {
                    Err(StowError::Unreachable(detail))
                } else {
                    Err(StowError::Refused {
                        status: code,
                        detail,
                    })
                };
            };
            Ok(files
                .iter()
                .map(|(_, uid)| match acks.get(uid) {
                    Some(Acknowledged::Stored(w)) => SentInstance {
                        status: Some(*w),
                        stored: true,
                        detail: None,
                    },
                    Some(Acknowledged::Failed(reason)) => SentInstance {
                        status: Some(*reason),
                        stored: false,
                        detail: Some(format!("{http}: Failure Reason {reason:#06X}")),
                    },
                    None if status.as_u16() == 200 => SentInstance {
                        status: Some(0),
                        stored: true,
                        detail: None,
                    },
                    None => SentInstance {
                        status: None,
                        stored: false,
                        detail: Some(format!("{http}: not named in the STOW-RS answer")),
                    },
                })
                .collect())
        }
    }

    /// An error with its sources (reqwest's own Display hides the cause).
    fn error_chain(e: &dyn std::error::Error) -> String {
        let mut s = e.to_string();
        let mut cur = e.source();
        while let Some(c) = cur {
            s.push_str(": ");
            s.push_str(&c.to_string());
            cur = c.source();
        }
        s
    }

    /// The first line of a non-DICOM answer, short, for the detail.
    fn snippet(body: &[u8]) -> String {
        let text: String = String::from_utf8_lossy(body)
            .lines()
            .map(str::trim)
            .find(|l| !l.is_empty())
            .unwrap_or("")
            .chars()
            .filter(|c| !c.is_control())
            .take(200)
            .collect();
        if text.is_empty() {
            String::new()
        } else {
            format!(": {text}")
        }
    }

    async fn read_limited(mut resp: reqwest::Response) -> Result<Vec<u8>, reqwest::Error> {
        let mut out = Vec::new();
        while let Some(chunk) = resp.chunk().await? {
            let room = MAX_ANSWER_BYTES.saturating_sub(out.len());
            out.extend_from_slice(&chunk[..chunk.len().min(room)]);
            if room <= chunk.len() {
                break;
            }
        }
        Ok(out)
    }

    impl App {
        fn stow_client(&self) -> Result<&StowClient, String> {
            if let Some(c) = self.outbound.web.get() {
                return Ok(c);
            }
            let c = StowClient::new()?;
            Ok(self.outbound.web.get_or_init(|| c))
        }

        /// Send the instances of `d` not yet stored to the DICOMweb origin `peer`, batch by batch; the
        /// new state, next attempt and error (as for DIMSE peers).
        pub(in crate::app) async fn send_web(
            &self,
            mut d: Delivery,
            peer: &WebPeer,
        ) -> (Delivery, DeliveryState, Option<i64>, Option<String>) {
            let client = match self.stow_client() {
                Ok(c) => c.clone(),
                Err(why) => return (d, DeliveryState::Failed, None, Some(why)),
            };
            let dir = export_dir(&self.store, d.job_id);
            let todo: Vec<usize> = (0..d.instances.len())
                .filter(|&k| d.instances[k].state != InstanceState::Succeeded)
                .collect();
            let mut refused: Option<String> = None;
            for batch in todo.chunks(peer.batch_instances.max(1)) {
                let files: Vec<(PathBuf, String)> = batch
                    .iter()
                    .map(|&k| {
                        let i = &d.instances[k];
                        (dir.join(&i.file), i.sop_instance_uid.clone())
                    })
                    .collect();
                let outcome = match &refused {
                    // The origin refused a whole request (credentials, size, media type): the next one
                    // would be refused alike.
                    Some(why) => Err(StowError::Refused {
                        status: 0,
                        detail: why.clone(),
                    }),
                    None => client.store(peer, &files).await,
                };
                match outcome {
                    Ok(sent) => {
                        for (&k, s) in batch.iter().zip(sent) {
                            let i = &mut d.instances[k];
                            i.status = s.status;
                            i.detail = s.detail;
                            i.state = if s.stored {
                                InstanceState::Succeeded
                            } else {
                                InstanceState::Failed
                            };
                        }
                    }
                    Err(StowError::Refused { detail, .. }) => {
                        for &k in batch {
                            let i = &mut d.instances[k];
                            i.status = None;
                            i.detail = Some(detail.clone());
                            i.state = InstanceState::Failed;
                        }
                        refused = Some(detail);
                    }
                    Err(StowError::Unreachable(reason)) => return self.unreachable(d, reason),
                }
            }
            let failed = d
                .instances
                .iter()
                .filter(|i| i.state != InstanceState::Succeeded)
                .count();
            if failed == 0 {
                (d, DeliveryState::Succeeded, None, None)
            } else {
                let why = match refused {
                    Some(r) => format!(
                        "{failed} of {} instances were not stored: {r}",
                        d.instances.len()
                    ),
                    None => format!(
                        "{failed} of {} instances were not stored by {}",
                        d.instances.len(),
                        peer.name
                    ),
                };
                (d, DeliveryState::Failed, None, Some(why))
            }
        }
    }
}

#[cfg(test)]
mod tests;
