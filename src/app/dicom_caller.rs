//! The port through which deliveries reach DIMSE peers: [`DicomCaller`], installed by the DICOM front door, so
//! that the application imports no front door.

use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;

use crate::config::dicom::Peer;

/// A boxed future (the port's methods are async).
pub type CallFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// Why a call to a peer failed as a whole (refused connection, rejected association, timeout, a broken
/// association): worth trying again later.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CallError(pub String);

/// What a peer answered for one file sent by C-STORE.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SentInstance {
    /// The peer's DIMSE status; `None` when the file was not sent (e.g. its SOP class was not accepted).
    pub status: Option<u16>,
    /// The status means stored (success or a warning).
    pub stored: bool,
    pub detail: Option<String>,
}

/// ctrecon calling DIMSE peers: the port the DICOM front door implements.
pub trait DicomCaller: Send + Sync + 'static {
    /// C-ECHO: the peer's status.
    fn echo<'a>(&'a self, peer: &'a Peer) -> CallFuture<'a, Result<u16, CallError>>;
    /// C-STORE `files` in one association: one answer per file, in order.
    fn store<'a>(
        &'a self,
        peer: &'a Peer,
        files: Vec<PathBuf>,
    ) -> CallFuture<'a, Result<Vec<SentInstance>, CallError>>;
}
