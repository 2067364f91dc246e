//! The jobs, results and leases the conformance checks start from, and the check of an illegal transition.

use crate::jobs::lifecycle::{Lease, Transition};
use crate::jobs::model::{
    FileInfo, Inserted, Job, JobRequest, JobResult, JobSpec, JobStatus, now_us,
};
use crate::jobs::store::{JobStore, StoreError};
use crate::recon::grid::VolumeGrid;
use crate::storage::JobId;

/// A small reconstruction job, queued, created at `created_us`.
pub fn sample_job(created_us: i64) -> Job {
    let request: JobRequest = match serde_json::from_value(serde_json::json!({
        "input": "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5",
        "algorithm": {"name": "fbp"},
        "grid": {"nx": 8, "ny": 8, "dx_mm": 1, "dy_mm": 1}
    })) {
        Ok(r) => r,
        Err(e) => panic!("the sample request parses: {e}"),
    };
    Job::queued(JobSpec::Reconstruction(request), 1024, created_us)
}

/// A result as a succeeded reconstruction records it.
pub fn sample_result() -> JobResult {
    JobResult {
        shape: [1, 8, 8],
        grid: VolumeGrid::cube(8, 1.0),
        volume: FileInfo {
            bytes: 384,
            sha256: "00".repeat(32),
        },
        min: 0.0,
        max: 1.0,
        mean: 0.5,
        metrics: None,
        units: Default::default(),
        frame: None,
        source_series: None,
        products: Vec::new(),
        warnings: Vec::new(),
        derivation: None,
    }
}

pub(super) fn lease_in(secs: i64) -> Lease {
    Lease {
        expires_us: now_us() + secs * 1_000_000,
    }
}

pub(super) async fn status(s: &dyn JobStore, id: JobId) -> JobStatus {
    match s.get(id).await {
        Ok(Some(j)) => j.status,
        other => panic!("job {id} readable: {other:?}"),
    }
}

pub(super) fn assert_illegal<T: std::fmt::Debug>(
    r: Result<T, StoreError>,
    from: Option<JobStatus>,
    event: Transition,
) {
    match r {
        Err(StoreError::Illegal(e)) => {
            assert_eq!(e.event, event, "{e}");
            assert_eq!(e.from, from, "{e}");
        }
        other => panic!("expected an illegal {event:?} from {from:?}, got {other:?}"),
    }
}

pub(super) async fn queued_job(s: &dyn JobStore, created_us: i64) -> JobId {
    let job = sample_job(created_us);
    match s.insert(&job, None).await {
        Ok(Inserted::New) => job.id,
        other => panic!("inserting a job: {other:?}"),
    }
}
