use super::*;

fn key(attr: Attr, v: &str) -> Key {
    Key::parse(attr, v).unwrap()
}

#[test]
fn an_empty_value_or_a_lone_star_matches_everything_even_an_absent_value() {
    for v in ["", "  ", "*"] {
        let k = key(Attr::PatientName, v);
        assert_eq!(k.matcher, Matcher::Universal);
        assert!(k.matches(None));
        assert!(k.matches(Some("DOE^JOHN")));
    }
}

#[test]
fn single_values_match_exactly_and_person_names_ignore_case() {
    let k = key(Attr::PatientId, "ABC123 ");
    assert!(k.matches(Some("ABC123")));
    assert!(!k.matches(Some("abc123")), "LO is case-sensitive");
    assert!(!k.matches(Some("ABC1234")));
    assert!(!k.matches(None), "an absent value matches only universally");
    let pn = key(Attr::PatientName, "Doe^John");
    assert!(pn.matches(Some("DOE^JOHN")));
    assert!(!pn.matches(Some("DOE^JANE")));
}

#[test]
fn wildcards_follow_the_ps3_4_examples() {
    // PS3.4 C.2.2.2.4: "*" any run, "?" exactly one character.
    let k = key(Attr::PatientName, "Smith*");
    assert!(matches!(k.matcher, Matcher::Wildcard(_)));
    assert!(k.matches(Some("SMITH^JOHN")));
    assert!(k.matches(Some("Smith")));
    assert!(!k.matches(Some("JONES^SMITH")));
    let d = key(Attr::StudyDescription, "CT?HEAD*");
    assert!(d.matches(Some("CT HEAD W/O")));
    assert!(d.matches(Some("CT_HEAD")));
    assert!(!d.matches(Some("CT  HEAD")));
    assert!(
        !d.matches(Some("ct head")),
        "LO wildcards are case-sensitive"
    );
    let mid = key(Attr::SeriesDescription, "*bone*mip");
    assert!(mid.matches(Some("sag bone 3mm mip")));
    assert!(!mid.matches(Some("sag bone 3mm mip x")));
    assert!(key(Attr::Modality, "C?").matches(Some("CT")));
    assert!(!key(Attr::Modality, "C?").matches(Some("C")));
}

#[test]
fn uid_lists_match_any_member_and_uids_take_no_wildcards() {
    let k = key(Attr::SeriesInstanceUid, "1.2.3\\1.2.4\\1.2.5");
    assert_eq!(
        k.matcher,
        Matcher::UidList(vec!["1.2.3".into(), "1.2.4".into(), "1.2.5".into()])
    );
    assert!(k.matches(Some("1.2.4")));
    assert!(!k.matches(Some("1.2.6")));
    let one = key(Attr::StudyInstanceUid, "1.2.3\0");
    assert!(one.matches(Some("1.2.3")));
    assert!(!one.matches(Some("1.2.30")));
    let star = key(Attr::SopInstanceUid, "1.2.*");
    assert!(
        !star.matches(Some("1.2.3")),
        "UI values are never wildcards"
    );
}

#[test]
fn date_ranges_are_inclusive_and_may_be_open() {
    let from = key(Attr::StudyDate, "20200101-");
    assert!(from.matches(Some("20200101")));
    assert!(from.matches(Some("20231231")));
    assert!(!from.matches(Some("20191231")));
    let until = key(Attr::StudyDate, "-20201231");
    assert!(until.matches(Some("19990101")));
    assert!(until.matches(Some("20201231")));
    assert!(!until.matches(Some("20210101")));
    let between = key(Attr::StudyDate, "20200301-20200331");
    assert!(between.matches(Some("20200315")));
    assert!(!between.matches(Some("20200401")));
    assert!(!between.matches(None));
    // The legacy form with dots is read too.
    assert!(between.matches(Some("2020.03.01")));
    let single = key(Attr::StudyDate, "20200315");
    assert!(single.matches(Some("20200315")));
    assert!(!single.matches(Some("20200316")));
}

#[test]
fn time_ranges_compare_times_not_strings() {
    let k = key(Attr::StudyTime, "0900-1000");
    assert!(k.matches(Some("093000")));
    assert!(k.matches(Some("090000.000")));
    assert!(
        k.matches(Some("100000")),
        "10:00:00 is within an upper bound of 10:00"
    );
    assert!(k.matches(Some("1000")));
    assert!(!k.matches(Some("110000")));
    assert!(!k.matches(Some("085959")));
    assert!(key(Attr::StudyTime, "1200-").matches(Some("235959.999999")));
}

#[test]
fn date_time_ranges_fill_missing_components() {
    let lo = comparable(Vr::Dt, "2020", false).unwrap();
    let hi = comparable(Vr::Dt, "2020", true).unwrap();
    let m = Matcher::Range(Some(lo), Some(hi));
    assert!(m.matches(Vr::Dt, Some("20200704123000")));
    assert!(!m.matches(Vr::Dt, Some("20210101")));
    assert!(is_range_dt("2020-2021"));
    assert!(!is_range_dt("20200101120000-0500"));
}

#[test]
fn malformed_dates_and_empty_ranges_are_bad_keys() {
    assert!(Key::parse(Attr::StudyDate, "2020-13").is_err());
    assert!(Key::parse(Attr::StudyDate, "yesterday").is_err());
    assert!(Key::parse(Attr::StudyDate, "-").is_err());
    assert!(
        Key::parse(Attr::StudyTime, "25").is_ok(),
        "only the form is checked"
    );
    assert!(Key::parse(Attr::StudyTime, "123").is_err());
}

#[test]
fn tags_levels_and_vrs_form_one_table() {
    for a in ATTRS {
        assert_eq!(Attr::from_tag(a.tag()), Some(*a));
    }
    assert!(ATTRS.windows(2).all(|w| w[0].tag() < w[1].tag()));
    assert_eq!(Attr::from_tag(0x0020_000D), Some(Attr::StudyInstanceUid));
    assert_eq!(Attr::StudyDate.level(), Level::Study);
    assert_eq!(Attr::unique_key(Level::Series), Attr::SeriesInstanceUid);
    assert_eq!(Level::parse("SERIES "), Some(Level::Series));
    assert_eq!(Level::parse("FRAME"), None);
    for a in ATTRS {
        assert_eq!(Attr::from_name(a.keyword()), Some(*a));
        assert_eq!(Attr::from_name(&format!("{:08X}", a.tag())), Some(*a));
    }
    assert_eq!(Attr::from_name("PatientAge"), None);
    assert_eq!(Attr::from_name("00101010"), None);
    assert!(
        Key::parse(Attr::NumberOfStudyRelatedInstances, "5")
            .unwrap()
            .matches(None)
    );
}
