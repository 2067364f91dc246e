//! Jobs: model and state machine, SQL repository, admission, the rayon worker engine, the work itself
//! (simulation, reconstruction) and the views derived from results.

pub mod engine;
pub mod model;
pub mod plan;
pub mod quality;
pub mod repo;
pub mod run;
pub mod views;

pub use engine::{CancelError, Engine, EngineConfig, JobEvent, StartError};
pub use model::{Dataset, DatasetKind, Job, JobRequest, JobResult, JobStatus, SimulationRequest};
pub use repo::{Db, DbError, IdempotencyKey, Inserted, JobFilter};
