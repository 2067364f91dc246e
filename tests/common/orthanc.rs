//! A real Orthanc for tests: its own config, storage and ports in a temp dir, started on demand, ready when
//! `GET /system` answers, stopped (SIGKILL, then waited for) by a drop guard.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

pub const ORTHANC: &str = "/usr/sbin/Orthanc";

/// Whether Orthanc is installed; without it, one skip line (or a failure under CTRECON_REQUIRE_PEERS=1).
pub fn orthanc_present() -> bool {
    let ok = Path::new(ORTHANC).is_file()
        && ["storescu", "echoscu"]
            .iter()
            .all(|t| Command::new(t).arg("--version").output().is_ok());
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "Orthanc or DCMTK is missing and CTRECON_REQUIRE_PEERS=1 (scripts/install-peers.sh)"
        );
        eprintln!(
            "skipped: Orthanc or DCMTK is not installed (scripts/install-peers.sh orthanc dcmtk)"
        );
    }
    ok
}

include!("ports.rs");

/// A running Orthanc.
pub struct Orthanc {
    child: Option<Child>,
    pub dir: tempfile::TempDir,
    pub http_port: u16,
    pub dicom_port: u16,
    pub ae_title: String,
    pub client: reqwest::Client,
}

impl Drop for Orthanc {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// How to start Orthanc.
#[derive(Default)]
pub struct OrthancOptions {
    /// Its DICOM port (0: a free one).
    pub dicom_port: u16,
    /// The ctrecon node it knows as the modality `CTRECON`.
    pub ctrecon_port: Option<u16>,
    /// A Lua script (e.g. a `ReceivedInstanceFilter`).
    pub lua: Option<String>,
    /// Load the DICOMweb plugin, with ctrecon's DICOMweb root (`http://…/dicom-web/`) as the server
    /// `ctrecon` and a bearer token for it.
    pub dicomweb: Option<(String, Option<String>)>,
    /// Its HTTP port (0: a free one).
    pub http_port: u16,
    /// HTTP basic authentication on, with this one user (user name, password); the harness's own client
    /// sends them.
    pub user: Option<(String, String)>,
}

/// Base64 (RFC 4648, padded) of `bytes`, for a basic `Authorization` header.
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::new();
    for c in bytes.chunks(3) {
        let n = (c[0] as u32) << 16
            | (*c.get(1).unwrap_or(&0) as u32) << 8
            | *c.get(2).unwrap_or(&0) as u32;
        for k in 0..4 {
            if k <= c.len() {
                out.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

pub const DICOMWEB_PLUGIN: &str = "/usr/share/orthanc/plugins/libOrthancDicomWeb.so";

/// Whether Orthanc and its DICOMweb plugin are installed; without them, one skip line (or a failure under
/// CTRECON_REQUIRE_PEERS=1).
pub fn orthanc_dicomweb_present() -> bool {
    let ok = Path::new(ORTHANC).is_file() && Path::new(DICOMWEB_PLUGIN).is_file();
    if !ok {
        assert!(
            std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
            "Orthanc or its DICOMweb plugin is missing and CTRECON_REQUIRE_PEERS=1 (scripts/install-peers.sh)"
        );
        eprintln!(
            "skipped: Orthanc or its DICOMweb plugin is not installed (scripts/install-peers.sh orthanc)"
        );
    }
    ok
}

impl Orthanc {
    pub async fn start(opts: OrthancOptions) -> Orthanc {
        let dir = tempfile::tempdir().expect("temp dir");
        let http_port = if opts.http_port == 0 {
            free_port()
        } else {
            opts.http_port
        };
        let dicom_port = if opts.dicom_port == 0 {
            free_port()
        } else {
            opts.dicom_port
        };
        let t = dir.path();
        let mut modalities = json!({});
        if let Some(p) = opts.ctrecon_port {
            modalities["CTRECON"] = json!(["CTRECON", "127.0.0.1", p]);
        }
        let mut config = json!({
            "Name": "TEST-ORTHANC", "StorageDirectory": t.join("db"), "IndexDirectory": t.join("db"),
            "HttpPort": http_port, "RemoteAccessAllowed": false, "AuthenticationEnabled": false,
            "DicomServerEnabled": true, "DicomAet": "ORTHANC", "DicomPort": dicom_port,
            "DicomCheckCalledAet": false, "DicomAlwaysAllowStore": true, "DicomAlwaysAllowEcho": true,
            "DicomCheckModalityHost": false, "DicomModalities": modalities, "StableAge": 1,
            "Plugins": [],
        });
        if let Some((url, token)) = &opts.dicomweb {
            let mut server = json!({ "Url": url });
            if let Some(t) = token {
                server["HttpHeaders"] = json!({ "Authorization": format!("Bearer {t}") });
            }
            config["Plugins"] = json!([DICOMWEB_PLUGIN]);
            config["DicomWeb"] = json!({
                "Enable": true, "Root": "/dicom-web/", "Ssl": false,
                "Host": format!("127.0.0.1:{http_port}"),
                "Servers": { "ctrecon": server },
            });
        }
        let mut client = reqwest::Client::builder();
        if let Some((user, password)) = &opts.user {
            config["AuthenticationEnabled"] = json!(true);
            config["RegisteredUsers"] = json!({ user: password });
            let mut headers = reqwest::header::HeaderMap::new();
            let basic = format!("Basic {}", base64(format!("{user}:{password}").as_bytes()));
            headers.insert(reqwest::header::AUTHORIZATION, basic.parse().unwrap());
            client = client.default_headers(headers);
        }
        if let Some(lua) = &opts.lua {
            let path = t.join("script.lua");
            std::fs::write(&path, lua).expect("lua script");
            config["LuaScripts"] = json!([path]);
        }
        let cfg: PathBuf = t.join("orthanc.json");
        std::fs::write(&cfg, serde_json::to_vec_pretty(&config).unwrap()).unwrap();
        std::fs::create_dir_all(t.join("logs")).unwrap();
        let child = Command::new(ORTHANC)
            .arg(format!("--logdir={}", t.join("logs").display()))
            .arg(&cfg)
            .env("TCP_NODELAY", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("Orthanc starts");
        let o = Orthanc {
            child: Some(child),
            dir,
            http_port,
            dicom_port,
            ae_title: "ORTHANC".into(),
            client: client.build().expect("a client"),
        };
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            if let Ok(r) = o.client.get(o.url("/system")).send().await
                && r.status().is_success()
            {
                return o;
            }
            assert!(Instant::now() < deadline, "Orthanc did not start");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}{}", self.http_port, path)
    }

    pub async fn get(&self, path: &str) -> Value {
        let r = self
            .client
            .get(self.url(path))
            .send()
            .await
            .expect("Orthanc answers");
        assert!(r.status().is_success(), "GET {path}: {}", r.status());
        r.json().await.expect("json")
    }

    pub async fn get_bytes(&self, path: &str) -> Vec<u8> {
        let r = self
            .client
            .get(self.url(path))
            .send()
            .await
            .expect("Orthanc answers");
        assert!(r.status().is_success(), "GET {path}: {}", r.status());
        r.bytes().await.expect("bytes").to_vec()
    }

    pub async fn post(&self, path: &str, body: Vec<u8>) -> Value {
        let r = self
            .client
            .post(self.url(path))
            .body(body)
            .send()
            .await
            .expect("Orthanc answers");
        assert!(r.status().is_success(), "POST {path}: {}", r.status());
        r.json().await.expect("json")
    }

    /// Orthanc ids of the instances it holds.
    pub async fn instances(&self) -> Vec<String> {
        serde_json::from_value(self.get("/instances").await).unwrap_or_default()
    }

    /// The simplified tags of an instance.
    pub async fn tags(&self, id: &str) -> Value {
        self.get(&format!("/instances/{id}/simplified-tags")).await
    }
}
