//! One association accepted by the node: C-ECHO and C-STORE, each instance streamed to a temporary file as
//! its fragments arrive, checked, then filed in its series (or refused with a DIMSE status, leaving nothing);
//! C-FIND and C-MOVE handed to [`super::query`] once their identifier arrived.

use std::sync::Arc;

use dicom_ul::association::AsyncServerAssociation;
use dicom_ul::pdu::{AbortRQServiceProviderReason, AbortRQSource, Pdu};
use tokio::net::TcpStream;

use super::command::{self, Command, status};
use super::inbox::{InstanceSink, SinkError};
use super::query::{self, Retrieval};
use super::tracker::{Arrival, Tracker};
use super::wire::{self, Incoming, Pdv};
use crate::dicom::{DicomError, check_uid, header_of, part10_prefix, read_header};

/// What this association may do, and the limits it runs under.
#[derive(Debug, Clone)]
pub struct Grant {
    pub calling_ae: String,
    pub may_store: bool,
    pub may_query: bool,
    pub may_retrieve: bool,
    pub max_instance_bytes: u64,
    pub dimse_timeout: std::time::Duration,
}

/// The instance being received.
struct Pending {
    command: Command,
    context_id: u8,
    /// `None` once the instance was refused: its remaining fragments are read and dropped.
    sink: Option<InstanceSink>,
    refusal: Option<(u16, String)>,
    /// The identifier of a C-FIND or C-MOVE request, as it arrives.
    identifier: Option<Vec<u8>>,
}

/// Why an association ended other than by release.
#[derive(Debug, thiserror::Error)]
pub enum AssociationEnd {
    #[error("aborted by the peer")]
    PeerAborted,
    #[error("no PDU for {0:?}")]
    Timeout(std::time::Duration),
    #[error("protocol error: {0}")]
    Protocol(String),
    #[error("network: {0}")]
    Network(String),
}

/// Serve an established association until it is released, aborted or fails.
pub async fn serve(
    mut assoc: AsyncServerAssociation<TcpStream>,
    grant: Grant,
    tracker: Arc<Tracker>,
    retrieval: Option<Retrieval>,
) -> Result<usize, AssociationEnd> {
    let mut command_bytes: Vec<u8> = Vec::new();
    let mut pending: Option<Pending> = None;
    let mut stored = 0usize;
    let max_pdu = assoc.acceptor_max_pdu_length();
    loop {
        let pdu =
            match tokio::time::timeout(grant.dimse_timeout, wire::receive(&mut assoc, max_pdu))
                .await
            {
                Ok(Ok(pdu)) => pdu,
                Ok(Err(e)) => {
                    // A PDU that cannot be read (malformed, or over the negotiated maximum length) ends the
                    // association with an A-ABORT (PS3.8 §9.3.8); a connection already gone takes none.
                    let _ = assoc.abort().await;
                    return Err(AssociationEnd::Network(e.to_string()));
                }
                Err(_) => {
                    let _ = assoc.abort().await;
                    return Err(AssociationEnd::Timeout(grant.dimse_timeout));
                }
            };
        let pdu = match pdu {
            Incoming::Data(data) => {
                for value in data.values() {
                    let step = if value.command {
                        on_command(
                            &mut assoc,
                            &grant,
                            &tracker,
                            value,
                            &mut command_bytes,
                            &mut pending,
                        )
                        .await
                    } else {
                        on_data(
                            &mut assoc,
                            &grant,
                            &tracker,
                            retrieval.as_ref(),
                            value,
                            &mut pending,
                        )
                        .await
                    };
                    match step {
                        Ok(true) => stored += 1,
                        Ok(false) => {}
                        Err(e) => {
                            let _ = assoc
                                .send(&Pdu::AbortRQ {
                                    source: AbortRQSource::ServiceProvider(
                                        AbortRQServiceProviderReason::UnexpectedPdu,
                                    ),
                                })
                                .await;
                            return Err(e);
                        }
                    }
                }
                continue;
            }
            Incoming::Other(pdu) => pdu,
        };
        match pdu {
            Pdu::ReleaseRQ => {
                let _ = assoc.send(&Pdu::ReleaseRP).await;
                return Ok(stored);
            }
            Pdu::AbortRQ { .. } => return Err(AssociationEnd::PeerAborted),
            other => {
                let _ = assoc
                    .send(&Pdu::AbortRQ {
                        source: AbortRQSource::ServiceProvider(
                            AbortRQServiceProviderReason::UnexpectedPdu,
                        ),
                    })
                    .await;
                return Err(AssociationEnd::Protocol(format!(
                    "unexpected {}",
                    other.short_description()
                )));
            }
        }
    }
}

async fn reply(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    context_id: u8,
    bytes: Vec<u8>,
) -> Result<(), AssociationEnd> {
    assoc
        .send(&command::pdu(context_id, bytes))
        .await
        .map_err(|e| AssociationEnd::Network(e.to_string()))
}

