//! C-CANCEL as provider: while a C-FIND or C-MOVE answers, the node looks (without waiting) at what the
//! caller sent; a C-CANCEL-RQ naming the operation's Message ID stops it, and the operation then ends with
//! the Cancel status (FE00) and, for C-MOVE, the sub-operation counts so far.
//!
//! Reading is cancel-safe: `dicom-ul` keeps bytes of a PDU that has not fully arrived in the association's
//! buffer. Without asynchronous operations negotiated, a caller sends nothing else during an operation: any
//! other PDU ends the association (an A-ABORT is the caller's abort).

use std::time::Duration;

use dicom_ul::association::AsyncServerAssociation;
use dicom_ul::pdu::{PDataValueType, Pdu};
use tokio::net::TcpStream;

use super::association::AssociationEnd;
use super::command;

/// Whether the caller asked to cancel the operation of `message_id`, from what already arrived.
pub(super) async fn requested(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    message_id: u16,
) -> Result<bool, AssociationEnd> {
    let pdu = match tokio::time::timeout(Duration::ZERO, assoc.receive()).await {
        Err(_) => return Ok(false),
        Ok(Err(e)) => return Err(AssociationEnd::Network(e.to_string())),
        Ok(Ok(pdu)) => pdu,
    };
    match pdu {
        Pdu::PData { data } => {
            let mut canceled = false;
            for v in data {
                if v.value_type != PDataValueType::Command || !v.is_last {
                    return Err(AssociationEnd::Protocol(
                        "a request arrived before the previous operation ended".into(),
                    ));
                }
                let cmd =
                    command::parse(&v.data).map_err(|e| AssociationEnd::Protocol(e.to_string()))?;
                if cmd.field != command::C_CANCEL_RQ {
                    return Err(AssociationEnd::Protocol(
                        "a request arrived before the previous operation ended".into(),
                    ));
                }
                // A cancel of another (finished) message has nothing to stop.
                canceled |= cmd.responded_to == Some(message_id);
            }
            if canceled {
                tracing::info!(message_id, "C-CANCEL received");
            }
            Ok(canceled)
        }
        Pdu::AbortRQ { .. } => Err(AssociationEnd::PeerAborted),
        other => Err(AssociationEnd::Protocol(format!(
            "unexpected {} during an operation",
            other.short_description()
        ))),
    }
}
