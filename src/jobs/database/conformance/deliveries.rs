//! Deliveries: listing and filters, the claim of a due delivery (once, one per destination), backoff,
//! per-instance outcomes, retry, and the end of claims.

use super::{Database, run};
use crate::jobs::deliveries::{
    Delivery, DeliveryFilter, DeliveryInstance, DeliveryState, InstanceState,
};
use crate::jobs::model::now_us;
use crate::storage::JobId;

const MINUTE_US: i64 = 60_000_000;

async fn queue(db: &Database, job: JobId, destination: &str) -> String {
    match db.insert_delivery(job, None, destination).await {
        Ok(id) => id,
        Err(e) => panic!("queueing a delivery: {e}"),
    }
}

async fn claim(db: &Database, now: i64) -> Option<Delivery> {
    match db.claim_due_delivery(now, now + MINUTE_US).await {
        Ok(d) => d,
        Err(e) => panic!("claiming: {e}"),
    }
}

async fn get(db: &Database, id: &str) -> Delivery {
    match db.get_delivery(id).await {
        Ok(Some(d)) => d,
        other => panic!("delivery {id} readable: {other:?}"),
    }
}

fn instance(n: u8) -> DeliveryInstance {
    DeliveryInstance {
        file: format!("{n}.dcm"),
        sop_class_uid: "1.2.840.10008.5.1.4.1.1.2".into(),
        sop_instance_uid: format!("1.2.3.{n}"),
        state: InstanceState::Pending,
        status: None,
        detail: None,
    }
}

/// Deliveries are listed newest first, filtered by state, job and rule, up to the limit.
pub async fn deliveries_are_listed_newest_first_and_filtered(db: &Database) {
    let (j1, j2) = (JobId::generate(), JobId::generate());
    let run_id = run(db, "r", "h").await.expect("a run");
    let r = db.list_runs(Some("r"), 1).await.expect("runs").remove(0);
    assert_eq!(r.id, run_id);
    let a = queue(db, j1, "PACS").await;
    let b = queue(db, j2, "PACS").await;
    let c = db
        .insert_delivery(j1, Some(&r), "ARCHIVE")
        .await
        .expect("queued");
    let ids = |v: Vec<Delivery>| v.into_iter().map(|d| d.id).collect::<Vec<_>>();
    let all = DeliveryFilter {
        limit: 10,
        ..DeliveryFilter::default()
    };
    assert_eq!(
        ids(db.list_deliveries(&all).await.expect("list")),
        vec![c.clone(), b.clone(), a.clone()]
    );
    let of_j1 = DeliveryFilter {
        job_id: Some(j1),
        ..all.clone()
    };
    assert_eq!(
        ids(db.list_deliveries(&of_j1).await.expect("list")),
        vec![c.clone(), a.clone()]
    );
    let of_rule = DeliveryFilter {
        rule_name: Some("r".into()),
        ..all.clone()
    };
    assert_eq!(
        ids(db.list_deliveries(&of_rule).await.expect("list")),
        vec![c.clone()]
    );
    let two = DeliveryFilter {
        limit: 2,
        ..all.clone()
    };
    assert_eq!(
        ids(db.list_deliveries(&two).await.expect("list")),
        vec![c.clone(), b.clone()]
    );
    let first = claim(db, now_us()).await.expect("a due delivery");
    assert_eq!(first.id, a);
    let sending = DeliveryFilter {
        state: Some(DeliveryState::Sending),
        ..all.clone()
    };
    assert_eq!(
        ids(db.list_deliveries(&sending).await.expect("list")),
        vec![a.clone()]
    );
    let queued = DeliveryFilter {
        state: Some(DeliveryState::Queued),
        ..all
    };
    assert_eq!(
        ids(db.list_deliveries(&queued).await.expect("list")),
        vec![c, b]
    );
}

/// Of two claims at once of the one due delivery, exactly one gets it (one more attempt, `sending`); while
/// a destination has a delivery in flight, the next claim takes another destination's.
pub async fn a_due_delivery_is_claimed_once_and_one_per_destination(db: &Database) {
    let job = JobId::generate();
    let a = queue(db, job, "PACS").await;
    let now = now_us();
    let (x, y) = tokio::join!(claim(db, now), claim(db, now));
    let won = match (x, y) {
        (Some(d), None) | (None, Some(d)) => d,
        other => panic!("exactly one claim wins: {other:?}"),
    };
    assert_eq!(
        (won.id.as_str(), won.state, won.attempts),
        (a.as_str(), DeliveryState::Sending, 1)
    );
    assert_eq!(get(db, &a).await.state, DeliveryState::Sending);
    let _second_to_pacs = queue(db, job, "PACS").await;
    let to_archive = queue(db, job, "ARCHIVE").await;
    let next = claim(db, now_us())
        .await
        .expect("another destination's delivery");
    assert_eq!(next.id, to_archive);
    assert!(
        claim(db, now_us()).await.is_none(),
        "PACS has a delivery in flight"
    );
}

