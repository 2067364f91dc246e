//! Deliveries: one send of a job's DICOM results to one DIMSE peer, with its state
//! (`queued → sending → succeeded | failed`, and `sending → queued` while the peer is unreachable and
//! attempts remain), attempts, the time of the next attempt, and what the peer answered for each
//! instance. Also the rule runs (a rule that fired for a series and the job it started). Model types and
//! the backoff; the rows live in `repo` and `pg`.

use serde::Serialize;

use super::rules::SeriesFacts;
use crate::error_code::Problem;
use crate::storage::{JobId, SeriesId};

/// Where a delivery is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum DeliveryState {
    Queued,
    Sending,
    Succeeded,
    Failed,
}

impl DeliveryState {
    pub const ALL: [DeliveryState; 4] = [
        DeliveryState::Queued,
        DeliveryState::Sending,
        DeliveryState::Succeeded,
        DeliveryState::Failed,
    ];
    pub fn as_str(self) -> &'static str {
        match self {
            DeliveryState::Queued => "queued",
            DeliveryState::Sending => "sending",
            DeliveryState::Succeeded => "succeeded",
            DeliveryState::Failed => "failed",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|x| x.as_str() == s)
    }
}

/// What became of one instance of a delivery.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum InstanceState {
    Pending,
    Succeeded,
    Failed,
}

impl InstanceState {
    pub fn as_str(self) -> &'static str {
        match self {
            InstanceState::Pending => "pending",
            InstanceState::Succeeded => "succeeded",
            InstanceState::Failed => "failed",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        [Self::Pending, Self::Succeeded, Self::Failed]
            .into_iter()
            .find(|x| x.as_str() == s)
    }
}

/// One DICOM instance of a delivery: a file of the job's exported results.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DeliveryInstance {
    /// File name under the job's `dicom/` results folder.
    #[serde(skip)]
    pub file: String,
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub state: InstanceState,
    /// The peer's DIMSE status (0 = success; e.g. 0xA700 out of resources, 0x0122 SOP class not
    /// supported), absent while pending or when the instance could not be sent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub status: Option<u16>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

/// A delivery as stored.
#[derive(Debug, Clone, PartialEq)]
pub struct Delivery {
    pub id: String,
    pub job_id: JobId,
    pub run_id: Option<String>,
    pub rule_name: Option<String>,
    /// AE title of the peer.
    pub destination: String,
    pub state: DeliveryState,
    pub attempts: u32,
    pub next_attempt_us: Option<i64>,
    pub last_error: Option<String>,
    pub created_us: i64,
    pub updated_us: i64,
    pub finished_us: Option<i64>,
    pub instances: Vec<DeliveryInstance>,
}

/// Filters of `GET /v1/deliveries`.
#[derive(Debug, Clone, Default)]
pub struct DeliveryFilter {
    pub state: Option<DeliveryState>,
    pub job_id: Option<JobId>,
    pub rule_name: Option<String>,
    pub limit: u32,
}

/// Where a rule run is: its job `running`, its results `delivering`, `done` (deliveries made, or none
/// wanted, or the job did not succeed — then `error` says why), or `refused` at admission.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RunState {
    Running,
    Delivering,
    Done,
    Refused,
}

impl RunState {
    pub fn as_str(self) -> &'static str {
        match self {
            RunState::Running => "running",
            RunState::Delivering => "delivering",
            RunState::Done => "done",
            RunState::Refused => "refused",
        }
    }
    pub fn parse(s: &str) -> Option<Self> {
        [Self::Running, Self::Delivering, Self::Done, Self::Refused]
            .into_iter()
            .find(|x| x.as_str() == s)
    }
}

/// A rule that fired for a series.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RuleRun {
    pub id: String,
    pub rule_name: String,
    pub content_hash: String,
    pub series_id: SeriesId,
    pub series_uid: String,
    pub calling_ae: Option<String>,
    pub job_id: Option<JobId>,
    pub state: RunState,
    pub error: Option<Problem>,
    pub created_us: i64,
}

/// A rule run about to be recorded, with what the rule saw.
#[derive(Debug, Clone)]
pub struct NewRun<'a> {
    pub rule_name: &'a str,
    pub content_hash: &'a str,
    pub series_id: SeriesId,
    pub series_uid: &'a str,
    pub facts: &'a SeriesFacts,
}

/// Microseconds to wait before attempt `attempts + 1` after `attempts` failed ones: `base · 2^(attempts−1)`,
/// at most `max`.
pub fn backoff_us(attempts: u32, base_ms: u64, max_ms: u64) -> i64 {
    let factor = 1u64 << attempts.saturating_sub(1).min(30);
    (base_ms.saturating_mul(factor).min(max_ms) as i64).saturating_mul(1000)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backoff_doubles_from_the_base_up_to_the_cap() {
        let b: Vec<i64> = (1..=6).map(|a| backoff_us(a, 500, 5_000) / 1000).collect();
        assert_eq!(b, [500, 1000, 2000, 4000, 5000, 5000]);
        assert_eq!(backoff_us(100, 500, 5_000), 5_000_000);
    }
}
