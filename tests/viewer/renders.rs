//! Renderings on the job page: a phantom is simulated and reconstructed (FDK) through the API, a volume job
//! renders it (a volume rendering and a rotating shaded surface), and the page must show exactly the pictures
//! the API serves — the same PNG and APNG bytes, the same decoded pixels and sizes — with their parameters
//! and orientation labels.

use serde_json::{Value, json};

use super::browser::{self, Browser};
use super::common::{TestApp, cone_geometry, spawn_app_with};

/// `(width, height, frames)` of a PNG or an animated PNG; each frame as RGBA bytes.
pub fn decode_frames(bytes: &[u8]) -> (u32, u32, Vec<Vec<u8>>) {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes.to_vec()));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut r = dec.read_info().expect("png header");
    let (w, h) = (r.info().width, r.info().height);
    let n = r.info().animation_control().map_or(1, |a| a.num_frames);
    let mut buf = vec![0; r.output_buffer_size().expect("png size")];
    let frames = (0..n)
        .map(|_| {
            let info = r.next_frame(&mut buf).expect("png frame");
            let px = &buf[..info.buffer_size()];
            match info.color_type {
                png::ColorType::Rgb => px.chunks(3).flat_map(|p| [p[0], p[1], p[2], 255]).collect(),
                png::ColorType::Rgba => px.to_vec(),
                other => panic!("unexpected colour type {other:?}"),
            }
        })
        .collect();
    (w, h, frames)
}

async fn api_bytes(app: &TestApp, path: &str, content_type: &str) -> Vec<u8> {
    let r = app.get(path).await;
    assert_eq!(r.status(), 200, "{path}");
    assert_eq!(
        r.headers()
            .get("content-type")
            .and_then(|v| v.to_str().ok()),
        Some(content_type),
        "{path}"
    );
    r.bytes().await.expect("body").to_vec()
}

/// Bytes of the page's last download of `path` (its Resource Timing entry: the page's policy allows no
/// fetch of its own blob URLs, so the body is measured where it arrived).
async fn fetched_size(b: &Browser, path: &str) -> u64 {
    let v = b
        .js(
            "const e = performance.getEntriesByType('resource').filter((r) => r.name.endsWith(arguments[0]));
             return e.length ? e[e.length - 1].decodedBodySize : -1;",
            vec![json!(path)],
        )
        .await;
    v.as_u64()
        .unwrap_or_else(|| panic!("the page did not fetch {path}"))
}

/// Distinct pictures an animated `<img>` shows over about `ms` milliseconds (RGBA, drawn on a canvas every
/// 25 ms).
async fn animation_frames(b: &Browser, css: &str, ms: u64) -> Vec<Vec<u8>> {
    let v = b
        .client
        .execute_async(
            "const [css, ms, done] = [arguments[0], arguments[1], arguments[arguments.length - 1]];
             const img = document.querySelector(css);
             const c = document.createElement('canvas');
             c.width = img.naturalWidth; c.height = img.naturalHeight;
             const ctx = c.getContext('2d');
             const seen = new Set(); const t0 = performance.now();
             const grab = () => {
               ctx.clearRect(0, 0, c.width, c.height); ctx.drawImage(img, 0, 0);
               const d = ctx.getImageData(0, 0, c.width, c.height).data; let s = '';
               for (let i = 0; i < d.length; i += 1) s += String.fromCharCode(d[i]);
               seen.add(btoa(s));
               if (performance.now() - t0 < ms) setTimeout(grab, 25); else done([...seen]);
             };
             grab();",
            vec![json!(css), json!(ms)],
        )
        .await
        .expect("watch the animation");
    v.as_array()
        .expect("frames")
        .iter()
        .map(|f| base64_decode(f.as_str().expect("base64")))
        .collect()
}

/// The pixels an `<img>` shows: (natural width, natural height, RGBA drawn on a canvas of that size).
async fn img_pixels(b: &Browser, css: &str) -> (u32, u32, Vec<u8>) {
    let v = b
        .js(
            "const img = document.querySelector(arguments[0]);
             const c = document.createElement('canvas');
             c.width = img.naturalWidth; c.height = img.naturalHeight;
             const ctx = c.getContext('2d'); ctx.drawImage(img, 0, 0);
             const d = ctx.getImageData(0, 0, c.width, c.height).data; let s = '';
             for (let i = 0; i < d.length; i += 1) s += String.fromCharCode(d[i]);
             return [c.width, c.height, btoa(s)];",
            vec![json!(css)],
        )
        .await;
    (
        v[0].as_u64().expect("width") as u32,
        v[1].as_u64().expect("height") as u32,
        base64_decode(v[2].as_str().expect("pixels")),
    )
}

