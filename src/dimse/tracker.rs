//! Series completion by stable age (as Orthanc's `StableAge`, the rule of [`crate::app::arrivals`], which
//! STOW-RS shares): a series is complete when no instance of it arrived for the configured time; it is then
//! sealed (its folder handed over) and announced.

use std::collections::HashSet;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use super::inbox::Inbox;
use crate::app::arrivals::{self, Arrivals, Arriving};

/// A series that stopped arriving: its instances are the `.dcm` files of `folder`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CompletedSeries {
    pub series_uid: String,
    pub study_uid: String,
    pub folder: PathBuf,
    pub instances: usize,
    pub bytes: u64,
    /// The AE title that sent it (the last caller, if several); empty after a restart.
    pub calling_ae: String,
}

/// The series still arriving, and the inbox they are filed in.
#[derive(Debug)]
pub struct Tracker {
    inbox: Inbox,
    arriving: Mutex<Arrivals>,
    /// Series a pull waits for: never sealed by their stable age, taken by the pull itself.
    claimed: Mutex<HashSet<String>>,
}

/// Which instance arrived, for filing.
#[derive(Debug, Clone, Copy)]
pub struct Arrival<'a> {
    pub study_uid: &'a str,
    pub series_uid: &'a str,
    pub sop_instance_uid: &'a str,
    pub calling_ae: &'a str,
    pub bytes: u64,
}

impl Tracker {
    /// A tracker over `inbox`; series left in `incoming/` by a restart count as arriving now.
    pub fn new(inbox: Inbox, stable_age: Duration) -> io::Result<Self> {
        let mut arriving = Arrivals::new(stable_age);
        for (uid, folder) in inbox.leftover_incoming()? {
            let (instances, bytes) = count(&folder)?;
            arriving.resume(
                &uid,
                Arriving {
                    study_uid: String::new(),
                    last: Instant::now(),
                    instances,
                    bytes,
                    calling_ae: String::new(),
                },
            );
        }
        Ok(Self {
            inbox,
            arriving: Mutex::new(arriving),
            claimed: Mutex::new(HashSet::new()),
        })
    }

    pub fn inbox(&self) -> &Inbox {
        &self.inbox
    }

    /// File a checked instance (blocking: call off the async threads). An instance filed again replaces
    /// its earlier copy and does not count twice. Returns once the instance is durably in its series
    /// folder (that folder synced after the lock is released).
    pub fn file(&self, temp: &Path, a: Arrival<'_>) -> io::Result<PathBuf> {
        let filed = {
            let mut arriving = self
                .arriving
                .lock()
                .map_err(|_| io::Error::other("series tracker poisoned"))?;
            let filed = self.inbox.file(temp, a.series_uid, a.sop_instance_uid)?;
            arriving.note(
                arrivals::Arrival {
                    study_uid: a.study_uid,
                    series_uid: a.series_uid,
                    calling_ae: a.calling_ae,
                    bytes: a.bytes,
                    new: !filed.replaced,
                },
                Instant::now(),
            );
            filed
        };
        filed.sync()?;
        Ok(filed.path)
    }

    /// Series arriving now: (series UID, instances so far).
    pub fn arriving(&self) -> Vec<(String, usize)> {
        self.arriving.lock().map(|a| a.list()).unwrap_or_default()
    }

    /// Seal every series whose last instance is older than the stable age at `now` (blocking).
    pub fn seal_due(&self, now: Instant) -> io::Result<Vec<CompletedSeries>> {
        let mut arriving = self
            .arriving
            .lock()
            .map_err(|_| io::Error::other("series tracker poisoned"))?;
        let claimed = self
            .claimed
            .lock()
            .map_err(|_| io::Error::other("series tracker poisoned"))?;
        let due = arriving.due(now, |uid| claimed.contains(uid));
        let mut out = Vec::new();
        for uid in due {
            let Some(a) = arriving.remove(&uid) else {
                continue;
            };
            let folder = self.inbox.seal(&uid)?;
            tracing::info!(series_uid = %uid, instances = a.instances, calling_ae = %a.calling_ae, "series complete");
            out.push(CompletedSeries {
                series_uid: uid,
                study_uid: a.study_uid,
                folder,
                instances: a.instances,
                bytes: a.bytes,
                calling_ae: a.calling_ae,
            });
        }
        Ok(out)
    }
}

impl Tracker {
    /// Keep series `uid` from being sealed by its stable age, for a pull that takes it itself; false when
    /// another pull holds it.
    pub fn claim(&self, uid: &str) -> bool {
        self.claimed
            .lock()
            .map(|mut c| c.insert(uid.to_string()))
            .unwrap_or(false)
    }

    /// Let series `uid` be sealed by its stable age again.
    pub fn unclaim(&self, uid: &str) {
        if let Ok(mut c) = self.claimed.lock() {
            c.remove(uid);
        }
    }

    /// Instances of series `uid` filed since it last started arriving.
    pub fn arrived(&self, uid: &str) -> usize {
        self.arriving
            .lock()
            .ok()
            .and_then(|a| a.get(uid).map(|s| s.instances))
            .unwrap_or(0)
    }

