//! The dependency rule, read from the sources:
//! - the pure modules (`recon`, `volume`, `mesh`, `series`, `render`) do not depend on the service stack, DICOM, the
//!   clock, the environment or the file system;
//! - the application layer (`app`) imports no front door (`http`, `cli`) and no web framework;
//! - the job-store adapter (`jobs`) and the blob-store adapter (`storage`) do not import each other's
//!   backends, and nothing below the front doors imports them;
//! - the top-level modules import each other without a cycle, and so do the modules inside `src/jobs`;
//! - no source file outside tests is over 500 lines.

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

type Graph = std::collections::BTreeMap<String, std::collections::BTreeSet<String>>;

/// Module path of a source file under `src`: `jobs/engine/relay.rs` → `["jobs", "engine", "relay"]`,
/// `jobs/imaging/mod.rs` → `["jobs", "imaging"]`.
fn module_path(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).expect("under src");
    let mut parts: Vec<String> = rel
        .components()
        .map(|c| {
            c.as_os_str()
                .to_string_lossy()
                .trim_end_matches(".rs")
                .to_string()
        })
        .collect();
    if parts
        .last()
        .is_some_and(|p| p == "mod" || p == "lib" || p == "main")
    {
        parts.pop();
    }
    parts
}

/// The code of a file outside comments and outside its `#[cfg(test)]` module (tests may import anything).
fn non_test_code(text: &str) -> String {
    let body = text.split("#[cfg(test)]").next().unwrap_or("");
    body.lines().map(code).collect::<Vec<_>>().join("\n")
}

/// The absolute module paths that `text` (the code of module `module`) names through `crate::`, `super::`
/// or `self::`; each member of a brace group (`use super::{a, b::c}`) counts.
fn named_paths(module: &[String], text: &str) -> Vec<Vec<String>> {
    let is_ident = |ch: char| ch.is_ascii_alphanumeric() || ch == '_';
    let ident_at = |rest: &str| -> String { rest.chars().take_while(|&ch| is_ident(ch)).collect() };
    let mut out = Vec::new();
    let mut i = 0;
    while i < text.len() {
        let rest = &text[i..];
        let boundary = text[..i]
            .chars()
            .next_back()
            .is_none_or(|ch| !is_ident(ch) && ch != ':');
        let (mut base, mut at) = if boundary && rest.starts_with("crate::") {
            (Vec::new(), 7)
        } else if boundary && rest.starts_with("self::") {
            (module.to_vec(), 6)
        } else if boundary && rest.starts_with("super::") {
            (module[..module.len().saturating_sub(1)].to_vec(), 7)
        } else {
            i += rest.chars().next().map_or(1, char::len_utf8);
            continue;
        };
        while rest[at..].starts_with("super::") {
            base.pop();
            at += 7;
        }
        // Segments `a::b::` extend the base; a brace group or a last name ends the path.
        loop {
            if rest[at..].starts_with('{') {
                let group = &rest[at + 1..rest[at..].find('}').map_or(rest.len(), |e| at + e)];
                for member in group.split(',') {
                    let name = ident_at(member.trim());
                    if !name.is_empty() && name != "self" {
                        out.push([base.clone(), vec![name]].concat());
                    }
                }
                break;
            }
            let name = ident_at(&rest[at..]);
            if name.is_empty() {
                break;
            }
            at += name.len();
            base.push(name);
            if rest[at..].starts_with("::") {
                at += 2;
            } else {
                out.push(base);
                break;
            }
        }
        i += at;
    }
    out
}

/// The modules directly inside `within` (`[]`: the top-level modules of `src/`) and the others of them that
/// each one's code names, by `crate::`, `super::` or `self::` paths. Test modules (`tests.rs`, `#[cfg(test)]`)
/// are left out.
fn module_graph_within(root: &Path, within: &[&str]) -> Graph {
    let src = root.join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let depth = within.len();
    let mut graph = Graph::new();
    for file in files {
        let module = module_path(&src, &file);
        let inside = module.len() > depth && module.iter().zip(within).all(|(m, w)| m == w);
        if !inside || module.last().is_some_and(|m| m == "tests") {
            continue;
        }
        let own = module[depth].clone();
        let text = non_test_code(&std::fs::read_to_string(&file).expect("read source"));
        let deps = graph.entry(own.clone()).or_default();
        for path in named_paths(&module, &text) {
            let under = path.len() > depth && path.iter().zip(within).all(|(p, w)| p == w);
            if under && path[depth] != own {
                deps.insert(path[depth].clone());
            }
        }
    }
    // Only modules that exist (a path's next segment may be an item of `within`, not a module).
    let known: std::collections::BTreeSet<String> = graph.keys().cloned().collect();
    for deps in graph.values_mut() {
        deps.retain(|d| known.contains(d));
    }
    graph
}

