//! C-FIND and C-MOVE as provider (Study Root and Patient Root Query/Retrieve) over the application's
//! instance index: a request's identifier becomes an [`app::query::Query`]; C-FIND answers one pending
//! response per match with the requested keys filled (keys the index does not hold are returned empty),
//! C-MOVE sends the matching instances to a destination from the peer list over a sub-association and
//! reports its progress.

use dicom_ul::association::AsyncServerAssociation;
use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu, PresentationContextNegotiated};
use tokio::net::TcpStream;

use super::association::{AssociationEnd, Grant};
use super::command::{self, Command, SubOperations, status};
use super::scu::{self, Caller, StoreOptions};
use crate::app::App;
use crate::app::matching::{Attr, Level};
use crate::app::query::{Found, Query};
use crate::config::dicom::Peer;
use crate::dicom::{IdentifierElement, read_identifier, write_identifier};
use crate::recon::control::Cancel;

pub const STUDY_ROOT_FIND: &str = "1.2.840.10008.5.1.4.1.2.2.1";
pub const STUDY_ROOT_MOVE: &str = "1.2.840.10008.5.1.4.1.2.2.2";
pub const PATIENT_ROOT_FIND: &str = "1.2.840.10008.5.1.4.1.2.1.1";
pub const PATIENT_ROOT_MOVE: &str = "1.2.840.10008.5.1.4.1.2.1.2";

/// The Query/Retrieve SOP classes the node provides.
pub const QUERY_RETRIEVE_SOP_CLASSES: &[&str] = &[
    STUDY_ROOT_FIND,
    STUDY_ROOT_MOVE,
    PATIENT_ROOT_FIND,
    PATIENT_ROOT_MOVE,
];

const QUERY_RETRIEVE_LEVEL: u32 = 0x0008_0052;
const SPECIFIC_CHARACTER_SET: u32 = 0x0008_0005;
const RETRIEVE_AE_TITLE: u32 = 0x0008_0054;
const FAILED_SOP_INSTANCE_UID_LIST: u32 = 0x0008_0058;

/// What C-FIND and C-MOVE need: the application (its index), ctrecon as the caller of sub-associations
/// (its AE title is also the Retrieve AE Title answered), and the peers it may send to.
#[derive(Clone)]
pub struct Retrieval {
    pub app: App,
    pub caller: Caller,
    pub peers: Vec<Peer>,
}

/// How often a C-MOVE in progress looks for a C-CANCEL while no sub-operation ends.
const CANCEL_POLL: std::time::Duration = std::time::Duration::from_millis(100);

/// A refusal: a final status and its comment.
type Refusal = (u16, String);

async fn send_command(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    context_id: u8,
    bytes: Vec<u8>,
) -> Result<(), AssociationEnd> {
    assoc
        .send(&command::pdu(context_id, bytes))
        .await
        .map_err(|e| AssociationEnd::Network(e.to_string()))
}

/// Send a data set in P-DATA fragments no larger than the caller admits.
async fn send_data(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    context_id: u8,
    bytes: &[u8],
) -> Result<(), AssociationEnd> {
    let max = match assoc.requestor_max_pdu_length() {
        0 => 16 << 10,
        n => n.min(1 << 20),
    };
    let chunk = (max as usize).saturating_sub(6).max(1024);
    let parts: Vec<&[u8]> = if bytes.is_empty() {
        vec![bytes]
    } else {
        bytes.chunks(chunk).collect()
    };
    let n = parts.len();
    for (i, part) in parts.into_iter().enumerate() {
        let pdu = Pdu::PData {
            data: vec![PDataValue {
                presentation_context_id: context_id,
                value_type: PDataValueType::Data,
                is_last: i + 1 == n,
                data: part.to_vec(),
            }],
        };
        assoc
            .send(&pdu)
            .await
            .map_err(|e| AssociationEnd::Network(e.to_string()))?;
    }
    Ok(())
}

