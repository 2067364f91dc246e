//! Cancellation and progress for long-running core functions.
//!
//! Every long computation takes a [`Control`]: a [`Cancel`] flag checked at least once per view, slice or
//! iteration, and a [`Progress`] sink. Cancelling makes the function return [`ReconError::Canceled`].

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::error::ReconError;

/// A shared cancel flag; cloning shares the flag.
#[derive(Debug, Clone, Default)]
pub struct Cancel(Arc<AtomicBool>);

impl Cancel {
    pub fn new() -> Self {
        Self::default()
    }
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }
    pub fn is_canceled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }
    /// `Err(Canceled)` once the flag is set.
    pub fn check(&self) -> Result<(), ReconError> {
        if self.is_canceled() {
            Err(ReconError::Canceled)
        } else {
            Ok(())
        }
    }
}

/// Receives progress reports. `fraction` is in [0, 1] over the whole call; `stage` names the step;
/// `residual` is ‖Ax − b‖ for iterative methods.
pub trait Progress: Send + Sync {
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>);
}

/// A progress sink that ignores everything.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn report(&self, _: &str, _: f64, _: Option<usize>, _: Option<f64>) {}
}

impl<F> Progress for F
where
    F: Fn(&str, f64, Option<usize>, Option<f64>) + Send + Sync,
{
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>) {
        self(stage, fraction, iteration, residual)
    }
}

/// A cancel flag and a progress sink, passed together to every long computation.
#[derive(Clone, Copy)]
pub struct Control<'a> {
    pub cancel: &'a Cancel,
    pub progress: &'a dyn Progress,
}

impl<'a> Control<'a> {
    pub fn new(cancel: &'a Cancel, progress: &'a dyn Progress) -> Self {
        Self { cancel, progress }
    }
    /// Check the cancel flag.
    pub fn check(&self) -> Result<(), ReconError> {
        self.cancel.check()
    }
    /// Report progress of a stage without iteration data.
    pub fn step(&self, stage: &str, fraction: f64) {
        self.progress
            .report(stage, fraction.clamp(0.0, 1.0), None, None);
    }
}

/// A `Control` that never cancels and reports nowhere: for tests, examples and benchmarks.
pub fn unattended() -> Control<'static> {
    static CANCEL: std::sync::LazyLock<Cancel> = std::sync::LazyLock::new(Cancel::new);
    Control {
        cancel: &CANCEL,
        progress: &NoProgress,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cancel_is_shared_between_clones_and_reported_as_canceled() {
        let a = Cancel::new();
        let b = a.clone();
        assert!(a.check().is_ok());
        b.cancel();
        assert_eq!(a.check(), Err(ReconError::Canceled));
    }
}
