//! What the page tests share: the API's and the page's job lists, choosing an option and clicking as a user
//! does, moving through the page with Tab and keys, the fit of the page in a narrow window, and long-running
//! jobs.

use std::time::Duration;

use fantoccini::actions::{InputSource, KeyAction, KeyActions};
use fantoccini::key::Key;
use serde_json::{Value, json};

use super::browser::Browser;
use super::common::TestApp;

/// Ids of `GET /v1/jobs?{query}`, sorted.
pub async fn api_ids(app: &TestApp, query: &str) -> Vec<String> {
    let v: Value = app
        .get(&format!("/v1/jobs?limit=200&{query}"))
        .await
        .json()
        .await
        .expect("json");
    let mut ids: Vec<String> = v["jobs"]
        .as_array()
        .expect("jobs")
        .iter()
        .map(|j| j["id"].as_str().expect("id").to_string())
        .collect();
    ids.sort();
    ids
}

/// Ids of the rows the page lists, sorted.
pub async fn page_ids(b: &Browser) -> Vec<String> {
    let v = b
        .js(
            "return [...document.querySelectorAll('#jobs-table tbody tr[data-id]')].map((r) => r.dataset.id).sort();",
            vec![],
        )
        .await;
    serde_json::from_value(v).expect("ids")
}

/// Set a `<select>` as a user would (value, then `change`).
pub async fn choose(b: &Browser, css: &str, value: &str) {
    b.js(
        "const s = document.querySelector(arguments[0]); s.value = arguments[1];
         if (s.value !== arguments[1]) return false;
         s.dispatchEvent(new Event('change', { bubbles: true })); return true;",
        vec![json!(css), json!(value)],
    )
    .await
    .as_bool()
    .filter(|&ok| ok)
    .unwrap_or_else(|| panic!("{css} has no option {value}"));
}

/// Wait until the list shows exactly `want` (sorted ids).
pub async fn list_shows(b: &Browser, want: &[String], what: &str) {
    let text = serde_json::to_string(want).expect("json");
    let script = format!(
        "return JSON.stringify([...document.querySelectorAll('#jobs-table tbody tr[data-id]')].map((r) => r.dataset.id).sort()) === {};",
        serde_json::to_string(&text).expect("json")
    );
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while b.js(&script, vec![]).await != json!(true) {
        assert!(
            std::time::Instant::now() < deadline,
            "{what}: the page lists {:?}, the API {want:?}",
            page_ids(b).await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A 2D SIRT of 100 000 iterations: runs until it is canceled.
pub async fn endless(app: &TestApp, input: &str) -> String {
    let j = app
        .submit(
            &json!({"input": input, "algorithm": {"name": "sirt", "iterations": 100000},
                        "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await;
    j["id"].as_str().expect("id").to_string()
}

pub async fn status_of(app: &TestApp, id: &str) -> Value {
    app.job(id).await["status"].clone()
}

pub async fn click(b: &Browser, css: &str) {
    b.find(css).await.click().await.expect("click");
}

/// Press one key (a character or a `fantoccini::key::Key`) on whatever has the focus.
pub async fn press(b: &Browser, key: char) {
    let keys = KeyActions::new("keyboard".into())
        .then(KeyAction::Down { value: key })
        .then(KeyAction::Up { value: key });
    b.client.perform_actions(keys).await.expect("a key press");
}

/// Press Tab until the focused element matches `css` (at most `max` presses), as a keyboard-only user moves
/// through the page; returns how many presses it took.
pub async fn tab_to(b: &Browser, css: &str, max: usize) -> usize {
    let mut seen = Vec::new();
    for n in 1..=max {
        press(b, char::from(Key::Tab)).await;
        let v = b
            .js(
                "const e = document.activeElement;
                 return [e.matches(arguments[0]), e.tagName + (e.id ? '#' + e.id : '') + '.' + e.className];",
                vec![json!(css)],
            )
            .await;
        if v[0] == json!(true) {
            return n;
        }
        seen.push(v[1].as_str().unwrap_or("").to_string());
    }
    panic!("Tab never reached {css} in {max} presses; focus went {seen:?}");
}

/// The page is no wider than the window (no horizontal scrolling), and each of `controls` is shown whole
/// inside it.
pub async fn fits_the_window(b: &Browser, what: &str, controls: &[&str]) {
    let v = b
        .js(
            "const s = document.scrollingElement;
             return [s.scrollWidth, innerWidth, arguments[0].map((css) => {
               const e = document.querySelector(css); if (!e) return [css, 'missing'];
               const r = e.getBoundingClientRect(); const st = getComputedStyle(e);
               const shown = r.width > 0 && r.height > 0 && r.left >= -0.5 && r.right <= innerWidth + 0.5
                 && st.visibility !== 'hidden' && st.display !== 'none';
               return shown ? null : [css, [r.left, r.right, r.width, r.height, st.visibility]];
             }).filter((x) => x)];",
            vec![json!(controls)],
        )
        .await;
    let (scroll, inner) = (v[0].as_f64().expect("width"), v[1].as_f64().expect("width"));
    assert!(
        scroll <= inner,
        "{what}: the page is {scroll} px wide in a {inner} px window"
    );
    assert_eq!(v[2], json!([]), "{what}: controls not shown whole");
}