/// The request's level and keys, or why it cannot be run.
fn parse_request(
    cmd: &Command,
    context: &PresentationContextNegotiated,
    identifier: &[u8],
) -> Result<(Vec<IdentifierElement>, Query), Refusal> {
    if context.abstract_syntax != cmd.sop_class_uid {
        return Err((
            status::SOP_CLASS_NOT_SUPPORTED,
            "SOP class differs from the presentation context".into(),
        ));
    }
    let elements = read_identifier(identifier, &context.transfer_syntax)
        .map_err(|e| (status::CANNOT_UNDERSTAND, e.to_string()))?;
    let level = elements
        .iter()
        .find(|e| e.tag == QUERY_RETRIEVE_LEVEL)
        .and_then(|e| Level::parse(&e.value))
        .ok_or_else(|| {
            (
                status::DATA_SET_MISMATCH,
                "no valid Query/Retrieve Level (0008,0052)".to_string(),
            )
        })?;
    let study_root = matches!(
        cmd.sop_class_uid.as_str(),
        STUDY_ROOT_FIND | STUDY_ROOT_MOVE
    );
    if study_root && level == Level::Patient {
        return Err((
            status::DATA_SET_MISMATCH,
            "the Study Root model has no PATIENT level".into(),
        ));
    }
    let keys: Vec<(u32, String)> = elements
        .iter()
        .filter(|e| e.tag != QUERY_RETRIEVE_LEVEL)
        .map(|e| (e.tag, e.value.clone()))
        .collect();
    let query = Query::new(level, &keys).map_err(|e| (status::CANNOT_UNDERSTAND, e.to_string()))?;
    Ok((elements, query))
}

/// The response identifier of one match: every requested key (filled when the index holds it at or above
/// the level, else empty), the unique keys of the level and those above it, and the character set.
fn response_identifier(
    requested: &[IdentifierElement],
    level: Level,
    study_root: bool,
    found: &Found,
    ae_title: &str,
) -> Vec<IdentifierElement> {
    let mut out: Vec<IdentifierElement> = Vec::with_capacity(requested.len() + 4);
    let fill = |tag: u32| -> String {
        match tag {
            QUERY_RETRIEVE_LEVEL => level.as_str().into(),
            RETRIEVE_AE_TITLE => ae_title.into(),
            _ => Attr::from_tag(tag)
                .filter(|a| a.level() <= level)
                .and_then(|a| found.value(a))
                .unwrap_or_default()
                .to_string(),
        }
    };
    for e in requested {
        if e.tag == SPECIFIC_CHARACTER_SET {
            continue;
        }
        out.push(IdentifierElement {
            tag: e.tag,
            vr: e.vr.clone(),
            value: fill(e.tag),
        });
    }
    let first = if study_root {
        Level::Study
    } else {
        Level::Patient
    };
    for l in [Level::Patient, Level::Study, Level::Series, Level::Image] {
        let unique = Attr::unique_key(l);
        if l >= first && l <= level && !out.iter().any(|e| e.tag == unique.tag()) {
            out.push(IdentifierElement {
                tag: unique.tag(),
                vr: if l == Level::Patient { "LO" } else { "UI" }.into(),
                value: fill(unique.tag()),
            });
        }
    }
    if !out.iter().any(|e| e.tag == QUERY_RETRIEVE_LEVEL) {
        out.push(IdentifierElement {
            tag: QUERY_RETRIEVE_LEVEL,
            vr: "CS".into(),
            value: level.as_str().into(),
        });
    }
    if out.iter().any(|e| !e.value.is_ascii()) {
        out.push(IdentifierElement {
            tag: SPECIFIC_CHARACTER_SET,
            vr: "CS".into(),
            value: "ISO_IR 192".into(),
        });
    }
    out.sort_by_key(|e| e.tag);
    out
}

