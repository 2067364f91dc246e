//! The slice viewer's three planes against the API's series volume and frame: the value and the LPS position
//! in mm under the pointer in each plane (origin + index × spacing along the direction), linked crosshairs
//! (a click in one plane moves the other two to the matching slice, which they then show, and draws the
//! crosshair at the matching pixel in each), the scale bar's length against the pixel spacing and the zoom,
//! and the wheel (one slice per notch).

use fantoccini::actions::{
    InputSource, MOUSE_BUTTON_LEFT, MouseActions, PointerAction, WheelAction, WheelActions,
};
use serde_json::{Value, json};

use super::browser::Browser;
use super::flow::{window, window_grey};
use super::renders::base64_decode;

/// The series' frame (LPS, mm) and its volume `[z][y][x]`.
pub struct Series<'a> {
    pub origin: [f64; 3],
    pub spacing: [f64; 3],
    /// Rows: the directions of the i, j and k index axes.
    pub direction: [[f64; 3]; 3],
    /// `[nx, ny, nz]`.
    pub n: [usize; 3],
    pub data: &'a [f32],
}

impl<'a> Series<'a> {
    pub fn new(frame: &Value, shape: &[usize], data: &'a [f32]) -> Self {
        fn v<T: serde::de::DeserializeOwned>(x: &Value) -> T {
            serde_json::from_value(x.clone()).expect("a frame")
        }
        Series {
            origin: v(&frame["origin_mm"]),
            spacing: v(&frame["spacing_mm"]),
            direction: v(&frame["direction"]),
            n: [shape[2], shape[1], shape[0]],
            data,
        }
    }

    fn value(&self, [i, j, k]: [usize; 3]) -> f32 {
        self.data[(k * self.n[1] + j) * self.n[0] + i]
    }

    /// LPS position (mm) of voxel `[i, j, k]`: origin + Σ index × spacing × direction.
    fn position(&self, v: [usize; 3]) -> [f64; 3] {
        std::array::from_fn(|c| {
            self.origin[c]
                + (0..3)
                    .map(|a| v[a] as f64 * self.spacing[a] * self.direction[a][c])
                    .sum::<f64>()
        })
    }
}

const PLANES: [&str; 3] = ["axial", "coronal", "sagittal"];

/// Voxel of image pixel (column, row) of `plane` at slice `index` (rows of coronal and sagittal run from
/// superior to inferior).
fn voxel(plane: &str, n: [usize; 3], index: usize, col: usize, row: usize) -> [usize; 3] {
    match plane {
        "axial" => [col, row, index],
        "coronal" => [col, index, n[2] - 1 - row],
        _ => [index, col, n[2] - 1 - row],
    }
}

/// Image pixel (column, row) of voxel `v` in `plane`, and the index of the slice through it.
fn pixel_of(plane: &str, n: [usize; 3], v: [usize; 3]) -> (usize, usize, usize) {
    match plane {
        "axial" => (v[0], v[1], v[2]),
        "coronal" => (v[0], n[2] - 1 - v[2], v[1]),
        _ => (v[1], n[2] - 1 - v[2], v[0]),
    }
}

/// Mm per image column of `plane`.
fn column_mm(plane: &str, spacing: [f64; 3]) -> f64 {
    if plane == "sagittal" {
        spacing[1]
    } else {
        spacing[0]
    }
}

async fn index(b: &Browser, plane: &str) -> usize {
    b.attr(&format!(".view-{plane}"), "data-index")
        .await
        .expect("data-index")
        .parse()
        .expect("an index")
}

