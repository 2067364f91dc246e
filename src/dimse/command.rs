//! DIMSE command sets (PS3.7 §9.3, §E): the few ctrecon reads and writes, always in implicit VR little
//! endian, with their Command Group Length.

use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::tags;
use dicom_object::InMemDicomObject;
use dicom_transfer_syntax_registry::entries::IMPLICIT_VR_LITTLE_ENDIAN;

pub const C_STORE_RQ: u16 = 0x0001;
pub const C_STORE_RSP: u16 = 0x8001;
pub const C_FIND_RQ: u16 = 0x0020;
pub const C_FIND_RSP: u16 = 0x8020;
pub const C_MOVE_RQ: u16 = 0x0021;
pub const C_MOVE_RSP: u16 = 0x8021;
pub const C_ECHO_RQ: u16 = 0x0030;
pub const C_ECHO_RSP: u16 = 0x8030;
pub const C_CANCEL_RQ: u16 = 0x0FFF;

/// Command Data Set Type (0000,0800) value meaning "no data set follows".
pub const NO_DATA_SET: u16 = 0x0101;

/// DIMSE status codes (PS3.7 Annex C, PS3.4 B.2.3).
pub mod status {
    pub const SUCCESS: u16 = 0x0000;
    /// Refused: SOP class not supported.
    pub const SOP_CLASS_NOT_SUPPORTED: u16 = 0x0122;
    /// Refused: not authorized.
    pub const NOT_AUTHORIZED: u16 = 0x0124;
    /// Refused: out of resources.
    pub const OUT_OF_RESOURCES: u16 = 0xA700;
    /// Error: data set does not match SOP class.
    pub const DATA_SET_MISMATCH: u16 = 0xA900;
    /// Error: cannot understand.
    pub const CANNOT_UNDERSTAND: u16 = 0xC000;
    /// Unrecognized operation.
    pub const UNRECOGNIZED_OPERATION: u16 = 0x0211;
    /// Pending: matches or sub-operations are continuing.
    pub const PENDING: u16 = 0xFF00;
    /// Cancel: matching or sub-operations were terminated by a C-CANCEL.
    pub const CANCEL: u16 = 0xFE00;
    /// C-MOVE refused: move destination unknown.
    pub const MOVE_DESTINATION_UNKNOWN: u16 = 0xA801;
    /// C-MOVE refused: out of resources, unable to perform sub-operations.
    pub const SUB_OPERATIONS_IMPOSSIBLE: u16 = 0xA702;
    /// Warning: sub-operations complete, one or more failures.
    pub const SUB_OPERATIONS_FAILED: u16 = 0xB000;
}

/// The largest command set ctrecon reads (bytes); real ones are a few hundred.
pub const MAX_COMMAND_BYTES: usize = 64 << 10;

/// The fields of a received command that ctrecon acts on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Command {
    pub field: u16,
    /// Message ID of a request, or Message ID Being Responded To of a response.
    pub message_id: u16,
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub has_data_set: bool,
    /// Status of a response.
    pub status: Option<u16>,
    pub error_comment: Option<String>,
    /// Move Destination (0000,0600) of a C-MOVE request.
    pub move_destination: Option<String>,
    /// Message ID Being Responded To (0000,0120) of a C-CANCEL request (or of a response).
    pub responded_to: Option<u16>,
    /// Sub-operation counts of a C-MOVE response (remaining absent from a final one).
    pub sub_operations: Option<SubOperations>,
}

/// Why a command set could not be read.
#[derive(Debug, thiserror::Error)]
#[error("malformed DIMSE command: {0}")]
pub struct CommandError(String);

fn text(obj: &InMemDicomObject, tag: Tag) -> Option<String> {
    let s = obj.get(tag)?.to_str().ok()?.into_owned();
    let s = s.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!s.is_empty()).then(|| s.to_string())
}

fn uint(obj: &InMemDicomObject, tag: Tag) -> Option<u16> {
    obj.get(tag)?.to_int::<u16>().ok()
}