/// Serve one C-FIND request whose identifier arrived whole.
pub async fn find(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    grant: &Grant,
    retrieval: &Retrieval,
    cmd: &Command,
    context: &PresentationContextNegotiated,
    identifier: &[u8],
) -> Result<(), AssociationEnd> {
    let final_status = |code: u16, comment: Option<&str>| {
        command::find_response(cmd.message_id, &cmd.sop_class_uid, code, comment)
    };
    let answer = if !grant.may_query {
        Err((
            status::NOT_AUTHORIZED,
            format!("{} may not query here", grant.calling_ae),
        ))
    } else {
        match parse_request(cmd, context, identifier) {
            Ok((elements, query)) => match retrieval.app.find_instances(&query).await {
                Ok(found) => Ok((elements, query, found)),
                Err(e) => {
                    tracing::error!(error = %e, "C-FIND failed");
                    Err((status::OUT_OF_RESOURCES, "the index cannot be read".into()))
                }
            },
            Err(r) => Err(r),
        }
    };
    let (elements, query, found) = match answer {
        Ok(a) => a,
        Err((code, comment)) => {
            tracing::warn!(status = format!("{code:04X}"), reason = %comment, "C-FIND refused");
            return send_command(assoc, context.id, final_status(code, Some(&comment))).await;
        }
    };
    let study_root = cmd.sop_class_uid == STUDY_ROOT_FIND;
    let ae_title = &retrieval.caller.ae_title;
    for (sent, f) in found.iter().enumerate() {
        let ident = response_identifier(&elements, query.level, study_root, f, ae_title);
        let bytes = match write_identifier(&ident, &context.transfer_syntax) {
            Ok(b) => b,
            Err(e) => {
                tracing::error!(error = %e, "cannot encode a C-FIND response");
                let comment = "cannot encode a response";
                return send_command(
                    assoc,
                    context.id,
                    final_status(status::CANNOT_UNDERSTAND, Some(comment)),
                )
                .await;
            }
        };
        if super::cancel::requested(assoc, cmd.message_id).await? {
            tracing::info!(level = query.level.as_str(), sent, "C-FIND canceled");
            return send_command(assoc, context.id, final_status(status::CANCEL, None)).await;
        }
        send_command(
            assoc,
            context.id,
            command::find_response(cmd.message_id, &cmd.sop_class_uid, status::PENDING, None),
        )
        .await?;
        send_data(assoc, context.id, &bytes).await?;
    }
    tracing::info!(
        level = query.level.as_str(),
        matches = found.len(),
        "C-FIND answered"
    );
    send_command(assoc, context.id, final_status(status::SUCCESS, None)).await
}

fn counts(total: usize, completed: usize, failed: usize, warning: usize) -> SubOperations {
    let c = |n: usize| n.min(u16::MAX as usize) as u16;
    SubOperations {
        remaining: c(total.saturating_sub(completed + failed + warning)),
        completed: c(completed),
        failed: c(failed),
        warning: c(warning),
    }
}

