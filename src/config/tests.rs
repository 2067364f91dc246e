use super::*;

fn env(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
    pairs
        .iter()
        .map(|(a, b)| (a.to_string(), b.to_string()))
        .collect()
}

#[test]
fn environment_overrides_defaults_and_unknown_variables_are_refused() {
    let s = Settings::load(
        None,
        env(&[
            ("CTRECON_MAX_CONCURRENT_JOBS", "5"),
            ("CTRECON_CORS_ORIGINS", "http://a.test, http://b.test"),
            ("PATH", "/bin"),
        ]),
    )
    .unwrap();
    assert_eq!(s.max_concurrent_jobs, 5);
    assert_eq!(s.cors_origins, ["http://a.test", "http://b.test"]);
    assert!(Settings::load(None, env(&[("CTRECON_NOPE", "1")])).is_err());
    assert!(Settings::load(None, env(&[("CTRECON_MAX_ATTEMPTS", "x")])).is_err());
}

#[test]
fn every_documented_environment_variable_is_accepted() {
    let docs = [
        include_str!("../../README.md"),
        include_str!("../../benches/README.md"),
        include_str!("../../Dockerfile"),
        include_str!("mod.rs"),
    ];
    let mut names: Vec<&str> = Vec::new();
    for d in docs {
        for (at, _) in d.match_indices("CTRECON_") {
            let end = d[at..]
                .find(|c: char| !(c.is_ascii_uppercase() || c.is_ascii_digit() || c == '_'))
                .map_or(d.len(), |e| at + e);
            names.push(&d[at..end]);
        }
    }
    names.sort_unstable();
    names.dedup();
    names.retain(|n| *n != "CTRECON_NOPE" && *n != "CTRECON_");
    assert!(names.len() >= 20, "{names:?}");
    for name in names {
        // A value every setting parses: a number where a number is wanted, else any text.
        let value = match name {
            "CTRECON_BIND" => "127.0.0.1:0",
            "CTRECON_DICOM_HOST" => "127.0.0.1",
            "CTRECON_ALLOW_INSECURE" => "true",
            "CTRECON_MU_WATER_PER_MM" => "0.02",
            "CTRECON_DATA_DIR" | "CTRECON_LOG_FORMAT" | "CTRECON_SIMD" => "avx2",
            n if n.ends_with("TOKENS")
                || n.ends_with("ORIGINS")
                || n.ends_with("SHA256")
                || n.ends_with("WEB_PEERS") =>
            {
                ""
            }
            _ => "1",
        };
        let r = Settings::load(None, env(&[(name, value)]));
        assert!(r.is_ok(), "{name}={value}: {:?}", r.err());
    }
}

#[test]
fn web_peers_come_from_the_environment_as_json_and_their_secrets_stay_out_of_debug() {
    let s = Settings::load(
        None,
        env(&[(
            "CTRECON_DICOM_WEB_PEERS",
            r#"[{"name": "ARCHIVE", "url": "http://pacs:8042/dicom-web", "bearer_token": "tok-123"}]"#,
        )]),
    )
    .unwrap();
    let w = s.dicom.web_peer("ARCHIVE").unwrap();
    assert_eq!(w.bearer_token.as_deref(), Some("tok-123"));
    assert_eq!((w.timeout_secs, w.batch_instances), (600, 200));
    assert!(!format!("{s:?}").contains("tok-123"));
    assert!(s.dicom.is_destination("ARCHIVE") && !s.dicom.is_destination("OTHER"));
    assert!(Settings::load(None, env(&[("CTRECON_DICOM_WEB_PEERS", "{\"name\": 1}")])).is_err());
}

#[test]
fn a_public_bind_needs_tokens_or_the_insecure_flag() {
    let mut s = Settings {
        bind: "0.0.0.0:8080".parse().unwrap(),
        ..Settings::default()
    };
    assert!(s.validate().is_err());
    s.api_tokens = vec!["a-long-enough-secret".into()];
    assert!(s.validate().is_ok());
    s.api_tokens.clear();
    s.allow_insecure = true;
    assert!(s.validate().is_ok());
    assert!(Settings::default().validate().is_ok());
}

#[test]
fn connection_caps_and_timeouts_come_from_the_environment_and_zero_timeouts_are_refused() {
    let s = Settings::load(
        None,
        env(&[
            ("CTRECON_HEADER_READ_TIMEOUT_MS", "2000"),
            ("CTRECON_IDLE_TIMEOUT_MS", "3000"),
            ("CTRECON_MAX_CONNECTIONS", "64"),
            ("CTRECON_MAX_CONNECTIONS_PER_IP", "0"),
            ("CTRECON_UPLOAD_MIN_BYTES", "1024"),
            ("CTRECON_UPLOAD_PROGRESS_WINDOW_SECS", "2"),
        ]),
    )
    .unwrap();
    assert_eq!((s.header_read_timeout_ms, s.idle_timeout_ms), (2000, 3000));
    assert_eq!((s.max_connections, s.max_connections_per_ip), (64, 0));
    assert_eq!(
        (s.upload_min_bytes, s.upload_progress_window_secs),
        (1024, 2)
    );
    assert!(s.validate().is_ok());
    let d = Settings::default();
    assert_eq!(
        (
            d.header_read_timeout_ms,
            d.max_connections,
            d.max_connections_per_ip
        ),
        (10_000, 2048, 256)
    );
    for broken in [
        Settings {
            header_read_timeout_ms: 0,
            ..Settings::default()
        },
        Settings {
            idle_timeout_ms: 0,
            ..Settings::default()
        },
        Settings {
            upload_progress_window_secs: 0,
            ..Settings::default()
        },
        Settings {
            max_connections: 0,
            ..Settings::default()
        },
    ] {
        assert!(broken.validate().is_err(), "{broken:?}");
    }
}