/// Read a command set.
pub fn parse(bytes: &[u8]) -> Result<Command, CommandError> {
    if bytes.len() > MAX_COMMAND_BYTES {
        return Err(CommandError(format!("{} bytes", bytes.len())));
    }
    let ts = IMPLICIT_VR_LITTLE_ENDIAN.erased();
    let obj = InMemDicomObject::read_dataset_with_ts(bytes, &ts)
        .map_err(|e| CommandError(e.to_string()))?;
    let field = uint(&obj, tags::COMMAND_FIELD)
        .ok_or_else(|| CommandError("no Command Field (0000,0100)".into()))?;
    let message_id = uint(&obj, tags::MESSAGE_ID)
        .or_else(|| uint(&obj, tags::MESSAGE_ID_BEING_RESPONDED_TO))
        .ok_or_else(|| CommandError("no Message ID (0000,0110)".into()))?;
    let data_set_type = uint(&obj, tags::COMMAND_DATA_SET_TYPE).unwrap_or(NO_DATA_SET);
    Ok(Command {
        field,
        message_id,
        sop_class_uid: text(&obj, tags::AFFECTED_SOP_CLASS_UID).unwrap_or_default(),
        sop_instance_uid: text(&obj, tags::AFFECTED_SOP_INSTANCE_UID).unwrap_or_default(),
        has_data_set: data_set_type != NO_DATA_SET,
        status: uint(&obj, tags::STATUS),
        error_comment: text(&obj, tags::ERROR_COMMENT),
        move_destination: text(&obj, tags::MOVE_DESTINATION),
        responded_to: uint(&obj, tags::MESSAGE_ID_BEING_RESPONDED_TO),
        sub_operations: uint(&obj, tags::NUMBER_OF_COMPLETED_SUBOPERATIONS).map(|completed| {
            SubOperations {
                remaining: uint(&obj, tags::NUMBER_OF_REMAINING_SUBOPERATIONS).unwrap_or(0),
                completed,
                failed: uint(&obj, tags::NUMBER_OF_FAILED_SUBOPERATIONS).unwrap_or(0),
                warning: uint(&obj, tags::NUMBER_OF_WARNING_SUBOPERATIONS).unwrap_or(0),
            }
        }),
    })
}

fn encode(elements: Vec<DataElement<InMemDicomObject>>) -> Vec<u8> {
    let obj = InMemDicomObject::command_from_element_iter(elements);
    let mut out = Vec::with_capacity(256);
    let ts = IMPLICIT_VR_LITTLE_ENDIAN.erased();
    // Writing a handful of in-memory elements to a Vec cannot fail.
    if let Err(e) = obj.write_dataset_with_ts(&mut out, &ts) {
        tracing::error!(error = %e, "cannot encode a DIMSE command");
    }
    out
}

fn us(tag: Tag, v: u16) -> DataElement<InMemDicomObject> {
    DataElement::new(tag, VR::US, PrimitiveValue::from(v))
}

fn ui(tag: Tag, uid: &str) -> DataElement<InMemDicomObject> {
    // UIDs are padded to even length with NUL.
    let mut s = uid.to_string();
    if s.len() % 2 == 1 {
        s.push('\0');
    }
    DataElement::new(tag, VR::UI, PrimitiveValue::from(s))
}

fn ae(tag: Tag, title: &str) -> DataElement<InMemDicomObject> {
    let mut s = title.to_string();
    if s.len() % 2 == 1 {
        s.push(' ');
    }
    DataElement::new(tag, VR::AE, PrimitiveValue::from(s))
}

/// C-ECHO-RQ.
pub fn echo_request(message_id: u16) -> Vec<u8> {
    encode(vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, VERIFICATION),
        us(tags::COMMAND_FIELD, C_ECHO_RQ),
        us(tags::MESSAGE_ID, message_id),
        us(tags::COMMAND_DATA_SET_TYPE, NO_DATA_SET),
    ])
}

/// C-ECHO-RSP.
pub fn echo_response(message_id: u16, status: u16) -> Vec<u8> {
    encode(vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, VERIFICATION),
        us(tags::COMMAND_FIELD, C_ECHO_RSP),
        us(tags::MESSAGE_ID_BEING_RESPONDED_TO, message_id),
        us(tags::COMMAND_DATA_SET_TYPE, NO_DATA_SET),
        us(tags::STATUS, status),
    ])
}

