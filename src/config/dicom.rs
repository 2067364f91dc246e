//! Settings of the DICOM node ([`crate::dimse`]) and of the peers ctrecon sends results to: the `dicom`
//! object of the configuration file, and `CTRECON_DICOM_*`. A destination is a DIMSE peer (`peers`, by AE
//! title) or a DICOMweb origin (`web_peers`, by name, sent to by STOW-RS).

use std::net::{IpAddr, Ipv4Addr};
use std::time::Duration;

use serde::Deserialize;

/// A remote application entity: who may call ctrecon, and where ctrecon sends.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Peer {
    /// Its AE title (1–16 characters).
    pub ae_title: String,
    /// Host name or address; an association from it must come from this address.
    pub host: String,
    pub port: u16,
    /// May send instances (C-STORE) to ctrecon.
    #[serde(default = "yes")]
    pub store: bool,
    /// May query (C-FIND).
    #[serde(default = "yes")]
    pub query: bool,
    /// May retrieve (C-MOVE).
    #[serde(default = "yes")]
    pub retrieve: bool,
}

fn yes() -> bool {
    true
}

/// A DICOMweb origin ctrecon sends results to by STOW-RS (`POST {url}/studies`), named like a DIMSE peer
/// in rule destinations and `POST /v1/deliveries`. Credentials: a bearer token, or a user name and password
/// (HTTP basic), or none.
#[derive(Clone, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WebPeer {
    /// The destination name (1–64 letters, digits, `-`, `_`, `.`), distinct from every DIMSE AE title.
    pub name: String,
    /// The DICOMweb root, e.g. `http://pacs:8042/dicom-web` (`http://` or `https://`).
    pub url: String,
    #[serde(default)]
    pub bearer_token: Option<String>,
    #[serde(default)]
    pub username: Option<String>,
    #[serde(default)]
    pub password: Option<String>,
    /// Longest STOW-RS request, body and answer included (seconds).
    #[serde(default = "web_timeout_secs")]
    pub timeout_secs: u64,
    /// Most instances in one STOW-RS request (a delivery with more is sent in several).
    #[serde(default = "web_batch_instances")]
    pub batch_instances: usize,
}

fn web_timeout_secs() -> u64 {
    600
}

fn web_batch_instances() -> usize {
    200
}

impl std::fmt::Debug for WebPeer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Credentials never reach a log.
        f.debug_struct("WebPeer")
            .field("name", &self.name)
            .field("url", &self.url)
            .field("bearer_token", &self.bearer_token.as_ref().map(|_| "…"))
            .field("username", &self.username)
            .field("password", &self.password.as_ref().map(|_| "…"))
            .field("timeout_secs", &self.timeout_secs)
            .field("batch_instances", &self.batch_instances)
            .finish()
    }
}

impl WebPeer {
    /// The STOW-RS endpoint: `{url}/studies`.
    pub fn studies_url(&self) -> String {
        format!("{}/studies", self.url.trim_end_matches('/'))
    }

    pub fn timeout(&self) -> Duration {
        Duration::from_secs(self.timeout_secs.max(1))
    }

    fn problem(&self) -> Option<String> {
        let name_ok = !self.name.is_empty()
            && self.name.len() <= 64
            && self
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'));
        if !name_ok {
            return Some(format!(
                "web peer name {:?} is not 1–64 letters, digits, '-', '_' or '.'",
                self.name
            ));
        }
        let url = self.url.trim();
        let rest = url
            .strip_prefix("http://")
            .or_else(|| url.strip_prefix("https://"));
        if url != self.url || rest.is_none_or(|r| r.is_empty() || r.starts_with('/')) {
            return Some(format!(
                "web peer {}: url must be an http:// or https:// DICOMweb root",
                self.name
            ));
        }
        if self.url.contains(['?', '#']) {
            return Some(format!(
                "web peer {}: url must be a DICOMweb root without query or fragment",
                self.name
            ));
        }
        let basic = self.username.is_some() || self.password.is_some();
        if self.bearer_token.is_some() && basic {
            return Some(format!(
                "web peer {}: give bearer_token or username/password, not both",
                self.name
            ));
        }
        if basic && (self.username.is_none() || self.password.is_none()) {
            return Some(format!(
                "web peer {}: username and password go together",
                self.name
            ));
        }
        if self
            .bearer_token
            .as_deref()
            .is_some_and(|t| t.is_empty() || !t.bytes().all(|b| b.is_ascii_graphic()))
        {
            return Some(format!(
                "web peer {}: bearer_token must be printable ASCII without spaces",
                self.name
            ));
        }
        if self.username.as_deref().is_some_and(|u| u.contains(':')) {
            return Some(format!(
                "web peer {}: a username cannot contain ':'",
                self.name
            ));
        }
        if self.timeout_secs == 0 || self.batch_instances == 0 {
            return Some(format!(
                "web peer {}: timeout_secs and batch_instances must be positive",
                self.name
            ));
        }
        None
    }
}

