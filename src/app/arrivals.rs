//! Series completion by stable age (as Orthanc's `StableAge`), shared by the doors that receive a series
//! instance by instance — the DICOM node's C-STORE (`dimse::tracker`, which files the instances in its
//! inbox) and STOW-RS (`app::stow`, which indexes them at once): a series is complete when no instance of
//! it arrived for the stable age, however many associations or requests brought it.
//!
//! Pure bookkeeping: the caller gives the time of each arrival and asks which series are due at a time it
//! gives, so the rule is tested without a clock.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// What arrived of one series so far.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Arriving {
    pub study_uid: String,
    /// When its last instance arrived.
    pub last: Instant,
    pub instances: usize,
    pub bytes: u64,
    /// The AE title that sent it (the last caller, if several); empty when unknown (STOW-RS, a restart).
    pub calling_ae: String,
}

/// The series still arriving, by Series Instance UID.
#[derive(Debug)]
pub struct Arrivals {
    stable_age: Duration,
    series: HashMap<String, Arriving>,
}

/// One instance that arrived, for [`Arrivals::note`].
#[derive(Debug, Clone, Copy)]
pub struct Arrival<'a> {
    pub study_uid: &'a str,
    pub series_uid: &'a str,
    pub calling_ae: &'a str,
    pub bytes: u64,
    /// False when it replaced an instance that had arrived already (it does not count twice).
    pub new: bool,
}

impl Arrivals {
    pub fn new(stable_age: Duration) -> Self {
        Self {
            stable_age,
            series: HashMap::new(),
        }
    }

    pub fn stable_age(&self) -> Duration {
        self.stable_age
    }

    /// How often a caller should ask for due series: a quarter of the stable age, 0.1 s to 1 s.
    pub fn tick(&self) -> Duration {
        (self.stable_age / 4).clamp(Duration::from_millis(100), Duration::from_secs(1))
    }

    /// Count an instance that arrived at `now`; its series starts ageing again.
    pub fn note(&mut self, a: Arrival<'_>, now: Instant) {
        let entry = self
            .series
            .entry(a.series_uid.to_string())
            .or_insert_with(|| Arriving {
                study_uid: a.study_uid.to_string(),
                last: now,
                instances: 0,
                bytes: 0,
                calling_ae: a.calling_ae.to_string(),
            });
        entry.last = now;
        if a.new {
            entry.instances += 1;
            entry.bytes += a.bytes;
        }
        if !a.study_uid.is_empty() {
            entry.study_uid = a.study_uid.to_string();
        }
        entry.calling_ae = a.calling_ae.to_string();
    }

    /// Take up a series found arriving at a start (its instances were kept by an earlier run).
    pub fn resume(&mut self, series_uid: &str, arriving: Arriving) {
        self.series.insert(series_uid.to_string(), arriving);
    }

    /// The series quiet for the stable age at `now`, except those `held` keeps, in UID order; they stay
    /// until [`Arrivals::remove`]d.
    pub fn due(&self, now: Instant, held: impl Fn(&str) -> bool) -> Vec<String> {
        let mut due: Vec<String> = self
            .series
            .iter()
            .filter(|(uid, _)| !held(uid))
            .filter(|(_, a)| now.saturating_duration_since(a.last) >= self.stable_age)
            .map(|(uid, _)| uid.clone())
            .collect();
        due.sort();
        due
    }

    pub fn remove(&mut self, series_uid: &str) -> Option<Arriving> {
        self.series.remove(series_uid)
    }

    pub fn get(&self, series_uid: &str) -> Option<&Arriving> {
        self.series.get(series_uid)
    }

    /// Series arriving now: (series UID, instances so far), in UID order.
    pub fn list(&self) -> Vec<(String, usize)> {
        let mut v: Vec<_> = self
            .series
            .iter()
            .map(|(k, a)| (k.clone(), a.instances))
            .collect();
        v.sort();
        v
    }

    pub fn is_empty(&self) -> bool {
        self.series.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arrival(series: &str, new: bool) -> Arrival<'_> {
        Arrival {
            study_uid: "1.2",
            series_uid: series,
            calling_ae: "SCU",
            bytes: 10,
            new,
        }
    }

    #[test]
    fn a_series_is_due_once_quiet_for_the_stable_age_however_its_instances_came() {
        let mut a = Arrivals::new(Duration::from_secs(5));
        let t0 = Instant::now();
        a.note(arrival("1.3", true), t0);
        a.note(arrival("1.3", true), t0 + Duration::from_secs(3));
        // The same instance again does not count twice, but the series ages from it.
        a.note(arrival("1.3", false), t0 + Duration::from_secs(4));
        a.note(arrival("1.4", true), t0);
        assert_eq!(a.due(t0 + Duration::from_secs(5), |_| false), vec!["1.4"]);
        assert!(
            a.due(t0 + Duration::from_secs(5), |uid| uid == "1.4")
                .is_empty()
        );
        assert_eq!(
            a.due(t0 + Duration::from_secs(9), |_| false),
            vec!["1.3", "1.4"]
        );
        let done = a.remove("1.3").unwrap();
        assert_eq!(
            (done.instances, done.bytes, done.calling_ae.as_str()),
            (2, 20, "SCU")
        );
        assert_eq!(a.list(), vec![("1.4".to_string(), 1)]);
        assert_eq!(a.tick(), Duration::from_secs(1));
        assert_eq!(
            Arrivals::new(Duration::ZERO).tick(),
            Duration::from_millis(100)
        );
    }
}