/// C-STORE-RQ (medium priority), optionally on behalf of a C-MOVE originator.
pub fn store_request(
    message_id: u16,
    sop_class_uid: &str,
    sop_instance_uid: &str,
    move_originator: Option<(&str, u16)>,
) -> Vec<u8> {
    let mut e = vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_STORE_RQ),
        us(tags::MESSAGE_ID, message_id),
        us(tags::PRIORITY, 0),
        us(tags::COMMAND_DATA_SET_TYPE, 0x0000),
        ui(tags::AFFECTED_SOP_INSTANCE_UID, sop_instance_uid),
    ];
    if let Some((title, id)) = move_originator {
        e.push(ae(tags::MOVE_ORIGINATOR_APPLICATION_ENTITY_TITLE, title));
        e.push(us(tags::MOVE_ORIGINATOR_MESSAGE_ID, id));
    }
    encode(e)
}

/// C-STORE-RSP, with an Error Comment on failure.
pub fn store_response(
    message_id: u16,
    sop_class_uid: &str,
    sop_instance_uid: &str,
    status: u16,
    comment: Option<&str>,
) -> Vec<u8> {
    let mut e = vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_STORE_RSP),
        us(tags::MESSAGE_ID_BEING_RESPONDED_TO, message_id),
        us(tags::COMMAND_DATA_SET_TYPE, NO_DATA_SET),
        us(tags::STATUS, status),
        ui(tags::AFFECTED_SOP_INSTANCE_UID, sop_instance_uid),
    ];
    if let Some(c) = comment {
        // Error Comment is LO: at most 64 characters.
        let c: String = c.chars().filter(|c| !c.is_control()).take(64).collect();
        let c = if c.len() % 2 == 1 { c + " " } else { c };
        e.push(DataElement::new(
            tags::ERROR_COMMENT,
            VR::LO,
            PrimitiveValue::from(c),
        ));
    }
    encode(e)
}

/// C-FIND-RQ (medium priority); the identifier follows.
pub fn find_request(message_id: u16, sop_class_uid: &str) -> Vec<u8> {
    encode(vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_FIND_RQ),
        us(tags::MESSAGE_ID, message_id),
        us(tags::PRIORITY, 0),
        us(tags::COMMAND_DATA_SET_TYPE, 0x0000),
    ])
}

/// C-MOVE-RQ (medium priority) to `destination`; the identifier follows.
pub fn move_request(message_id: u16, sop_class_uid: &str, destination: &str) -> Vec<u8> {
    encode(vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_MOVE_RQ),
        us(tags::MESSAGE_ID, message_id),
        ae(tags::MOVE_DESTINATION, destination),
        us(tags::PRIORITY, 0),
        us(tags::COMMAND_DATA_SET_TYPE, 0x0000),
    ])
}

/// C-FIND-RSP: `pending` says whether an identifier follows (a match) or this is the final response.
pub fn find_response(
    message_id: u16,
    sop_class_uid: &str,
    status: u16,
    comment: Option<&str>,
) -> Vec<u8> {
    let with_data = status == status::PENDING || status == 0xFF01;
    let mut e = vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_FIND_RSP),
        us(tags::MESSAGE_ID_BEING_RESPONDED_TO, message_id),
        us(
            tags::COMMAND_DATA_SET_TYPE,
            if with_data { 0x0000 } else { NO_DATA_SET },
        ),
        us(tags::STATUS, status),
    ];
    e.extend(error_comment(comment));
    encode(e)
}

/// Sub-operation counts of a C-MOVE response.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SubOperations {
    pub remaining: u16,
    pub completed: u16,
    pub failed: u16,
    pub warning: u16,
}

