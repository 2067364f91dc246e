//! Data sets as P-DATA fragments no larger than the peer admits: from memory, or streamed from a file's
//! data set offset in PDU-sized reads (never whole in memory).

use std::path::Path;

use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu};
use tokio::io::{AsyncReadExt, AsyncSeekExt};

use super::client::Assoc;
use super::{Caller, ScuError};
use crate::config::dicom::Peer;

/// Send an in-memory data set as P-DATA fragments no larger than the peer admits.
pub(super) async fn send_buffer(
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

/// Send the data set at `offset` of `file` as P-DATA fragments no larger than the peer admits.
pub(super) async fn send_data_set(
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
