//! The allow-list of the DICOM node: which calling AE titles may call from which address (the peers'
//! host names resolved once at start), applied to a caller's A-ASSOCIATE-RQ before it may take an
//! association slot ([`Peers::may_call`]) and by the negotiation itself ([`Gate`]).

use std::net::IpAddr;

use dicom_ul::association::server::AccessControl;
use dicom_ul::pdu::{AssociationRJServiceUserReason, UserIdentity};

use super::admission;
use crate::config::dicom::NodeSettings;

/// Calling AE titles allowed from one remote address (`None`: any).
pub struct Gate {
    pub allowed: Option<Vec<String>>,
}

impl AccessControl for Gate {
    fn check_access(
        &self,
        this_ae_title: &str,
        calling_ae_title: &str,
        called_ae_title: &str,
        _user_identity: Option<&UserIdentity>,
    ) -> Result<(), AssociationRJServiceUserReason> {
        if called_ae_title.trim() != this_ae_title.trim() {
            return Err(AssociationRJServiceUserReason::CalledAETitleNotRecognized);
        }
        match &self.allowed {
            Some(list) if !list.iter().any(|a| a == calling_ae_title.trim()) => {
                Err(AssociationRJServiceUserReason::CallingAETitleNotRecognized)
            }
            _ => Ok(()),
        }
    }
}

/// The peers' addresses, resolved once at start.
pub struct Peers {
    pub settings: NodeSettings,
    addresses: Vec<(String, Vec<IpAddr>)>,
}

impl Peers {
    pub async fn resolve(settings: NodeSettings) -> Self {
        let mut addresses = Vec::new();
        for p in &settings.peers {
            let ips = match tokio::net::lookup_host((p.host.as_str(), p.port)).await {
                Ok(it) => it.map(|a| a.ip()).collect(),
                Err(e) => {
                    tracing::warn!(peer = %p.ae_title, host = %p.host, error = %e, "cannot resolve a DICOM peer");
                    Vec::new()
                }
            };
            addresses.push((p.ae_title.clone(), ips));
        }
        Self {
            settings,
            addresses,
        }
    }

    /// The AE titles that may call from `ip`, or `None` when the node has no allow-list.
    pub fn allowed_from(&self, ip: IpAddr) -> Option<Vec<String>> {
        if self.settings.peers.is_empty() {
            return None;
        }
        Some(
            self.addresses
                .iter()
                .filter(|(_, ips)| ips.iter().any(|a| same_host(*a, ip)))
                .map(|(ae, _)| ae.clone())
                .collect(),
        )
    }

    /// Whether an A-ASSOCIATE-RQ from `ip` calling `called` as `calling` passes the allow-list (the rule the
    /// negotiation applies with [`Gate`]).
    pub fn may_call(&self, ip: IpAddr, called: &str, calling: &str) -> bool {
        let gate = Gate {
            allowed: self.allowed_from(ip),
        };
        gate.check_access(&self.settings.ae_title, calling, called, None)
            .is_ok()
    }
}

fn same_host(a: IpAddr, b: IpAddr) -> bool {
    admission::canonical(a) == admission::canonical(b)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::dicom::Peer;

    fn ip(s: &str) -> IpAddr {
        s.parse().unwrap()
    }

    #[tokio::test]
    async fn a_peer_may_call_ctrecon_only_from_its_own_address() {
        let peer = Peer {
            ae_title: "PEER".into(),
            host: "127.0.0.1".into(),
            port: 104,
            store: true,
            query: true,
            retrieve: true,
        };
        let peers = Peers::resolve(NodeSettings {
            peers: vec![peer],
            ..NodeSettings::default()
        })
        .await;
        assert!(peers.may_call(ip("127.0.0.1"), "CTRECON", "PEER"));
        assert!(peers.may_call(ip("::ffff:127.0.0.1"), "CTRECON  ", "PEER "));
        assert!(!peers.may_call(ip("127.0.0.2"), "CTRECON", "PEER"));
        assert!(!peers.may_call(ip("127.0.0.1"), "OTHER", "PEER"));
        assert!(!peers.may_call(ip("127.0.0.1"), "CTRECON", "STRANGER"));
        // Without an allow-list (a loopback node) any caller may call CTRECON.
        let open = Peers::resolve(NodeSettings::default()).await;
        assert!(open.may_call(ip("127.0.0.9"), "CTRECON", "ANYONE"));
        assert!(!open.may_call(ip("127.0.0.9"), "OTHER", "ANYONE"));
    }
}
