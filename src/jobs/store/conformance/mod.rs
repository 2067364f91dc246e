//! The conformance suite of the [`JobStore`] port: what every adapter must do, as async checks that panic
//! on a violation. An adapter's test file instantiates all of them with one line:
//!
//! ```ignore
//! ctrecon::job_store_conformance!(async { my_adapter().await });
//! ```
//! (the expression makes a fresh, empty store for each check).

use super::{JobStore, Renewed, StoreError};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::lifecycle::{JobState, Lease, Outcome, Transition};
use crate::jobs::model::{IdempotencyKey, Inserted, JobFilter, JobStatus, now_us};
use crate::storage::JobId;

mod samples;

use samples::{assert_illegal, lease_in, queued_job, status};
pub use samples::{sample_job, sample_result};

/// A job is stored as submitted and read back whole; the queue is oldest first.
pub async fn inserted_jobs_read_back_and_queue_oldest_first(s: &dyn JobStore) {
    let t = now_us();
    let a = sample_job(t);
    let b = sample_job(t + 1);
    assert_eq!(s.insert(&a, None).await.ok(), Some(Inserted::New));
    assert_eq!(s.insert(&b, None).await.ok(), Some(Inserted::New));
    let back = s
        .get(a.id)
        .await
        .ok()
        .flatten()
        .expect("the job reads back");
    assert_eq!(back, a);
    assert_eq!(s.state(a.id).await.ok().flatten(), Some(JobState::Queued));
    assert!(matches!(s.get(JobId::generate()).await, Ok(None)));
    let queue = s.queued(10).await.expect("queue");
    assert_eq!(queue, vec![(a.id, 1024), (b.id, 1024)]);
}

/// The same Idempotency-Key inserts once and names the first job afterwards.
pub async fn an_idempotency_key_inserts_once(s: &dyn JobStore) {
    let key = IdempotencyKey {
        route: "POST /v1/jobs",
        key: "k-1".into(),
        fingerprint: "f-1".into(),
    };
    let a = sample_job(now_us());
    let b = sample_job(now_us());
    assert_eq!(s.insert(&a, Some(&key)).await.ok(), Some(Inserted::New));
    assert_eq!(
        s.insert(&b, Some(&key)).await.ok(),
        Some(Inserted::Existing {
            resource_id: a.id.to_string(),
            fingerprint: "f-1".into()
        })
    );
    assert!(matches!(s.get(b.id).await, Ok(None)));
}

/// Claim counts an attempt and holds a lease; a second claim of the same job is illegal.
pub async fn a_claim_counts_an_attempt_and_cannot_be_repeated(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    let lease = lease_in(30);
    assert_eq!(s.claim(id, lease).await.ok(), Some(1));
    assert_eq!(
        s.state(id).await.ok().flatten(),
        Some(JobState::Running {
            attempt: 1,
            lease: Some(lease)
        })
    );
    assert!(s.queued(10).await.expect("queue").is_empty());
    assert_illegal(
        s.claim(id, lease).await,
        Some(JobStatus::Running),
        Transition::Claim,
    );
    assert_illegal(
        s.claim(JobId::generate(), lease).await,
        None,
        Transition::Claim,
    );
}

/// A heartbeat renews the lease of the attempt that holds it, and no other.
pub async fn a_heartbeat_renews_only_the_current_attempt(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    assert_eq!(s.claim(id, lease_in(1)).await.ok(), Some(1));
    let renewed = lease_in(60);
    assert!(s.heartbeat(id, 1, renewed).await.is_ok());
    assert_eq!(
        s.state(id).await.ok().flatten(),
        Some(JobState::Running {
            attempt: 1,
            lease: Some(renewed)
        })
    );
    assert!(matches!(
        s.heartbeat(id, 2, renewed).await,
        Err(StoreError::LeaseLost)
    ));
    let queued = queued_job(s, now_us()).await;
    assert!(matches!(
        s.heartbeat(queued, 1, renewed).await,
        Err(StoreError::LeaseLost)
    ));
}

