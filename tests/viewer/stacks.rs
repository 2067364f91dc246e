//! Image stacks on the job page (MIP/MinIP projections, thick-slab MPRs, rotating MIPs) against the API: the
//! frame a stack shows is the product's `.npy` values at that frame through the window preset chosen beside
//! it, pixel for pixel.

use serde_json::json;

use super::browser::Browser;
use super::common::{TestApp, read_npy_f32};
use super::flow::window_grey;
use super::renders::base64_decode;

/// Width and level (HU) of the page's window presets.
fn preset(name: &str) -> (f64, f64) {
    match name {
        "soft_tissue" => (400.0, 40.0),
        "lung" => (1500.0, -600.0),
        "liver" => (150.0, 90.0),
        "bone" => (2500.0, 480.0),
        "brain" => (80.0, 40.0),
        other => panic!("no window preset {other}"),
    }
}

/// The frame stack `index` of job `job` shows, checked against the API's `.npy` of the product through the
/// preset chosen beside it (a grey level off by one where the two roundings of a boundary value differ, no
/// more); returns `(frame, pixels compared)`.
pub async fn stack_matches(
    b: &Browser,
    app: &TestApp,
    token: Option<&str>,
    job: &str,
    index: usize,
) -> (usize, usize) {
    let v = b
        .js(
            "const el = document.querySelector(`.product[data-index='${arguments[0]}']`);
             const c = el.querySelector('canvas.product-image');
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
             let s = ''; for (let x = 0; x < d.length; x += 4) s += String.fromCharCode(d[x]);
             return [Number(el.dataset.frame), el.querySelector('select.preset').value, c.width, c.height, btoa(s)];",
            vec![json!(index)],
        )
        .await;
    let frame = v[0].as_u64().expect("frame") as usize;
    let (ww, wl) = preset(v[1].as_str().expect("preset"));
    let (cols, rows) = (
        v[2].as_u64().expect("width") as usize,
        v[3].as_u64().expect("height") as usize,
    );
    let shown = base64_decode(v[4].as_str().expect("pixels"));
    let path = format!("/v1/jobs/{job}/result/products/{index}?format=npy");
    let mut req = app.client.get(app.url(&path));
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let r = req.send().await.expect("request");
    assert_eq!(r.status(), 200, "{path}");
    let (shape, data) = read_npy_f32(&r.bytes().await.expect("body"));
    let shape = if shape.len() == 2 {
        vec![1, shape[0], shape[1]]
    } else {
        shape
    };
    assert_eq!(
        (shape[1], shape[2]),
        (rows, cols),
        "product {index}: the canvas is the product's image size"
    );
    assert!(
        frame < shape[0],
        "product {index}: frame {frame} of {shape:?}"
    );
    let values = &data[frame * rows * cols..(frame + 1) * rows * cols];
    let mut exact = 0;
    for (n, (&v, &g)) in values.iter().zip(&shown).enumerate() {
        let want = window_grey(v, ww, wl);
        assert!(
            want.abs_diff(g) <= 1,
            "product {index}, frame {frame}, pixel ({}, {}): value {v} is grey {want} in W {ww} L {wl}, the page shows {g}",
            n % cols,
            n / cols
        );
        exact += usize::from(want == g);
    }
    assert!(
        exact * 1000 >= values.len() * 999,
        "product {index}: {exact} of {} pixels exact",
        values.len()
    );
    // Not a blank picture: the window shows structure.
    let levels = shown
        .iter()
        .fold([false; 256], |mut seen, &g| {
            seen[usize::from(g)] = true;
            seen
        })
        .iter()
        .filter(|&&s| s)
        .count();
    assert!(levels >= 8, "product {index}: {levels} grey levels shown");
    (frame, values.len())
}

