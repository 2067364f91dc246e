//! The instance index: received instances read by scope, one received copy per SOP Instance UID, a job's
//! results indexed once, and the received instances pending assembly claimed once and settled.

use super::{Database, finished, sample_job, succeeded, volume_job};
use crate::jobs::model::{
    IndexScope, IndexedInstance, Inserted, NewInstance, ReplacedCopy, now_us,
};
use crate::storage::{InstanceId, InstanceOwner, UploadId};

const MINUTE_US: i64 = 60_000_000;

fn row(study: &str, series: &str, n: i64) -> NewInstance {
    NewInstance {
        id: InstanceId::generate(),
        series_id: None,
        instance: IndexedInstance {
            sop_class_uid: "1.2.840.10008.5.1.4.1.1.2".into(),
            sop_instance_uid: format!("{series}.{n}"),
            transfer_syntax: "1.2.840.10008.1.2.1".into(),
            study_uid: study.into(),
            series_uid: series.into(),
            patient_id: Some("P-1".into()),
            patient_name: Some("Doe^Jane".into()),
            patient_birth_date: Some("19700101".into()),
            patient_sex: Some("F".into()),
            study_date: Some("20261125".into()),
            study_time: Some("101500".into()),
            accession_number: Some("A-7".into()),
            study_description: Some("CT chest".into()),
            referring_physician: None,
            study_id: Some("S-1".into()),
            modality: Some("CT".into()),
            series_number: Some(3),
            series_description: Some("lung 1 mm".into()),
            body_part: Some("CHEST".into()),
            instance_number: Some(n),
            bytes: 1000 + n as u64,
        },
        sha256: Some(format!("{n:064x}")),
    }
}

async fn upload(db: &Database) -> UploadId {
    let id = UploadId::generate();
    assert_eq!(
        db.insert_open_upload(id, None).await.ok(),
        Some(Inserted::New)
    );
    id
}

async fn read(
    db: &Database,
    study: Option<&str>,
    series: Option<&str>,
) -> Vec<(InstanceId, IndexedInstance)> {
    let scope = IndexScope {
        study_uid: study.map(str::to_string),
        series_uid: series.map(str::to_string),
    };
    match db.indexed_instances(&scope).await {
        Ok(rows) => rows.into_iter().map(|r| (r.id, r.instance)).collect(),
        Err(e) => panic!("reading the index: {e}"),
    }
}

/// Received instances read back whole, with their owner, newest first, narrowed by study and series UID;
/// their upload is listed as owning instances.
pub async fn received_instances_are_indexed_and_read_by_scope(db: &Database) {
    let u = upload(db).await;
    let first = vec![
        row("1.1", "1.1.1", 1),
        row("1.1", "1.1.1", 2),
        row("1.1", "1.1.2", 1),
    ];
    assert_eq!(
        db.insert_instances(InstanceOwner::Upload(u), &first)
            .await
            .ok(),
        Some(true)
    );
    let later = vec![row("2.1", "2.1.1", 1)];
    assert_eq!(
        db.insert_instances(InstanceOwner::Upload(u), &later)
            .await
            .ok(),
        Some(true)
    );
    let all = db
        .indexed_instances(&IndexScope::default())
        .await
        .expect("index");
    assert_eq!(all.len(), 4);
    assert_eq!(
        (all[0].id, &all[0].instance),
        (later[0].id, &later[0].instance)
    );
    assert!(
        all.iter()
            .all(|r| r.owner == InstanceOwner::Upload(u) && r.series_id.is_none())
    );
    let mut study: Vec<InstanceId> = read(db, Some("1.1"), None)
        .await
        .into_iter()
        .map(|(id, _)| id)
        .collect();
    study.sort_by_key(|i| i.to_string());
    let mut want: Vec<InstanceId> = first.iter().map(|r| r.id).collect();
    want.sort_by_key(|i| i.to_string());
    assert_eq!(study, want);
    let series = read(db, Some("1.1"), Some("1.1.1")).await;
    assert_eq!(series.len(), 2);
    assert!(series.iter().all(|(_, i)| i.series_uid == "1.1.1"));
    assert_eq!(
        read(db, None, Some("1.1.2")).await,
        vec![(first[2].id, first[2].instance.clone())]
    );
    assert!(read(db, Some("2.1"), Some("1.1.1")).await.is_empty());
    assert_eq!(db.uploads_with_instances().await.ok(), Some(vec![u]));
}