/// A failed attempt with attempts left queues the delivery again at its backoff time, which the next-due
/// time reports; it is not claimed before. An attempt that no longer holds the claim records nothing.
pub async fn a_failed_attempt_backs_off_until_due_again(db: &Database) {
    let id = queue(db, JobId::generate(), "PACS").await;
    let due = db
        .next_delivery_due()
        .await
        .expect("due")
        .expect("a due time");
    assert!(due <= now_us());
    let d = claim(db, now_us()).await.expect("claimed");
    assert!(matches!(db.next_delivery_due().await, Ok(None)));
    let again = now_us() + 5_000_000;
    let ended = db
        .finish_delivery_attempt(
            &d,
            DeliveryState::Queued,
            Some(again),
            Some("association refused"),
        )
        .await;
    assert_eq!(ended.ok(), Some(true));
    let back = get(db, &id).await;
    assert_eq!(
        (
            back.state,
            back.attempts,
            back.next_attempt_us,
            back.last_error.as_deref(),
            back.finished_us
        ),
        (
            DeliveryState::Queued,
            1,
            Some(again),
            Some("association refused"),
            None
        )
    );
    assert_eq!(db.next_delivery_due().await.ok(), Some(Some(again)));
    assert!(claim(db, again - 1).await.is_none());
    let d2 = claim(db, again).await.expect("due again");
    assert_eq!(d2.attempts, 2);
    let stale = db
        .finish_delivery_attempt(&d, DeliveryState::Succeeded, None, None)
        .await;
    assert_eq!(stale.ok(), Some(false));
    assert_eq!(get(db, &id).await.state, DeliveryState::Sending);
}

/// Each instance's state, DIMSE status and detail are kept in order; a failed delivery (and only one) can be
/// retried: attempts start again, its failed instances are pending again and its sent ones stay sent.
pub async fn instance_statuses_are_recorded_and_retry_resends_the_failed(db: &Database) {
    let id = queue(db, JobId::generate(), "PACS").await;
    let mut d = claim(db, now_us()).await.expect("claimed");
    d.instances = vec![instance(1), instance(2), instance(3)];
    assert!(db.set_delivery_instances(&d.id, &d.instances).await.is_ok());
    assert_eq!(get(db, &id).await.instances, d.instances);
    assert_eq!(db.retry_delivery(&id).await.ok(), Some(false));
    d.instances[0].state = InstanceState::Succeeded;
    d.instances[0].status = Some(0);
    d.instances[1].state = InstanceState::Failed;
    d.instances[1].status = Some(0xA700);
    d.instances[1].detail = Some("out of resources".into());
    d.instances[2].state = InstanceState::Failed;
    d.instances[2].detail = Some("not sent".into());
    let ended = db
        .finish_delivery_attempt(&d, DeliveryState::Failed, None, Some("2 of 3 failed"))
        .await;
    assert_eq!(ended.ok(), Some(true));
    let failed = get(db, &id).await;
    assert_eq!(failed.state, DeliveryState::Failed);
    assert!(failed.finished_us.is_some());
    assert_eq!(failed.instances, d.instances);
    assert_eq!(db.retry_delivery(&id).await.ok(), Some(true));
    assert_eq!(db.retry_delivery(&id).await.ok(), Some(false));
    let retried = get(db, &id).await;
    assert_eq!(
        (retried.state, retried.attempts, retried.finished_us),
        (DeliveryState::Queued, 0, None)
    );
    let states: Vec<(InstanceState, Option<u16>, Option<&str>)> = retried
        .instances
        .iter()
        .map(|i| (i.state, i.status, i.detail.as_deref()))
        .collect();
    assert_eq!(
        states,
        vec![
            (InstanceState::Succeeded, Some(0), None),
            (InstanceState::Pending, None, None),
            (InstanceState::Pending, None, None),
        ]
    );
}

/// A claim is renewed only by the attempt that holds it; a delivery whose claim ended is queued again (its
/// attempt still counted), one whose claim holds is not — except at the start of the one process that owns a
/// SQLite database, which queues every `sending` one again.
pub async fn only_expired_claims_are_requeued(db: &Database) {
    let job = JobId::generate();
    let live = queue(db, job, "PACS").await;
    let lost = queue(db, job, "ARCHIVE").await;
    let now = now_us();
    let d = db
        .claim_due_delivery(now, now + MINUTE_US)
        .await
        .expect("claim")
        .expect("one");
    assert_eq!(d.id, live);
    let e = db
        .claim_due_delivery(now, now - 1)
        .await
        .expect("claim")
        .expect("another");
    assert_eq!(e.id, lost);
    assert_eq!(
        db.renew_delivery_claim(&live, 2, now + 2 * MINUTE_US)
            .await
            .ok(),
        Some(false)
    );
    assert_eq!(
        db.renew_delivery_claim(&live, 1, now + 2 * MINUTE_US)
            .await
            .ok(),
        Some(true)
    );
    assert_eq!(db.requeue_expired_deliveries().await.ok(), Some(1));
    let back = get(db, &lost).await;
    assert_eq!((back.state, back.attempts), (DeliveryState::Queued, 1));
    assert_eq!(get(db, &live).await.state, DeliveryState::Sending);
    let at_start = db.requeue_interrupted_deliveries().await.expect("requeue");
    if db.is_shared() {
        assert_eq!(at_start, 0);
        assert_eq!(get(db, &live).await.state, DeliveryState::Sending);
    } else {
        assert_eq!(at_start, 1);
        assert_eq!(get(db, &live).await.state, DeliveryState::Queued);
    }
}