/// C-MOVE-RSP; `with_identifier` when a data set (the Failed SOP Instance UID List) follows.
pub fn move_response(
    message_id: u16,
    sop_class_uid: &str,
    status: u16,
    counts: Option<SubOperations>,
    with_identifier: bool,
    comment: Option<&str>,
) -> Vec<u8> {
    let mut e = vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, sop_class_uid),
        us(tags::COMMAND_FIELD, C_MOVE_RSP),
        us(tags::MESSAGE_ID_BEING_RESPONDED_TO, message_id),
        us(
            tags::COMMAND_DATA_SET_TYPE,
            if with_identifier { 0x0000 } else { NO_DATA_SET },
        ),
        us(tags::STATUS, status),
    ];
    if let Some(c) = counts {
        if status == status::PENDING {
            e.push(us(tags::NUMBER_OF_REMAINING_SUBOPERATIONS, c.remaining));
        }
        e.push(us(tags::NUMBER_OF_COMPLETED_SUBOPERATIONS, c.completed));
        e.push(us(tags::NUMBER_OF_FAILED_SUBOPERATIONS, c.failed));
        e.push(us(tags::NUMBER_OF_WARNING_SUBOPERATIONS, c.warning));
    }
    e.extend(error_comment(comment));
    encode(e)
}

fn error_comment(comment: Option<&str>) -> Option<DataElement<InMemDicomObject>> {
    let c: String = comment?
        .chars()
        .filter(|c| !c.is_control())
        .take(64)
        .collect();
    let c = if c.len() % 2 == 1 { c + " " } else { c };
    Some(DataElement::new(
        tags::ERROR_COMMENT,
        VR::LO,
        PrimitiveValue::from(c),
    ))
}

/// Response to a request ctrecon does not perform.
pub fn unrecognized_response(request: &Command) -> Vec<u8> {
    encode(vec![
        ui(tags::AFFECTED_SOP_CLASS_UID, &request.sop_class_uid),
        us(tags::COMMAND_FIELD, request.field | 0x8000),
        us(tags::MESSAGE_ID_BEING_RESPONDED_TO, request.message_id),
        us(tags::COMMAND_DATA_SET_TYPE, NO_DATA_SET),
        us(tags::STATUS, status::UNRECOGNIZED_OPERATION),
    ])
}

/// The P-DATA PDU carrying one whole command set on presentation context `context_id`.
pub fn pdu(context_id: u8, bytes: Vec<u8>) -> dicom_ul::pdu::Pdu {
    use dicom_ul::pdu::{PDataValue, PDataValueType, Pdu};
    Pdu::PData {
        data: vec![PDataValue {
            presentation_context_id: context_id,
            value_type: PDataValueType::Command,
            is_last: true,
            data: bytes,
        }],
    }
}

/// The Verification SOP class (C-ECHO).
pub const VERIFICATION: &str = "1.2.840.10008.1.1";

/// Whether a response status means success (warnings 0001 and Bxxx count as stored).
pub fn is_stored(status: u16) -> bool {
    status == status::SUCCESS || status == 0x0001 || (status & 0xF000) == 0xB000
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_store_request_reads_back_with_its_uids_and_an_even_group_length() {
        let bytes = store_request(7, "1.2.840.10008.5.1.4.1.1.2", "1.2.3.45", None);
        // Command Group Length (0000,0000) UL counts the bytes after it.
        assert_eq!(&bytes[..8], &[0, 0, 0, 0, 4, 0, 0, 0]);
        let len = u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize;
        assert_eq!(len, bytes.len() - 12);
        let c = parse(&bytes).unwrap();
        assert_eq!(c.field, C_STORE_RQ);
        assert_eq!(c.message_id, 7);
        assert_eq!(c.sop_class_uid, "1.2.840.10008.5.1.4.1.1.2");
        assert_eq!(c.sop_instance_uid, "1.2.3.45");
        assert!(c.has_data_set);
    }

    #[test]
    fn a_failure_response_carries_status_and_a_bounded_comment() {
        let long = "x".repeat(200);
        let c = parse(&store_response(
            3,
            "1.2",
            "1.2.3",
            status::CANNOT_UNDERSTAND,
            Some(&long),
        ))
        .unwrap();
        assert_eq!(c.field, C_STORE_RSP);
        assert_eq!(c.status, Some(status::CANNOT_UNDERSTAND));
        assert_eq!(c.error_comment.as_deref().map(str::len), Some(64));
        assert!(!c.has_data_set);
        assert!(!is_stored(status::CANNOT_UNDERSTAND));
        assert!(is_stored(0xB007));
    }

    #[test]
    fn garbage_and_oversized_commands_are_errors() {
        assert!(parse(&[1, 2, 3]).is_err());
        assert!(parse(&vec![0u8; MAX_COMMAND_BYTES + 1]).is_err());
    }
}
