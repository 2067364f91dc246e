//! ctrecon as a service class user: C-ECHO to test a peer, C-STORE of Part 10 files to a peer, each file's
//! data set sent as it is stored (streamed from disk in PDU-sized fragments, never whole in memory), or, for
//! a peer that accepted its SOP class only in the other uncompressed little-endian syntax, re-encoded (one
//! instance in memory). A file whose SOP class the peer rejected is reported as not sent, with the reason.

use std::path::{Path, PathBuf};
use std::time::Duration;

use dicom_ul::association::client::ClientAssociationOptions;
use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu, PresentationContextResultReason};
use tokio::io::{AsyncReadExt, AsyncSeekExt};

use super::command::{self, VERIFICATION};
use crate::config::dicom::Peer;
use crate::dicom::{
    EXPLICIT_LE, IMPLICIT_LE, Part10, data_set_as, le_interchangeable, read_part10,
};

/// How ctrecon calls a peer.
#[derive(Debug, Clone)]
pub struct Caller {
    /// ctrecon's AE title as the calling AE.
    pub ae_title: String,
    /// Limit of each network step (connect, negotiate, one response).
    pub timeout: Duration,
    pub max_pdu_length: u32,
}

/// Why a call to a peer failed as a whole.
#[derive(Debug, thiserror::Error)]
pub enum ScuError {
    #[error("cannot associate with {peer}: {reason}")]
    Associate { peer: String, reason: String },
    #[error("{peer} did not answer within {0:?}", .timeout)]
    Timeout { peer: String, timeout: Duration },
    #[error("network error with {peer}: {reason}")]
    Network { peer: String, reason: String },
    #[error("{peer} answered with something other than a DIMSE response: {reason}")]
    Protocol { peer: String, reason: String },
}

/// What became of one file sent by C-STORE.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StoreOutcome {
    pub file: PathBuf,
    pub sop_instance_uid: String,
    /// The peer's DIMSE status; `None` when the file was not sent.
    pub status: Option<u16>,
    /// The peer's Error Comment, or why the file was not sent.
    pub detail: Option<String>,
}

impl StoreOutcome {
    pub fn stored(&self) -> bool {
        self.status.is_some_and(command::is_stored)
    }
}

pub(super) type Assoc = dicom_ul::association::AsyncClientAssociation<tokio::net::TcpStream>;

fn address(peer: &Peer) -> String {
    format!("{}:{}", peer.host, peer.port)
}

pub(super) async fn timed<T, E: std::fmt::Display>(
    peer: &Peer,
    limit: Duration,
    f: impl std::future::Future<Output = Result<T, E>>,
    wrap: impl FnOnce(String) -> ScuError,
) -> Result<T, ScuError> {
    match tokio::time::timeout(limit, f).await {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(wrap(e.to_string())),
        Err(_) => Err(ScuError::Timeout {
            peer: peer.ae_title.clone(),
            timeout: limit,
        }),
    }
}

pub(super) async fn associate(
    caller: &Caller,
    peer: &Peer,
    contexts: &[(String, Vec<String>)],
) -> Result<Assoc, ScuError> {
    let mut options = ClientAssociationOptions::new()
        .calling_ae_title(caller.ae_title.clone())
        .called_ae_title(peer.ae_title.clone())
        .max_pdu_length(caller.max_pdu_length)
        .read_timeout(caller.timeout)
        .write_timeout(caller.timeout)
        .connection_timeout(caller.timeout);
    for (sop, ts) in contexts {
        options = options.with_presentation_context(sop.clone(), ts.clone());
    }
    let name = peer.ae_title.clone();
    let assoc = timed(
        peer,
        caller.timeout,
        options.establish_async(address(peer)),
        |reason| ScuError::Associate { peer: name, reason },
    )
    .await?;
    let mut assoc = assoc;
    let _ = assoc.inner_stream().set_nodelay(true);
    Ok(assoc)
}

/// The next command set the peer sends (data sets, if any, are skipped).
async fn response(
    assoc: &mut Assoc,
    caller: &Caller,
    peer: &Peer,
) -> Result<command::Command, ScuError> {
    let mut buf = Vec::new();
    loop {
        let name = peer.ae_title.clone();
        let pdu = timed(peer, caller.timeout, assoc.receive(), |reason| {
            ScuError::Network { peer: name, reason }
        })
        .await?;
        let protocol = |reason: String| ScuError::Protocol {
            peer: peer.ae_title.clone(),
            reason,
        };
        match pdu {
            Pdu::PData { data } => {
                for v in data {
                    if v.value_type != PDataValueType::Command {
                        continue;
                    }
                    if buf.len() + v.data.len() > command::MAX_COMMAND_BYTES {
                        return Err(protocol("command set too long".into()));
                    }
                    buf.extend_from_slice(&v.data);
                    if v.is_last {
                        return command::parse(&buf).map_err(|e| protocol(e.to_string()));
                    }
                }
            }
            Pdu::AbortRQ { source } => return Err(protocol(format!("aborted ({source:?})"))),
            other => {
                return Err(protocol(format!(
                    "unexpected {}",
                    other.short_description()
                )));
            }
        }
    }
}

