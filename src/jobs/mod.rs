//! Jobs: model and state machine, SQL repository, admission, the rayon worker engine, the work itself
//! (simulation, reconstruction) and the views derived from results.

pub mod cache;
pub mod engine;
pub mod imaging;
pub mod ingest;
pub mod model;
pub mod plan;
pub mod quality;
pub mod render_outputs;
pub mod render_products;
pub mod repo;
pub mod retention;
pub mod run;
pub mod views;

pub use engine::{CancelError, Engine, EngineConfig, JobEvent, StartError};
pub use model::{
    Dataset, DatasetKind, Job, JobRequest, JobResult, JobSpec, JobStatus, JobSummary, SeriesRecord,
    SimulationRequest, UploadRecord,
};
pub use repo::{Appended, Completed, Db, DbError, IdempotencyKey, Inserted, JobFilter};
