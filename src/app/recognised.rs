//! Series sent again: what every door does with a series whose instances ctrecon holds already (the
//! instances themselves follow [`super::instances::resent`]: one received copy per SOP Instance UID).
//!
//! - After assembly, every door ([`App::recognise_series`]): a ready series whose record equals a stored
//!   series' in everything but its id, upload and time (the same Series Instance UID, volume bytes,
//!   geometry, patient and study, instance count, transfer syntaxes and warnings) is answered as that stored
//!   series, with the warning `series_already_stored`: no series row and no volume are added, and the
//!   processing rules, which run once per series content, do not run again.
//! - Before assembly, C-STORE ([`App::receive_series`]; STOW-RS alike, since a request of copies only leaves
//!   nothing pending): an arrival that brought only copies the index holds assembles nothing. One that
//!   brought new or changed instances is assembled with the stored copies of the rest of its series, so the
//!   series is rebuilt once and whole, however few of its instances were sent again.

use std::collections::HashSet;

use serde_json::Value;

use super::series::Received;
use super::{App, AppResult};
use crate::dicom::UploadFile;
use crate::jobs::SeriesRecord;
use crate::jobs::ingest::{Ingested, Staged};
use crate::jobs::model::{IndexScope, StoredInstance};
use crate::series::Warning;
use crate::storage::sweep::BlobKind;
use crate::storage::{InstanceOwner, SeriesId};

/// Whether two JSON values are equal, numbers within a relative 1e-9 (a record read back from the database
/// went through decimal text).
fn close(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => match (x.as_f64(), y.as_f64()) {
            (Some(x), Some(y)) => (x - y).abs() <= 1e-9 * x.abs().max(y.abs()).max(1e-300),
            _ => x == y,
        },
        (Value::Array(x), Value::Array(y)) => {
            x.len() == y.len() && x.iter().zip(y).all(|(x, y)| close(x, y))
        }
        (Value::Object(x), Value::Object(y)) => {
            x.len() == y.len() && x.iter().all(|(k, v)| y.get(k).is_some_and(|w| close(v, w)))
        }
        _ => a == b,
    }
}

/// Whether `stored` holds what `made` holds, but for the ids and the time.
pub fn same_series(stored: &SeriesRecord, made: &SeriesRecord) -> bool {
    let bare = |r: &SeriesRecord| {
        let mut v = serde_json::to_value(r).unwrap_or_default();
        if let Some(m) = v.as_object_mut() {
            for k in ["id", "upload_id", "created_us"] {
                m.remove(k);
            }
        }
        v
    };
    stored.series_uid == made.series_uid && close(&bare(stored), &bare(made))
}

impl App {
    /// Answer each ready series of `ingested` that equals a stored series ([`same_series`], its volume still
    /// there) as that stored series, with the warning `series_already_stored`, its staged volume discarded.
    /// Returns the ids of the stored series answered; the other ready series are new. A database failure
    /// here is logged and the series counts as new.
    pub async fn recognise_series(
        &self,
        ingested: &mut Ingested,
        staged: &mut Staged,
    ) -> HashSet<SeriesId> {
        let mut known = HashSet::new();
        for outcome in ingested.series.iter_mut() {
            let Some(made) = &outcome.series else {
                continue;
            };
            let stored = match self.db.series_with_uid(&made.series_uid).await {
                Ok(s) => s,
                Err(e) => {
                    tracing::warn!(error = %e, "stored series could not be compared with a new one");
                    continue;
                }
            };
            let Some(same) = stored.into_iter().find(|s| same_series(s, made)) else {
                continue;
            };
            let lost = self
                .db
                .blob_missing(BlobKind::Series, &same.id.to_string())
                .await
                .unwrap_or(true);
            if lost {
                continue;
            }
            if let Some(temp) = staged.take(made.id) {
                temp.discard().await;
            }
            tracing::info!(series_id = %same.id, series_uid = %same.series_uid, "the series was stored already with the same content");
            outcome.report.warnings.push(Warning {
                code: "series_already_stored",
                message: format!(
                    "series {} was stored already with the same content (series {}): no new series is made",
                    same.series_uid, same.id
                ),
            });
            known.insert(same.id);
            outcome.series = Some(same);
        }
        known
    }