pub(super) async fn send_command(
    assoc: &mut Assoc,
    peer: &Peer,
    context: u8,
    bytes: Vec<u8>,
) -> Result<(), ScuError> {
    assoc
        .send(&command::pdu(context, bytes))
        .await
        .map_err(|e| ScuError::Network {
            peer: peer.ae_title.clone(),
            reason: e.to_string(),
        })
}

/// C-ECHO: the peer's status (0 = success).
pub async fn echo(caller: &Caller, peer: &Peer) -> Result<u16, ScuError> {
    let contexts = vec![(
        VERIFICATION.to_string(),
        vec!["1.2.840.10008.1.2".to_string()],
    )];
    let mut assoc = associate(caller, peer, &contexts).await?;
    let context =
        accepted(&assoc, VERIFICATION, "1.2.840.10008.1.2").ok_or_else(|| ScuError::Associate {
            peer: peer.ae_title.clone(),
            reason: "verification not accepted".into(),
        })?;
    send_command(&mut assoc, peer, context, command::echo_request(1)).await?;
    let rsp = response(&mut assoc, caller, peer).await?;
    let _ = assoc.release().await;
    Ok(rsp.status.unwrap_or(command::status::CANNOT_UNDERSTAND))
}

fn accepted(assoc: &Assoc, sop_class: &str, ts: &str) -> Option<u8> {
    assoc
        .presentation_contexts()
        .iter()
        .find(|pc| {
            pc.reason == PresentationContextResultReason::Acceptance
                && pc.abstract_syntax == sop_class
                && pc.transfer_syntax == ts
        })
        .map(|pc| pc.id)
}

/// C-STORE each file in one association. A file that cannot be read or whose SOP class and transfer
/// syntax the peer did not accept is reported and skipped; the others are sent.
pub async fn store(
    caller: &Caller,
    peer: &Peer,
    files: &[PathBuf],
) -> Result<Vec<StoreOutcome>, ScuError> {
    store_with(caller, peer, files, &StoreOptions::default()).await
}

/// How a C-STORE batch is sent: on behalf of a C-MOVE, and who hears of each outcome as it comes.
#[derive(Debug, Clone, Default)]
pub struct StoreOptions {
    /// The C-MOVE this sending serves: its caller's AE title and its Message ID.
    pub move_originator: Option<(String, u16)>,
    /// Receives each file's outcome as soon as it is known.
    pub progress: Option<tokio::sync::mpsc::UnboundedSender<StoreOutcome>>,
    /// Once set, no further file is sent (the association is released; the files not sent have no outcome).
    pub cancel: Option<crate::recon::control::Cancel>,
}