/// Move the pointer (dx, dy) CSS pixels from the centre of `plane`'s image and read what the readout says:
/// the voxel, the value, the position (mm) and the text. Checks the voxel is the one under the pointer.
async fn hover(
    b: &Browser,
    s: &Series<'_>,
    plane: &str,
    dx: f64,
    dy: f64,
) -> ([usize; 3], f32, [f64; 3], String) {
    let css = format!(".view-{plane} canvas.image");
    let rect = b
        .js(
            "const c = document.querySelector(arguments[0]); const r = c.getBoundingClientRect();
             const ro = c.closest('.view').querySelector('.readout');
             for (const k of ['i', 'j', 'k', 'value', 'positionMm']) delete ro.dataset[k];
             return [r.width, r.height, c.width, c.height];",
            vec![json!(css)],
        )
        .await;
    let f = |k: usize| rect[k].as_f64().expect("number");
    let canvas = b.find(&css).await;
    let hover = MouseActions::new("mouse".into()).then(PointerAction::MoveToElement {
        element: canvas,
        duration: None,
        x: dx,
        y: dy,
    });
    b.client.perform_actions(hover).await.expect("hover");
    let ro = format!(".view-{plane} .readout");
    b.until(
        &format!("document.querySelector('{ro}').dataset.positionMm"),
        10,
    )
    .await;
    let at = |name: &'static str| {
        let ro = &ro;
        async move { b.attr(ro, name).await.expect(name) }
    };
    let v: [usize; 3] = [
        at("data-i").await.parse().expect("i"),
        at("data-j").await.parse().expect("j"),
        at("data-k").await.parse().expect("k"),
    ];
    let col = ((f(0) / 2.0 + dx) / f(0) * f(2)).floor() as usize;
    let row = ((f(1) / 2.0 + dy) / f(1) * f(3)).floor() as usize;
    let want = voxel(plane, s.n, index(b, plane).await, col, row);
    let (_, _, slice) = pixel_of(plane, s.n, want);
    let (_, _, got_slice) = pixel_of(plane, s.n, v);
    assert_eq!(
        got_slice, slice,
        "{plane}: the readout is on the shown slice"
    );
    assert!(
        (0..3).all(|a| v[a].abs_diff(want[a]) <= 1),
        "{plane}: pointer over voxel {want:?}, the readout says {v:?}"
    );
    let value: f32 = at("data-value").await.parse().expect("value");
    let pos: Vec<f64> = at("data-position-mm")
        .await
        .split(',')
        .map(|x| x.parse().expect("mm"))
        .collect();
    (v, value, [pos[0], pos[1], pos[2]], b.text(&ro).await)
}

/// The crosshair in `plane`'s overlay: (column, row) of the overlay pixels it lights most, and how many
/// pixels light that column and that row, and the overlay's size.
async fn crosshair(b: &Browser, plane: &str) -> [usize; 6] {
    let v = b
        .js(
            "const c = document.querySelector(`.view-${arguments[0]} canvas.overlay`);
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
             const cols = new Array(c.width).fill(0); const rows = new Array(c.height).fill(0);
             for (let y = 0; y < c.height; y += 1) for (let x = 0; x < c.width; x += 1)
               if (d[(y * c.width + x) * 4 + 3] > 0) { cols[x] += 1; rows[y] += 1; }
             const top = (a) => a.indexOf(Math.max(...a));
             return [top(cols), top(rows), Math.max(...cols), Math.max(...rows), c.width, c.height];",
            vec![json!(plane)],
        )
        .await;
    serde_json::from_value(v).expect("numbers")
}

/// `plane`'s image is slice `index` of the volume through the current window, pixel for pixel.
async fn shows_slice(b: &Browser, s: &Series<'_>, plane: &str, index: usize) {
    let (ww, wl) = window(b).await;
    let v = b
        .js(
            "const c = document.querySelector(`.view-${arguments[0]} canvas.image`);
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
             let t = ''; for (let x = 0; x < d.length; x += 4) t += String.fromCharCode(d[x]);
             return [c.width, btoa(t)];",
            vec![json!(plane)],
        )
        .await;
    let cols = v[0].as_u64().expect("width") as usize;
    let shown = base64_decode(v[1].as_str().expect("pixels"));
    let mut exact = 0;
    for (n, &g) in shown.iter().enumerate() {
        let want = window_grey(
            s.value(voxel(plane, s.n, index, n % cols, n / cols)),
            ww,
            wl,
        );
        assert!(
            want.abs_diff(g) <= 1,
            "{plane} slice {index}, pixel ({}, {}): {g} shown, {want} wanted",
            n % cols,
            n / cols
        );
        exact += usize::from(want == g);
    }
    assert!(
        exact * 1000 >= shown.len() * 999,
        "{plane}: {exact} of {} exact",
        shown.len()
    );
}

