//! Rayon pools, one for each computation running at a time.
//!
//! A rayon thread that waits for a stolen part of its own work runs whatever else is queued on its pool,
//! a whole job included, and returns to its own work only once that is done. On one shared pool a request's
//! simulation could thus wait for a 10 000-iteration job started beside it, and a short job for a long one.
//! Here each job and each request's computation runs alone on a pool of its own: the pools are kept and
//! reused, and at most `slots` computations of a kind run at once (the scheduler bounds jobs by itself).

use std::panic::AssertUnwindSafe;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use rayon::ThreadPool;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

/// Pools of `threads` threads each, for one kind of work.
pub(super) struct Pools {
    kind: &'static str,
    threads: usize,
    /// Pools no computation holds now; at most `slots` are kept.
    idle: Arc<Mutex<Vec<Arc<ThreadPool>>>>,
    slots: Arc<Semaphore>,
    max_idle: usize,
    /// Pools built so far.
    built: AtomicUsize,
}

/// Why a computation could not start.
#[derive(Debug, thiserror::Error)]
#[error("cannot start a thread pool: {0}")]
pub(super) struct PoolError(String);

impl Pools {
    pub(super) fn new(kind: &'static str, threads: usize, slots: usize) -> Self {
        let slots = slots.max(1);
        Self {
            kind,
            threads: threads.max(1),
            idle: Arc::new(Mutex::new(Vec::new())),
            slots: Arc::new(Semaphore::new(slots)),
            max_idle: slots,
            built: AtomicUsize::new(0),
        }
    }

    /// Wait for a free slot (when every slot is taken).
    pub(super) async fn slot(&self) -> Option<OwnedSemaphorePermit> {
        self.slots.clone().acquire_owned().await.ok()
    }

    /// Run `f` alone on a pool of its own, holding `slot` until it returns. `f` sends its result itself
    /// and catches its own panics.
    pub(super) fn spawn<F>(&self, slot: Option<OwnedSemaphorePermit>, f: F) -> Result<(), PoolError>
    where
        F: FnOnce() + Send + 'static,
    {
        let pool = self.take()?;
        let (idle, max_idle) = (self.idle.clone(), self.max_idle);
        let home = pool.clone();
        pool.spawn(move || {
            // `f` catches its own panics; this only guards the hand-back below.
            let _ = std::panic::catch_unwind(AssertUnwindSafe(f));
            // The pool is free again before the slot is: a computation that gets the slot finds it idle.
            if let Ok(mut idle) = idle.lock()
                && idle.len() < max_idle
            {
                idle.push(home);
            }
            drop(slot);
        });
        Ok(())
    }

    /// An idle pool, or a new one.
    fn take(&self) -> Result<Arc<ThreadPool>, PoolError> {
        if let Some(p) = self.idle.lock().ok().and_then(|mut idle| idle.pop()) {
            return Ok(p);
        }
        let kind = self.kind;
        let n = self.built.fetch_add(1, Ordering::Relaxed) + 1;
        tracing::debug!(
            kind,
            threads = self.threads,
            pools = n,
            "a thread pool was built"
        );
        rayon::ThreadPoolBuilder::new()
            .num_threads(self.threads)
            .thread_name(move |i| format!("ctrecon-{kind}-{i}"))
            .build()
            .map(Arc::new)
            .map_err(|e| PoolError(e.to_string()))
    }

    #[cfg(test)]
    fn built(&self) -> usize {
        self.built.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;
    use std::sync::atomic::AtomicBool;
    use std::time::{Duration, Instant};

    /// Work that splits into nested joins, as the kernels do.
    fn split_work(n: usize) -> usize {
        (0..n)
            .into_par_iter()
            .with_max_len(1)
            .map(|i| {
                std::thread::sleep(Duration::from_micros(200));
                i
            })
            .sum()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_short_computation_finishes_while_a_long_one_started_beside_it_runs() {
        let pools = Arc::new(Pools::new("test", 2, 4));
        for round in 0..20 {
            // The long one stops only once the short one is done: run together on one pool, the long one
            // may be taken by a thread waiting inside the short one, and neither ends.
            let short_done = Arc::new(AtomicBool::new(false));
            let (long_tx, long_rx) = tokio::sync::oneshot::channel();
            let (short_tx, short_rx) = tokio::sync::oneshot::channel();
            let s = pools.slot().await;
            pools
                .spawn(s, move || {
                    let _ = short_tx.send(split_work(64));
                })
                .unwrap();
            let flag = short_done.clone();
            let s = pools.slot().await;
            pools
                .spawn(s, move || {
                    let t0 = Instant::now();
                    let mut total = 0;
                    while !flag.load(Ordering::SeqCst) && t0.elapsed() < Duration::from_secs(20) {
                        total += split_work(8);
                    }
                    let _ = long_tx.send(total);
                })
                .unwrap();
            let short = tokio::time::timeout(Duration::from_secs(10), short_rx)
                .await
                .unwrap_or_else(|_| panic!("round {round}: the short computation waited"))
                .unwrap();
            assert_eq!(short, 64 * 63 / 2);
            short_done.store(true, Ordering::SeqCst);
            tokio::time::timeout(Duration::from_secs(10), long_rx)
                .await
                .unwrap()
                .unwrap();
        }
        // The pools were reused: forty computations, two at a time, on no more pools than slots.
        assert!((2..=4).contains(&pools.built()), "{} pools", pools.built());
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn no_more_than_the_slots_run_at_once() {
        let pools = Arc::new(Pools::new("test", 1, 2));
        let a = pools.slot().await;
        let b = pools.slot().await;
        assert!(
            tokio::time::timeout(Duration::from_millis(200), pools.slot())
                .await
                .is_err(),
            "a third slot was given"
        );
        let (tx, rx) = tokio::sync::oneshot::channel();
        pools
            .spawn(a, move || {
                let _ = tx.send(());
            })
            .unwrap();
        rx.await.unwrap();
        // The slot comes back once the computation is over.
        let c = tokio::time::timeout(Duration::from_secs(5), pools.slot())
            .await
            .expect("the slot came back");
        drop((b, c));
    }
}
