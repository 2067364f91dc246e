//! Presentation contexts of a C-STORE batch: the transfer syntaxes proposed for a stored file, the accepted
//! context a file can be sent in, and why one cannot be sent, in the peer's terms.

use dicom_ul::pdu::PresentationContextResultReason;

use super::client::Assoc;
use crate::config::dicom::Peer;
use crate::dicom::{EXPLICIT_LE, IMPLICIT_LE, le_interchangeable};

/// little-endian syntax when it is one of them (sent re-encoded if only that one is accepted).
pub(super) fn proposed_syntaxes(ts: &str) -> Vec<String> {
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
pub(super) fn accepted_for(assoc: &Assoc, sop_class: &str, ts: &str) -> Option<(u8, String)> {
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
pub(super) fn refusal(assoc: &Assoc, peer: &Peer, sop_class: &str, ts: &str) -> String {
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
