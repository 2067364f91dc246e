//! Per-view (or per-row) progress of one stage, counted across threads.

use std::sync::atomic::{AtomicUsize, Ordering};

use crate::recon::control::Control;

/// Counts finished items of a stage and reports the fraction done after each.
pub(crate) struct Ticker<'a> {
    ctl: Control<'a>,
    stage: &'static str,
    total: usize,
    done: AtomicUsize,
}

impl<'a> Ticker<'a> {
    pub fn new(ctl: Control<'a>, stage: &'static str, total: usize) -> Self {
        ctl.step(stage, 0.0);
        Self {
            ctl,
            stage,
            total: total.max(1),
            done: AtomicUsize::new(0),
        }
    }
    /// One more item done.
    pub fn tick(&self) {
        self.add(1);
    }
    /// `n` more items done.
    pub fn add(&self, n: usize) {
        let done = self.done.fetch_add(n, Ordering::Relaxed) + n;
        self.ctl.step(self.stage, done as f64 / self.total as f64);
    }
}