/// The DICOM node (DIMSE service class provider), off unless `port` is set.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeSettings {
    /// ctrecon's AE title; associations calling another title are rejected.
    pub ae_title: String,
    /// TCP port of the listener; absent = no listener (0 = any free port).
    pub port: Option<u16>,
    /// Address of the listener: loopback unless `allow_insecure` is set or `peers` lists who may call.
    pub host: IpAddr,
    /// Accept calls from any AE title on a non-loopback address without a peer list.
    pub allow_insecure: bool,
    /// The AE allow-list (and destinations). Empty = any calling AE, which only a loopback node allows.
    pub peers: Vec<Peer>,
    /// DICOMweb origins results are sent to by STOW-RS (destinations by name).
    pub web_peers: Vec<WebPeer>,
    /// Largest PDU ctrecon receives (bytes).
    pub max_pdu_length: u32,
    /// Time for a caller to complete association negotiation (seconds).
    pub association_timeout_secs: u64,
    /// Time for a caller to send its whole A-ASSOCIATE-RQ after connecting (seconds, at most
    /// `association_timeout_secs`); a connection still without one is closed. It holds no association slot.
    pub negotiation_timeout_secs: u64,
    /// Connections from one address still waiting for their A-ASSOCIATE-RQ; one more closes the oldest.
    pub max_pending_per_address: usize,
    /// Connections from all addresses still waiting for their A-ASSOCIATE-RQ; one more closes the oldest.
    /// 0 = 4 × `max_associations`, at least 64.
    pub max_pending: usize,
    /// Longest silence inside an association before it is aborted (seconds).
    pub dimse_timeout_secs: u64,
    /// Associations served at once, counted from a known caller's complete A-ASSOCIATE-RQ; more are rejected
    /// (transient, local limit exceeded).
    pub max_associations: usize,
    /// A series is complete when no instance of it arrived for this long (seconds).
    pub stable_age_secs: u64,
    /// Largest instance accepted by C-STORE (bytes).
    pub max_instance_bytes: u64,
    /// Processing rules read at every start (the `POST /v1/rules` body each); read-only in the API.
    pub rules: Vec<serde_json::Value>,
    /// First wait before a delivery to an unreachable peer is tried again (milliseconds); doubled after
    /// each failed attempt up to `delivery_retry_max_ms`.
    pub delivery_retry_base_ms: u64,
    pub delivery_retry_max_ms: u64,
    /// Attempts of a delivery to an unreachable peer before it is `failed`.
    pub delivery_max_attempts: u32,
}

impl Default for NodeSettings {
    fn default() -> Self {
        Self {
            ae_title: "CTRECON".into(),
            port: None,
            host: IpAddr::V4(Ipv4Addr::LOCALHOST),
            allow_insecure: false,
            peers: Vec::new(),
            web_peers: Vec::new(),
            max_pdu_length: 65_536,
            association_timeout_secs: 30,
            negotiation_timeout_secs: 5,
            max_pending_per_address: 8,
            max_pending: 0,
            dimse_timeout_secs: 60,
            max_associations: 16,
            stable_age_secs: 15,
            max_instance_bytes: 2 << 30,
            rules: Vec::new(),
            delivery_retry_base_ms: 5_000,
            delivery_retry_max_ms: 600_000,
            delivery_max_attempts: 10,
        }
    }
}

impl NodeSettings {
    pub fn association_timeout(&self) -> Duration {
        Duration::from_secs(self.association_timeout_secs.max(1))
    }

