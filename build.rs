//! Build steps: rebuild when a migration is added or changed (`sqlx::migrate!` embeds the folder at compile
//! time), and gzip every file of the web viewer (`web/`) into `$OUT_DIR/web-gz/<path>.gz`, which
//! `src/http/web.rs` embeds beside the plain bytes so the page's assets need no compression per request.

use std::io::Write;
use std::path::Path;

fn gzip_tree(dir: &Path, root: &Path, out: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        panic!("cannot read {}", dir.display());
    };
    for entry in entries.flatten() {
        let path = entry.path();
        if path.is_dir() {
            gzip_tree(&path, root, out);
            continue;
        }
        let Ok(rel) = path.strip_prefix(root) else {
            continue;
        };
        let target = out.join(format!("{}.gz", rel.display()));
        if let Some(parent) = target.parent() {
            std::fs::create_dir_all(parent).expect("create the gzip folder");
        }
        let bytes = std::fs::read(&path).expect("read a web file");
        // No file name and mtime 0 in the header: the same input always gives the same bytes (and ETag).
        let mut gz = flate2::GzBuilder::new()
            .mtime(0)
            .write(Vec::new(), flate2::Compression::best());
        gz.write_all(&bytes).expect("gzip");
        let gz = gz.finish().expect("gzip");
        std::fs::write(&target, gz).expect("write a gzip file");
    }
}

fn main() {
    println!("cargo:rerun-if-changed=migrations");
    println!("cargo:rerun-if-changed=web");
    let out = std::env::var_os("OUT_DIR").expect("OUT_DIR is set by cargo");
    let manifest =
        std::env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR is set by cargo");
    let root = Path::new(&manifest).join("web");
    gzip_tree(&root, &root, &Path::new(&out).join("web-gz"));
}
