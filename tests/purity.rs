//! The pure modules (`recon`, `volume`, `mesh`, `series`, `render`) must not depend on the service stack, DICOM, the clock,
//! the environment or the file system. This test reads their sources and fails on a forbidden path.

use std::path::{Path, PathBuf};

const PURE: &[&str] = &[
    "src/recon",
    "src/volume",
    "src/mesh",
    "src/series",
    "src/render",
];
const FORBIDDEN: &[&str] = &[
    "tokio",
    "axum",
    "tower",
    "sqlx",
    "hyper",
    "reqwest",
    "dicom",
    "std::env",
    "std::fs",
    "std::path",
    "std::net",
    "SystemTime",
    "Instant::now",
    "std::process",
];

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("read {}: {e}", dir.display())) {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// Code of a line without its `//` comment (string literals are rare enough in these modules).
fn code(line: &str) -> &str {
    line.split("//").next().unwrap_or("")
}

/// `(line number, forbidden word)` for every forbidden path used in `text` outside comments.
fn scan(text: &str) -> Vec<(usize, &'static str)> {
    let ident = |ch: Option<char>| ch.is_some_and(|ch| ch.is_alphanumeric() || ch == '_');
    let mut hits = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let c = code(line);
        for word in FORBIDDEN {
            let used = c.match_indices(word).any(|(i, _)| {
                !ident(c[..i].chars().next_back()) && !ident(c[i + word.len()..].chars().next())
            });
            if used {
                hits.push((n + 1, *word));
            }
        }
    }
    hits
}

#[test]
fn pure_modules_import_no_service_dicom_clock_env_or_filesystem() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for dir in PURE {
        rust_files(&root.join(dir), &mut files);
    }
    assert!(
        files.len() >= 3,
        "expected the pure modules' sources, found {files:?}"
    );
    let mut bad = Vec::new();
    for file in files {
        let text = std::fs::read_to_string(&file).expect("read source");
        for (line, word) in scan(&text) {
            bad.push(format!("{}:{line}: `{word}`", file.display()));
        }
    }
    assert!(
        bad.is_empty(),
        "forbidden imports in pure modules:\n{}",
        bad.join("\n")
    );
}

#[test]
fn the_scan_flags_imports_and_paths_but_not_comments_or_longer_names() {
    let text = "use tokio::sync;\n/// no tokio here\nlet tokio_like = 1;\nlet p = std::env::var(\"X\");\nx.dicom_tag // dicom";
    assert_eq!(scan(text), vec![(1, "tokio"), (4, "std::env")]);
}