    /// Assemble and record a series the DICOM node received whole (`files`, the instances of its folder,
    /// all of Series Instance UID `series_uid`, sent by `calling_ae`), fire the processing rules and index its
    /// instances; `None` when every instance is a copy the index holds (nothing is assembled or recorded).
    /// New and changed instances are assembled with the stored copies of the rest of the series, whose rows
    /// are then linked to the series made.
    pub async fn receive_series(
        &self,
        series_uid: &str,
        files: Vec<UploadFile>,
        calling_ae: Option<&str>,
    ) -> AppResult<Option<Received>> {
        let paths = files.iter().map(|f| f.path.clone()).collect();
        let arrived = self.read_arrived(paths).await?;
        let read = arrived.len();
        let sorted = self.sort_arrived(arrived).await?;
        if read > 0 && read == files.len() && sorted.fresh.is_empty() {
            tracing::info!(
                series_uid,
                recognised = sorted.recognised.len(),
                repeated = sorted.repeated.len(),
                "the series was sent again unchanged: nothing is assembled"
            );
            return Ok(None);
        }
        let here: HashSet<&str> = sorted
            .fresh
            .iter()
            .chain(sorted.recognised.iter().map(|(a, _)| a))
            .chain(&sorted.repeated)
            .map(|a| a.instance.sop_instance_uid.as_str())
            .collect();
        let scope = IndexScope {
            study_uid: None,
            series_uid: Some(series_uid.to_string()),
        };
        let mut seen = HashSet::new();
        let others: Vec<StoredInstance> = self
            .db
            .indexed_instances(&scope)
            .await?
            .into_iter()
            .filter(|r| matches!(r.owner, InstanceOwner::Upload(_)))
            .filter(|r| !here.contains(r.instance.sop_instance_uid.as_str()))
            .filter(|r| seen.insert(r.instance.sop_instance_uid.clone()))
            .collect();
        let bytes = sorted
            .fresh
            .iter()
            .chain(sorted.recognised.iter().map(|(a, _)| a))
            .map(|a| a.instance.bytes)
            .chain(others.iter().map(|r| r.instance.bytes))
            .sum();
        let mut all = files;
        all.extend(others.iter().map(|r| UploadFile {
            label: r.instance.sop_instance_uid.clone(),
            path: self.instance_file(r),
        }));
        if !others.is_empty() {
            tracing::info!(
                series_uid,
                stored = others.len(),
                "the series is assembled with its stored instances"
            );
        }
        let received = self.ingest_received_from(all, bytes, calling_ae).await?;
        let records: Vec<SeriesRecord> = received.ingested.ready().cloned().collect();
        if let Err(e) = self
            .index_sorted(received.upload_id, sorted, &records)
            .await
        {
            tracing::error!(upload_id = %received.upload_id, error = %e, "received instances not indexed");
        }
        if let Some(s) = records.iter().find(|s| s.series_uid == series_uid)
            && !others.is_empty()
        {
            let ids: Vec<_> = others.iter().map(|r| r.id).collect();
            self.db.settle_instances(&ids, Some(s.id)).await?;
        }
        Ok(Some(received))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_read_back_through_text_are_equal_and_other_values_are_not() {
        let a = serde_json::json!({"x": [0.1, 2.0], "s": "1.2", "n": null});
        let b = serde_json::json!({"x": [0.1 + 1e-17, 2.0], "s": "1.2", "n": null});
        assert!(close(&a, &b));
        assert!(!close(
            &a,
            &serde_json::json!({"x": [0.1, 2.1], "s": "1.2", "n": null})
        ));
        assert!(!close(
            &a,
            &serde_json::json!({"x": [0.1, 2.0], "s": "1.3", "n": null})
        ));
        assert!(!close(
            &a,
            &serde_json::json!({"x": [0.1, 2.0], "s": "1.2"})
        ));
    }
}
