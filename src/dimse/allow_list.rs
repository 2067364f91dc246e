//! The allow-list of the DICOM node: which calling AE titles may call from which address (the peers'
//! host names resolved once at start), applied by the association negotiation ([`Gate`]).

use std::net::IpAddr;

use dicom_ul::association::server::AccessControl;
use dicom_ul::pdu::{AssociationRJServiceUserReason, UserIdentity};

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
}

fn same_host(a: IpAddr, b: IpAddr) -> bool {
    let canon = |ip: IpAddr| match ip {
        IpAddr::V6(v6) => v6
            .to_ipv4_mapped()
            .map(IpAddr::V4)
            .unwrap_or(IpAddr::V6(v6)),
        v4 => v4,
    };
    canon(a) == canon(b)
}
