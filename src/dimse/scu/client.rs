//! The association with a peer as service class user: establishing it (every network step under the
//! caller's timeout), sending a command set, reading the peer's next response, and the context it accepted.

use std::time::Duration;

use dicom_ul::association::client::ClientAssociationOptions;
use dicom_ul::pdu::{PDataValueType, Pdu, PresentationContextResultReason};

use super::{Caller, ScuError};
use crate::config::dicom::Peer;
use crate::dimse::command;

pub(in crate::dimse) type Assoc =
    dicom_ul::association::AsyncClientAssociation<tokio::net::TcpStream>;

fn address(peer: &Peer) -> String {
    format!("{}:{}", peer.host, peer.port)
}

pub(in crate::dimse) async fn timed<T, E: std::fmt::Display>(
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

pub(in crate::dimse) async fn associate(
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
pub(super) async fn response(
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

pub(in crate::dimse) async fn send_command(
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

pub(super) fn accepted(assoc: &Assoc, sop_class: &str, ts: &str) -> Option<u8> {
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