/// A received copy of a SOP Instance UID replaces the copies indexed before, whichever upload holds them
/// (they are answered for their files to be removed), and is found by its SOP Instance UID with its hash;
/// a job's result with the same UID is not a received copy and stays.
pub async fn a_received_copy_replaces_the_one_indexed_before(db: &Database) {
    let (a, b) = (upload(db).await, upload(db).await);
    let first = vec![row("3.1", "3.1.1", 1), row("3.1", "3.1.1", 2)];
    assert_eq!(
        db.insert_received(a, &first, false).await.ok(),
        Some(vec![])
    );
    let job = finished(db, volume_job(), succeeded()).await;
    assert_eq!(
        db.insert_instances(InstanceOwner::Job(job), &[row("3.1", "3.1.1", 2)])
            .await
            .ok(),
        Some(true)
    );
    let mut again = row("3.1", "3.1.1", 2);
    again.sha256 = Some("f".repeat(64));
    assert_eq!(
        db.insert_received(b, std::slice::from_ref(&again), false)
            .await
            .ok(),
        Some(vec![ReplacedCopy {
            upload: a,
            id: first[1].id
        }])
    );
    let uids = vec![
        "3.1.1.1".to_string(),
        "3.1.1.2".to_string(),
        "9.9".to_string(),
    ];
    let copies = db.received_copies(&uids).await.expect("copies");
    let mut got: Vec<(String, InstanceId, Option<String>)> = copies
        .into_iter()
        .map(|r| (r.instance.sop_instance_uid, r.id, r.sha256))
        .collect();
    got.sort();
    assert_eq!(
        got,
        vec![
            ("3.1.1.1".into(), first[0].id, first[0].sha256.clone()),
            ("3.1.1.2".into(), again.id, again.sha256.clone()),
        ]
    );
    assert_eq!(
        read(db, None, Some("3.1.1")).await.len(),
        3,
        "two received, one result"
    );
}

/// Succeeded volume jobs are to index until their results are; indexing a job's results twice, even at
/// once, writes them once (the later call answers false); a job without instances is marked once.
pub async fn a_jobs_results_are_indexed_once(db: &Database) {
    let volume = finished(db, volume_job(), succeeded()).await;
    let _reconstruction = finished(db, sample_job(now_us()), succeeded()).await;
    let other = finished(db, volume_job(), succeeded()).await;
    assert_eq!(db.jobs_to_index().await.ok(), Some(vec![volume, other]));
    assert_eq!(db.job_indexed(volume).await.ok(), Some(false));
    let rows = vec![row("1.1", "1.1.900", 1), row("1.1", "1.1.900", 2)];
    let again = vec![row("1.1", "1.1.900", 1), row("1.1", "1.1.900", 2)];
    let owner = InstanceOwner::Job(volume);
    let (a, b) = tokio::join!(
        db.insert_instances(owner, &rows),
        db.insert_instances(owner, &again)
    );
    let (a, b) = (a.expect("index"), b.expect("index"));
    assert!(a ^ b, "exactly one indexing writes: {a} {b}");
    let indexed = read(db, None, Some("1.1.900")).await;
    assert_eq!(indexed.len(), 2);
    assert_eq!(db.insert_instances(owner, &rows).await.ok(), Some(false));
    assert_eq!(read(db, None, Some("1.1.900")).await.len(), 2);
    assert_eq!(db.job_indexed(volume).await.ok(), Some(true));
    assert_eq!(db.jobs_to_index().await.ok(), Some(vec![other]));
    assert_eq!(db.mark_job_indexed(other).await.ok(), Some(true));
    assert_eq!(db.mark_job_indexed(other).await.ok(), Some(false));
    assert_eq!(db.jobs_to_index().await.ok(), Some(vec![]));
    let owners: Vec<InstanceOwner> = db
        .indexed_instances(&IndexScope::default())
        .await
        .expect("index")
        .into_iter()
        .map(|r| r.owner)
        .collect();
    assert_eq!(owners, vec![owner, owner]);
}