/// Serve one C-MOVE request whose identifier arrived whole.
pub async fn move_instances(
    assoc: &mut AsyncServerAssociation<TcpStream>,
    grant: &Grant,
    retrieval: &Retrieval,
    cmd: &Command,
    context: &PresentationContextNegotiated,
    identifier: &[u8],
) -> Result<(), AssociationEnd> {
    let respond = |code: u16, c: Option<SubOperations>, data: bool, comment: Option<&str>| {
        command::move_response(cmd.message_id, &cmd.sop_class_uid, code, c, data, comment)
    };
    let plan: Result<(Peer, Vec<std::path::PathBuf>, Vec<String>), Refusal> = async {
        if !grant.may_retrieve {
            return Err((
                status::NOT_AUTHORIZED,
                format!("{} may not retrieve here", grant.calling_ae),
            ));
        }
        let (_, query) = parse_request(cmd, context, identifier)?;
        let dest_ae = cmd.move_destination.clone().unwrap_or_default();
        let dest = retrieval
            .peers
            .iter()
            .find(|p| p.ae_title == dest_ae)
            .cloned()
            .ok_or_else(|| {
                (
                    status::MOVE_DESTINATION_UNKNOWN,
                    format!("move destination {dest_ae:?} is not a known peer"),
                )
            })?;
        let found = retrieval.app.find_instances(&query).await.map_err(|e| {
            tracing::error!(error = %e, "C-MOVE query failed");
            (
                status::OUT_OF_RESOURCES,
                "the index cannot be read".to_string(),
            )
        })?;
        let mut files = Vec::new();
        let mut uids = Vec::new();
        let mut seen = std::collections::HashSet::new();
        for f in &found {
            for i in &f.instances {
                if seen.insert(i.instance.sop_instance_uid.clone()) {
                    files.push(retrieval.app.instance_file(i));
                    uids.push(i.instance.sop_instance_uid.clone());
                }
            }
        }
        Ok((dest, files, uids))
    }
    .await;
    let (dest, files, uids) = match plan {
        Ok(p) => p,
        Err((code, comment)) => {
            tracing::warn!(status = format!("{code:04X}"), reason = %comment, "C-MOVE refused");
            return send_command(
                assoc,
                context.id,
                respond(code, None, false, Some(&comment)),
            )
            .await;
        }
    };
    let total = files.len();
    tracing::info!(destination = %dest.ae_title, instances = total, "C-MOVE started");
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let stop = Cancel::new();
    let options = StoreOptions {
        move_originator: Some((grant.calling_ae.clone(), cmd.message_id)),
        progress: Some(tx),
        cancel: Some(stop.clone()),
    };
    let caller = retrieval.caller.clone();
    let peer = dest.clone();
    let sending = tokio::spawn(async move {
        if files.is_empty() {
            return Ok(Vec::new());
        }
        scu::store_with(&caller, &peer, &files, &options).await
    });
    let (mut completed, mut failed, mut warning) = (0usize, 0usize, 0usize);
    let mut failed_uids: Vec<String> = Vec::new();
    loop {
        let next = tokio::select! {
            o = rx.recv() => Some(o),
            _ = tokio::time::sleep(CANCEL_POLL) => None,
        };
        if !stop.is_canceled() && super::cancel::requested(assoc, cmd.message_id).await? {
            // The sub-association stops before its next instance; the outcomes so far still come.
            stop.cancel();
        }
        let o = match next {
            None => continue,
            Some(None) => break,
            Some(Some(o)) => o,
        };
        match o.status {
            Some(s) if s == status::SUCCESS => completed += 1,
            Some(s) if command::is_stored(s) => warning += 1,
            _ => {
                failed += 1;
                failed_uids.push(o.sop_instance_uid.clone());
            }
        }
        if completed + failed + warning < total && !stop.is_canceled() {
            send_command(
                assoc,
                context.id,
                respond(
                    status::PENDING,
                    Some(counts(total, completed, failed, warning)),
                    false,
                    None,
                ),
            )
            .await?;
        }
    }
    let outcome = sending
        .await
        .map_err(|e| AssociationEnd::Protocol(e.to_string()))?;
    if let Err(e) = outcome {
        // The sub-association failed: whatever was not answered counts as failed.
        tracing::warn!(error = %e, "C-MOVE sub-association failed");
        let answered = completed + failed + warning;
        failed += total - answered;
        let done: std::collections::HashSet<&String> = failed_uids.iter().collect();
        let rest: Vec<String> = uids
            .iter()
            .skip(answered)
            .filter(|u| !done.contains(u))
            .cloned()
            .collect();
        failed_uids.extend(rest);
        if completed + warning == 0 {
            let c = counts(total, completed, failed, warning);
            return send_command(
                assoc,
                context.id,
                respond(
                    status::SUB_OPERATIONS_IMPOSSIBLE,
                    Some(c),
                    false,
                    Some(&e.to_string()),
                ),
            )
            .await;
        }
    }
    let c = counts(total, completed, failed, warning);
    if stop.is_canceled() && completed + failed + warning < total {
        tracing::info!(completed, failed, warning, "C-MOVE canceled");
        return send_command(
            assoc,
            context.id,
            respond(status::CANCEL, Some(c), false, None),
        )
        .await;
    }
    tracing::info!(completed, failed, warning, "C-MOVE finished");
    if failed == 0 && warning == 0 {
        return send_command(
            assoc,
            context.id,
            respond(status::SUCCESS, Some(c), false, None),
        )
        .await;
    }
    let list = IdentifierElement {
        tag: FAILED_SOP_INSTANCE_UID_LIST,
        vr: "UI".into(),
        value: failed_uids.join("\\"),
    };
    let bytes = write_identifier(&[list], &context.transfer_syntax).unwrap_or_default();
    let with_data = failed > 0 && !bytes.is_empty();
    send_command(
        assoc,
        context.id,
        respond(status::SUB_OPERATIONS_FAILED, Some(c), with_data, None),
    )
    .await?;
    if with_data {
        send_data(assoc, context.id, &bytes).await?;
    }
    Ok(())
}
