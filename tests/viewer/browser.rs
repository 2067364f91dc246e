//! Headless Chromium driven over WebDriver: chromedriver on a free loopback port, one session per test,
//! stopped in a drop guard. Without Chromium or chromedriver a test prints one skip line and passes, unless
//! `CTRECON_REQUIRE_PEERS=1` (CI), where it fails.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::elements::Element;
use fantoccini::{Client, ClientBuilder, Locator};
use hyper_util::client::legacy::connect::HttpConnector;
use serde_json::{Value, json};

pub struct Browser {
    pub client: Client,
    driver: Child,
}

impl Drop for Browser {
    /// Stop chromedriver and the Chromium it started: they share a process group of their own.
    fn drop(&mut self) {
        let group = format!("-{}", self.driver.id());
        let _ = Command::new("kill").args(["-TERM", "--", &group]).status();
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH").and_then(|paths| {
        std::env::split_paths(&paths)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

/// Skip (one line) or, with `CTRECON_REQUIRE_PEERS=1`, fail.
pub fn skip(test: &str, why: &str) {
    assert!(
        std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
        "{test}: {why}, and CTRECON_REQUIRE_PEERS=1 (run scripts/install-peers.sh)"
    );
    eprintln!("SKIPPED {test}: {why} (scripts/install-peers.sh installs it)");
}

include!("../common/ports.rs");

/// Start chromedriver and a headless Chromium session of `width` × `height`; `None` (after the skip line)
/// when they are not installed.
pub async fn start(test: &str, width: u32, height: u32) -> Option<Browser> {
    let (Some(driver_bin), Some(_)) = (
        which("chromedriver"),
        which("chromium").or_else(|| which("chromium-browser")),
    ) else {
        skip(test, "chromium or chromedriver is not installed");
        return None;
    };
    let port = free_port();
    let driver = Command::new(driver_bin)
        .arg(format!("--port={port}"))
        .process_group(0)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("chromedriver starts");
    let url = format!("http://127.0.0.1:{port}");
    let deadline = Instant::now() + Duration::from_secs(30);
    let http = reqwest::Client::new();
    while http.get(format!("{url}/status")).send().await.is_err() {
        assert!(Instant::now() < deadline, "chromedriver did not answer");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let caps = json!({"goog:chromeOptions": {"args": [
        "--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--disable-dev-shm-usage",
        "--use-gl=angle", "--use-angle=swiftshader", format!("--window-size={width},{height}")
    ]}});
    let caps = match caps {
        Value::Object(m) => m,
        _ => unreachable!(),
    };
    let client = ClientBuilder::new(HttpConnector::new())
        .capabilities(caps)
        .connect(&url)
        .await
        .expect("a Chromium session");
    Some(Browser { client, driver })
}

/// Where screenshots go: `CTRECON_SCREENSHOT_DIR`, or `screenshots/` in the cargo target directory.
pub fn screenshot_dir() -> PathBuf {
    let dir = std::env::var_os("CTRECON_SCREENSHOT_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_TARGET_TMPDIR"))
                .parent()
                .unwrap_or(Path::new("."))
                .join("screenshots")
        });
    std::fs::create_dir_all(&dir).expect("screenshot directory");
    dir
}

impl Browser {
    pub async fn goto(&self, url: &str) {
        self.client.goto(url).await.expect("navigate");
    }

    /// The first element matching `css`, waiting at most `secs` seconds for it.
    pub async fn wait_for(&self, css: &str, secs: u64) -> Element {
        match self
            .client
            .wait()
            .at_most(Duration::from_secs(secs))
            .every(Duration::from_millis(50))
            .for_element(Locator::Css(css))
            .await
        {
            Ok(e) => e,
            Err(e) => {
                let body = self.text("body").await;
                panic!("no {css} after {secs} s ({e}); the page says:\n{body}")
            }
        }
    }

    pub async fn find(&self, css: &str) -> Element {
        self.client
            .find(Locator::Css(css))
            .await
            .unwrap_or_else(|e| panic!("no {css}: {e}"))
    }

    pub async fn text(&self, css: &str) -> String {
        match self.client.find(Locator::Css(css)).await {
            Ok(e) => e.text().await.unwrap_or_default(),
            Err(_) => String::new(),
        }
    }

    pub async fn attr(&self, css: &str, name: &str) -> Option<String> {
        self.find(css).await.attr(name).await.expect("attribute")
    }

    pub async fn js(&self, script: &str, args: Vec<Value>) -> Value {
        self.client
            .execute(script, args)
            .await
            .unwrap_or_else(|e| panic!("script failed: {e}\n{script}"))
    }

    /// Poll a script until it returns a truthy value (at most `secs` seconds).
    pub async fn until(&self, script: &str, secs: u64) -> Value {
        let deadline = Instant::now() + Duration::from_secs(secs);
        let body = if script.contains("return") {
            script.to_string()
        } else {
            format!("return ({script});")
        };
        loop {
            let v = self.js(&body, vec![]).await;
            if !(v.is_null() || v == json!(false) || v == json!("") || v == json!(0)) {
                return v;
            }
            if Instant::now() > deadline {
                let body = self.text("body").await;
                panic!("not true after {secs} s: {script}\nthe page says:\n{body}");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Save a screenshot of the whole window as `<dir>/<name>.png`; returns the PNG bytes.
    pub async fn shot(&self, name: &str) -> Vec<u8> {
        let png = self.client.screenshot().await.expect("screenshot");
        let path = screenshot_dir().join(format!("{name}.png"));
        std::fs::write(&path, &png).expect("write screenshot");
        png
    }
}

/// Decode a PNG screenshot into RGBA rows: (width, height, pixels).
pub fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut dec = png::Decoder::new(std::io::Cursor::new(bytes));
    dec.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = dec.read_info().expect("png header");
    let mut buf = vec![0; reader.output_buffer_size().expect("png size")];
    let info = reader.next_frame(&mut buf).expect("png frame");
    buf.truncate(info.buffer_size());
    let rgba = match info.color_type {
        png::ColorType::Rgba => buf,
        png::ColorType::Rgb => buf
            .chunks(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        other => panic!("unexpected screenshot colour type {other:?}"),
    };
    (info.width, info.height, rgba)
}
