//! ctrecon: CT reconstruction as a library, a command-line tool and an HTTP service.
//!
//! Module map and the dependency rule, `{http, dimse, cli} → app → jobs → {dicom, storage} → {recon, volume,
//! mesh, render}`
//! (see `ARCHITECTURE.md`):
//! - [`recon`]: the pure reconstruction core (geometry, phantoms, projectors, filters, algorithms, metrics);
//! - [`volume`]: pure image-domain operations (slices, MPR, MIP, window/level, PNG encoding);
//! - [`mesh`]: pure surface extraction, clipping and STL;
//! - [`render`]: pure volume rendering, shaded surfaces and cut-away views;
//! - [`series`]: pure assembly of image slices into a volume; [`dicom`]: DICOM reading and writing;
//! - [`scans`]: scanner formats (TIFF stacks, Nikon `.xtekct`, Bruker SkyScan `.log`) read view by view;
//! - [`storage`]: blob store (and its port, [`storage::port::Blobs`]); [`jobs`]: job model, lifecycle, the
//!   `JobStore` port and its SQLite adapter, the engine and the job kinds;
//! - [`app`]: the application layer (commands and queries every front door calls);
//! - [`http`]: the axum service; [`dimse`]: the DICOM node; [`cli`]: the `ctrecon` command line.
//!
//! The pure modules (`recon`, `volume`, `mesh`, `series`, `render`) import no async runtime, HTTP, database or DICOM crate and
//! read no clock, environment or path; `tests/purity.rs` enforces it.

pub mod app;
pub mod cli;
pub mod config;
pub mod dicom;
pub mod dimse;
pub mod error_code;
pub mod http;
pub mod jobs;
pub mod mesh;
pub mod recon;
pub mod render;
pub mod scans;
pub mod series;
pub mod storage;
pub mod telemetry;
pub mod volume;
