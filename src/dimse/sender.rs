//! The application's [`DicomCaller`] port over [`scu`](super::scu): C-ECHO and C-STORE to configured
//! peers, with ctrecon's AE title, PDU size and DIMSE timeout.

use std::path::PathBuf;

use super::command;
use super::scu::{self, Caller};
use crate::app::deliveries::{CallError, CallFuture, DicomCaller, SentInstance};
use crate::config::dicom::{NodeSettings, Peer};

/// ctrecon calling peers by DIMSE.
#[derive(Debug, Clone)]
pub struct ScuCaller {
    caller: Caller,
}

impl ScuCaller {
    pub fn new(settings: &NodeSettings) -> Self {
        Self {
            caller: Caller {
                ae_title: settings.ae_title.clone(),
                timeout: settings.dimse_timeout(),
                max_pdu_length: settings.max_pdu_length,
            },
        }
    }
}

impl DicomCaller for ScuCaller {
    fn echo<'a>(&'a self, peer: &'a Peer) -> CallFuture<'a, Result<u16, CallError>> {
        Box::pin(async move {
            scu::echo(&self.caller, peer)
                .await
                .map_err(|e| CallError(e.to_string()))
        })
    }

    fn store<'a>(
        &'a self,
        peer: &'a Peer,
        files: Vec<PathBuf>,
    ) -> CallFuture<'a, Result<Vec<SentInstance>, CallError>> {
        Box::pin(async move {
            let outcomes = scu::store(&self.caller, peer, &files)
                .await
                .map_err(|e| CallError(e.to_string()))?;
            Ok(outcomes
                .into_iter()
                .map(|o| SentInstance {
                    stored: o.status.is_some_and(command::is_stored),
                    status: o.status,
                    detail: o.detail,
                })
                .collect())
        })
    }
}