/// Click (dx, dy) from the centre of `plane`'s image: every plane moves to the clicked voxel, shows its
/// slice and draws the crosshair at its pixel.
async fn click_links(b: &Browser, s: &Series<'_>, plane: &str, dx: f64, dy: f64) -> [usize; 3] {
    let (v, ..) = hover(b, s, plane, dx, dy).await;
    let canvas = b.find(&format!(".view-{plane} canvas.image")).await;
    let click = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: canvas,
            duration: None,
            x: dx,
            y: dy,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::Up {
            button: MOUSE_BUTTON_LEFT,
        });
    b.client.perform_actions(click).await.expect("click");
    for other in PLANES {
        let (col, row, slice) = pixel_of(other, s.n, v);
        b.until(
            &format!("document.querySelector('.view-{other}').dataset.index === '{slice}'"),
            10,
        )
        .await;
        // Where the crosshair belongs in the overlay (CSS pixels): the middle of the voxel's image pixel,
        // rounded as the page draws it. The overlay is drawn on the next animation frame.
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        let (want, [x, y, lit_col, lit_row, w, h]) = loop {
            let c = crosshair(b, other).await;
            let at = |i: usize, count: usize, size: usize| {
                ((i as f64 + 0.5) / count as f64 * size as f64 + 0.5).floor() as usize
            };
            let want = (
                at(col, canvas_cols(s.n, other), c[4]),
                at(row, canvas_rows(s.n, other), c[5]),
            );
            if (c[0], c[1]) == want || std::time::Instant::now() > deadline {
                break (want, c);
            }
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        };
        assert_eq!(
            (x, y),
            want,
            "{other}: the crosshair of voxel {v:?} (image pixel {col}, {row}) in a {w} × {h} overlay"
        );
        // Dashed 4 on, 4 off: about half of each line's pixels are lit.
        assert!(
            lit_col * 10 >= h * 4 && lit_row * 10 >= w * 4,
            "{other}: {lit_col} of {h} and {lit_row} of {w} pixels lit"
        );
        if other != plane {
            shows_slice(b, s, other, slice).await;
        }
    }
    v
}

fn canvas_cols(n: [usize; 3], plane: &str) -> usize {
    if plane == "sagittal" { n[1] } else { n[0] }
}

fn canvas_rows(n: [usize; 3], plane: &str) -> usize {
    if plane == "axial" { n[1] } else { n[2] }
}

/// Each plane's scale bar: a round length (the largest of 1, 2, 5, 10, 20, 25, 50, 100, 200, 500 mm within a
/// quarter of the image's width) drawn as long as that many mm are on screen at the current zoom.
pub async fn scale_bars(b: &Browser, spacing: [f64; 3], n: [usize; 3], what: &str) {
    const STEPS: [f64; 10] = [1.0, 2.0, 5.0, 10.0, 20.0, 25.0, 50.0, 100.0, 200.0, 500.0];
    for plane in PLANES {
        let v = b
            .js(
                "const v = document.querySelector(`.view-${arguments[0]}`);
                 return [v.querySelector('.scalebar-line').getBoundingClientRect().width,
                         Number(v.querySelector('.scalebar').dataset.mm),
                         v.querySelector('canvas.image').getBoundingClientRect().width,
                         v.querySelector('.scalebar-text').textContent];",
                vec![json!(plane)],
            )
            .await;
        let (px, mm, css_w) = (
            v[0].as_f64().expect("px"),
            v[1].as_f64().expect("mm"),
            v[2].as_f64().expect("width"),
        );
        let width_mm = canvas_cols(n, plane) as f64 * column_mm(plane, spacing);
        let want_px = mm * css_w / width_mm;
        assert!(
            (px - want_px).abs() <= 1.0,
            "{what}, {plane}: a {mm} mm bar is {px} px; {css_w} px show {width_mm} mm, so {want_px:.2} px"
        );
        let quarter = width_mm / 4.0;
        let want_mm = STEPS
            .iter()
            .copied()
            .filter(|&s| s <= quarter * 1.005)
            .fold(STEPS[0], f64::max);
        assert_eq!(mm, want_mm, "{what}, {plane}: {width_mm} mm wide");
        assert_eq!(v[3], json!(format!("{mm} mm")), "{what}, {plane}");
        eprintln!(
            "{what}, {plane}: {mm} mm bar of {px} px ({:.4} mm per screen px)",
            width_mm / css_w
        );
    }
}

