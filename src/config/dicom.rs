//! Settings of the DICOM node ([`crate::dimse`]): the `dicom` object of the configuration file, and
//! `CTRECON_DICOM_*`.

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
    /// Largest PDU ctrecon receives (bytes).
    pub max_pdu_length: u32,
    /// Time for a caller to complete association negotiation (seconds).
    pub association_timeout_secs: u64,
    /// Longest silence inside an association before it is aborted (seconds).
    pub dimse_timeout_secs: u64,
    /// Associations served at once; more are rejected (transient, local limit exceeded).
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
            max_pdu_length: 65_536,
            association_timeout_secs: 30,
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

    #[test]
    fn ae_titles_are_short_and_printable() {
        assert!(is_ae_title("CTRECON"));
        assert!(is_ae_title("STORE SCP"));
        for bad in ["", "   ", "A_TITLE_LONGER_THAN_16", "BACK\\SLASH", "TAB\tX"] {
            assert!(!is_ae_title(bad), "{bad:?}");
        }
    }
}