/// Bytes of standard base64 text (as `btoa` writes it).
pub fn base64_decode(text: &str) -> Vec<u8> {
    let value = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let clean: Vec<u8> = text.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::with_capacity(clean.len() * 3 / 4);
    for chunk in clean.chunks(4) {
        let v: Vec<u32> = chunk.iter().map(|&c| u32::from(value(c))).collect();
        let n = v.iter().fold(0u32, |a, &x| (a << 6) | x) << (6 * (4 - v.len()));
        let bytes = [(n >> 16) as u8, (n >> 8) as u8, n as u8];
        out.extend_from_slice(&bytes[..v.len() - 1]);
    }
    out
}

/// The facts `dd[data-fact=name]` of product `index` on the page.
async fn fact(b: &Browser, index: usize, name: &str) -> String {
    b.text(&format!(
        ".render-product[data-index='{index}'] dd[data-fact='{name}']"
    ))
    .await
}

pub async fn renderings() {
    let Some(b) = browser::start("viewer: renderings", 1280, 800).await else {
        return;
    };
    // A DICOM node and a PACS peer where nothing listens: a job that pulls from it fails at run time.
    let free = || {
        std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map(|a| a.port())
            .expect("a free port")
    };
    let (node_port, down_port) = (free(), free());
    let app = spawn_app_with(|s| {
        s.memory_budget_bytes = 2 << 30;
        s.dicom.port = Some(node_port);
        s.dicom.dimse_timeout_secs = 3;
        s.dicom.peers = vec![ctrecon::dimse::Peer {
            ae_title: "DOWN".into(),
            host: "127.0.0.1".into(),
            port: down_port,
            store: true,
            query: true,
            retrieve: true,
        }];
    })
    .await;

    // A small phantom: 48 cone-beam views of the 3D Shepp–Logan (radius 14 mm), FDK on 32³ voxels of 1 mm.
    let dataset = app.simulate(cone_geometry(48, 48), 14.0).await;
    let recon = app
        .submit(&json!({"input": dataset, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 32, "ny": 32, "nz": 32, "spacing_mm": [1, 1, 1]}}))
        .await;
    let recon_id = recon["id"].as_str().expect("id").to_string();
    let done = app.finish(&recon_id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let mean = done["result"]["mean"].as_f64().expect("mean");

    // The renderings: a volume rendering (bone preset, 72 × 56) and a shaded surface at the volume's mean
    // (inside the head, above the air around it) seen from the left, rotating in 6 frames (64 × 48).
    let iso = (mean * 1e6).round() / 1e6;
    let job = app
        .submit(&json!({"kind": "volume", "input": recon_id, "products": [
            {"type": "volume_render", "preset": "bone", "size": [72, 56]},
            {"type": "surface_render", "units": "native", "surfaces": [{"iso": iso, "color": [0.9, 0.8, 0.6]}],
             "camera": {"view": "left", "elevation_deg": 20}, "size": [64, 48], "frames": 6}
        ]}))
        .await;
    let id = job["id"].as_str().expect("id").to_string();
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    let products = done["result"]["products"]
        .as_array()
        .expect("products")
        .clone();
    assert_eq!(products[0]["shape"], json!([1, 56, 72]));
    assert_eq!(products[1]["shape"], json!([6, 48, 64]));

    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    for (k, p) in products.iter().enumerate() {
        let card = format!(".render-product[data-index='{k}']");
        b.wait_for(&format!("{card}[data-frame='0'] img.render-still"), 60)
            .await;
        b.until(
            &format!("document.querySelector(\"{card} img.render-still\").complete"),
            10,
        )
        .await;
        assert_eq!(
            b.attr(&card, "data-type").await.as_deref(),
            p["type"].as_str()
        );
        let base = format!("/v1/jobs/{id}/result/products/{k}");
        let png = api_bytes(&app, &format!("{base}?format=png&frame=0"), "image/png").await;
        let still = format!("{card} img.render-still");
        assert_eq!(
            fetched_size(&b, &format!("/products/{k}?format=png&frame=0")).await,
            png.len() as u64,
            "product {k}: the page fetched the API's PNG"
        );
        let (w, h, frames) = decode_frames(&png);
        let (sw, sh, shown) = img_pixels(&b, &still).await;
        let size = &p["shape"];
        assert_eq!(
            (sw, sh),
            (w, h),
            "product {k}: the picture's size is the product's"
        );
        assert_eq!(
            (u64::from(w), u64::from(h)),
            (
                size[2].as_u64().expect("columns"),
                size[1].as_u64().expect("rows")
            )
        );
        assert!(
            shown == frames[0],
            "product {k}: the pixels shown are the PNG's"
        );
        let lit = frames[0]
            .chunks(4)
            .filter(|px| px[..3].iter().any(|&c| c > 8))
            .count();
        assert!(
            lit * 20 > (w * h) as usize,
            "product {k}: the phantom covers {lit} of {} pixels",
            w * h
        );
        // Parameters and orientation labels are the job's.
        assert_eq!(
            fact(&b, k, "description").await,
            p["description"].as_str().expect("text")
        );
        assert_eq!(fact(&b, k, "frames").await, size[0].to_string());
        assert_eq!(fact(&b, k, "size").await, format!("{w} × {h} px"));
        for side in ["top", "bottom", "left", "right"] {
            assert_eq!(
                b.text(&format!("{card} .orient-{side}")).await,
                p["orientation"][side].as_str().unwrap_or(""),
                "product {k}: the {side} label"
            );
        }
    }
    assert_eq!(fact(&b, 0, "preset").await, "bone");
    assert_eq!(fact(&b, 1, "surfaces").await, format!("iso {iso}"));
    assert!(
        fact(&b, 1, "camera")
            .await
            .starts_with("left view, azimuth 0°, elevation 20°")
    );
    let single = b
        .js(
            "return document.querySelector(\".render-product[data-index='0'] button.play\") === null;",
            vec![],
        )
        .await;
    assert_eq!(single, json!(true), "a single picture has no Play button");
    b.js(
        "document.getElementById('products').scrollIntoView();",
        vec![],
    )
    .await;
    b.shot("job-renderings").await;

    // Frame 4 of the rotation through the slider: the API's frame 4, not frame 0.
    let card = ".render-product[data-index='1']";
    b.js(
        "const s = document.querySelector(arguments[0] + ' input.frame'); s.value = '4';
         s.dispatchEvent(new Event('input'));",
        vec![json!(card)],
    )
    .await;
    b.wait_for(&format!("{card}[data-frame='4']"), 20).await;
    let base = format!("/v1/jobs/{id}/result/products/1");
    let png4 = api_bytes(&app, &format!("{base}?format=png&frame=4"), "image/png").await;
    let png0 = api_bytes(&app, &format!("{base}?format=png&frame=0"), "image/png").await;
    assert!(png4 != png0, "the rotation's frames differ");
    assert_eq!(
        fetched_size(&b, "/products/1?format=png&frame=4").await,
        png4.len() as u64
    );
    let (_, _, shown) = img_pixels(&b, &format!("{card} img.render-still")).await;
    assert!(shown == decode_frames(&png4).2[0]);
    assert_eq!(b.text(&format!("{card} .frame-label")).await, "frame 5 / 6");

    // Play: the API's animated PNG, all six frames, in place of the still.
    b.find(&format!("{card} button.play"))
        .await
        .click()
        .await
        .expect("play");
    b.wait_for(&format!("{card}[data-playing='true']"), 20)
        .await;
    b.until(
        &format!("document.querySelector(\"{card} img.render-apng\").complete && document.querySelector(\"{card} img.render-apng\").naturalWidth > 0"),
        20,
    )
    .await;
    let apng = api_bytes(&app, &format!("{base}?format=apng"), "image/apng").await;
    assert_eq!(
        fetched_size(&b, "/products/1?format=apng").await,
        apng.len() as u64
    );
    let (w, h, frames) = decode_frames(&apng);
    assert_eq!((w, h, frames.len()), (64, 48, 6));
    assert!(
        frames[4] == decode_frames(&png4).2[0],
        "APNG frame 4 is PNG frame 4"
    );
    // What the page shows: the APNG's first frame, pixel for pixel, where the page draws the image (a canvas
    // draws an animated image's first frame) ...
    let css = format!("{card} img.render-apng");
    b.js(
        "document.querySelector(arguments[0]).scrollIntoView({ block: 'center' });",
        vec![json!(css)],
    )
    .await;
    let drawn = animation_frames(&b, &css, 0).await;
    assert!(
        drawn.len() == 1 && drawn[0] == frames[0],
        "the APNG's first frame is drawn"
    );
    // ... and on screen it moves: screenshots of the element a loop apart differ (100 ms a frame).
    let mut seen: Vec<Vec<u8>> = Vec::new();
    for _ in 0..12 {
        let png = b
            .find(&css)
            .await
            .screenshot()
            .await
            .expect("element screenshot");
        let (_, _, px) = super::browser::decode_png(&png);
        if !seen.contains(&px) {
            seen.push(px);
        }
        tokio::time::sleep(std::time::Duration::from_millis(70)).await;
    }
    assert!(
        seen.len() >= 3,
        "the rotation plays: {} distinct pictures in 12 screenshots",
        seen.len()
    );
    let visible = b
        .js(
            "const c = document.querySelector(arguments[0]);
             return [c.querySelector('img.render-apng').hidden, c.querySelector('img.render-still').hidden];",
            vec![json!(card)],
        )
        .await;
    assert_eq!(
        visible,
        json!([false, true]),
        "the animation replaces the still"
    );
    b.shot("job-renderings-playing").await;

    // The downloads list the renderings' PNG, APNG, uint8 .npy and RGB Secondary Capture.
    let urls: Value = b
        .js(
            "return [...document.querySelectorAll('#downloads button[data-url]')].map((x) => x.dataset.url);",
            vec![],
        )
        .await;
    for want in [
        format!("{base}?format=png"),
        format!("{base}?format=apng"),
        format!("{base}?format=npy"),
        format!("{base}?format=dicom"),
    ] {
        assert!(
            urls.as_array()
                .expect("urls")
                .iter()
                .any(|u| u.as_str() == Some(want.as_str())),
            "{want} in {urls}"
        );
    }
    let not_apng = format!("/v1/jobs/{id}/result/products/0?format=apng");
    assert!(
        !urls
            .as_array()
            .expect("urls")
            .iter()
            .any(|u| u.as_str() == Some(not_apng.as_str())),
        "a single frame has no animation to download"
    );

    failed_job_page(&b, &app).await;
}

