//! The list-wide job feed behind `GET /v1/events`: every job's creation, status changes, progress and
//! deletion, numbered in one sequence, kept in a ring of the newest [`FEED_CAPACITY`] events.
//!
//! One forwarder task turns the engine's job events into feed events (a change of status is `Status`, any
//! other change `Progress`, a repeat of what was last seen nothing); submission and deletion add theirs
//! directly. Readers keep a cursor (the last sequence number they sent) and read the ring from it, so a slow
//! reader costs no memory beyond the ring: one that falls behind the ring's oldest event, or whose engine
//! channel lagged, gets `Resync` and reloads the list.
//!
//! Sequence numbers start at 1 in each process; an event id is `{boot}-{seq}`, where `boot` names the
//! process, so a `Last-Event-ID` from another process (or an earlier run) is recognised as unknown.
//! With a shared PostgreSQL database the engine also hears what the other processes relay (their jobs'
//! status and progress, jobs submitted and deleted through them; `jobs::engine::relay`), so the feed of any
//! process covers every job; a notification lost on the way becomes `Resync`.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};

use tokio::sync::{broadcast, watch};

use crate::jobs::{Job, JobEvent, JobStatus, JobSummary, Remote};
use crate::storage::JobId;

/// Events the ring keeps; a reader further behind than this gets `Resync`.
pub const FEED_CAPACITY: usize = 4096;

/// What happened to a job.
#[derive(Debug, Clone, PartialEq)]
pub enum FeedItem {
    /// A job was submitted (its summary as stored).
    Created(JobSummary),
    /// A job's status changed.
    Status(JobEvent),
    /// A job's progress or stage changed, its status did not.
    Progress(JobEvent),
    /// A job was deleted.
    Deleted(JobId),
    /// Events were lost before they reached the feed: a reader must reload the list.
    Resync,
}

/// What a reader gets from its cursor.
#[derive(Debug, Clone, PartialEq)]
pub enum Since {
    /// The events after the cursor (possibly none), oldest first, with their sequence numbers.
    Items(Vec<(u64, FeedItem)>),
    /// Events after the cursor have left the ring: reload, then read from [`Feed::latest`].
    Gone,
}

#[derive(Debug, Default)]
struct Ring {
    /// The sequence number of the newest event (0: none yet).
    last: u64,
    items: VecDeque<(u64, FeedItem)>,
    /// The last status, progress and stage seen of each job that is not finished.
    seen: HashMap<JobId, (JobStatus, u8, String)>,
    /// The final status of the jobs that finished most recently (at most [`FINISHED_KEPT`]), for a
    /// submission announced after its job's end.
    finished: VecDeque<(JobId, JobStatus)>,
}

/// Finished jobs whose final status the feed remembers.
const FINISHED_KEPT: usize = 1024;

/// The feed; cheap to clone.
#[derive(Clone)]
pub struct Feed {
    ring: Arc<Mutex<Ring>>,
    latest: watch::Sender<u64>,
    boot: u64,
}

impl std::fmt::Debug for Feed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Feed").field("boot", &self.boot).finish()
    }
}

impl Default for Feed {
    fn default() -> Self {
        Self::new()
    }
}

impl Feed {
    /// An empty feed named by a fresh `boot` number.
    pub fn new() -> Self {
        let (latest, _) = watch::channel(0);
        Self {
            ring: Arc::new(Mutex::new(Ring::default())),
            latest,
            boot: uuid::Uuid::new_v4().as_u64_pair().0 >> 12,
        }
    }

    /// The number naming this process's sequence.
    pub fn boot(&self) -> u64 {
        self.boot
    }

    /// The event id of sequence number `seq`.
    pub fn event_id(&self, seq: u64) -> String {
        format!("{}-{seq}", self.boot)
    }

    /// The sequence number of an event id of this process; `None` for an id of another process or run.
    pub fn seq_of(&self, id: &str) -> Option<u64> {
        let (boot, seq) = id.trim().split_once('-')?;
        let seq: u64 = seq.parse().ok()?;
        (boot.parse::<u64>().ok()? == self.boot && seq <= self.latest()).then_some(seq)
    }

    /// The sequence number of the newest event (0: none yet).
    pub fn latest(&self) -> u64 {
        *self.latest.borrow()
    }

