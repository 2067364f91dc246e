//! C-STORE of Part 10 files to a peer in one association: the contexts proposed from the files' SOP
//! classes and syntaxes, each file sent in the context accepted for it (streamed from disk, or re-encoded in
//! the other uncompressed little-endian syntax), and each file's outcome, also reported as it comes.

use std::path::{Path, PathBuf};

use super::client::{associate, response, send_command};
use super::contexts::{accepted_for, proposed_syntaxes, refusal};
use super::pdata::{send_buffer, send_data_set};
use super::{Caller, ScuError};
use crate::config::dicom::Peer;
use crate::dicom::{Part10, data_set_as, read_part10};
use crate::dimse::command;

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