/// Play stack `index` as a loop: the shown frame advances by one (wrapping) and the picture changes; Pause
/// holds a frame, which is then the API's.
pub async fn plays(b: &Browser, app: &TestApp, token: Option<&str>, job: &str, index: usize) {
    let card = format!(".product[data-index='{index}']");
    b.js(
        "document.querySelector(arguments[0]).scrollIntoView({ block: 'center' });",
        vec![json!(card)],
    )
    .await;
    b.find(&format!("{card} button.play"))
        .await
        .click()
        .await
        .expect("play");
    b.wait_for(&format!("{card}[data-playing='true']"), 10)
        .await;
    // What is shown every 40 ms: the frame and a sum of the canvas' grey levels, until six frames went by
    // (at most 8 s: a loaded machine slows the loop down, it does not stop it).
    let seen = b
        .client
        .execute_async(
            "const [css, done] = [arguments[0], arguments[arguments.length - 1]];
             const el = document.querySelector(css); const c = el.querySelector('canvas.product-image');
             const out = []; const t0 = performance.now();
             const look = () => {
               const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
               let sum = 0; for (let x = 0; x < d.length; x += 16) sum += d[x];
               out.push([Number(el.dataset.frame), sum]);
               const frames = new Set(out.map((o) => o[0])).size;
               if (frames < 6 && performance.now() - t0 < 8000) setTimeout(look, 40); else done(out);
             };
             look();",
            vec![json!(card)],
        )
        .await
        .expect("watch the loop");
    let seen: Vec<(usize, u64)> = serde_json::from_value(seen).expect("frames");
    let frames = b
        .attr(&format!("{card} input.frame"), "max")
        .await
        .expect("max")
        .parse::<usize>()
        .expect("a count")
        + 1;
    let mut distinct: Vec<usize> = seen.iter().map(|s| s.0).collect();
    distinct.sort_unstable();
    distinct.dedup();
    let mut pictures: Vec<u64> = seen.iter().map(|s| s.1).collect();
    pictures.sort_unstable();
    pictures.dedup();
    assert!(
        distinct.len() >= 4 && pictures.len() >= 4,
        "the loop plays: frames {distinct:?}, {} distinct pictures in {} looks",
        pictures.len(),
        seen.len()
    );
    for w in seen.windows(2) {
        let step = (w[1].0 + frames - w[0].0) % frames;
        // Between two looks the loop moved on by a frame or a few (80 ms a frame), never backwards.
        assert!(step <= frames / 2, "frame {} then {}", w[0].0, w[1].0);
    }
    b.find(&format!("{card} button.play"))
        .await
        .click()
        .await
        .expect("pause");
    b.wait_for(&format!("{card}[data-playing='false']"), 10)
        .await;
    let held = b.attr(&card, "data-frame").await.expect("frame");
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    assert_eq!(
        b.attr(&card, "data-frame").await.expect("frame"),
        held,
        "paused"
    );
    let (frame, _) = stack_matches(b, app, token, job, index).await;
    // The letters around the picture are the API's sides of the frame shown: the held one, and a quarter
    // turn on (for a rotation, seen from the side: other letters than the first frame's).
    let quarter = (frame + frames / 4) % frames;
    let held_sides = letters_match(b, app, token, job, index, frame).await;
    let quarter_sides = letters_match(b, app, token, job, index, quarter).await;
    if frames >= 4 && b.attr(&card, "data-type").await.as_deref() == Some("rotating") {
        assert_ne!(
            held_sides, quarter_sides,
            "frames {frame} and {quarter} of a rotation are seen from different sides"
        );
    }
    eprintln!(
        "loop of {frames} frames: {} frames and {} pictures seen in {} looks, paused at frame {frame}",
        distinct.len(),
        pictures.len(),
        seen.len()
    );
}

/// Step stack `index` to `frame` with its slider; the four letters around the picture must be the API's
/// sides of that frame (`frame_orientations[frame]`, else `orientation`). Returns them.
async fn letters_match(
    b: &Browser,
    app: &TestApp,
    token: Option<&str>,
    job: &str,
    index: usize,
    frame: usize,
) -> serde_json::Value {
    let shown = b
        .js(
            "const el = document.querySelector(`.product[data-index='${arguments[0]}']`);
             const s = el.querySelector('input.frame');
             s.value = String(arguments[1]); s.dispatchEvent(new Event('input'));
             return [Number(el.dataset.frame), Object.fromEntries([...el.querySelectorAll('span.orient')]
               .map((o) => [o.dataset.side, o.textContent]))];",
            vec![json!(index), json!(frame)],
        )
        .await;
    assert_eq!(
        shown[0],
        json!(frame),
        "product {index}: stepped to frame {frame}"
    );
    let mut req = app.client.get(app.url(&format!("/v1/jobs/{job}")));
    if let Some(t) = token {
        req = req.bearer_auth(t);
    }
    let j: serde_json::Value = req
        .send()
        .await
        .expect("request")
        .json()
        .await
        .expect("job");
    let p = &j["result"]["products"][index];
    let want = p["frame_orientations"]
        .get(frame)
        .unwrap_or(&p["orientation"]);
    for side in ["left", "right", "top", "bottom"] {
        assert_eq!(
            shown[1][side], want[side],
            "product {index}, frame {frame}: the {side} letter"
        );
    }
    shown[1].clone()
}
