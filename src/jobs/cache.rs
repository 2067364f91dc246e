//! A read-through cache of job rows for this process, so that status polls do not each cost a database
//! round trip (SQLite runs every query on a connection thread, which waits for a core when the workers
//! keep them all busy).
//!
//! Every write of a job goes through [`super::database::Database`], which invalidates the entry after the
//! write. A read fills the cache only if no invalidation happened while it queried (a generation counter),
//! so a stale row can never be cached after a newer write. Only a database this process owns (SQLite) has
//! one.

use std::collections::HashMap;
use std::sync::Mutex;

use super::model::Job;
use crate::storage::JobId;

/// Entries kept at most; the cache is emptied when it would grow beyond.
const CAPACITY: usize = 4096;

#[derive(Debug, Default)]
struct Entries {
    generation: u64,
    jobs: HashMap<JobId, Job>,
}

#[derive(Debug, Default)]
pub struct JobCache {
    inner: Mutex<Entries>,
}

impl JobCache {
    pub fn get(&self, id: JobId) -> Option<Job> {
        self.inner.lock().ok()?.jobs.get(&id).cloned()
    }

    /// The generation to pass to [`JobCache::fill`] (read it before querying).
    pub fn generation(&self) -> u64 {
        self.inner.lock().map(|e| e.generation).unwrap_or(u64::MAX)
    }

    /// Cache `job` read from the database, unless an invalidation happened since `generation`.
    pub fn fill(&self, job: &Job, generation: u64) {
        if let Ok(mut e) = self.inner.lock()
            && e.generation == generation
        {
            if e.jobs.len() >= CAPACITY {
                e.jobs.clear();
            }
            e.jobs.insert(job.id, job.clone());
        }
    }

    /// Forget `id` (call after writing it).
    pub fn invalidate(&self, id: JobId) {
        if let Ok(mut e) = self.inner.lock() {
            e.generation += 1;
            e.jobs.remove(&id);
        }
    }

    /// Forget everything (call after a write of many jobs).
    pub fn clear(&self) {
        if let Ok(mut e) = self.inner.lock() {
            e.generation += 1;
            e.jobs.clear();
        }
    }
}
