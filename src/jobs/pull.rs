//! Volume jobs whose series comes from a PACS: the port through which the engine pulls it
//! ([`SeriesPuller`], filled by the DICOM front door, which runs C-FIND and C-MOVE and assembles what
//! arrives like an upload), and the progress of such a job (retrieval first, then the volume work scaled
//! into the rest of the bar).

use std::future::Future;
use std::pin::Pin;

use super::model::PacsSeries;
use super::run::RunError;
use crate::recon::control::{Cancel, Progress};
use crate::storage::SeriesId;

/// A boxed future (the port's method is async).
pub type PullFuture<'a> = Pin<Box<dyn Future<Output = Result<SeriesId, RunError>> + Send + 'a>>;

/// Share of a pulled job's progress bar that the retrieval and assembly take.
pub const PULL_SHARE: f64 = 0.4;

/// Pulls a series from a PACS and stores it as a series: the port the DICOM node implements.
pub trait SeriesPuller: Send + Sync + 'static {
    /// Find `source` on its peer, retrieve it to this node, assemble it and return the stored series.
    /// Reports progress in [0, 1] of the retrieval; stops with [`RunError::Canceled`] soon after `cancel`
    /// is set; a peer that fails, holds no such series or goes silent ends it with a problem that says so.
    fn pull<'a>(
        &'a self,
        source: &'a PacsSeries,
        cancel: &'a Cancel,
        progress: &'a dyn Progress,
    ) -> PullFuture<'a>;
}

/// Progress of one part of a job mapped onto `[start, start + span]` of the whole bar.
pub struct Scaled<'a> {
    pub inner: &'a dyn Progress,
    pub start: f64,
    pub span: f64,
}

impl Progress for Scaled<'_> {
    fn report(&self, stage: &str, fraction: f64, iteration: Option<usize>, residual: Option<f64>) {
        let f = self.start + self.span * fraction.clamp(0.0, 1.0);
        self.inner.report(stage, f, iteration, residual);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn scaled_progress_lands_inside_its_share_of_the_bar() {
        let seen = Mutex::new(Vec::new());
        let record = |s: &str, f: f64, _: Option<usize>, _: Option<f64>| {
            seen.lock().unwrap().push((s.to_string(), f))
        };
        let after_pull = Scaled {
            inner: &record,
            start: PULL_SHARE,
            span: 1.0 - PULL_SHARE,
        };
        after_pull.report("loading", 0.0, None, None);
        after_pull.report("mip", 0.5, None, None);
        after_pull.report("done", 2.0, None, None);
        let seen = seen.into_inner().unwrap();
        assert_eq!(seen[0], ("loading".to_string(), 0.4));
        assert!((seen[1].1 - 0.7).abs() < 1e-12);
        assert_eq!(seen[2].1, 1.0);
    }
}