    /// A receiver that changes whenever an event is added.
    pub fn watch(&self) -> watch::Receiver<u64> {
        self.latest.subscribe()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Ring> {
        // A panic while holding the lock leaves a consistent ring (every change is one push or pop).
        self.ring.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn push(&self, ring: &mut Ring, item: FeedItem) {
        ring.last += 1;
        let seq = ring.last;
        ring.items.push_back((seq, item));
        while ring.items.len() > FEED_CAPACITY {
            ring.items.pop_front();
        }
        self.latest.send_replace(seq);
    }

    /// Record a submitted job (before the engine hears of it).
    pub fn created(&self, job: &Job) {
        self.created_elsewhere(JobSummary::of(job));
    }

    /// Record a job submitted through another process, by the summary it relayed. Notifications of
    /// different processes are not ordered: when the job's status was heard first (a worker claimed it, or
    /// even finished it, before the submission's announcement arrived), the submission is shown with that
    /// status, so that no job's row goes back.
    pub fn created_elsewhere(&self, mut summary: JobSummary) {
        let mut ring = self.lock();
        if let Some((status, progress, stage)) = ring.seen.get(&summary.id) {
            summary.status = *status;
            summary.progress = *progress;
            summary.stage = stage.clone();
        } else if let Some((_, status)) = ring.finished.iter().find(|(id, _)| *id == summary.id) {
            summary.status = *status;
            summary.progress = 100;
        } else {
            ring.seen.insert(
                summary.id,
                (summary.status, summary.progress, summary.stage.clone()),
            );
        }
        self.push(&mut ring, FeedItem::Created(summary));
    }

    /// Record a deleted job.
    pub fn deleted(&self, id: JobId) {
        let mut ring = self.lock();
        ring.seen.remove(&id);
        self.push(&mut ring, FeedItem::Deleted(id));
    }

    /// Record an event of the engine: a status change, a progress change, or nothing when it repeats
    /// what was last seen of the job.
    pub fn engine_event(&self, e: JobEvent) {
        let mut ring = self.lock();
        let now = (e.status, e.progress, e.stage.clone());
        let before = if e.status.is_terminal() {
            ring.finished.push_back((e.id, e.status));
            if ring.finished.len() > FINISHED_KEPT {
                ring.finished.pop_front();
            }
            ring.seen.remove(&e.id)
        } else {
            ring.seen.insert(e.id, now.clone())
        };
        let item = match before {
            Some(b) if b == now && e.iteration.is_none() => return,
            Some((status, _, _)) if status == e.status => FeedItem::Progress(e),
            _ => FeedItem::Status(e),
        };
        self.push(&mut ring, item);
    }

    /// Record that engine events were lost.
    pub fn lost(&self) {
        let mut ring = self.lock();
        ring.seen.clear();
        self.push(&mut ring, FeedItem::Resync);
    }

    /// At most `max` events after sequence number `after`.
    pub fn since(&self, after: u64, max: usize) -> Since {
        let ring = self.lock();
        let oldest = ring.items.front().map_or(ring.last + 1, |(s, _)| *s);
        if after + 1 < oldest {
            return Since::Gone;
        }
        let skip = (after + 1 - oldest) as usize;
        Since::Items(ring.items.iter().skip(skip).take(max).cloned().collect())
    }

    /// Forward what other processes announce (submissions, deletions, lost notifications) into the feed
    /// until the engine's channel closes.
    pub fn spawn_remote_forwarder(&self, mut remote: broadcast::Receiver<Remote>) {
        let feed = self.clone();
        tokio::spawn(async move {
            loop {
                match remote.recv().await {
                    Ok(Remote::Created(summary)) => feed.created_elsewhere(summary),
                    Ok(Remote::Deleted(id)) => feed.deleted(id),
                    Ok(Remote::Lost) | Err(broadcast::error::RecvError::Lagged(_)) => feed.lost(),
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        });
    }

    /// Forward the engine's events into the feed until the engine's channel closes.
    pub fn spawn_forwarder(&self, mut events: broadcast::Receiver<JobEvent>) {
        let feed = self.clone();
        tokio::spawn(async move {
            loop {
                match events.recv().await {
                    Ok(e) => feed.engine_event(e),
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!(missed = n, "job feed missed engine events");
                        feed.lost();
                    }
                    Err(broadcast::error::RecvError::Closed) => return,
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn event(id: JobId, status: JobStatus, progress: u8) -> JobEvent {
        JobEvent {
            id,
            status,
            progress,
            stage: String::new(),
            iteration: None,
            residual: None,
        }
    }

    /// `(kind, status)` of every item in the feed.
    fn shown(feed: &Feed) -> Vec<(&'static str, JobStatus)> {
        let Since::Items(items) = feed.since(0, 100) else {
            panic!("nothing left the ring")
        };
        items
            .iter()
            .filter_map(|(_, i)| match i {
                FeedItem::Created(s) => Some(("created", s.status)),
                FeedItem::Status(e) => Some(("status", e.status)),
                FeedItem::Progress(e) => Some(("progress", e.status)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_submission_announced_after_its_job_started_or_ended_does_not_send_the_job_back() {
        let summary = |id: JobId| JobSummary {
            id,
            kind: "reconstruction".into(),
            status: JobStatus::Queued,
            progress: 0,
            stage: String::new(),
            created_us: 0,
            started_us: None,
            finished_us: None,
            has_metrics: false,
            product_indexes: vec![],
        };
        // Running heard before the submission: the submission shows running, and the next progress is
        // progress, not a second start.
        let feed = Feed::new();
        let id = JobId::generate();
        feed.engine_event(event(id, JobStatus::Running, 10));
        feed.created_elsewhere(summary(id));
        feed.engine_event(event(id, JobStatus::Running, 20));
        feed.engine_event(event(id, JobStatus::Succeeded, 100));
        assert_eq!(
            shown(&feed),
            [
                ("status", JobStatus::Running),
                ("created", JobStatus::Running),
                ("progress", JobStatus::Running),
                ("status", JobStatus::Succeeded),
            ]
        );
        // The whole run heard before the submission: it is shown finished and nothing stays tracked.
        let feed = Feed::new();
        let id = JobId::generate();
        feed.engine_event(event(id, JobStatus::Running, 0));
        feed.engine_event(event(id, JobStatus::Failed, 100));
        feed.created_elsewhere(summary(id));
        assert_eq!(shown(&feed).last(), Some(&("created", JobStatus::Failed)));
        assert!(feed.lock().seen.is_empty());
        // In order, nothing changes.
        let feed = Feed::new();
        let id = JobId::generate();
        feed.created_elsewhere(summary(id));
        feed.engine_event(event(id, JobStatus::Running, 0));
        assert_eq!(
            shown(&feed),
            [
                ("created", JobStatus::Queued),
                ("status", JobStatus::Running)
            ]
        );
    }

    #[test]
    fn status_changes_progress_and_repeats_are_told_apart() {
        let feed = Feed::new();
        let id = JobId::generate();
        feed.engine_event(event(id, JobStatus::Queued, 0));
        feed.engine_event(event(id, JobStatus::Queued, 0));
        feed.engine_event(event(id, JobStatus::Running, 0));
        feed.engine_event(event(id, JobStatus::Running, 40));
        feed.engine_event(event(id, JobStatus::Succeeded, 100));
        feed.deleted(id);
        let Since::Items(items) = feed.since(0, 100) else {
            panic!("nothing left the ring")
        };
        let kinds: Vec<(u64, &str)> = items
            .iter()
            .map(|(s, i)| {
                let k = match i {
                    FeedItem::Status(e) if e.status == JobStatus::Queued => "queued",
                    FeedItem::Status(e) if e.status == JobStatus::Running => "running",
                    FeedItem::Status(_) => "finished",
                    FeedItem::Progress(_) => "progress",
                    FeedItem::Deleted(_) => "deleted",
                    _ => "other",
                };
                (*s, k)
            })
            .collect();
        assert_eq!(
            kinds,
            [
                (1, "queued"),
                (2, "running"),
                (3, "progress"),
                (4, "finished"),
                (5, "deleted")
            ]
        );
        assert_eq!(feed.latest(), 5);
        assert_eq!(feed.since(3, 1), Since::Items(vec![items[3].clone()]));
        assert_eq!(feed.since(5, 10), Since::Items(vec![]));
    }

    #[test]
    fn a_reader_behind_the_ring_is_told_to_reload_and_ids_name_the_process() {
        let feed = Feed::new();
        for _ in 0..FEED_CAPACITY + 10 {
            feed.deleted(JobId::generate());
        }
        assert_eq!(feed.since(0, 10), Since::Gone);
        assert_eq!(feed.since(9, 10), Since::Gone);
        let Since::Items(items) = feed.since(10, 1) else {
            panic!("the 11th event is the oldest kept")
        };
        assert_eq!(items[0].0, 11);
        let id = feed.event_id(42);
        assert_eq!(feed.seq_of(&id), Some(42));
        assert_eq!(feed.seq_of(&Feed::new().event_id(42)), None);
        assert_eq!(feed.seq_of(&feed.event_id(FEED_CAPACITY as u64 + 11)), None);
        assert_eq!(feed.seq_of("nonsense"), None);
    }
}
