//! ctrecon as a service class user: C-ECHO to test a peer, C-STORE of Part 10 files to a peer, each file's
//! data set sent as it is stored (streamed from disk in PDU-sized fragments, never whole in memory), or, for
//! a peer that accepted its SOP class only in the other uncompressed little-endian syntax, re-encoded (one
//! instance in memory). A file whose SOP class the peer rejected is reported as not sent, with the reason.
//!
//! This file holds the caller, its errors and C-ECHO; `client` the association and its command exchange,
//! `store` the C-STORE batch, `contexts` the presentation contexts it proposes and picks, `pdata` the data
//! set fragments.

mod client;
mod contexts;
mod pdata;
mod store;

use std::time::Duration;

use super::command::{self, VERIFICATION};
use crate::config::dicom::Peer;

pub(in crate::dimse) use client::{Assoc, associate, send_command, timed};
pub use store::{StoreOptions, StoreOutcome, store, store_with};

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

/// C-ECHO: the peer's status (0 = success).
pub async fn echo(caller: &Caller, peer: &Peer) -> Result<u16, ScuError> {
    let contexts = vec![(
        VERIFICATION.to_string(),
        vec!["1.2.840.10008.1.2".to_string()],
    )];
    let mut assoc = associate(caller, peer, &contexts).await?;
    let context = client::accepted(&assoc, VERIFICATION, "1.2.840.10008.1.2").ok_or_else(|| {
        ScuError::Associate {
            peer: peer.ae_title.clone(),
            reason: "verification not accepted".into(),
        }
    })?;
    send_command(&mut assoc, peer, context, command::echo_request(1)).await?;
    let rsp = client::response(&mut assoc, caller, peer).await?;
    let _ = assoc.release().await;
    Ok(rsp.status.unwrap_or(command::status::CANNOT_UNDERSTAND))
}
