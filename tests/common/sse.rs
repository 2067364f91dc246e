//! A Server-Sent Events reader for the tests: events (name, id, JSON data) read from a streaming response,
//! each within a bound that stops a hang.

use std::time::{Duration, Instant};

use serde_json::Value;

/// A Server-Sent Events reader over a streaming response.
pub struct Sse {
    resp: reqwest::Response,
    buf: String,
}

/// One event: name, id (empty when none) and data.
#[derive(Debug, Clone)]
pub struct Ev {
    pub name: String,
    pub id: String,
    pub data: Value,
}

impl Sse {
    pub async fn open(client: &reqwest::Client, url: &str, last_id: Option<&str>) -> Sse {
        let mut req = client.get(url).header("accept", "text/event-stream");
        if let Some(id) = last_id {
            req = req.header("last-event-id", id);
        }
        let resp = req.send().await.expect("request");
        assert_eq!(resp.status(), 200);
        assert_eq!(resp.headers()["content-type"], "text/event-stream");
        Sse {
            resp,
            buf: String::new(),
        }
    }

    /// The next event (comments skipped), within `secs` seconds.
    pub async fn next(&mut self, secs: u64) -> Ev {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            if let Some(cut) = self.buf.find("\n\n") {
                let block: String = self.buf.drain(..cut + 2).collect();
                let mut ev = Ev {
                    name: "message".into(),
                    id: String::new(),
                    data: Value::Null,
                };
                let mut data = String::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        ev.name = v.trim().into();
                    } else if let Some(v) = line.strip_prefix("id:") {
                        ev.id = v.trim().into();
                    } else if let Some(v) = line.strip_prefix("data:") {
                        data.push_str(v.trim_start());
                    }
                }
                if data.is_empty() {
                    continue;
                }
                ev.data = serde_json::from_str(&data).expect("json data");
                return ev;
            }
            let left = deadline.saturating_duration_since(Instant::now());
            let chunk = tokio::time::timeout(left, self.resp.chunk())
                .await
                .expect("an event in time")
                .expect("stream")
                .expect("the stream stays open");
            self.buf
                .push_str(&String::from_utf8_lossy(&chunk).replace("\r\n", "\n"));
        }
    }

    /// Events until `done` holds for one (included).
    pub async fn until(&mut self, secs: u64, done: impl Fn(&Ev) -> bool) -> Vec<Ev> {
        let mut out = Vec::new();
        loop {
            let e = self.next(secs).await;
            let stop = done(&e);
            out.push(e);
            if stop {
                return out;
            }
        }
    }
}
