//! The built-in web viewer: the files under `web/`, embedded in the binary at build time and served at `/`
//! (the page) and `/web/{path}` (its CSS, JavaScript modules and the vendored three.js).
//!
//! A request names an entry of a fixed table, never a file: no path is built from client text. Every answer
//! carries its content type, a strong ETag (SHA-256 of the bytes; `If-None-Match` → 304), `Cache-Control:
//! no-cache` (revalidate, since names carry no hash) and a strict Content-Security-Policy: scripts, styles,
//! fonts and connections from this origin only, no inline script or style, no frames, no plugins. The page
//! holds no secret and is served without a token; everything it shows comes from the `/v1` API, which it
//! calls with the bearer token the user enters.
//!
//! Every file is also embedded gzip-compressed (made by `build.rs` at build time, so no request compresses
//! anything): a client whose `Accept-Encoding` takes gzip gets those bytes with `Content-Encoding: gzip`
//! wherever they are smaller. The two encodings are two representations with two strong ETags (the gzip
//! one ends in `-gzip`), and every answer says `Vary: Accept-Encoding`.

use std::sync::LazyLock;

use axum::Router;
use axum::extract::Path;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use sha2::{Digest, Sha256};

/// The policy of every viewer answer: nothing inline, nothing from elsewhere.
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; script-src 'self'; style-src 'self'; \
     img-src 'self' blob: data:; connect-src 'self'; base-uri 'none'; form-action 'none'; \
     frame-ancestors 'none'";

macro_rules! assets {
    ($($path:literal),* $(,)?) => {
        /// `(path under web/, bytes, gzip of the bytes)` of every embedded file.
        const FILES: &[(&str, &[u8], &[u8])] = &[
            $((
                $path,
                include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/web/", $path)),
                include_bytes!(concat!(env!("OUT_DIR"), "/web-gz/", $path, ".gz")),
            )),*
        ];
    };
}

assets!(
    "index.html",
    "css/viewer.css",
    "js/api.js",
    "js/app.js",
    "js/dom.js",
    "js/job.js",
    "js/jobs.js",
    "js/mesh.js",
    "js/npy.js",
    "js/orient.js",
    "js/products.js",
    "js/protocols.js",
    "js/send.js",
    "js/slices.js",
    "js/sliceview.js",
    "js/upload.js",
    "vendor/three/LICENSE",
    "vendor/three/OrbitControls.js",
    "vendor/three/three.core.js",
    "vendor/three/three.module.js",
);

/// One embedded file with what its answer needs.
struct Asset {
    path: &'static str,
    bytes: &'static [u8],
    etag: HeaderValue,
    /// The gzip representation and its ETag, when it is smaller than the file.
    gzip: Option<(&'static [u8], HeaderValue)>,
    content_type: &'static str,
}

fn content_type(path: &str) -> &'static str {
    match path.rsplit_once('.').map(|(_, ext)| ext) {
        Some("html") => "text/html; charset=utf-8",
        Some("css") => "text/css; charset=utf-8",
        Some("js") => "text/javascript; charset=utf-8",
        Some("png") => "image/png",
        Some("svg") => "image/svg+xml",
        _ => "text/plain; charset=utf-8",
    }
}

static ASSETS: LazyLock<Vec<Asset>> = LazyLock::new(|| {
    FILES
        .iter()
        .map(|&(path, bytes, gz)| {
            let hash = crate::storage::npy::hex(&Sha256::digest(bytes));
            // A hex digest in quotes is always a valid header value.
            let tag = |suffix: &str| {
                HeaderValue::from_str(&format!("\"{}{suffix}\"", &hash[..32]))
                    .unwrap_or(HeaderValue::from_static("\"0\""))
            };
            Asset {
                path,
                bytes,
                etag: tag(""),
                gzip: (gz.len() < bytes.len()).then(|| (gz, tag("-gzip"))),
                content_type: content_type(path),
            }
        })
        .collect()
});

fn lookup(path: &str) -> Option<&'static Asset> {
    ASSETS.iter().find(|a| a.path == path)
}

/// The security headers every viewer answer carries.
fn secure(resp: &mut Response) {
    let h = resp.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CONTENT_SECURITY_POLICY),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
}

/// Whether `Accept-Encoding` takes gzip: `gzip` or `*` listed with a quality above 0 (RFC 9110 §12.5.3).
fn accepts_gzip(req: &HeaderMap) -> bool {
    req.get_all(header::ACCEPT_ENCODING)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|item| {
            let mut parts = item.split(';');
            let coding = parts.next().unwrap_or("").trim();
            let quality = parts
                .filter_map(|p| p.trim().strip_prefix("q="))
                .find_map(|q| q.trim().parse::<f32>().ok())
                .unwrap_or(1.0);
            (coding.eq_ignore_ascii_case("gzip") || coding == "*") && quality > 0.0
        })
}

