use super::*;

fn rule(v: serde_json::Value) -> RuleSpec {
    serde_json::from_value(v).unwrap()
}

#[test]
fn wildcards_match_like_dicom_and_ignore_case() {
    assert!(wildcard("*spine*", "CT L-SPINE 3mm"));
    assert!(wildcard("CT", "ct "));
    assert!(wildcard("C?", "CT"));
    assert!(!wildcard("C?", "CTA"));
    assert!(wildcard("*", ""));
    assert!(wildcard("a*b*c", "axxbyyc"));
    assert!(!wildcard("a*b*c", "axxbyy"));
    assert!(!wildcard("spine", "spine2"));
}

#[test]
fn a_series_matches_only_when_every_condition_holds() {
    let r = rule(
        json!({"name": "spine", "protocol": "spine", "destinations": [],
        "match": {"modality": "CT", "series_description": "*spine*", "image_type": ["original"],
                  "slice_thickness_mm": {"min": 0.5, "max": 3}, "instances": {"min": 10},
                  "calling_ae": ["SCANNER"]}}),
    );
    let s = SeriesFacts {
        modality: Some("CT".into()),
        body_part: Some("SPINE".into()),
        series_description: Some("L-Spine bone".into()),
        image_type: vec!["ORIGINAL".into(), "PRIMARY".into(), "AXIAL".into()],
        slice_thickness_mm: Some(1.25),
        instances: 120,
        calling_ae: Some("SCANNER".into()),
    };
    assert!(r.matches(&s));
    for other in [
        SeriesFacts {
            modality: Some("MR".into()),
            ..s.clone()
        },
        SeriesFacts {
            slice_thickness_mm: Some(5.0),
            ..s.clone()
        },
        SeriesFacts {
            slice_thickness_mm: None,
            ..s.clone()
        },
        SeriesFacts {
            instances: 9,
            ..s.clone()
        },
        SeriesFacts {
            calling_ae: None,
            ..s.clone()
        },
        SeriesFacts {
            image_type: vec!["DERIVED".into()],
            ..s.clone()
        },
        SeriesFacts {
            series_description: Some("chest".into()),
            ..s.clone()
        },
    ] {
        assert!(!r.matches(&other), "{other:?}");
    }
}

#[test]
fn validation_names_bad_patterns_unknown_peers_and_bad_templates() {
    let peer = |ae: &str| ae == "PACS";
    let ok = json!({"name": "r1", "protocol": "bone_stl", "destinations": ["PACS"]});
    assert_eq!(rule(ok.clone()).validate(peer), Ok(()));
    let mut unknown = ok.clone();
    unknown["destinations"] = json!(["NOPE"]);
    assert!(matches!(
        rule(unknown).validate(peer),
        Err(RuleProblem::UnknownPeer(_))
    ));
    let mut pattern = ok.clone();
    pattern["match"] = json!({"series_description": "[abc]"});
    assert!(matches!(
        rule(pattern).validate(peer),
        Err(RuleProblem::BadPattern(_))
    ));
    let mut name = ok.clone();
    name["name"] = json!("Has Space");
    assert!(matches!(
        rule(name).validate(peer),
        Err(RuleProblem::Invalid(_))
    ));
    let mut both = ok.clone();
    both["job"] = json!({"products": []});
    assert!(matches!(
        rule(both).validate(peer),
        Err(RuleProblem::Invalid(_))
    ));
    let mut range = ok;
    range["match"] = json!({"instances": {"min": 5, "max": 2}});
    assert!(matches!(
        rule(range).validate(peer),
        Err(RuleProblem::Invalid(_))
    ));
    let unknown_field = json!({"name": "r", "protocol": "spine", "colour": 1});
    assert!(serde_json::from_value::<RuleSpec>(unknown_field).is_err());
}

#[test]
fn the_shipped_protocols_are_valid_volume_job_templates() {
    let spine = Protocol::Spine.template();
    assert_eq!(spine.products.len(), 3);
    assert!(
        matches!(&spine.products[0], ProductSpec::Mpr(m) if m.spacing_mm == Some(3.0)
        && m.slab.as_ref().is_some_and(|s| s.thickness_mm == 3.0))
    );
    let bone = Protocol::BoneStl.template();
    assert_eq!(bone.products.len(), 2);
    assert!(matches!(&bone.products[0], ProductSpec::Mesh(m) if m.iso == 300.0));
    assert!(matches!(&bone.products[1], ProductSpec::Rotating(r) if r.frames == 36));
    let lung = Protocol::Lung.template();
    assert_eq!(lung.products.len(), 2);
    assert!(matches!(&lung.products[1], ProductSpec::Mpr(m) if m.spacing_mm == Some(10.0)));
    for p in Protocol::ALL {
        // The name is the one serde reads, and every body parses into a non-empty template.
        assert_eq!(serde_json::to_value(p).ok(), Some(json!(p.name())));
        assert!(!p.template().products.is_empty(), "{p:?}");
    }
}