/// Series with pending instances are listed oldest first; the pending instances of a series are claimed by
/// one caller at a time (two at once: one gets them), again once the claim ended, and settled ones leave
/// the pending list and cannot be claimed.
pub async fn pending_instances_are_claimed_once_and_settled(db: &Database) {
    let u = upload(db).await;
    let p = vec![row("1.1", "1.1.1", 1), row("1.1", "1.1.1", 2)];
    assert!(
        db.insert_received(u, &p, true)
            .await
            .is_ok_and(|replaced| replaced.is_empty())
    );
    tokio::time::sleep(std::time::Duration::from_millis(2)).await;
    let q = vec![row("1.1", "1.1.2", 1)];
    assert!(
        db.insert_received(u, &q, true)
            .await
            .is_ok_and(|replaced| replaced.is_empty())
    );
    let series = |v: &[(&str, &str)]| {
        v.iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect::<Vec<_>>()
    };
    assert_eq!(
        db.pending_series().await.ok(),
        Some(series(&[("1.1.1", "1.1"), ("1.1.2", "1.1")]))
    );
    let now = now_us();
    let (x, y) = tokio::join!(
        db.claim_pending_instances("1.1.1", now, now + MINUTE_US),
        db.claim_pending_instances("1.1.1", now, now + MINUTE_US)
    );
    let (x, y) = (x.expect("claim"), y.expect("claim"));
    let mut want: Vec<InstanceId> = p.iter().map(|r| r.id).collect();
    want.sort_by_key(|i| i.to_string());
    match (x.is_empty(), y.is_empty()) {
        (false, true) => assert_eq!(x, want),
        (true, false) => assert_eq!(y, want),
        _ => panic!("exactly one claim gets the instances: {x:?} {y:?}"),
    }
    assert!(db.settle_instances(&want, None).await.is_ok());
    assert!(db.settle_instances(&want, None).await.is_ok());
    assert_eq!(
        db.pending_series().await.ok(),
        Some(series(&[("1.1.2", "1.1")]))
    );
    assert_eq!(
        db.claim_pending_instances("1.1.1", now, now + MINUTE_US)
            .await
            .ok(),
        Some(vec![])
    );
    assert_eq!(
        read(db, None, Some("1.1.1")).await.len(),
        2,
        "settled instances stay indexed"
    );
    let q_ids = vec![q[0].id];
    assert_eq!(
        db.claim_pending_instances("1.1.2", now, now - 1).await.ok(),
        Some(q_ids.clone())
    );
    assert_eq!(
        db.claim_pending_instances("1.1.2", now, now + MINUTE_US)
            .await
            .ok(),
        Some(q_ids.clone())
    );
    assert_eq!(
        db.claim_pending_instances("1.1.2", now, now + MINUTE_US)
            .await
            .ok(),
        Some(vec![])
    );
    let released = db.release_instance_claims().await.expect("release");
    if db.is_shared() {
        assert_eq!(released, 0);
        assert_eq!(
            db.claim_pending_instances("1.1.2", now, now + MINUTE_US)
                .await
                .ok(),
            Some(vec![])
        );
    } else {
        assert_eq!(released, 1);
        assert_eq!(
            db.claim_pending_instances("1.1.2", now, now + MINUTE_US)
                .await
                .ok(),
            Some(q_ids)
        );
    }
}
