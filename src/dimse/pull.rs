//! ctrecon querying and retrieving from a peer (Study Root C-FIND and C-MOVE as service class user): the
//! building blocks of pulling a series from a PACS.

use std::collections::VecDeque;

use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu, PresentationContextResultReason};

use super::command::{self, Command, SubOperations, status};
use super::query::{STUDY_ROOT_FIND, STUDY_ROOT_MOVE};
use super::scu::{Assoc, Caller, ScuError, associate, send_command, timed};
use crate::config::dicom::Peer;
use crate::dicom::{IdentifierElement, MAX_IDENTIFIER_BYTES, read_identifier, write_identifier};
use crate::recon::control::Cancel;

const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const IMPLICIT_LE: &str = "1.2.840.10008.1.2";

/// What a C-MOVE came to: the peer's final status and its sub-operation counts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MoveOutcome {
    pub status: u16,
    pub sub_operations: SubOperations,
}

/// The messages of one association, read PDU by PDU (a PDU may carry several fragments).
struct Messages {
    pending: VecDeque<PDataValue>,
}

impl Messages {
    async fn next_value(
        &mut self,
        assoc: &mut Assoc,
        caller: &Caller,
        peer: &Peer,
    ) -> Result<PDataValue, ScuError> {
        loop {
            if let Some(v) = self.pending.pop_front() {
                return Ok(v);
            }
            let name = peer.ae_title.clone();
            let pdu = timed(peer, caller.timeout, assoc.receive(), |reason| {
                ScuError::Network { peer: name, reason }
            })
            .await?;
            match pdu {
                Pdu::PData { data } => self.pending.extend(data),
                Pdu::AbortRQ { source } => {
                    return Err(protocol(peer, format!("aborted ({source:?})")));
                }
                other => {
                    return Err(protocol(
                        peer,
                        format!("unexpected {}", other.short_description()),
                    ));
                }
            }
        }
    }

    /// The next command and, when one follows it, its data set.
    async fn next(
        &mut self,
        assoc: &mut Assoc,
        caller: &Caller,
        peer: &Peer,
    ) -> Result<(Command, Option<Vec<u8>>), ScuError> {
        let mut buf = Vec::new();
        let cmd = loop {
            let v = self.next_value(assoc, caller, peer).await?;
            if v.value_type != PDataValueType::Command {
                return Err(protocol(peer, "a data set without a command".into()));
            }
            if buf.len() + v.data.len() > command::MAX_COMMAND_BYTES {
                return Err(protocol(peer, "command set too long".into()));
            }
            buf.extend_from_slice(&v.data);
            if v.is_last {
                break command::parse(&buf).map_err(|e| protocol(peer, e.to_string()))?;
            }
        };
        if !cmd.has_data_set {
            return Ok((cmd, None));
        }
        let mut data = Vec::new();
        loop {
            let v = self.next_value(assoc, caller, peer).await?;
            if v.value_type != PDataValueType::Data {
                return Err(protocol(peer, "a command inside a data set".into()));
            }
            if data.len() + v.data.len() > MAX_IDENTIFIER_BYTES {
                return Err(protocol(peer, "identifier too long".into()));
            }
            data.extend_from_slice(&v.data);
            if v.is_last {
                return Ok((cmd, Some(data)));
            }
        }
    }
}

fn protocol(peer: &Peer, reason: String) -> ScuError {
    ScuError::Protocol {
        peer: peer.ae_title.clone(),
        reason,
    }
}

/// Associate for `sop_class` and send its request with `keys`; returns the association, the accepted
/// transfer syntax and the reader of the responses.
async fn request(
    caller: &Caller,
    peer: &Peer,
    sop_class: &str,
    rq: impl FnOnce(u8) -> Vec<u8>,
    keys: &[IdentifierElement],
) -> Result<(Assoc, String, Messages), ScuError> {
    let contexts = vec![(
        sop_class.to_string(),
        vec![EXPLICIT_LE.to_string(), IMPLICIT_LE.to_string()],
    )];
    let mut assoc = associate(caller, peer, &contexts).await?;
    let (context, ts) = assoc
        .presentation_contexts()
        .iter()
        .find(|pc| {
            pc.reason == PresentationContextResultReason::Acceptance
                && pc.abstract_syntax == sop_class
        })
        .map(|pc| (pc.id, pc.transfer_syntax.clone()))
        .ok_or_else(|| ScuError::Associate {
            peer: peer.ae_title.clone(),
            reason: format!("{sop_class} not accepted"),
        })?;
    let identifier = write_identifier(keys, &ts).map_err(|e| protocol(peer, e.to_string()))?;
    send_command(&mut assoc, peer, context, rq(context)).await?;
    let max = match assoc.acceptor_max_pdu_length() {
        0 => 16 << 10,
        n => n.min(1 << 20),
    };
    let parts: Vec<&[u8]> = identifier
        .chunks((max as usize).saturating_sub(6).max(1024))
        .collect();
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
        assoc.send(&pdu).await.map_err(|e| ScuError::Network {
            peer: peer.ae_title.clone(),
            reason: e.to_string(),
        })?;
    }
    let messages = Messages {
        pending: VecDeque::new(),
    };
    Ok((assoc, ts, messages))
}

