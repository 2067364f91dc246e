//! The destinations ctrecon knows, as `GET /v1/peers` shows them: the DIMSE peers (`dicom.peers`) and the
//! DICOMweb origins (`dicom.web_peers`), each with its kind; credentials are named, never shown.

use serde_json::{Value, json};

use crate::config::dicom::{Peer, WebPeer};

/// The JSON representation of a configured DIMSE peer.
pub fn peer_json(p: &Peer) -> Value {
    json!({
        "kind": "dimse",
        "ae_title": p.ae_title,
        "host": p.host,
        "port": p.port,
        "store": p.store,
        "query": p.query,
        "retrieve": p.retrieve,
        "links": {"echo": format!("/v1/peers/{}/echo", p.ae_title)},
    })
}

/// The JSON representation of a configured DICOMweb origin: its name, its root (any user information in the URL left
/// out) and which credentials it is sent, never their values.
pub fn web_peer_json(p: &WebPeer) -> Value {
    let auth = if p.bearer_token.is_some() {
        "bearer"
    } else if p.username.is_some() {
        "basic"
    } else {
        "none"
    };
    json!({
        "kind": "dicomweb",
        "name": p.name,
        "url": without_userinfo(&p.url),
        "auth": auth,
        "batch_instances": p.batch_instances,
        "timeout_secs": p.timeout_secs,
    })
}

/// `url` without a `user:password@` in its authority.
fn without_userinfo(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    let end = rest.find('/').unwrap_or(rest.len());
    match rest[..end].rfind('@') {
        Some(at) => format!("{scheme}://{}", &rest[at + 1..]),
        None => url.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_web_peer_is_shown_with_its_kind_and_without_its_secrets() {
        let p: WebPeer = serde_json::from_value(json!({
            "name": "ARCHIVE", "url": "https://ops:hunter2@pacs.example/dicom-web",
            "bearer_token": "s3cr3t-token"
        }))
        .unwrap();
        let v = web_peer_json(&p);
        assert_eq!(v["kind"], "dicomweb");
        assert_eq!(v["url"], "https://pacs.example/dicom-web");
        assert_eq!(v["auth"], "bearer");
        let text = v.to_string();
        assert!(
            !text.contains("s3cr3t") && !text.contains("hunter2"),
            "{text}"
        );
        assert_eq!(without_userinfo("http://a/b@c"), "http://a/b@c");
    }
}