fn serve(asset: Option<&'static Asset>, req: &HeaderMap) -> Response {
    let Some(a) = asset else {
        let mut r = (
            StatusCode::NOT_FOUND,
            [(header::CONTENT_TYPE, "text/plain; charset=utf-8")],
            "no such viewer file\n",
        )
            .into_response();
        secure(&mut r);
        return r;
    };
    let (body, etag, gzip) = match &a.gzip {
        Some((gz, tag)) if accepts_gzip(req) => (*gz, tag, true),
        _ => (a.bytes, &a.etag, false),
    };
    let fresh = req
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| {
            v.split(',')
                .any(|t| t.trim() == "*" || t.trim().as_bytes() == etag.as_bytes())
        });
    let mut r = if fresh {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, a.content_type)], body).into_response()
    };
    let h = r.headers_mut();
    h.insert(header::ETAG, etag.clone());
    h.insert(header::VARY, HeaderValue::from_static("accept-encoding"));
    if gzip && !fresh {
        h.insert(header::CONTENT_ENCODING, HeaderValue::from_static("gzip"));
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    secure(&mut r);
    r
}

async fn index(headers: HeaderMap) -> Response {
    serve(lookup("index.html"), &headers)
}

async fn file(Path(path): Path<String>, headers: HeaderMap) -> Response {
    serve(lookup(&path), &headers)
}

/// The viewer's routes: `/` and `/web/{path}`, open without a token.
pub fn router() -> Router {
    Router::new()
        .route("/", get(index))
        .route("/web/{*path}", get(file))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn walk(dir: &std::path::Path, root: &std::path::Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(&p, root, out);
            } else if let Ok(rel) = p.strip_prefix(root) {
                out.push(rel.to_string_lossy().replace('\\', "/"));
            }
        }
    }

    #[test]
    fn every_file_under_web_is_embedded_except_notes() {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("web");
        let mut found = Vec::new();
        walk(&root, &root, &mut found);
        found.retain(|p| !p.ends_with("README.md"));
        found.sort();
        let mut listed: Vec<String> = FILES.iter().map(|(p, _, _)| p.to_string()).collect();
        listed.sort();
        assert_eq!(found, listed);
    }

    #[test]
    fn scripts_and_styles_are_typed_and_the_policy_forbids_inline_code() {
        assert_eq!(
            lookup("js/app.js").map(|a| a.content_type),
            Some("text/javascript; charset=utf-8")
        );
        assert_eq!(
            lookup("css/viewer.css").map(|a| a.content_type),
            Some("text/css; charset=utf-8")
        );
        assert!(!CONTENT_SECURITY_POLICY.contains("unsafe-inline"));
        assert!(!CONTENT_SECURITY_POLICY.contains("unsafe-eval"));
        let html =
            std::str::from_utf8(lookup("index.html").map(|a| a.bytes).unwrap_or(b"")).unwrap_or("");
        assert!(!html.contains("<script>") && !html.contains("style=\""));
        assert!(lookup("../Cargo.toml").is_none());
    }

    fn accept(v: &str) -> bool {
        let mut h = HeaderMap::new();
        h.insert(
            header::ACCEPT_ENCODING,
            HeaderValue::from_str(v).unwrap_or(HeaderValue::from_static("")),
        );
        accepts_gzip(&h)
    }

    #[test]
    fn gzip_is_chosen_only_when_the_client_takes_it() {
        assert!(accept("gzip"));
        assert!(accept("gzip, deflate, br, zstd"));
        assert!(accept("br;q=1.0, GZIP;q=0.5"));
        assert!(accept("*"));
        assert!(!accept("gzip;q=0"));
        assert!(!accept("gzip; q=0.0, br"));
        assert!(!accept("identity"));
        assert!(!accept("br, deflate"));
        assert!(!accept_none());
    }

    fn accept_none() -> bool {
        accepts_gzip(&HeaderMap::new())
    }

    #[test]
    fn the_gzip_copy_of_three_js_is_a_quarter_of_it_and_unpacks_to_the_same_bytes() {
        use std::io::Read;
        let a = lookup("vendor/three/three.core.js").expect("embedded");
        let (gz, etag) = a.gzip.as_ref().expect("a gzip representation");
        assert!(
            gz.len() * 4 < a.bytes.len(),
            "{} of {} bytes",
            gz.len(),
            a.bytes.len()
        );
        let mut out = Vec::new();
        flate2::read::GzDecoder::new(*gz)
            .read_to_end(&mut out)
            .expect("gunzip");
        assert!(out == a.bytes);
        assert_ne!(etag, a.etag);
        assert!(etag.to_str().is_ok_and(|t| t.ends_with("-gzip\"")));
    }
}