/// Each outcome is recorded once; terminal states never change again.
pub async fn outcomes_are_recorded_once_and_terminal_states_never_change(s: &dyn JobStore) {
    let ok = queued_job(s, now_us()).await;
    let bad = queued_job(s, now_us()).await;
    let stop = queued_job(s, now_us()).await;
    for id in [ok, bad, stop] {
        assert_eq!(s.claim(id, lease_in(30)).await.ok(), Some(1));
    }
    let result = sample_result();
    let problem = Problem::new(ErrorCode::ReconstructionFailed, "refused");
    assert!(
        s.finish(ok, 1, &Outcome::Succeeded(Box::new(result.clone())))
            .await
            .is_ok()
    );
    assert!(
        s.finish(bad, 1, &Outcome::Failed(problem.clone()))
            .await
            .is_ok()
    );
    assert!(s.finish(stop, 1, &Outcome::Canceled).await.is_ok());
    let job = s.get(ok).await.ok().flatten().expect("job");
    assert_eq!((job.status, job.progress), (JobStatus::Succeeded, 100));
    assert_eq!(job.result.as_ref(), Some(&result));
    assert!(job.finished_us.is_some() && job.started_us.is_some());
    assert_eq!(
        s.state(ok).await.ok().flatten(),
        Some(JobState::Succeeded(Box::new(result)))
    );
    assert_eq!(
        s.state(bad).await.ok().flatten(),
        Some(JobState::Failed(problem))
    );
    assert_eq!(s.state(stop).await.ok().flatten(), Some(JobState::Canceled));
    // A bug that tries to move a finished job is refused, and changes nothing.
    assert_illegal(
        s.finish(ok, 1, &Outcome::Canceled).await,
        Some(JobStatus::Succeeded),
        Transition::Cancel,
    );
    assert_illegal(
        s.claim(bad, lease_in(30)).await,
        Some(JobStatus::Failed),
        Transition::Claim,
    );
    assert_illegal(
        s.hand_back(stop, 1).await,
        Some(JobStatus::Canceled),
        Transition::HandBack,
    );
    assert_illegal(
        s.cancel_queued(ok).await,
        Some(JobStatus::Succeeded),
        Transition::Cancel,
    );
    assert_eq!(status(s, ok).await, JobStatus::Succeeded);
    // A queued job cannot finish without running.
    let q = queued_job(s, now_us()).await;
    assert_illegal(
        s.finish(q, 1, &Outcome::Failed(Problem::internal())).await,
        Some(JobStatus::Queued),
        Transition::Fail,
    );
    assert_eq!(status(s, q).await, JobStatus::Queued);
}

/// Cancel: a queued job at once; a running one is flagged, and then cannot be handed back.
pub async fn cancel_ends_queued_jobs_and_flags_running_ones(s: &dyn JobStore) {
    let q = queued_job(s, now_us()).await;
    assert!(s.cancel_queued(q).await.is_ok());
    assert_eq!(status(s, q).await, JobStatus::Canceled);
    let r = queued_job(s, now_us()).await;
    assert_eq!(s.claim(r, lease_in(30)).await.ok(), Some(1));
    assert_illegal(
        s.cancel_queued(r).await,
        Some(JobStatus::Running),
        Transition::Cancel,
    );
    assert_eq!(
        s.heartbeat(r, 1, lease_in(30)).await.ok(),
        Some(Renewed {
            cancel_requested: false
        })
    );
    assert!(s.request_cancel(r).await.is_ok());
    let job = s.get(r).await.ok().flatten().expect("job");
    assert!(job.cancel_requested);
    // The worker running it learns of the request at its next heartbeat (it may be another process).
    assert_eq!(
        s.heartbeat(r, 1, lease_in(30)).await.ok(),
        Some(Renewed {
            cancel_requested: true
        })
    );
    assert_illegal(
        s.hand_back(r, 1).await,
        Some(JobStatus::Running),
        Transition::HandBack,
    );
    assert!(s.finish(r, 1, &Outcome::Canceled).await.is_ok());
    assert_eq!(status(s, r).await, JobStatus::Canceled);
}

/// A graceful hand-back returns the job to the queue without spending its attempt.
pub async fn a_hand_back_requeues_without_spending_the_attempt(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    assert_eq!(s.claim(id, lease_in(30)).await.ok(), Some(1));
    assert!(s.set_progress(id, 1, 40, "filtering").await.is_ok());
    assert!(matches!(
        s.hand_back(id, 2).await,
        Err(StoreError::LeaseLost)
    ));
    assert!(s.hand_back(id, 1).await.is_ok());
    let job = s.get(id).await.ok().flatten().expect("job");
    assert_eq!(
        (job.status, job.attempts, job.progress),
        (JobStatus::Queued, 0, 0)
    );
    assert_eq!(s.claim(id, lease_in(30)).await.ok(), Some(1));
}

