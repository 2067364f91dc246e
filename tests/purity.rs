//! The dependency rule, read from the sources:
//! - the pure modules (`recon`, `volume`, `mesh`, `series`, `render`) do not depend on the service stack, DICOM, the
//!   clock, the environment or the file system;
//! - the application layer (`app`) imports no front door (`http`, `cli`) and no web framework;
//! - the job-store adapter (`jobs`) and the blob-store adapter (`storage`) do not import each other's
//!   backends, and nothing below the front doors imports them;
//! - the top-level modules import each other without a cycle.

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

/// Top-level modules of `src/` (a folder or a file) and the other top-level modules each one names as
/// `crate::<module>`.
fn module_graph(
    root: &Path,
) -> std::collections::BTreeMap<String, std::collections::BTreeSet<String>> {
    let src = root.join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut graph = std::collections::BTreeMap::<String, std::collections::BTreeSet<String>>::new();
    for file in files {
        let rel = file.strip_prefix(&src).expect("under src");
        let first = rel.components().next().expect("a component");
        let top = first
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        let text = std::fs::read_to_string(&file).expect("read source");
        let deps = graph.entry(top.clone()).or_default();
        for line in text.lines() {
            let c = code(line);
            for (i, _) in c.match_indices("crate::") {
                let name: String = c[i + 7..]
                    .chars()
                    .take_while(|ch| ch.is_ascii_lowercase() || *ch == '_')
                    .collect();
                if !name.is_empty() && name != top {
                    deps.insert(name);
                }
            }
        }
    }
    graph
}

/// Whether `to` is reachable from `from` in `graph`.
fn reaches(
    graph: &std::collections::BTreeMap<String, std::collections::BTreeSet<String>>,
    from: &str,
    to: &str,
) -> bool {
    let mut seen = std::collections::BTreeSet::new();
    let mut stack = vec![from.to_string()];
    while let Some(m) = stack.pop() {
        for d in graph.get(&m).into_iter().flatten() {
            if d == to {
                return true;
            }
            if seen.insert(d.clone()) {
                stack.push(d.clone());
            }
        }
    }
    false
}

#[test]
fn top_level_modules_import_each_other_without_a_cycle() {
    let graph = module_graph(Path::new(env!("CARGO_MANIFEST_DIR")));
    assert!(
        graph.contains_key("app") && graph.contains_key("jobs"),
        "{graph:?}"
    );
    let mut cycles = Vec::new();
    for (m, deps) in &graph {
        for d in deps {
            if graph.contains_key(d) && reaches(&graph, d, m) {
                cycles.push(format!("{m} → {d} → … → {m}"));
            }
        }
    }
    assert!(cycles.is_empty(), "module cycles:\n{}", cycles.join("\n"));
}

#[test]
fn the_application_layer_imports_no_front_door() {
    let graph = module_graph(Path::new(env!("CARGO_MANIFEST_DIR")));
    for front in ["http", "dimse", "cli"] {
        assert!(
            !reaches(&graph, "app", front),
            "app reaches the front door `{front}`: {graph:?}"
        );
    }
    let mut files = Vec::new();
    rust_files(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("src/app"),
        &mut files,
    );
    for file in files {
        let text = std::fs::read_to_string(&file).expect("read source");
        for (n, line) in text.lines().enumerate() {
            let c = code(line);
            assert!(
                !c.contains("axum") && !c.contains("tower") && !c.contains("hyper"),
                "{}:{}: the application layer imports a web framework",
                file.display(),
                n + 1
            );
        }
    }
}

#[test]
fn adapters_and_lower_layers_import_no_front_door_and_the_stores_not_each_other() {
    let graph = module_graph(Path::new(env!("CARGO_MANIFEST_DIR")));
    for lower in [
        "jobs", "storage", "dicom", "series", "recon", "volume", "mesh", "render", "app", "config",
    ] {
        for front in ["http", "dimse", "cli"] {
            assert!(
                !reaches(&graph, lower, front),
                "`{lower}` reaches the front door `{front}`"
            );
        }
    }
    // Front doors are adapters beside each other: the HTTP routes and the DICOM node do not import each other.
    assert!(!reaches(&graph, "http", "dimse"), "http reaches dimse");
    assert!(!reaches(&graph, "dimse", "http"), "dimse reaches http");
    // The blob store knows nothing of the job store (the job store may name blob ids).
    assert!(!reaches(&graph, "storage", "jobs"), "storage reaches jobs");
}

#[test]
fn the_scan_flags_imports_and_paths_but_not_comments_or_longer_names() {
    let text = "use tokio::sync;\n/// no tokio here\nlet tokio_like = 1;\nlet p = std::env::var(\"X\");\nx.dicom_tag // dicom";
    assert_eq!(scan(text), vec![(1, "tokio"), (4, "std::env")]);
}