/// [`store`] with options.
pub async fn store_with(
    caller: &Caller,
    peer: &Peer,
    files: &[PathBuf],
    options: &StoreOptions,
) -> Result<Vec<StoreOutcome>, ScuError> {
    let mut outcomes = Outcomes {
        list: Vec::with_capacity(files.len()),
        progress: options.progress.clone(),
    };
    let originator = options
        .move_originator
        .as_ref()
        .map(|(ae, id)| (ae.as_str(), *id));
    let list = files.to_vec();
    let metas: Vec<Result<Part10, String>> = tokio::task::spawn_blocking(move || {
        list.iter()
            .map(|f| read_part10(f).map_err(|e| e.to_string()))
            .collect()
    })
    .await
    .map_err(|e| ScuError::Protocol {
        peer: peer.ae_title.clone(),
        reason: e.to_string(),
    })?;
    let mut contexts: Vec<(String, Vec<String>)> = Vec::new();
    for m in metas.iter().flatten() {
        let c = (
            m.sop_class_uid.clone(),
            proposed_syntaxes(&m.transfer_syntax),
        );
        if !contexts.contains(&c) && contexts.len() < 128 {
            contexts.push(c);
        }
    }
    if contexts.is_empty() {
        for (file, m) in files.iter().zip(metas) {
            outcomes.push(not_sent(file, String::new(), m.err().unwrap_or_default()));
        }
        return Ok(outcomes.list);
    }
    let mut assoc = associate(caller, peer, &contexts).await?;
    for (i, (file, meta)) in files.iter().zip(metas).enumerate() {
        if options.cancel.as_ref().is_some_and(|c| c.is_canceled()) {
            break;
        }
        let meta = match meta {
            Ok(m) => m,
            Err(reason) => {
                outcomes.push(not_sent(file, String::new(), reason));
                continue;
            }
        };
        let Some((context, ts)) = accepted_for(&assoc, &meta.sop_class_uid, &meta.transfer_syntax)
        else {
            outcomes.push(not_sent(
                file,
                meta.sop_instance_uid.clone(),
                refusal(&assoc, peer, &meta.sop_class_uid, &meta.transfer_syntax),
            ));
            continue;
        };
        // A peer that accepted only the other little-endian syntax gets the data set re-encoded.
        let transcoded = if ts == meta.transfer_syntax {
            None
        } else {
            let (path, to) = (file.clone(), ts.clone());
            let limit = MAX_TRANSCODED_BYTES;
            match tokio::task::spawn_blocking(move || data_set_as(&path, &to, limit)).await {
                Ok(Ok(bytes)) => Some(bytes),
                Ok(Err(e)) => {
                    outcomes.push(not_sent(
                        file,
                        meta.sop_instance_uid.clone(),
                        format!("cannot re-encode it in {ts}: {e}"),
                    ));
                    continue;
                }
                Err(e) => {
                    outcomes.push(not_sent(file, meta.sop_instance_uid.clone(), e.to_string()));
                    continue;
                }
            }
        };
        let message_id = (i % 0xFFFF) as u16 + 1;
        let rq = command::store_request(
            message_id,
            &meta.sop_class_uid,
            &meta.sop_instance_uid,
            originator,
        );
        send_command(&mut assoc, peer, context, rq).await?;
        match &transcoded {
            None => {
                send_data_set(&mut assoc, caller, peer, context, file, meta.dataset_offset).await?
            }
            Some(bytes) => send_buffer(&mut assoc, caller, peer, context, bytes).await?,
        }
        let rsp = response(&mut assoc, caller, peer).await?;
        outcomes.push(StoreOutcome {
            file: file.clone(),
            sop_instance_uid: meta.sop_instance_uid,
            status: rsp.status,
            detail: rsp.error_comment,
        });
    }
    let _ = assoc.release().await;
    Ok(outcomes.list)
}

/// Largest instance re-encoded for a peer (it is held whole in memory while sent).
const MAX_TRANSCODED_BYTES: u64 = 1 << 30;

/// The transfer syntaxes proposed for a file stored in `ts`: its own, then the other uncompressed
/// little-endian syntax when it is one of them (sent re-encoded if only that one is accepted).
fn proposed_syntaxes(ts: &str) -> Vec<String> {
    let mut out = vec![ts.to_string()];
    for other in [EXPLICIT_LE, IMPLICIT_LE] {
        if other != ts && le_interchangeable(ts, other) {
            out.push(other.to_string());
        }
    }
    out
}

/// The accepted context for `sop_class` in which a file stored in `ts` can be sent: the same syntax first,
/// else the other little-endian one. Returns its id and transfer syntax.
fn accepted_for(assoc: &Assoc, sop_class: &str, ts: &str) -> Option<(u8, String)> {
    let usable = assoc.presentation_contexts().iter().filter(|pc| {
        pc.reason == PresentationContextResultReason::Acceptance && pc.abstract_syntax == sop_class
    });
    let mut fallback = None;
    for pc in usable {
        if pc.transfer_syntax == ts {
            return Some((pc.id, pc.transfer_syntax.clone()));
        }
        if fallback.is_none() && le_interchangeable(ts, &pc.transfer_syntax) {
            fallback = Some((pc.id, pc.transfer_syntax.clone()));
        }
    }
    fallback
}

/// Why a file of `sop_class` stored in `ts` cannot be sent on this association, in the peer's terms.
fn refusal(assoc: &Assoc, peer: &Peer, sop_class: &str, ts: &str) -> String {
    let name = sop_class_name(sop_class);
    let offered: Vec<_> = assoc
        .presentation_contexts()
        .iter()
        .filter(|pc| pc.abstract_syntax == sop_class)
        .collect();
    match offered
        .iter()
        .find(|pc| pc.reason != PresentationContextResultReason::Acceptance)
    {
        Some(pc) => format!(
            "{} rejected the presentation context of SOP class {sop_class}{name} ({:?})",
            peer.ae_title, pc.reason
        ),
        None if offered.is_empty() => format!(
            "{} did not accept SOP class {sop_class}{name} (no presentation context)",
            peer.ae_title
        ),
        None => format!(
            "{} accepted SOP class {sop_class}{name} only in a transfer syntax it cannot be converted to \
             from {ts}",
            peer.ae_title
        ),
    }
}