    /// How long a connection may wait before its whole A-ASSOCIATE-RQ has arrived: `negotiation_timeout_secs`
    /// (at least 1 s), at most the association timeout.
    pub fn negotiation_timeout(&self) -> Duration {
        Duration::from_secs(self.negotiation_timeout_secs.max(1)).min(self.association_timeout())
    }

    /// Connections waiting for their A-ASSOCIATE-RQ at once, from all addresses (`max_pending`, or
    /// 4 × `max_associations` and at least 64 when it is 0).
    pub fn pending_cap(&self) -> usize {
        if self.max_pending > 0 {
            self.max_pending
        } else {
            self.max_associations.saturating_mul(4).max(64)
        }
    }

    pub fn dimse_timeout(&self) -> Duration {
        Duration::from_secs(self.dimse_timeout_secs.max(1))
    }

    pub fn stable_age(&self) -> Duration {
        Duration::from_secs(self.stable_age_secs)
    }

    /// The peer called `ae_title`, if listed.
    pub fn peer(&self, ae_title: &str) -> Option<&Peer> {
        self.peers.iter().find(|p| p.ae_title == ae_title)
    }

    /// The DICOMweb origin called `name`, if configured.
    pub fn web_peer(&self, name: &str) -> Option<&WebPeer> {
        self.web_peers.iter().find(|p| p.name == name)
    }

    /// Whether `name` is a destination results can be sent to: a DIMSE peer's AE title or a web peer's name.
    pub fn is_destination(&self, name: &str) -> bool {
        self.peer(name).is_some() || self.web_peer(name).is_some()
    }

    /// Why these settings cannot be used, if they cannot.
    pub fn problem(&self) -> Option<String> {
        if !is_ae_title(&self.ae_title) {
            return Some(format!(
                "ae_title {:?} is not 1–16 printable characters without backslash",
                self.ae_title
            ));
        }
        if let Some(p) = self.peers.iter().find(|p| !is_ae_title(&p.ae_title)) {
            return Some(format!("peer AE title {:?} is not valid", p.ae_title));
        }
        if let Some(why) = self.web_peers_problem() {
            return Some(why);
        }
        if self.port.is_some()
            && !self.host.is_loopback()
            && !self.allow_insecure
            && self.peers.is_empty()
        {
            return Some(
                "a DICOM listener on a non-loopback address needs `peers` (an AE allow-list) or \
                 `allow_insecure`"
                    .into(),
            );
        }
        if self.max_pdu_length < 4096 || self.max_pdu_length > (16 << 20) {
            return Some("max_pdu_length must be between 4096 and 16 MiB".into());
        }
        if self.delivery_max_attempts == 0 || self.delivery_retry_base_ms == 0 {
            return Some(
                "delivery_max_attempts and delivery_retry_base_ms must be positive".into(),
            );
        }
        if self.max_associations == 0 || self.max_instance_bytes == 0 {
            return Some("max_associations and max_instance_bytes must be positive".into());
        }
        if self.max_pending_per_address == 0 {
            return Some("max_pending_per_address must be positive".into());
        }
        None
    }
}

impl NodeSettings {
    fn web_peers_problem(&self) -> Option<String> {
        if !self.web_peers.is_empty() && !cfg!(feature = "dicomweb-client") {
            return Some(
                "web_peers (DICOMweb destinations) need ctrecon built with the `dicomweb-client` \
                 feature"
                    .into(),
            );
        }
        for (k, w) in self.web_peers.iter().enumerate() {
            if let Some(why) = w.problem() {
                return Some(why);
            }
            if self.peer(&w.name).is_some() || self.web_peers[..k].iter().any(|o| o.name == w.name)
            {
                return Some(format!(
                    "web peer name {:?} is already a destination (names and AE titles are one namespace)",
                    w.name
                ));
            }
        }
        None
    }
}

