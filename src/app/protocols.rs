//! The shipped volume protocols as `GET /v1/protocols` lists them: the same steps and products a rule that
//! names the protocol runs (`jobs::rules::Protocol`), in the body `POST /v1/jobs` takes, so a client that
//! offers them as presets (the viewer) and the rules run one protocol.

use serde::Serialize;

use crate::jobs::rules::Protocol;
use crate::volume::WindowPreset;

/// One protocol: its name, what it makes, the window of its Secondary Capture results, and the body of
/// a volume job (`steps` and `products`, without `kind` and `input`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProtocolPreset {
    pub name: &'static str,
    pub description: &'static str,
    pub window: WindowPreset,
    pub steps: serde_json::Value,
    pub products: serde_json::Value,
}

/// The answer of `GET /v1/protocols`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Protocols {
    pub protocols: Vec<ProtocolPreset>,
}

/// Every shipped protocol, in [`Protocol::ALL`] order.
pub fn shipped() -> Protocols {
    let protocols = Protocol::ALL
        .iter()
        .map(|&p| {
            let mut body = p.body();
            ProtocolPreset {
                name: p.name(),
                description: p.description(),
                window: p.window(),
                steps: body["steps"].take(),
                products: body["products"].take(),
            }
        })
        .collect();
    Protocols { protocols }
}
