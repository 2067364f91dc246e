//! The job lifecycle: the typed states, the events that move a job between them, and the one table of
//! legal transitions every job store obeys.
//!
//! ```text
//!            claim                succeed
//!   queued ─────────► running ─────────────► succeeded
//!     │  ▲               │  │   fail
//!     │  └───────────────┘  ├──────────────► failed
//!     │   hand back /       │   cancel
//!     │   lease expired     └──────────────► canceled
//!     │            cancel                        ▲
//!     └──────────────────────────────────────────┘
//! ```
//! `running → queued` happens only by a graceful hand-back (the attempt is returned) or an expired lease
//! (the attempt is kept, so a job that keeps killing its workers runs out of attempts). Terminal states never
//! change.

use super::model::{JobResult, JobStatus};
use crate::error_code::Problem;

/// A claim on a running job: the worker holding it must renew it (heartbeat) before `expires_us`
/// (microseconds since the Unix epoch), or the job goes back to the queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Lease {
    pub expires_us: i64,
}

/// A job's state, with what each state carries.
#[derive(Debug, Clone, PartialEq)]
pub enum JobState {
    Queued,
    /// Claimed for its `attempt`-th run (1-based), held by `lease`.
    Running {
        attempt: u32,
        lease: Option<Lease>,
    },
    /// Done; the outcome carries the products, metrics and warnings.
    Succeeded(Box<JobResult>),
    Failed(Problem),
    Canceled,
}

impl JobState {
    /// The status of this state.
    pub fn status(&self) -> JobStatus {
        match self {
            JobState::Queued => JobStatus::Queued,
            JobState::Running { .. } => JobStatus::Running,
            JobState::Succeeded(_) => JobStatus::Succeeded,
            JobState::Failed(_) => JobStatus::Failed,
            JobState::Canceled => JobStatus::Canceled,
        }
    }
}

/// An event that moves a job.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Transition {
    /// A worker starts a queued job (counts an attempt).
    Claim,
    /// A running job stopped for a graceful shutdown goes back to the queue (its attempt is returned).
    HandBack,
    /// A running job whose lease expired (its worker died) goes back to the queue (its attempt is kept).
    LeaseExpired,
    Succeed,
    Fail,
    /// A queued job is canceled at once; a running one when it stops at its next check.
    Cancel,
}

impl Transition {
    pub fn as_str(self) -> &'static str {
        match self {
            Transition::Claim => "claim",
            Transition::HandBack => "hand_back",
            Transition::LeaseExpired => "lease_expired",
            Transition::Succeed => "succeed",
            Transition::Fail => "fail",
            Transition::Cancel => "cancel",
        }
    }
}

/// The legal transitions, `(from, event, to)`: the only place they are written.
const LEGAL: &[(JobStatus, Transition, JobStatus)] = &[
    (JobStatus::Queued, Transition::Claim, JobStatus::Running),
    (JobStatus::Queued, Transition::Cancel, JobStatus::Canceled),
    (JobStatus::Running, Transition::HandBack, JobStatus::Queued),
    (
        JobStatus::Running,
        Transition::LeaseExpired,
        JobStatus::Queued,
    ),
    (
        JobStatus::Running,
        Transition::Succeed,
        JobStatus::Succeeded,
    ),
    (JobStatus::Running, Transition::Fail, JobStatus::Failed),
    (JobStatus::Running, Transition::Cancel, JobStatus::Canceled),
];

/// A transition the lifecycle forbids (or a job that is not there to move).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("a {} job cannot {}", .from.map_or("missing", JobStatus::as_str), .event.as_str())]
pub struct IllegalTransition {
    /// The job's status when the transition was tried; `None` when there is no such job.
    pub from: Option<JobStatus>,
    pub event: Transition,
}

/// Where `event` takes a job in status `from`, or why it cannot.
pub fn transition(from: JobStatus, event: Transition) -> Result<JobStatus, IllegalTransition> {
    LEGAL
        .iter()
        .find(|(f, e, _)| *f == from && *e == event)
        .map(|(_, _, to)| *to)
        .ok_or(IllegalTransition {
            from: Some(from),
            event,
        })
}

/// The statuses from which `event` is legal (what a store's guarded update checks).
pub fn sources(event: Transition) -> impl Iterator<Item = JobStatus> {
    LEGAL
        .iter()
        .filter(move |(_, e, _)| *e == event)
        .map(|(f, _, _)| *f)
}

/// How a run ended, as the engine reports it to the store.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    Succeeded(Box<JobResult>),
    Failed(Problem),
    Canceled,
}

impl Outcome {
    pub fn transition(&self) -> Transition {
        match self {
            Outcome::Succeeded(_) => Transition::Succeed,
            Outcome::Failed(_) => Transition::Fail,
            Outcome::Canceled => Transition::Cancel,
        }
    }
    pub fn status(&self) -> JobStatus {
        match self {
            Outcome::Succeeded(_) => JobStatus::Succeeded,
            Outcome::Failed(_) => JobStatus::Failed,
            Outcome::Canceled => JobStatus::Canceled,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terminal_states_never_change_and_running_goes_back_only_by_hand_back_or_lease() {
        let events = [
            Transition::Claim,
            Transition::HandBack,
            Transition::LeaseExpired,
            Transition::Succeed,
            Transition::Fail,
            Transition::Cancel,
        ];
        for from in JobStatus::ALL {
            for e in events {
                let to = transition(from, e);
                if from.is_terminal() {
                    assert!(to.is_err(), "{from:?} --{e:?}--> {to:?}");
                }
                if from == JobStatus::Running && to == Ok(JobStatus::Queued) {
                    assert!(matches!(e, Transition::HandBack | Transition::LeaseExpired));
                }
            }
        }
        assert_eq!(
            transition(JobStatus::Succeeded, Transition::Claim),
            Err(IllegalTransition {
                from: Some(JobStatus::Succeeded),
                event: Transition::Claim
            })
        );
        assert_eq!(
            sources(Transition::Cancel).collect::<Vec<_>>(),
            vec![JobStatus::Queued, JobStatus::Running]
        );
    }
}
