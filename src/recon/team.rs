//! A team of pool threads for many small steps in a row: a leader runs the steps and hands each
//! step's chunks of work to partners that spin between steps instead of sleeping.
//!
//! A SART update with one view lasts tens of microseconds; waking sleeping pool threads for each of
//! its parallel loops costs about what the loop saves. [`with_team`] starts up to `partners` pool
//! tasks that stay awake for the whole body; [`Team::run`] publishes one step (its chunk count and
//! work), and leader and partners claim its chunks one at a time until none is left. The leader
//! never waits for a partner to *start*: if no pool thread picks a partner task up (the pool is busy
//! with other work), the leader claims every chunk itself and the partner task, run later, finds the
//! team stopped and returns. It waits only for chunks a partner has claimed, which a running thread
//! finishes. The body must not call into the pool itself (a pool call could run a partner task on
//! the leader's own thread, which would then spin waiting for itself).

use std::cell::Cell;
use std::hint::spin_loop;
use std::sync::atomic::{AtomicPtr, AtomicU64, AtomicUsize, Ordering::SeqCst};

/// Bits of the claim word for the next chunk from the front and the end of the unclaimed chunks
/// (the leader claims from the front, partners from the back, so that from step to step each
/// thread tends to work on the same data); the epoch (the step's number) takes the 24 bits above.
const INDEX_BITS: u32 = 20;
const INDEX_MASK: u64 = (1 << INDEX_BITS) - 1;
const EPOCH_SHIFT: u32 = 2 * INDEX_BITS;
/// The claim word of a stopped team (its epoch is the largest one, never used for a step).
const STOP: u64 = u64::MAX;
const LAST_EPOCH: u64 = (STOP >> EPOCH_SHIFT) - 1;
/// Spins of an idle partner before it starts yielding its thread between looks.
const SPINS: u32 = 1 << 14;

type Job<'a> = &'a (dyn Fn(usize) + Sync);

struct Shared {
    /// `epoch << 40 | end << 20 | next` of the current step (chunks `next .. end` unclaimed), or
    /// [`STOP`].
    claim: AtomicU64,
    /// Chunks of the current step finished.
    done: AtomicUsize,
    /// The current step's work: a [`Job`] on the leader's stack, alive while the step runs.
    job: AtomicPtr<()>,
}

/// Counts a claimed chunk as done when dropped, also when its work unwinds.
struct Done<'a>(&'a AtomicUsize);

impl Drop for Done<'_> {
    fn drop(&mut self) {
        self.0.fetch_add(1, SeqCst);
    }
}

impl Shared {
    /// Claim and run chunks of step `epoch`, from the back of the unclaimed ones where `back`, until
    /// none is left or another step has begun.
    #[allow(unsafe_code)]
    fn work(&self, epoch: u64, back: bool) {
        loop {
            let cur = self.claim.load(SeqCst);
            let (end, next) = ((cur >> INDEX_BITS) & INDEX_MASK, cur & INDEX_MASK);
            if cur >> EPOCH_SHIFT != epoch || next >= end {
                return;
            }
            let (new, chunk) = if back {
                (cur - (1 << INDEX_BITS), end - 1)
            } else {
                (cur + 1, next)
            };
            if self
                .claim
                .compare_exchange_weak(cur, new, SeqCst, SeqCst)
                .is_err()
            {
                continue;
            }
            let _done = Done(&self.done);
            // SAFETY: chunk `chunk` of step `epoch` is claimed and not done, so the leader is inside
            // `Team::run` of this step, waiting for it, and `job` points to that call's live `Job`
            // (stored before the step's claim word, which the successful exchange read).
            let job = unsafe { *(self.job.load(SeqCst) as *const Job<'static>) };
            job(chunk as usize);
        }
    }

    /// A partner: join each new step until the team stops.
    fn partner(&self) {
        let (mut seen, mut idle) = (0u64, 0u32);
        loop {
            let cur = self.claim.load(SeqCst);
            if cur == STOP {
                return;
            }
            let epoch = cur >> EPOCH_SHIFT;
            if epoch != seen {
                seen = epoch;
                self.work(epoch, true);
                idle = 0;
            } else if idle < SPINS {
                idle += 1;
                spin_loop();
            } else {
                std::thread::yield_now();
            }
        }
    }
}

/// The leader's handle (see the module docs).
pub struct Team<'s> {
    shared: Option<&'s Shared>,
    epoch: Cell<u64>,
}

impl Team<'_> {
    /// A team of the calling thread alone: [`Team::run`] runs every chunk in order.
    pub fn solo() -> Self {
        Self {
            shared: None,
            epoch: Cell::new(0),
        }
    }

