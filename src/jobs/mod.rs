//! Jobs, in layers that import only downwards (`tests/purity.rs` checks that the modules of this folder import
//! each other without a cycle):
//!
//! 1. `model`: what a job is — requests (the volume and rendering requests among them), statuses, results,
//!    products and the stored records of series, uploads and datasets. Beside it, depending only on it:
//!    `lifecycle` (typed states, the one table of legal transitions), `rules` and `deliveries` (the DICOM
//!    node's rules and what they send), `plan` and `quality` (admission and figures of reconstructions),
//!    `iso_range`, `ingest` (DICOM → series problems), `cache`.
//! 2. `store`: the `JobStore` port, the outcomes both databases answer, and the conformance suite.
//! 3. The adapter: `database`, one SQL adapter for SQLite and PostgreSQL (each statement written once, a
//!    dialect seam for what differs; datasets, uploads, series and the DICOM node's tables besides jobs,
//!    with the node tables' conformance suite); `sweep` and `retention` work on it.
//! 4. What jobs make: `run` (reconstruction, simulation), `views` (a *view*: a 2D image, a mesh or a derived
//!    series rendered from a result on request, and the renderings of stored products), `render_products`
//!    (volume and surface renderings made by a job), `imaging` (volume jobs: planning, steps, products),
//!    `export` (a job's DICOM results), `pull` (series fetched from a PACS).
//! 5. `engine`: the pool, scheduling, leases, cancel and progress; it runs the job kinds above.
//!
//! Words: a *product* is what a job makes and keeps (`product-{i}`); a *view* is rendered from a result or a
//! product when asked for, and cached.

pub mod cache;
pub mod database;
pub mod deliveries;
pub mod engine;
pub mod export;
pub mod imaging;
pub mod ingest;
pub mod iso_range;
pub mod lifecycle;
pub mod model;
pub mod plan;
pub mod pull;
pub mod quality;
pub mod render_products;
pub mod retention;
pub mod rules;
pub mod run;
pub mod store;
pub mod sweep;
pub mod views;

pub use database::Database;
pub use database::{Db, PgDb};
pub use engine::{CancelError, Engine, EngineConfig, JobEvent, Remote, StartError};
pub use lifecycle::{IllegalTransition, JobState, Lease, Outcome, Transition};
pub use model::{
    Dataset, DatasetKind, Job, JobRequest, JobResult, JobSpec, JobStatus, JobSummary, SeriesRecord,
    SimulationRequest, UploadRecord,
};
pub use model::{IdempotencyKey, Inserted, JobFilter};
pub use store::{Appended, Completed, DbError, UploadDeleted};
pub use store::{JobStore, StoreError};