/// `" (<name>)"` for the SOP classes ctrecon sends, else nothing.
fn sop_class_name(uid: &str) -> &'static str {
    match uid {
        "1.2.840.10008.5.1.4.1.1.2" => " (CT Image Storage)",
        "1.2.840.10008.5.1.4.1.1.2.1" => " (Enhanced CT Image Storage)",
        "1.2.840.10008.5.1.4.1.1.7" => " (Secondary Capture Image Storage)",
        "1.2.840.10008.5.1.4.1.1.7.4" => {
            " (Multi-frame True Color Secondary Capture Image Storage)"
        }
        "1.2.840.10008.5.1.4.1.1.104.3" => " (Encapsulated STL Storage)",
        _ => "",
    }
}

/// Send an in-memory data set as P-DATA fragments no larger than the peer admits.
async fn send_buffer(
    assoc: &mut Assoc,
    caller: &Caller,
    peer: &Peer,
    context: u8,
    bytes: &[u8],
) -> Result<(), ScuError> {
    let peer_max = match assoc.acceptor_max_pdu_length() {
        0 => 64 << 10,
        n => n.min(1 << 20),
    };
    let chunk = (peer_max as usize).saturating_sub(6).max(1024);
    let parts: Vec<&[u8]> = if bytes.is_empty() {
        vec![bytes]
    } else {
        bytes.chunks(chunk).collect()
    };
    let n = parts.len();
    for (i, part) in parts.into_iter().enumerate() {
        let pdu = Pdu::PData {
            data: vec![PDataValue {
                presentation_context_id: context,
                value_type: PDataValueType::Data,
                is_last: i + 1 == n,
                data: part.to_vec(),
            }],
        };
        match tokio::time::timeout(caller.timeout, assoc.send(&pdu)).await {
            Ok(r) => r.map_err(|e| ScuError::Network {
                peer: peer.ae_title.clone(),
                reason: e.to_string(),
            })?,
            Err(_) => {
                return Err(ScuError::Timeout {
                    peer: peer.ae_title.clone(),
                    timeout: caller.timeout,
                });
            }
        }
    }
    Ok(())
}

/// The outcomes so far, each also sent to the progress listener.
struct Outcomes {
    list: Vec<StoreOutcome>,
    progress: Option<tokio::sync::mpsc::UnboundedSender<StoreOutcome>>,
}

impl Outcomes {
    fn push(&mut self, o: StoreOutcome) {
        if let Some(p) = &self.progress {
            let _ = p.send(o.clone());
        }
        self.list.push(o);
    }
}

fn not_sent(file: &Path, sop_instance_uid: String, reason: String) -> StoreOutcome {
    StoreOutcome {
        file: file.to_path_buf(),
        sop_instance_uid,
        status: None,
        detail: Some(reason),
    }
}

/// Send the data set at `offset` of `file` as P-DATA fragments no larger than the peer admits.
async fn send_data_set(
    assoc: &mut Assoc,
    caller: &Caller,
    peer: &Peer,
    context: u8,
    file: &Path,
    offset: u64,
) -> Result<(), ScuError> {
    let net = |reason: String| ScuError::Network {
        peer: peer.ae_title.clone(),
        reason,
    };
    let mut f = tokio::fs::File::open(file)
        .await
        .map_err(|e| net(e.to_string()))?;
    let size = f.metadata().await.map_err(|e| net(e.to_string()))?.len();
    f.seek(std::io::SeekFrom::Start(offset))
        .await
        .map_err(|e| net(e.to_string()))?;
    // A PDV item takes 6 bytes of the PDU's length (4 length, context id, control header).
    let peer_max = match assoc.acceptor_max_pdu_length() {
        0 => 64 << 10,
        n => n.min(1 << 20),
    };
    let chunk = (peer_max as usize).saturating_sub(6).max(1024);
    let mut remaining = size.saturating_sub(offset);
    let mut buf = vec![0u8; chunk];
    loop {
        let n = (remaining.min(chunk as u64)) as usize;
        f.read_exact(&mut buf[..n])
            .await
            .map_err(|e| net(e.to_string()))?;
        remaining -= n as u64;
        let pdu = Pdu::PData {
            data: vec![PDataValue {
                presentation_context_id: context,
                value_type: PDataValueType::Data,
                is_last: remaining == 0,
                data: buf[..n].to_vec(),
            }],
        };
        match tokio::time::timeout(caller.timeout, assoc.send(&pdu)).await {
            Ok(r) => r.map_err(|e| net(e.to_string()))?,
            Err(_) => {
                return Err(ScuError::Timeout {
                    peer: peer.ae_title.clone(),
                    timeout: caller.timeout,
                });
            }
        }
        if remaining == 0 {
            return Ok(());
        }
    }
}