    /// Run `job(0)`, …, `job(chunks − 1)`, shared with the partners that are awake, and return when
    /// all have finished. Chunks may run in any order and at once: each must touch its own data.
    #[allow(unsafe_code)]
    pub fn run(&self, chunks: usize, job: &(dyn Fn(usize) + Sync)) {
        let epoch = self.epoch.get() + 1;
        let shared = match self.shared {
            Some(s) if chunks > 1 && chunks as u64 <= INDEX_MASK && epoch <= LAST_EPOCH => s,
            _ => {
                (0..chunks).for_each(job);
                return;
            }
        };
        self.epoch.set(epoch);
        let job_ref: Job<'_> = job;
        shared
            .job
            .store(&job_ref as *const Job<'_> as *mut (), SeqCst);
        shared.done.store(0, SeqCst);
        let start = epoch << EPOCH_SHIFT | (chunks as u64) << INDEX_BITS;
        shared.claim.store(start, SeqCst);
        // On the way out, also when a chunk of the leader's unwinds: close the step to claims and
        // wait for the chunks taken, so that none outlives `job_ref`.
        struct Close<'a>(&'a Shared, u64, u64);
        impl Drop for Close<'_> {
            fn drop(&mut self) {
                let &mut Close(shared, epoch, chunks) = self;
                let cur = shared.claim.swap(epoch << EPOCH_SHIFT, SeqCst);
                let (end, next) = ((cur >> INDEX_BITS) & INDEX_MASK, cur & INDEX_MASK);
                let claimed = (chunks - end.saturating_sub(next)) as usize;
                while shared.done.load(SeqCst) < claimed {
                    spin_loop();
                }
            }
        }
        let _close = Close(shared, epoch, chunks as u64);
        shared.work(epoch, false);
    }
}

/// Run `body` with a team of the calling thread and up to `partners` pool tasks (see the module
/// docs; the body must not call into the pool).
pub fn with_team<R: Send>(partners: usize, body: impl FnOnce(&Team<'_>) -> R + Send) -> R {
    if partners == 0 {
        return body(&Team::solo());
    }
    let shared = Shared {
        claim: AtomicU64::new(0),
        done: AtomicUsize::new(0),
        job: AtomicPtr::new(std::ptr::null_mut()),
    };
    struct Stop<'a>(&'a Shared);
    impl Drop for Stop<'_> {
        fn drop(&mut self) {
            self.0.claim.store(STOP, SeqCst);
        }
    }
    rayon::scope(|scope| {
        for _ in 0..partners {
            scope.spawn(|_| shared.partner());
        }
        let _stop = Stop(&shared);
        body(&Team {
            shared: Some(&shared),
            epoch: Cell::new(0),
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn every_chunk_of_every_step_runs_once() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let counts: Vec<AtomicUsize> = (0..64).map(|_| AtomicUsize::new(0)).collect();
        let threads = Mutex::new(std::collections::BTreeSet::new());
        pool.install(|| {
            with_team(2, |team| {
                for step in 0..2000usize {
                    let chunks = 1 + step % 64;
                    team.run(chunks, &|i| {
                        counts[i].fetch_add(1, SeqCst);
                        if step % 100 == 0 {
                            threads
                                .lock()
                                .unwrap()
                                .insert(format!("{:?}", std::thread::current().id()));
                            std::thread::sleep(std::time::Duration::from_micros(200));
                        }
                    });
                }
            })
        });
        for (i, c) in counts.iter().enumerate() {
            // chunk i runs in the steps with chunks > i: step % 64 ≥ i
            let expected = (0..2000usize).filter(|s| s % 64 >= i).count();
            assert_eq!(c.load(SeqCst), expected, "chunk {i}");
        }
        assert!(threads.lock().unwrap().len() >= 2, "partners never joined");
    }

    #[test]
    fn a_busy_pool_leaves_the_leader_to_work_alone() {
        // One pool thread: the partner task cannot start until the body has returned.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let total = AtomicUsize::new(0);
        pool.install(|| {
            with_team(3, |team| {
                for _ in 0..100 {
                    team.run(8, &|i| {
                        total.fetch_add(i, SeqCst);
                    });
                }
            })
        });
        assert_eq!(total.load(SeqCst), 100 * 28);
    }

    #[test]
    fn a_panicking_chunk_reaches_the_caller_after_the_others_finish() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let finished = AtomicUsize::new(0);
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            pool.install(|| {
                with_team(1, |team| {
                    team.run(16, &|i| {
                        if i == 3 {
                            panic!("chunk 3");
                        }
                        std::thread::sleep(std::time::Duration::from_micros(100));
                        finished.fetch_add(1, SeqCst);
                    })
                })
            })
        }));
        assert!(result.is_err());
        // Every chunk claimed before the panic closed the step has finished by now.
        assert!(finished.load(SeqCst) <= 15);
    }
}