pub async fn planes(b: &Browser, s: &Series<'_>) {
    // The readout in each plane: the voxel under the pointer, its value and its LPS position.
    for (plane, dx, dy) in [
        ("axial", 40.0, -25.0),
        ("coronal", -35.0, 30.0),
        ("sagittal", 25.0, 45.0),
    ] {
        let (v, value, pos, text) = hover(b, s, plane, dx, dy).await;
        assert_eq!(value, s.value(v), "{plane}: the value of voxel {v:?}");
        let want = s.position(v);
        for c in 0..3 {
            assert!(
                (pos[c] - want[c]).abs() < 1e-6,
                "{plane}: voxel {v:?} is at {want:?} mm, the readout says {pos:?}"
            );
        }
        // The text shows the same position to 0.1 mm and the value in HU.
        let inside = text
            .split_once("LPS (")
            .and_then(|(_, r)| r.split_once(") mm"))
            .map(|(p, _)| p)
            .unwrap_or_else(|| panic!("{plane}: no LPS position in {text:?}"));
        let shown: Vec<f64> = inside.split(", ").map(|x| x.parse().expect("mm")).collect();
        for c in 0..3 {
            assert!(
                (shown[c] - want[c]).abs() <= 0.051,
                "{plane}: {text:?} vs {want:?}"
            );
        }
        assert!(
            text.starts_with(&format!("{} HU", value.round())),
            "{plane}: {text:?}"
        );
        eprintln!("{plane}: voxel {v:?} = {value} HU at LPS {want:?} mm");
    }

    // Linked crosshairs: a click in the axial plane, then one in the sagittal plane.
    let a = click_links(b, s, "axial", -60.0, 35.0).await;
    let c = click_links(b, s, "sagittal", 30.0, -40.0).await;
    assert_eq!(
        c[0], a[0],
        "a click in the sagittal plane keeps its own slice"
    );
    b.shot("series-crosshairs").await;

    scale_bars(b, s.spacing, s.n, "1280 × 800").await;
}

/// Wheel notches over `plane`: each moves one slice (towards superior for a notch away from the user), and
/// the page itself does not scroll.
pub async fn wheel(b: &Browser, plane: &str) {
    let centre = b
        .js(
            "const r = document.querySelector(`.view-${arguments[0]} canvas.image`).getBoundingClientRect();
             return [Math.round(r.left + r.width / 2), Math.round(r.top + r.height / 2), scrollY];",
            vec![json!(plane)],
        )
        .await;
    let (x, y) = (
        centre[0].as_i64().expect("x"),
        centre[1].as_i64().expect("y"),
    );
    let start = index(b, plane).await;
    for (notches, delta, want) in [(5, -100, start + 5), (2, 100, start + 3)] {
        let mut wheel = WheelActions::new("wheel".into());
        for _ in 0..notches {
            wheel.push(WheelAction::Scroll {
                duration: None,
                x,
                y,
                delta_x: 0,
                delta_y: delta,
            });
        }
        b.client.perform_actions(wheel).await.expect("wheel");
        b.until(
            &format!("document.querySelector('.view-{plane}').dataset.index === '{want}'"),
            10,
        )
        .await;
    }
    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    assert_eq!(index(b, plane).await, start + 3, "5 notches up, 2 down");
    assert_eq!(
        b.js("return scrollY", vec![]).await,
        centre[2],
        "the wheel scrolls the slices, not the page"
    );
}
