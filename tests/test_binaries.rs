//! The integration tests are compiled into the few test binaries that Cargo.toml names (`autotests = false`):
//! each binary links the whole crate and compiles the test helpers again, so one binary per file made most of
//! the build of `cargo test`. A file in `tests/` that no binary names would never be compiled nor run; this
//! test finds such a file.

use std::collections::BTreeSet;
use std::path::Path;

/// The `path`s of Cargo.toml's `[[test]]` entries, relative to `tests/`.
fn binaries(manifest: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut in_test = false;
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_test = line == "[[test]]";
        } else if in_test && let Some(rest) = line.strip_prefix("path") {
            let value = rest.trim_start_matches([' ', '=']).trim_matches('"');
            if let Some(file) = value.strip_prefix("tests/") {
                out.insert(file.to_string());
            }
        }
    }
    out
}

/// The files a binary's root names as modules, relative to `tests/`: `mod x;` is `x.rs`, and
/// `#[path = "p"] mod x;` is `p`.
fn modules(root: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut path: Option<String> = None;
    for line in root.lines().map(str::trim) {
        if let Some(p) = line
            .strip_prefix("#[path = \"")
            .and_then(|r| r.strip_suffix("\"]"))
        {
            path = Some(p.to_string());
        } else if let Some(name) = line.strip_prefix("mod ").and_then(|r| r.strip_suffix(';')) {
            out.insert(path.take().unwrap_or_else(|| format!("{name}.rs")));
        } else if !line.is_empty() && !line.starts_with("//") {
            path = None;
        }
    }
    out
}

/// The files that must be named: every `tests/*.rs` and every `tests/*/main.rs` (a directory's other files are
/// modules of its `main.rs`; `tests/common/` holds the helpers the roots name).
fn test_files(tests: &Path) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for entry in std::fs::read_dir(tests).expect("read tests/") {
        let path = entry.expect("directory entry").path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .expect("UTF-8 name")
            .to_string();
        if path.is_dir() {
            if path.join("main.rs").is_file() {
                out.insert(format!("{name}/main.rs"));
            }
        } else if name.ends_with(".rs") {
            out.insert(name);
        }
    }
    out
}

#[test]
fn every_test_file_is_compiled_into_a_test_binary() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).expect("read Cargo.toml");
    let roots = binaries(&manifest);
    assert!(
        roots.len() >= 2,
        "Cargo.toml names the test binaries: {roots:?}"
    );
    let mut named = roots.clone();
    for r in &roots {
        let text = std::fs::read_to_string(root.join("tests").join(r)).expect("read a test root");
        named.extend(modules(&text));
    }
    let missing: Vec<_> = test_files(&root.join("tests"))
        .difference(&named)
        .cloned()
        .collect();
    assert!(
        missing.is_empty(),
        "test files no test binary compiles (add them to a binary's root, e.g. tests/service.rs): {missing:?}"
    );
    // And nothing named is missing on disk (a stale line would fail to compile anyway, but say which).
    for n in &named {
        let file = root.join("tests").join(n);
        let folder = file.with_extension("").join("mod.rs");
        assert!(
            file.is_file() || folder.is_file(),
            "named but absent: tests/{n}"
        );
    }
}

#[test]
fn the_parsers_read_the_lines_they_are_meant_for() {
    let manifest = "[package]\npath = \"x\"\n[[test]]\nname = \"a\"\npath = \"tests/a.rs\"\n\n[[bench]]\npath = \"benches/b.rs\"\n[[test]]\npath=\"tests/c.rs\"\n";
    assert_eq!(
        binaries(manifest),
        BTreeSet::from(["a.rs".to_string(), "c.rs".to_string()])
    );
    let root = "mod common;\n#[path = \"common/s3.rs\"]\nmod s3;\n\n// mod commented;\nmod api_jobs;\n#[path = \"viewer/main.rs\"]\nmod viewer;\n";
    assert_eq!(
        modules(root),
        BTreeSet::from([
            "common.rs".to_string(),
            "common/s3.rs".to_string(),
            "api_jobs.rs".to_string(),
            "viewer/main.rs".to_string(),
        ])
    );
}
