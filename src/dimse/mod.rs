//! The DICOM node: ctrecon as a DIMSE service class provider (C-ECHO, C-STORE, C-FIND, C-MOVE) beside the
//! HTTP API.
//!
//! A front door like the HTTP routes: it receives instances over DICOM upper-layer associations
//! (`dicom-ul`), streams each to disk as its fragments arrive, checks it with the same hardened reader as
//! uploads, files it by series, and announces a series as complete once no instance of it arrived for the
//! stable age. [`feed`] hands every complete series to the application, which assembles and records it
//! like an upload.
//!
//! - [`NodeSettings`]: the `dicom` configuration (AE title, port, allow-list, limits), kept with the other
//!   settings in [`crate::config`];
//! - [`command`]: DIMSE command sets; `cancel`: C-CANCEL of a C-FIND or C-MOVE in progress;
//! - [`inbox`] and [`tracker`]: where instances go, and when a series is complete;
//! - [`node`]: the listener; `admission`: connections before negotiation (pending caps, the request read
//!   ahead, association slots); `allow_list`: who may call from where; [`association`]: one association;
//!   [`query`]: C-FIND and C-MOVE over the application's instance index; [`scu`]: ctrecon calling a peer;
//!   [`pull`]: ctrecon querying and retrieving from a peer; [`puller`]: a volume job's series pulled from a
//!   PACS through them.

mod admission;
mod allow_list;
pub mod association;
mod cancel;
pub mod command;
pub mod feed;
pub mod inbox;
pub mod node;
pub mod pull;
pub mod puller;
pub mod query;
pub mod scu;
pub mod sender;
pub mod tracker;
mod wire;

pub use crate::config::dicom::{NodeSettings, Peer};
pub use feed::serve_node;
pub use node::{DicomNode, NodeError};
pub use tracker::CompletedSeries;