/// Top-level modules of `src/` and the other top-level modules each one names.
fn module_graph(root: &Path) -> Graph {
    module_graph_within(root, &[])
}

/// Every `a → b → … → a` in `graph`, one line per edge on a cycle.
fn cycles(graph: &Graph) -> Vec<String> {
    let mut found = Vec::new();
    for (m, deps) in graph {
        for d in deps {
            if reaches(graph, d, m) {
                found.push(format!("{m} → {d} → … → {m}"));
            }
        }
    }
    found
}

/// Whether `to` is reachable from `from` in `graph`.
fn reaches(graph: &Graph, from: &str, to: &str) -> bool {
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
    let found = cycles(&graph);
    assert!(found.is_empty(), "module cycles:\n{}", found.join("\n"));
}

#[test]
fn the_modules_of_jobs_import_each_other_without_a_cycle() {
    let graph = module_graph_within(Path::new(env!("CARGO_MANIFEST_DIR")), &["jobs"]);
    for layer in ["model", "store", "database", "engine", "imaging", "views"] {
        assert!(graph.contains_key(layer), "{layer} missing: {graph:?}");
    }
    // The layers point one way: the model names none of the others, the store only the model's neighbours.
    assert!(
        graph["model"].is_empty(),
        "model imports {:?}",
        graph["model"]
    );
    // The port names no adapter; the one SQL adapter (`database`) serves both databases.
    assert!(!reaches(&graph, "store", "database"));
    assert!(!reaches(&graph, "imaging", "engine") && !reaches(&graph, "views", "imaging"));
    let found = cycles(&graph);
    assert!(
        found.is_empty(),
        "cycles inside src/jobs:\n{}",
        found.join("\n")
    );
}

#[test]
fn no_source_file_is_over_500_lines_outside_tests() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut long: Vec<String> = files
        .iter()
        .filter(|f| module_path(&src, f).last().is_none_or(|m| m != "tests"))
        .filter_map(|f| {
            let lines = std::fs::read_to_string(f)
                .expect("read source")
                .lines()
                .count();
            (lines > 500).then(|| format!("{} ({lines} lines)", f.display()))
        })
        .collect();
    long.sort();
    assert!(
        long.is_empty(),
        "files over 500 lines:\n{}",
        long.join("\n")
    );
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
        "scans",
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
fn paths_resolve_from_the_module_that_names_them() {
    let m: Vec<String> = ["jobs", "engine", "relay"].map(String::from).to_vec();
    let text = "use super::{Engine, progress::Sink};\nuse super::super::model::Job;\nuse crate::jobs::{store, self};\nlet x = self::helper; my_super::x; a::crate::b";
    let got: Vec<String> = named_paths(&m, text).iter().map(|p| p.join("::")).collect();
    assert_eq!(
        got,
        [
            "jobs::engine::Engine",
            "jobs::engine::progress",
            "jobs::model::Job",
            "jobs::store",
            "jobs::engine::relay::helper"
        ]
    );
    let cyclic: Graph = [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")]
        .iter()
        .fold(Graph::new(), |mut g, (x, y)| {
            g.entry(x.to_string()).or_default().insert(y.to_string());
            g
        });
    assert_eq!(cycles(&cyclic).len(), 3, "{:?}", cycles(&cyclic));
}

#[test]
fn the_scan_flags_imports_and_paths_but_not_comments_or_longer_names() {
    let text = "use tokio::sync;\n/// no tokio here\nlet tokio_like = 1;\nlet p = std::env::var(\"X\");\nx.dicom_tag // dicom";
    assert_eq!(scan(text), vec![(1, "tokio"), (4, "std::env")]);
}