/// A command fragment; returns whether an instance was stored (never, for a command).
async fn on_command(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    grant: &Grant,
    tracker: &Tracker,
    value: Pdv<'_>,
    buf: &mut Vec<u8>,
    pending: &mut Option<Pending>,
) -> Result<bool, AssociationEnd> {
    if pending.is_some() {
        return Err(AssociationEnd::Protocol(
            "a command arrived before the previous data set ended".into(),
        ));
    }
    if buf.len() + value.data.len() > command::MAX_COMMAND_BYTES {
        return Err(AssociationEnd::Protocol("command set too long".into()));
    }
    buf.extend_from_slice(value.data);
    if !value.last {
        return Ok(false);
    }
    let cmd = command::parse(buf).map_err(|e| AssociationEnd::Protocol(e.to_string()))?;
    buf.clear();
    let context = assoc
        .presentation_contexts()
        .iter()
        .find(|pc| pc.id == value.context_id)
        .cloned()
        .ok_or_else(|| AssociationEnd::Protocol("unknown presentation context".into()))?;
    match cmd.field {
        command::C_ECHO_RQ => {
            reply(
                assoc,
                value.context_id,
                command::echo_response(cmd.message_id, status::SUCCESS),
            )
            .await?;
        }
        command::C_STORE_RQ if cmd.has_data_set => {
            let mut refusal = if !grant.may_store {
                Some((
                    status::NOT_AUTHORIZED,
                    format!("{} may not store here", grant.calling_ae),
                ))
            } else if context.abstract_syntax != cmd.sop_class_uid {
                Some((
                    status::SOP_CLASS_NOT_SUPPORTED,
                    "SOP class differs from the presentation context".into(),
                ))
            } else if let Err(e) = check_uid(
                "the request",
                "Affected SOP Instance UID (0000,1000)",
                Some(&cmd.sop_instance_uid),
            ) {
                Some((status::CANNOT_UNDERSTAND, error_comment(&e)))
            } else {
                None
            };
            let sink = match refusal {
                Some(_) => None,
                None => {
                    let prefix = part10_prefix(
                        &cmd.sop_class_uid,
                        &cmd.sop_instance_uid,
                        &context.transfer_syntax,
                    )
                    .map_err(|e| AssociationEnd::Protocol(e.to_string()))?;
                    match tracker.inbox().begin(
                        &prefix,
                        grant.max_instance_bytes.saturating_add(prefix.len() as u64),
                    ) {
                        Ok(sink) => Some(sink),
                        Err(e) => {
                            refusal = Some((status::OUT_OF_RESOURCES, e.to_string()));
                            None
                        }
                    }
                }
            };
            *pending = Some(Pending {
                command: cmd,
                context_id: value.context_id,
                sink,
                refusal,
                identifier: None,
            });
        }
        command::C_FIND_RQ | command::C_MOVE_RQ if cmd.has_data_set => {
            *pending = Some(Pending {
                command: cmd,
                context_id: value.context_id,
                sink: None,
                refusal: None,
                identifier: Some(Vec::new()),
            });
        }
        // A cancel that arrives while a C-FIND or C-MOVE answers is taken by that operation (`cancel`); one
        // read here came after its operation ended: there is nothing left to cancel, and it has no response.
        command::C_CANCEL_RQ => {}
        _ => {
            reply(
                assoc,
                value.context_id,
                command::unrecognized_response(&cmd),
            )
            .await?;
        }
    }
    Ok(false)
}