/// An expired lease re-queues the job keeping its attempt; after `max_attempts` claims it fails.
pub async fn an_expired_lease_requeues_then_fails_after_max_attempts(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    let live = queued_job(s, now_us()).await;
    assert_eq!(s.claim(live, lease_in(600)).await.ok(), Some(1));
    let past = Lease {
        expires_us: now_us() - 1,
    };
    assert_eq!(s.claim(id, past).await.ok(), Some(1));
    let e = s.expire_leases(now_us(), 2).await.expect("expire");
    assert_eq!((e.requeued, e.failed), (vec![id], vec![]));
    let job = s.get(id).await.ok().flatten().expect("job");
    assert_eq!((job.status, job.attempts), (JobStatus::Queued, 1));
    assert_eq!(status(s, live).await, JobStatus::Running);
    assert_eq!(s.claim(id, past).await.ok(), Some(2));
    // The lost worker's heartbeat for its old attempt is refused.
    assert!(matches!(
        s.heartbeat(id, 1, lease_in(30)).await,
        Err(StoreError::LeaseLost)
    ));
    let e = s.expire_leases(now_us(), 2).await.expect("expire");
    assert_eq!((e.requeued, e.failed), (vec![], vec![id]));
    match s.state(id).await.ok().flatten() {
        Some(JobState::Failed(p)) => assert_eq!(p.code, ErrorCode::AttemptsExhausted),
        other => panic!("expected failed, got {other:?}"),
    }
}

/// A worker whose lease expired and whose job was claimed again can neither finish it nor report its
/// progress: its outcome is refused and leaves nothing behind, and the current attempt finishes it.
pub async fn a_stale_worker_can_neither_finish_nor_report_progress(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    let past = Lease {
        expires_us: now_us() - 1,
    };
    assert_eq!(s.claim(id, past).await.ok(), Some(1));
    let e = s.expire_leases(now_us(), 3).await.expect("expire");
    assert_eq!(e.requeued, vec![id]);
    // Re-queued and not yet claimed again: the stale outcome is illegal (the job is queued).
    assert_illegal(
        s.finish(id, 1, &Outcome::Succeeded(Box::new(sample_result())))
            .await,
        Some(JobStatus::Queued),
        Transition::Succeed,
    );
    assert_eq!(s.claim(id, lease_in(30)).await.ok(), Some(2));
    assert!(s.set_progress(id, 2, 30, "filtering").await.is_ok());
    let mut stale = sample_result();
    stale.mean = -1.0;
    assert!(matches!(
        s.finish(id, 1, &Outcome::Succeeded(Box::new(stale))).await,
        Err(StoreError::LeaseLost)
    ));
    assert!(matches!(
        s.finish(id, 1, &Outcome::Failed(Problem::internal())).await,
        Err(StoreError::LeaseLost)
    ));
    assert!(s.set_progress(id, 1, 77, "stale").await.is_ok());
    let job = s.get(id).await.ok().flatten().expect("job");
    assert_eq!(
        (job.status, job.attempts, job.progress, job.stage.as_str()),
        (JobStatus::Running, 2, 30, "filtering")
    );
    assert!(job.result.is_none() && job.error.is_none());
    let result = sample_result();
    assert!(
        s.finish(id, 2, &Outcome::Succeeded(Box::new(result.clone())))
            .await
            .is_ok()
    );
    assert_eq!(
        s.state(id).await.ok().flatten(),
        Some(JobState::Succeeded(Box::new(result)))
    );
}

/// Progress is kept while running only.
pub async fn progress_is_persisted_while_running_only(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    assert!(s.set_progress(id, 1, 50, "early").await.is_ok());
    assert_eq!(s.get(id).await.ok().flatten().map(|j| j.progress), Some(0));
    assert_eq!(s.claim(id, lease_in(30)).await.ok(), Some(1));
    assert!(s.set_progress(id, 1, 42, "backprojecting").await.is_ok());
    let job = s.get(id).await.ok().flatten().expect("job");
    assert_eq!((job.progress, job.stage.as_str()), (42, "backprojecting"));
}