/// An AE title: 1–16 characters of the default repertoire, no backslash or control character, not all
/// spaces.
pub fn is_ae_title(s: &str) -> bool {
    !s.trim().is_empty()
        && s.len() <= 16
        && s.chars()
            .all(|c| c.is_ascii() && !c.is_ascii_control() && c != '\\')
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_public_listener_needs_an_allow_list_or_an_explicit_opt_out() {
        let mut s = NodeSettings {
            port: Some(11112),
            host: "0.0.0.0".parse().unwrap(),
            ..NodeSettings::default()
        };
        assert!(s.problem().is_some());
        s.peers.push(Peer {
            ae_title: "PACS".into(),
            host: "10.0.0.2".into(),
            port: 104,
            store: true,
            query: true,
            retrieve: true,
        });
        assert_eq!(s.problem(), None);
        s.peers.clear();
        s.allow_insecure = true;
        assert_eq!(s.problem(), None);
    }

    fn web(name: &str, url: &str) -> WebPeer {
        WebPeer {
            name: name.into(),
            url: url.into(),
            bearer_token: None,
            username: None,
            password: None,
            timeout_secs: 600,
            batch_instances: 200,
        }
    }

    #[test]
    fn web_peers_need_an_http_root_one_kind_of_credentials_and_a_name_of_their_own() {
        let ok = |w: WebPeer| {
            NodeSettings {
                web_peers: vec![w],
                peers: vec![Peer {
                    ae_title: "PACS".into(),
                    host: "127.0.0.1".into(),
                    port: 104,
                    store: true,
                    query: true,
                    retrieve: true,
                }],
                ..NodeSettings::default()
            }
            .problem()
        };
        let good = web("ARCHIVE", "https://pacs.example/dicom-web/");
        if cfg!(feature = "dicomweb-client") {
            assert_eq!(ok(good.clone()), None);
            assert_eq!(good.studies_url(), "https://pacs.example/dicom-web/studies");
            let basic = WebPeer {
                username: Some("alice".into()),
                password: Some("s3cret".into()),
                ..good.clone()
            };
            assert_eq!(ok(basic.clone()), None);
            assert!(!format!("{basic:?}").contains("s3cret"));
        } else {
            assert!(ok(good.clone()).unwrap().contains("dicomweb-client"));
            return;
        }
        for bad in [
            web("PACS", "http://x/dicom-web"),
            web("has space", "http://x/dicom-web"),
            web("A", "ftp://x/dicom-web"),
            web("A", "http:///dicom-web"),
            web("A", " http://x"),
            web("A", "http://x/dicom-web?q=1"),
            WebPeer {
                bearer_token: Some("t".into()),
                username: Some("u".into()),
                password: Some("p".into()),
                ..web("A", "http://x")
            },
            WebPeer {
                username: Some("u".into()),
                ..web("A", "http://x")
            },
            WebPeer {
                bearer_token: Some("two words".into()),
                ..web("A", "http://x")
            },
            WebPeer {
                batch_instances: 0,
                ..web("A", "http://x")
            },
        ] {
            assert!(ok(bad.clone()).is_some(), "{bad:?}");
        }
        let twice = NodeSettings {
            web_peers: vec![web("A", "http://x"), web("A", "http://y")],
            ..NodeSettings::default()
        };
        assert!(twice.problem().unwrap().contains("already"));
    }

    #[test]
    fn connections_wait_for_their_request_at_most_the_association_timeout_and_64_at_least_in_all() {
        let s = NodeSettings::default();
        assert_eq!(s.negotiation_timeout(), Duration::from_secs(5));
        assert_eq!(s.pending_cap(), 64);
        let s = NodeSettings {
            association_timeout_secs: 2,
            max_associations: 40,
            ..s
        };
        assert_eq!(s.negotiation_timeout(), Duration::from_secs(2));
        assert_eq!(s.pending_cap(), 160);
        assert_eq!(
            NodeSettings {
                max_pending: 10,
                ..s
            }
            .pending_cap(),
            10
        );
        let none_per_address = NodeSettings {
            max_pending_per_address: 0,
            ..NodeSettings::default()
        };
        assert!(none_per_address.problem().is_some());
    }

    #[test]
    fn ae_titles_are_short_and_printable() {
        assert!(is_ae_title("CTRECON"));
        assert!(is_ae_title("STORE SCP"));
        for bad in ["", "   ", "A_TITLE_LONGER_THAN_16", "BACK\\SLASH", "TAB\tX"] {
            assert!(!is_ae_title(bad), "{bad:?}");
        }
    }
}