/// A data set fragment; returns whether it completed a stored instance.
async fn on_data(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    grant: &Grant,
    tracker: &Arc<Tracker>,
    retrieval: Option<&Retrieval>,
    value: Pdv<'_>,
    pending: &mut Option<Pending>,
) -> Result<bool, AssociationEnd> {
    let Some(p) = pending.as_mut() else {
        return Err(AssociationEnd::Protocol(
            "a data set fragment arrived without a C-STORE request".into(),
        ));
    };
    if p.context_id != value.context_id {
        return Err(AssociationEnd::Protocol(
            "a data set fragment on another presentation context".into(),
        ));
    }
    if let Some(buf) = p.identifier.as_mut() {
        if buf.len() + value.data.len() > crate::dicom::MAX_IDENTIFIER_BYTES {
            return Err(AssociationEnd::Protocol("identifier too long".into()));
        }
        buf.extend_from_slice(value.data);
        if !value.last {
            return Ok(false);
        }
        let Some(Pending {
            command: cmd,
            context_id,
            identifier: Some(bytes),
            ..
        }) = pending.take()
        else {
            return Ok(false);
        };
        on_query(assoc, grant, retrieval, cmd, context_id, bytes).await?;
        return Ok(false);
    }
    if let Some(sink) = p.sink.as_mut()
        && let Err(e) = sink.write(value.data).await
    {
        p.sink = None;
        p.refusal = Some(match e {
            SinkError::TooLarge(limit) => (
                status::OUT_OF_RESOURCES,
                format!("instance larger than {limit} bytes"),
            ),
            SinkError::Io(e) => {
                tracing::error!(error = %e, "cannot write an instance");
                (status::OUT_OF_RESOURCES, "storage unavailable".into())
            }
        });
    }
    if !value.last {
        return Ok(false);
    }
    let Some(Pending {
        command: cmd,
        context_id,
        sink,
        refusal,
        ..
    }) = pending.take()
    else {
        return Ok(false);
    };
    let (code, comment) = match (sink, refusal) {
        (Some(sink), None) => file(sink, &cmd, grant, tracker).await,
        (_, Some(refusal)) => refusal,
        (None, None) => (status::OUT_OF_RESOURCES, "storage unavailable".into()),
    };
    if code != status::SUCCESS {
        tracing::warn!(sop_instance_uid = %cmd.sop_instance_uid, status = format!("{code:04X}"), reason = %comment, "instance refused");
    }
    let comment = (code != status::SUCCESS).then_some(comment.as_str());
    reply(
        assoc,
        context_id,
        command::store_response(
            cmd.message_id,
            &cmd.sop_class_uid,
            &cmd.sop_instance_uid,
            code,
            comment,
        ),
    )
    .await?;
    Ok(code == status::SUCCESS)
}

/// Run a C-FIND or C-MOVE whose identifier arrived whole.
async fn on_query(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    grant: &Grant,
    retrieval: Option<&Retrieval>,
    cmd: Command,
    context_id: u8,
    identifier: Vec<u8>,
) -> Result<(), AssociationEnd> {
    let context = assoc
        .presentation_contexts()
        .iter()
        .find(|pc| pc.id == context_id)
        .cloned()
        .ok_or_else(|| AssociationEnd::Protocol("unknown presentation context".into()))?;
    let Some(retrieval) = retrieval else {
        return reply(assoc, context_id, command::unrecognized_response(&cmd)).await;
    };
    use tracing::Instrument as _;
    if cmd.field == command::C_FIND_RQ {
        query::find(assoc, grant, retrieval, &cmd, &context, &identifier)
            .instrument(tracing::info_span!("c_find"))
            .await
    } else {
        query::move_instances(assoc, grant, retrieval, &cmd, &context, &identifier)
            .instrument(tracing::info_span!("c_move"))
            .await
    }
}

/// Write out, sync and check a received instance and file it in its series, all in one blocking task:
/// (status, reason). The header is read from memory when the instance was held whole.
async fn file(
    sink: InstanceSink,
    cmd: &Command,
    grant: &Grant,
    tracker: &Arc<Tracker>,
) -> (u16, String) {
    let bytes = sink.written();
    let (cmd, tracker, calling_ae) = (cmd.clone(), tracker.clone(), grant.calling_ae.clone());
    let max = grant.max_instance_bytes.saturating_add(64 << 10);
    let checked = tokio::task::spawn_blocking(move || {
        let received = match sink.finish() {
            Ok(r) => r,
            Err(e) => {
                tracing::error!(error = %e, "cannot sync an instance");
                return (status::OUT_OF_RESOURCES, "storage unavailable".into());
            }
        };
        let header = match received.bytes() {
            Some(b) => header_of(&cmd.sop_instance_uid, b),
            None => read_header(received.path(), max),
        };
        let header = match header {
            Ok(h) => h,
            Err(e) => return (status::CANNOT_UNDERSTAND, error_comment(&e)),
        };
        if header.sop_instance_uid != cmd.sop_instance_uid
            || header.sop_class_uid != cmd.sop_class_uid
        {
            return (
                status::DATA_SET_MISMATCH,
                "SOP class or instance of the data set differs from the request".into(),
            );
        }
        let arrival = Arrival {
            study_uid: &header.study_uid,
            series_uid: &header.series_uid,
            sop_instance_uid: &header.sop_instance_uid,
            calling_ae: &calling_ae,
            bytes,
        };
        match tracker.file(received.path(), arrival) {
            Ok(_) => {
                received.keep();
                (status::SUCCESS, String::new())
            }
            Err(e) => {
                tracing::error!(error = %e, "cannot file an instance");
                (status::OUT_OF_RESOURCES, "storage unavailable".into())
            }
        }
    })
    .await;
    checked.unwrap_or_else(|_| (status::CANNOT_UNDERSTAND, "malformed data set".into()))
}

/// The Error Comment of a refused data set: the catalogue code first, since the comment is cut at 64
/// characters; a malformed UID is named by its attribute and defect (never its value).
fn error_comment(e: &DicomError) -> String {
    match e {
        DicomError::InvalidUid {
            attribute, reason, ..
        } => format!("{}: {attribute}: {reason}", e.code()),
        _ => format!("{}: {e}", e.code()),
    }
}
