//! The job page's downloads against the API: every button fetches its file with the page's token (200, the
//! size the API sends) under a file name of its own, and each file is what the API says the result is — the
//! volume's shape, the derived series' slice count, the mesh's triangles, a product's frames and size.

use std::io::Read;

use serde_json::{Value, json};

use super::browser::Browser;
use super::common::{TestApp, read_npy_f32};

/// `[z, y, x]` of an `.npy` header.
fn npy_shape(bytes: &[u8]) -> Vec<usize> {
    let header_len = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
    let header = std::str::from_utf8(&bytes[10..10 + header_len]).expect("an ASCII header");
    let shape = header
        .split_once("'shape': (")
        .and_then(|(_, r)| r.split_once(')'))
        .map(|(s, _)| s)
        .expect("a shape");
    shape
        .split(',')
        .filter(|x| !x.trim().is_empty())
        .map(|x| x.trim().parse().expect("a length"))
        .collect()
}

/// What a file must be: its content type and a check of its bytes against the job.
fn expect(url: &str, job: &Value, body: &[u8]) -> &'static str {
    let r = &job["result"];
    let shape = |v: &Value| -> Vec<usize> { serde_json::from_value(v.clone()).expect("a shape") };
    if url.ends_with("/volume.npy") {
        assert_eq!(npy_shape(body), shape(&r["shape"]), "{url}");
        return "application/x-npy";
    }
    if url.ends_with("/series.zip") {
        let mut zip = zip::ZipArchive::new(std::io::Cursor::new(body)).expect("a ZIP");
        assert_eq!(
            zip.len(),
            shape(&r["shape"])[0],
            "{url}: one file per slice"
        );
        let mut first = Vec::new();
        zip.by_index(0)
            .expect("a member")
            .read_to_end(&mut first)
            .expect("read");
        assert_eq!(&first[128..132], b"DICM", "{url}");
        return "application/zip";
    }
    let (path, query) = url.split_once('?').unwrap_or((url, ""));
    let index: usize = path
        .rsplit('/')
        .next()
        .and_then(|i| i.parse().ok())
        .expect("a product");
    let p = &r["products"][index];
    match (p["type"].as_str(), query) {
        (Some("mesh"), "") => {
            let triangles = p["mesh"]["triangles"].as_u64().expect("triangles") as usize;
            assert_eq!(
                body.len(),
                84 + 50 * triangles,
                "{url}: a binary STL of the API's triangles"
            );
            "model/stl"
        }
        (_, "format=dicom") => {
            assert_eq!(&body[128..132], b"DICM", "{url}");
            "application/dicom"
        }
        (_, "format=npy") => {
            assert_eq!(npy_shape(body), shape(&p["shape"]), "{url}");
            let (_, values) = read_npy_f32(body);
            assert_eq!(values.len(), shape(&p["shape"]).iter().product::<usize>());
            "application/x-npy"
        }
        (_, "format=png") => {
            let d = png::Decoder::new(std::io::Cursor::new(body));
            let info = d.read_info().expect("a PNG");
            let s = shape(&p["shape"]);
            assert_eq!(
                (info.info().width as usize, info.info().height as usize),
                (s[2], s[1]),
                "{url}: the product's first frame"
            );
            "image/png"
        }
        other => panic!("{url}: no download expected for {other:?}"),
    }
}

/// Click every download the job page offers; each must arrive whole, as the API serves it.
pub async fn every_download_answers(b: &Browser, app: &TestApp, token: &str, job: &Value) {
    let id = job["id"].as_str().expect("id");
    b.js(
        "performance.setResourceTimingBufferSize(2000); performance.clearResourceTimings();
         window.saved = [];
         HTMLAnchorElement.prototype.click = function () { window.saved.push(this.download); };
         document.getElementById('downloads').scrollIntoView();",
        vec![],
    )
    .await;
    let urls: Vec<String> = serde_json::from_value(
        b.js(
            "return [...document.querySelectorAll('#downloads button[data-url]')].map((x) => x.dataset.url);",
            vec![],
        )
        .await,
    )
    .expect("urls");
    let products = job["result"]["products"].as_array().expect("products");
    // The volume, the derived series, and per product its files (a mesh: STL and DICOM; a stack: npy, PNG
    // and DICOM).
    let want = 2 + products
        .iter()
        .map(|p| if p["type"] == "mesh" { 2 } else { 3 })
        .sum::<usize>();
    assert_eq!(urls.len(), want, "{urls:?}");
    for (n, url) in urls.iter().enumerate() {
        b.js(
            "document.querySelectorAll('#downloads button[data-url]')[arguments[0]].click();",
            vec![json!(n)],
        )
        .await;
        b.until(&format!("window.saved.length === {}", n + 1), 120)
            .await;
        let r = app
            .client
            .get(app.url(url))
            .bearer_auth(token)
            .send()
            .await
            .expect("request");
        assert_eq!(r.status(), 200, "{url}");
        let content_type = r
            .headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        let body = r.bytes().await.expect("body");
        assert_eq!(content_type, expect(url, job, &body), "{url}");
        let got = b
            .js(
                "const e = performance.getEntriesByType('resource').filter((r) => r.name.endsWith(arguments[0]));
                 return e.length ? [e[e.length - 1].responseStatus, e[e.length - 1].decodedBodySize] : null;",
                vec![json!(url)],
            )
            .await;
        assert_eq!(
            got,
            json!([200, body.len()]),
            "{url}: the page's download got the API's {} bytes",
            body.len()
        );
        eprintln!("download {url}: 200 {content_type}, {} bytes", body.len());
    }
    let names: Vec<String> =
        serde_json::from_value(b.js("return window.saved", vec![]).await).expect("names");
    let short = &id[..8];
    assert!(names.iter().all(|n| n.starts_with(short)), "{names:?}");
    let mut unique = names.clone();
    unique.sort();
    unique.dedup();
    assert_eq!(unique.len(), names.len(), "a file name each: {names:?}");
    assert_eq!(b.text("#downloads .msg").await, "", "no download failed");
}
