//! Series received by STOW-RS, assembled once stable: every stored instance counts as an arrival of its
//! series ([`super::arrivals`], the rule the DICOM node uses); a series quiet for the stable age is assembled
//! from the received instances the index holds of it (the newest copy of each SOP instance, whichever
//! request brought it), recorded like an uploaded series, its instances linked to it, and the processing
//! rules fired. The instances stay indexed whatever the assembly says (a Secondary Capture or a broken slice
//! makes no series, and is still served).
//!
//! This runs whether or not the DICOM node listens. Instances indexed as pending and not yet assembled when
//! the process stopped are taken up at the next start, as arriving then. With several processes on one
//! PostgreSQL database each assembles the series it received; the pending instances of a series are claimed
//! by the assembling process, so another one (taking up pending series at its start, or those of a lost
//! process every [`ASSEMBLY_CLAIM`]) does not assemble the same arrival again.

use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tracing::Instrument as _;

use super::arrivals::{Arrival, Arrivals, Arriving};
use super::{App, AppResult};
use crate::dicom::UploadFile;
use crate::jobs::model::now_us;
use crate::jobs::model::{IndexScope, IndexedInstance, StoredInstance};
use crate::storage::InstanceOwner;

/// How long the received instances of a series being assembled stay this process's (an assembly that takes
/// longer may be repeated by another process of a shared database; the instances are then linked to the
/// later series).
pub const ASSEMBLY_CLAIM: Duration = Duration::from_secs(600);

/// The series arriving by STOW-RS; shared by every clone of the [`App`].
#[derive(Debug)]
pub struct StowSeries {
    arrivals: Mutex<Arrivals>,
    started: AtomicBool,
}

impl StowSeries {
    pub fn new(stable_age: Duration) -> Arc<Self> {
        Arc::new(Self {
            arrivals: Mutex::new(Arrivals::new(stable_age)),
            started: AtomicBool::new(false),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Arrivals> {
        // Every change is one call on the map: a panic while holding the lock leaves it consistent.
        self.arrivals.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl App {
    /// Count stored instances as arrivals of their series (now), and make sure assembly runs.
    pub(super) fn stowed<'a>(&self, instances: impl Iterator<Item = &'a IndexedInstance>) {
        {
            let mut a = self.stow_series.lock();
            let now = Instant::now();
            for i in instances {
                a.note(
                    Arrival {
                        study_uid: &i.study_uid,
                        series_uid: &i.series_uid,
                        calling_ae: "",
                        bytes: i.bytes,
                        new: true,
                    },
                    now,
                );
            }
        }
        self.spawn_stow_assembly();
    }

    /// Series arriving by STOW-RS now: (series UID, instances so far).
    pub fn stow_arriving(&self) -> Vec<(String, usize)> {
        self.stow_series.lock().list()
    }

    /// Start assembling the series received by STOW-RS once stable (once per process). Series left pending
    /// by an earlier run are taken up first; on a shared database, those left by a lost process are taken
    /// up again every [`ASSEMBLY_CLAIM`] (a series another process is assembling is skipped: it holds the
    /// claim on its instances).
    pub fn spawn_stow_assembly(&self) {
        if self.stow_series.started.swap(true, Ordering::SeqCst) {
            return;
        }
        let app = self.clone();
        tokio::spawn(async move {
            match app.db.release_instance_claims().await {
                Ok(0) => {}
                Ok(n) => {
                    tracing::info!(instances = n, "claims of an interrupted assembly released")
                }
                Err(e) => {
                    tracing::error!(error = %e, "claims of an interrupted assembly cannot be released")
                }
            }
            app.resume_pending_series().await;
            let mut resumed = Instant::now();
            let tick = app.stow_series.lock().tick();
            loop {
                tokio::time::sleep(tick).await;
                if app.db.is_shared() && resumed.elapsed() >= ASSEMBLY_CLAIM {
                    app.resume_pending_series().await;
                    resumed = Instant::now();
                }
                let due = {
                    let mut a = app.stow_series.lock();
                    let due = a.due(Instant::now(), |_| false);
                    for uid in &due {
                        a.remove(uid);
                    }
                    due
                };
                for uid in due {
                    let span = tracing::info_span!("stowed_series", series_uid = %uid);
                    if let Err(e) = app.assemble_stowed(&uid).instrument(span).await {
                        tracing::error!(series_uid = %uid, error = %e, "a series received by STOW-RS was not assembled");
                    }
                }
            }
        });
    }

    /// Count the series with received instances pending assembly as arriving now (those this process
    /// tracks already stay as they are).
    async fn resume_pending_series(&self) {
        match self.db.pending_series().await {
            Ok(pending) => {
                let mut a = self.stow_series.lock();
                for (uid, study_uid) in pending {
                    if a.get(&uid).is_some() {
                        continue;
                    }
                    tracing::info!(series_uid = %uid, "a series received by STOW-RS is taken up again");
                    a.resume(
                        &uid,
                        Arriving {
                            study_uid,
                            last: Instant::now(),
                            instances: 0,
                            bytes: 0,
                            calling_ae: String::new(),
                        },
                    );
                }
            }
            Err(e) => tracing::error!(error = %e, "series pending assembly cannot be listed"),
        }
    }

    /// Assemble series `uid` from the received instances the index holds of it, link them to the series
    /// made and fire the processing rules. Its pending instances are claimed first: when another assembly
    /// (of this or another process) holds them all, or none is pending, there is nothing to do.
    async fn assemble_stowed(&self, uid: &str) -> AppResult<()> {
        let now = now_us();
        let until = now.saturating_add(ASSEMBLY_CLAIM.as_micros() as i64);
        if self
            .db
            .claim_pending_instances(uid, now, until)
            .await?
            .is_empty()
        {
            tracing::info!(series_uid = %uid, "no instance of the series is left to assemble here");
            return Ok(());
        }
        let scope = IndexScope {
            study_uid: None,
            series_uid: Some(uid.to_string()),
        };
        let received: Vec<StoredInstance> = self
            .db
            .indexed_instances(&scope)
            .await?
            .into_iter()
            .filter(|r| matches!(r.owner, InstanceOwner::Upload(_)))
            .collect();
        if received.is_empty() {
            return Ok(());
        }
        // Newest first: the newest copy of each SOP instance.
        let mut seen = HashSet::new();
        let used: Vec<&StoredInstance> = received
            .iter()
            .filter(|r| seen.insert(r.instance.sop_instance_uid.clone()))
            .collect();
        let files: Vec<UploadFile> = used
            .iter()
            .map(|r| UploadFile {
                label: r.instance.sop_instance_uid.clone(),
                path: self.instance_file(r),
            })
            .collect();
        let bytes = used.iter().map(|r| r.instance.bytes).sum();
        let r = self.record_received(files, bytes).await?;
        let series = r
            .ingested
            .ready()
            .find(|s| s.series_uid == uid)
            .map(|s| s.id);
        let ids: Vec<_> = received.iter().map(|r| r.id).collect();
        self.db.settle_instances(&ids, series).await?;
        tracing::info!(upload_id = %r.upload_id, series_uid = %uid, instances = used.len(), series_id = ?series, "series received by STOW-RS assembled");
        self.fire_rules(&r.ingested, None).await;
        Ok(())
    }
}
