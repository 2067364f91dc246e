//! The built-in web viewer in a real headless Chromium (WebDriver) against the real server on a random port:
//! the page is served with its security headers, a DICOM series goes in through the drop zone's file input,
//! the bone protocol runs and the page follows it to `succeeded` through Server-Sent Events, the value under
//! the cursor equals the API's volume, window changes recolour the canvas as the window formula says, the
//! mesh is drawn and its triangle count is the API's, and a wrong token or a stopped server give the page's
//! messages. Screenshots of each view go to `screenshots/` in the target directory (or
//! `CTRECON_SCREENSHOT_DIR`); the figures (time to first slice, frames per second, page weight) are printed.

#[path = "../common/mod.rs"]
mod common;

mod browser;
mod checks;
mod flow;

use common::spawn_app_with;

const TOKEN: &str = "viewer-test-token-0123456789abcdef";

#[tokio::test]
async fn the_page_and_its_modules_are_served_with_types_etags_and_a_strict_policy() {
    let app = spawn_app_with(|s| s.api_tokens = vec![TOKEN.into()]).await;
    let r = app.get("/").await;
    assert_eq!(r.status(), 200, "the page needs no token");
    let h = r.headers().clone();
    assert_eq!(h["content-type"], "text/html; charset=utf-8");
    let csp = h["content-security-policy"].to_str().expect("ascii");
    assert!(csp.contains("script-src 'self'") && csp.contains("style-src 'self'"));
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"));
    assert_eq!(h["x-content-type-options"], "nosniff");
    let html = r.text().await.expect("body");
    assert!(html.contains(r#"<script type="module" src="/web/js/app.js"></script>"#));

    let r = app.get("/web/js/app.js").await;
    assert_eq!(r.status(), 200);
    assert_eq!(
        r.headers()["content-type"],
        "text/javascript; charset=utf-8"
    );
    assert_eq!(r.headers()["cache-control"], "no-cache");
    let etag = r.headers()["etag"].clone();
    let again = app
        .client
        .get(app.url("/web/js/app.js"))
        .header("if-none-match", etag.clone())
        .send()
        .await
        .expect("request");
    assert_eq!(again.status(), 304);
    assert_eq!(again.headers()["etag"], etag);
    let three = app.get("/web/vendor/three/three.module.js").await;
    assert_eq!(three.status(), 200);
    assert!(three.text().await.expect("body").contains("REVISION"));

    // Names outside the table are not found (a request never becomes a file path).
    for missing in ["/web/js/nope.js", "/web/js", "/web/index.html/x"] {
        assert_eq!(app.get(missing).await.status(), 404, "{missing}");
    }
    // The API stays behind the token.
    assert_eq!(app.get("/v1/jobs").await.status(), 401);
}

#[tokio::test]
async fn a_wrong_token_and_a_stopped_server_show_the_pages_messages() {
    flow::token_and_server_down(TOKEN).await;
}

#[tokio::test]
async fn lidc_upload_bone_protocol_slices_window_and_mesh_in_chromium() {
    flow::lidc(TOKEN).await;
}