/// Lists filter by status, kind and creation time, newest first, and page with a cursor.
pub async fn lists_filter_and_paginate_newest_first(s: &dyn JobStore) {
    let t0 = now_us();
    let mut ids = Vec::new();
    for k in 0..5 {
        ids.push(queued_job(s, t0 + k).await);
    }
    assert_eq!(s.claim(ids[1], lease_in(30)).await.ok(), Some(1));
    let all = |limit| JobFilter {
        limit,
        ..JobFilter::default()
    };
    let page1 = s.list(&all(2)).await.expect("list");
    assert_eq!(
        page1.iter().map(|j| j.id).collect::<Vec<_>>(),
        vec![ids[4], ids[3]]
    );
    let page2 = s
        .list(&JobFilter {
            before_id: Some(ids[3]),
            ..all(10)
        })
        .await
        .expect("list");
    assert_eq!(
        page2.iter().map(|j| j.id).collect::<Vec<_>>(),
        vec![ids[2], ids[1], ids[0]]
    );
    let running = s
        .list(&JobFilter {
            statuses: vec![JobStatus::Running],
            ..all(10)
        })
        .await
        .expect("list");
    assert_eq!(
        running.iter().map(|j| j.id).collect::<Vec<_>>(),
        vec![ids[1]]
    );
    let none = s
        .list(&JobFilter {
            kind: Some("volume".into()),
            ..all(10)
        })
        .await
        .expect("list");
    assert!(none.is_empty());
    let recent = s
        .list(&JobFilter {
            created_after_us: Some(t0 + 2),
            ..all(10)
        })
        .await
        .expect("list");
    assert_eq!(
        recent.iter().map(|j| j.id).collect::<Vec<_>>(),
        vec![ids[4], ids[3]]
    );
}

/// Only finished jobs can be deleted.
pub async fn only_finished_jobs_are_deleted(s: &dyn JobStore) {
    let id = queued_job(s, now_us()).await;
    assert_eq!(s.delete_finished(id).await.ok(), Some(false));
    assert!(s.cancel_queued(id).await.is_ok());
    assert_eq!(s.delete_finished(id).await.ok(), Some(true));
    assert!(matches!(s.get(id).await, Ok(None)));
    assert_eq!(s.delete_finished(id).await.ok(), Some(false));
}

/// Instantiate every conformance check as a `#[tokio::test]` for the store that `$make` (an expression
/// evaluating to a future of a fresh store) builds. One line per adapter.
///
/// `job_store_conformance!(optional $make)` takes a future of an `Option` of a store instead: `None` (a
/// store whose server is missing, after the caller printed why) makes each check return at once.
#[macro_export]
macro_rules! job_store_conformance {
    (optional $make:expr) => {
        $crate::job_store_conformance!(@all optional $make);
    };
    (@all $mode:ident $make:expr) => {
        $crate::job_store_conformance!(@each $mode $make;
            inserted_jobs_read_back_and_queue_oldest_first,
            an_idempotency_key_inserts_once,
            a_claim_counts_an_attempt_and_cannot_be_repeated,
            a_heartbeat_renews_only_the_current_attempt,
            outcomes_are_recorded_once_and_terminal_states_never_change,
            cancel_ends_queued_jobs_and_flags_running_ones,
            a_hand_back_requeues_without_spending_the_attempt,
            an_expired_lease_requeues_then_fails_after_max_attempts,
            a_stale_worker_can_neither_finish_nor_report_progress,
            progress_is_persisted_while_running_only,
            lists_filter_and_paginate_newest_first,
            only_finished_jobs_are_deleted,
        );
    };
    (@each $mode:ident $make:expr; $($case:ident),* $(,)?) => {
        $( $crate::job_store_conformance!(@one $mode $make; $case); )*
    };
    (@one plain $make:expr; $case:ident) => {
        #[tokio::test]
        async fn $case() {
            let store = $make.await;
            $crate::jobs::store::conformance::$case(&store).await;
        }
    };
    (@one optional $make:expr; $case:ident) => {
        #[tokio::test]
        async fn $case() {
            let Some(store) = $make.await else {
                return;
            };
            $crate::jobs::store::conformance::$case(&store).await;
        }
    };
    ($make:expr) => {
        $crate::job_store_conformance!(@all plain $make);
    };
}
