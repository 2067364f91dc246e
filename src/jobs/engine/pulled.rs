//! The input of a volume job pulled from a PACS: the engine hands it to the installed [`SeriesPuller`]
//! and keeps the job's lease and progress alive while the peer sends it.

use std::sync::{Arc, Mutex};

use super::progress::{Latest, Sink};
use super::{Engine, heartbeat_interval};
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::PacsSeries;
use crate::jobs::pull::{PULL_SHARE, Scaled, SeriesPuller};
use crate::jobs::run::RunError;
use crate::recon::control::Cancel;
use crate::storage::{JobId, SeriesId};

impl Engine {
    /// Install the puller of series from PACS peers (the DICOM node does, once it listens); false when one
    /// was installed already.
    pub fn install_puller(&self, puller: Arc<dyn SeriesPuller>) -> bool {
        self.inner.puller.set(puller).is_ok()
    }

    /// Whether this engine can pull series from PACS peers (a DICOM node runs in this process).
    pub fn can_pull(&self) -> bool {
        self.inner.puller.get().is_some()
    }

    /// Pull the series of a running job, renewing its lease and persisting its progress meanwhile.
    pub(super) async fn pull_input(
        &self,
        id: JobId,
        attempt: u32,
        source: &PacsSeries,
        cancel: &Cancel,
        sink: &Sink,
        latest: &Mutex<Latest>,
    ) -> Result<SeriesId, RunError> {
        let Some(puller) = self.inner.puller.get().cloned() else {
            return Err(RunError::Failed(Problem::new(
                ErrorCode::DicomNodeOff,
                "no DICOM node runs in the process that ran this job: a series cannot be pulled here",
            )));
        };
        let progress = Scaled {
            inner: sink,
            start: 0.0,
            span: PULL_SHARE,
        };
        let pull = puller.pull(source, cancel, &progress);
        tokio::pin!(pull);
        let mut tick = tokio::time::interval(self.inner.config.progress_interval);
        let mut heartbeat = tokio::time::interval(heartbeat_interval(self.inner.config.lease));
        loop {
            tokio::select! {
                r = &mut pull => return r,
                _ = tick.tick() => self.persist_progress(id, attempt, latest).await,
                _ = heartbeat.tick() => self.renew(id, attempt, cancel).await,
            }
        }
    }
}
