use super::*;

#[test]
fn a_job_request_takes_typed_specs_and_refuses_unknown_fields() {
    let ok = r#"{"input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
                 "algorithm": {"name": "fbp", "filter": "hann"},
                 "grid": {"nx": 64, "ny": 64, "dx_mm": 1, "dy_mm": 1}}"#;
    let r: JobRequest = serde_json::from_str(ok).unwrap();
    assert_eq!(r.outputs, [OutputKind::Volume]);
    assert!(matches!(r.grid, OutputGrid::Image(_)));
    let extra = ok.replace("\"grid\"", "\"colour\": 1, \"grid\"");
    assert!(serde_json::from_str::<JobRequest>(&extra).is_err());
    let bad_param = ok.replace("\"hann\"", "\"hann\", \"iterations\": 3");
    assert!(serde_json::from_str::<JobRequest>(&bad_param).is_err());
}

#[test]
fn timestamps_round_trip_through_rfc3339() {
    let t = 1_795_000_000_123_456;
    assert_eq!(parse_rfc3339(&rfc3339(t)), Some(t));
    assert!(rfc3339(t).ends_with('Z'));
}
