use super::*;

/// Orthanc 1.10 with its DICOMweb plugin 1.7, answering a STOW-RS of one CT instance (200), whitespace
/// removed.
const ORTHANC_STORED: &str = r#"{"00080005":{"Value":["ISO_IR100"],"vr":"CS"},"00081190":{"Value":["http://127.0.0.1:18942/dicom-web/studies/1.3.6.1.4.1.14519.5.2.1.6279.6001.298806137288633453246975630178"],"vr":"UR"},"00081198":{"vr":"SQ"},"00081199":{"Value":[{"00081150":{"Value":["1.2.840.10008.5.1.4.1.1.2"],"vr":"UI"},"00081155":{"Value":["1.3.6.1.4.1.14519.5.2.1.6279.6001.262721256650280657946440242654"],"vr":"UI"},"00081190":{"Value":["http://127.0.0.1:18942/dicom-web/studies/1.3.6.1.4.1.14519.5.2.1.6279.6001.298806137288633453246975630178/series/1.3.6.1.4.1.14519.5.2.1.6279.6001.179049373636438705059720603192/instances/1.3.6.1.4.1.14519.5.2.1.6279.6001.262721256650280657946440242654"],"vr":"UR"}}],"vr":"SQ"}}"#;

/// The same Orthanc answering the instance posted to `/studies/1.2.3.4`, another study (409).
const ORTHANC_OTHER_STUDY: &str = r#"{"00080005":{"Value":["ISO_IR100"],"vr":"CS"},"00081198":{"Value":[{"00081150":{"Value":["1.2.840.10008.5.1.4.1.1.2"],"vr":"UI"},"00081155":{"Value":["1.3.6.1.4.1.14519.5.2.1.6279.6001.262721256650280657946440242654"],"vr":"UI"},"00081197":{"Value":[272],"vr":"US"}}],"vr":"SQ"},"00081199":{"vr":"SQ"}}"#;

const UID: &str = "1.3.6.1.4.1.14519.5.2.1.6279.6001.262721256650280657946440242654";

#[test]
fn an_instance_in_the_referenced_sop_sequence_was_stored() {
    let acks = read_stow_response(ORTHANC_STORED.as_bytes()).unwrap();
    assert_eq!(acks.len(), 1);
    assert_eq!(acks[UID], Acknowledged::Stored(0));
}

#[test]
fn an_instance_in_the_failed_sop_sequence_failed_with_its_reason() {
    let acks = read_stow_response(ORTHANC_OTHER_STUDY.as_bytes()).unwrap();
    assert_eq!(acks.len(), 1);
    // 272 = 0x0110, processing failure.
    assert_eq!(acks[UID], Acknowledged::Failed(0x0110));
}

#[test]
fn warnings_count_as_stored_and_answers_without_either_sequence_are_not_stow_responses() {
    let body = r#"[{"00081199":{"vr":"SQ","Value":[{"00081155":{"vr":"UI","Value":["1.2"]},"00081196":{"vr":"US","Value":[45056]}}]},
                  "00081198":{"vr":"SQ","Value":[{"00081155":{"vr":"UI","Value":["1.3"]}}]}}]"#;
    let acks = read_stow_response(body.as_bytes()).unwrap();
    assert_eq!(acks["1.2"], Acknowledged::Stored(0xB000));
    assert_eq!(acks["1.3"], Acknowledged::Failed(0xC000));
    for not in [&b"{}"[..], b"<html>401</html>", b"", br#"{"00080005":{}}"#] {
        assert_eq!(read_stow_response(not), None);
    }
}

#[test]
fn the_declared_body_length_is_the_length_of_the_framed_parts() {
    let f = Framing::new();
    let parts: [&[u8]; 3] = [b"DICM-one", b"", &[7u8; 1000]];
    let mut body = Vec::new();
    for p in parts {
        body.extend_from_slice(f.head(p.len() as u64).as_bytes());
        body.extend_from_slice(p);
        body.extend_from_slice(Framing::TAIL.as_bytes());
    }
    body.extend_from_slice(f.close().as_bytes());
    let sizes: Vec<u64> = parts.iter().map(|p| p.len() as u64).collect();
    assert_eq!(f.body_length(&sizes), body.len() as u64);
    assert!(f.content_type().contains("type=\"application/dicom\""));
    assert!(f.content_type().ends_with(&f.boundary));
    assert_ne!(Framing::new(), f, "each body gets a boundary of its own");
}