    /// Seal series `uid` now, whatever its age (blocking); `None` when nothing of it arrived.
    pub fn take(&self, uid: &str) -> io::Result<Option<CompletedSeries>> {
        let mut arriving = self
            .arriving
            .lock()
            .map_err(|_| io::Error::other("series tracker poisoned"))?;
        let Some(a) = arriving.remove(uid) else {
            return Ok(None);
        };
        let folder = self.inbox.seal(uid)?;
        Ok(Some(CompletedSeries {
            series_uid: uid.to_string(),
            study_uid: a.study_uid,
            folder,
            instances: a.instances,
            bytes: a.bytes,
            calling_ae: a.calling_ae,
        }))
    }

    /// Remove what arrived of series `uid` (blocking): a pull that failed or was canceled leaves nothing.
    pub fn discard(&self, uid: &str) -> io::Result<()> {
        if let Some(done) = self.take(uid)? {
            std::fs::remove_dir_all(done.folder)?;
        }
        Ok(())
    }
}

/// `.dcm` files of a folder and their total size.
pub fn count(folder: &Path) -> io::Result<(usize, u64)> {
    let (mut n, mut bytes) = (0, 0);
    for entry in std::fs::read_dir(folder)? {
        let entry = entry?;
        if entry.path().extension().is_some_and(|e| e == "dcm") {
            n += 1;
            bytes += entry.metadata()?.len();
        }
    }
    Ok((n, bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arrival<'a>(series: &'a str, sop: &'a str) -> Arrival<'a> {
        Arrival {
            study_uid: "1.2",
            series_uid: series,
            sop_instance_uid: sop,
            calling_ae: "SCU",
            bytes: 4,
        }
    }

    #[test]
    fn a_series_is_sealed_once_it_has_been_quiet_for_the_stable_age() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let tracker = Tracker::new(inbox, Duration::from_secs(5)).unwrap();
        let temp = |name: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, b"DATA").unwrap();
            p
        };
        tracker
            .file(&temp("a"), arrival("1.2.3", "1.2.3.1"))
            .unwrap();
        tracker
            .file(&temp("b"), arrival("1.2.3", "1.2.3.2"))
            .unwrap();
        // The same instance again replaces the first copy.
        tracker
            .file(&temp("c"), arrival("1.2.3", "1.2.3.2"))
            .unwrap();
        tracker
            .file(&temp("d"), arrival("1.2.4", "1.2.4.1"))
            .unwrap();
        let t0 = Instant::now();
        assert!(tracker.seal_due(t0).unwrap().is_empty());
        let done = tracker.seal_due(t0 + Duration::from_secs(6)).unwrap();
        assert_eq!(done.len(), 2);
        let s = done.iter().find(|s| s.series_uid == "1.2.3").unwrap();
        assert_eq!((s.instances, s.bytes, s.calling_ae.as_str()), (2, 8, "SCU"));
        assert_eq!(count(&s.folder).unwrap(), (2, 8));
        assert!(tracker.arriving().is_empty());
    }

    #[test]
    fn a_claimed_series_is_not_sealed_by_age_and_is_taken_or_discarded_by_its_pull() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let tracker = Tracker::new(inbox.clone(), Duration::ZERO).unwrap();
        let temp = |name: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, b"DATA").unwrap();
            p
        };
        assert!(tracker.claim("1.5"));
        assert!(!tracker.claim("1.5"), "one pull at a time");
        tracker.file(&temp("a"), arrival("1.5", "1.5.1")).unwrap();
        tracker.file(&temp("b"), arrival("1.5", "1.5.2")).unwrap();
        tracker.file(&temp("c"), arrival("1.6", "1.6.1")).unwrap();
        assert_eq!(tracker.arrived("1.5"), 2);
        let sealed = tracker.seal_due(Instant::now()).unwrap();
        assert_eq!(
            sealed
                .iter()
                .map(|s| s.series_uid.as_str())
                .collect::<Vec<_>>(),
            vec!["1.6"]
        );
        let taken = tracker.take("1.5").unwrap().unwrap();
        assert_eq!((taken.instances, count(&taken.folder).unwrap().0), (2, 2));
        assert_eq!(tracker.take("1.5").unwrap(), None);

        tracker.file(&temp("d"), arrival("1.5", "1.5.3")).unwrap();
        tracker.discard("1.5").unwrap();
        assert_eq!(tracker.arrived("1.5"), 0);
        assert!(inbox.leftover_incoming().unwrap().is_empty());
        let complete = inbox.leftover_complete().unwrap();
        assert_eq!(complete.len(), 2, "1.6 sealed by age, 1.5 taken");
        assert!(complete.contains(&taken.folder));
        tracker.unclaim("1.5");
        assert!(tracker.claim("1.5"));
    }

    #[test]
    fn series_left_arriving_by_a_restart_are_picked_up_again() {
        let dir = tempfile::tempdir().unwrap();
        let inbox = Inbox::open(dir.path()).unwrap();
        let tracker = Tracker::new(inbox.clone(), Duration::ZERO).unwrap();
        let p = dir.path().join("x");
        std::fs::write(&p, b"DATA").unwrap();
        tracker.file(&p, arrival("1.9", "1.9.1")).unwrap();
        drop(tracker);
        let again = Tracker::new(Inbox::open(dir.path()).unwrap(), Duration::ZERO).unwrap();
        assert_eq!(again.arriving(), vec![("1.9".to_string(), 1)]);
        let done = again.seal_due(Instant::now()).unwrap();
        assert_eq!(done[0].instances, 1);
    }
}