/// A job that fails at run time (the PACS it pulls its series from does not answer): its page follows it
/// to `failed` and shows the problem's title, detail and code, and its attempts, as the API records them.
async fn failed_job_page(b: &Browser, app: &TestApp) {
    let job = app
        .submit(&json!({"kind": "volume",
            "input": {"pacs": "DOWN", "series_instance_uid": "1.2.826.0.1.3680043.8.498.99"},
            "products": [{"type": "projection", "axis": "coronal", "kind": "mip"}]}))
        .await;
    let id = job["id"].as_str().expect("id").to_string();
    b.goto(&app.url(&format!("/#/job/{id}"))).await;
    b.wait_for("#job-status [data-status=failed]", 60).await;
    let done = app.finish(&id).await;
    assert_eq!(done["status"], "failed", "{done}");
    let error = &done["error"];
    assert_eq!(error["code"], "pull_failed", "{done}");
    b.wait_for("#job-error .error-title", 10).await;
    assert_eq!(
        b.text("#job-error .error-title").await,
        error["title"].as_str().expect("title")
    );
    assert_eq!(
        b.text("#job-error .error-detail").await,
        error["detail"].as_str().expect("detail")
    );
    assert_eq!(b.text("#job-error .error-code").await.trim(), "pull_failed");
    let attempts = b
        .js(
            "const dt = [...document.querySelectorAll('#job-summary dt')].find((d) => d.textContent === 'Attempts');
             return dt ? dt.nextElementSibling.textContent : null;",
            vec![],
        )
        .await;
    assert_eq!(attempts, json!(done["attempts"].to_string()), "{done}");
    // No results to show or download for a failed job.
    assert_eq!(
        b.js("return [document.getElementById('slice-panel'), document.getElementById('downloads')].every((e) => e === null);", vec![]).await,
        json!(true)
    );
    eprintln!(
        "failed job: {} — {}",
        error["title"].as_str().unwrap_or(""),
        error["detail"].as_str().unwrap_or("")
    );
    b.shot("job-failed").await;
}