/// C-FIND in the Study Root model: the identifier of every match. A final status other than success is
/// an error naming it.
pub async fn find(
    caller: &Caller,
    peer: &Peer,
    keys: &[IdentifierElement],
) -> Result<Vec<Vec<IdentifierElement>>, ScuError> {
    let (mut assoc, ts, mut messages) = request(
        caller,
        peer,
        STUDY_ROOT_FIND,
        |_| command::find_request(1, STUDY_ROOT_FIND),
        keys,
    )
    .await?;
    let mut found = Vec::new();
    loop {
        let (cmd, data) = messages.next(&mut assoc, caller, peer).await?;
        match cmd.status {
            Some(status::PENDING | 0xFF01) => {
                let data =
                    data.ok_or_else(|| protocol(peer, "a match without identifier".into()))?;
                found.push(read_identifier(&data, &ts).map_err(|e| protocol(peer, e.to_string()))?);
            }
            Some(status::SUCCESS) => break,
            other => {
                let _ = assoc.abort().await;
                return Err(protocol(
                    peer,
                    format!(
                        "C-FIND ended with status {:04X}{}",
                        other.unwrap_or(0xFFFF),
                        cmd.error_comment
                            .map(|c| format!(": {c}"))
                            .unwrap_or_default()
                    ),
                ));
            }
        }
    }
    let _ = assoc.release().await;
    Ok(found)
}

/// C-MOVE in the Study Root model: ask `peer` to send what `keys` select to `destination`; waits for the
/// final response.
pub async fn retrieve(
    caller: &Caller,
    peer: &Peer,
    destination: &str,
    keys: &[IdentifierElement],
) -> Result<MoveOutcome, ScuError> {
    let never = Cancel::new();
    retrieve_watched(caller, peer, destination, keys, &never, &|_| {})
        .await
        .map(|o| {
            o.unwrap_or(MoveOutcome {
                status: status::CANCEL,
                sub_operations: SubOperations::default(),
            })
        })
}

/// How often a retrieval looks at its cancel flag.
const CANCEL_POLL: std::time::Duration = std::time::Duration::from_millis(200);

/// [`retrieve`], telling `pending` the sub-operation counts of each pending response; `None` when `cancel`
/// was set before the final response (the association is then aborted, which ends the peer's
/// sub-operations).
pub async fn retrieve_watched(
    caller: &Caller,
    peer: &Peer,
    destination: &str,
    keys: &[IdentifierElement],
    cancel: &Cancel,
    pending: &(dyn Fn(SubOperations) + Sync),
) -> Result<Option<MoveOutcome>, ScuError> {
    let (mut assoc, _, mut messages) = request(
        caller,
        peer,
        STUDY_ROOT_MOVE,
        |_| command::move_request(1, STUDY_ROOT_MOVE, destination),
        keys,
    )
    .await?;
    let canceled = || async {
        while !cancel.is_canceled() {
            tokio::time::sleep(CANCEL_POLL).await;
        }
    };
    loop {
        let next = tokio::select! {
            r = messages.next(&mut assoc, caller, peer) => Some(r),
            _ = canceled() => None,
        };
        let Some(next) = next else {
            let _ = assoc.abort().await;
            return Ok(None);
        };
        let (cmd, _) = next?;
        let status = cmd.status.unwrap_or(status::CANNOT_UNDERSTAND);
        if status != status::PENDING {
            let _ = assoc.release().await;
            return Ok(Some(MoveOutcome {
                status,
                sub_operations: cmd.sub_operations.unwrap_or_default(),
            }));
        }
        if let Some(counts) = cmd.sub_operations {
            pending(counts);
        }
    }
}
