//! Jobs, layered inside: `model` (and `volume_spec`, the volume request) ← `lifecycle` (typed states, the one
//! table of legal transitions) ← `store` (the `JobStore` port and its conformance suite) ← `repo` (the
//! SQLite adapter, with datasets, uploads and series), `pg` (its PostgreSQL twin), `database` (the one of
//! them the service runs on) ← `engine` (pool, scheduling, leases, cancel, progress)
//! → the job kinds it runs: `run` (reconstruction, simulation; admission in `plan`), `imaging` (volume
//! jobs and their products; `iso_range` checks their iso-values against the data), `views` (rendered 2D images
//! and meshes of results), `ingest` (DICOM → series).

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
pub mod pg;
pub mod plan;
pub mod pull;
pub mod quality;
pub mod render_outputs;
pub mod render_products;
pub mod repo;
pub mod retention;
pub mod rules;
pub mod run;
pub mod store;
pub mod views;
pub mod volume_spec;

pub use database::Database;
pub use engine::{CancelError, Engine, EngineConfig, JobEvent, Remote, StartError};
pub use lifecycle::{IllegalTransition, JobState, Lease, Outcome, Transition};
pub use model::{
    Dataset, DatasetKind, Job, JobRequest, JobResult, JobSpec, JobStatus, JobSummary, SeriesRecord,
    SimulationRequest, UploadRecord,
};
pub use pg::PgDb;
pub use repo::{
    Appended, Completed, Db, DbError, IdempotencyKey, Inserted, JobFilter, UploadDeleted,
};
pub use store::{JobStore, StoreError};
