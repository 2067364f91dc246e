//! The instance index: rows of the DICOM instances ctrecon holds, with the attributes queries match, and
//! which upload, series or job each belongs to (every value bound, never part of the query text). Matching
//! itself happens in the application (`app::query`), over the rows read here. With several processes on one
//! (PostgreSQL) database:
//! - a job's results are indexed once: the `indexed_jobs` row is inserted first, `ON CONFLICT DO NOTHING`,
//!   in the transaction that inserts the instance rows, so of two processes indexing one job at once the
//!   second waits for the first to commit, then writes nothing ([`Database::insert_instances`] answers
//!   false);
//! - received instances pending assembly are claimed ([`Database::claim_pending_instances`]) by one process
//!   at a time, until the claim ends; settling them ([`Database::settle_instances`]) sets the same values when
//!   repeated, so it is idempotent.

use super::driver::{assembled, query};
use super::node_rows::{INSTANCE_COLUMNS, replaced_copy, stored_instance};
use super::{Database, DbError};
use crate::jobs::model::{IndexScope, NewInstance, ReplacedCopy, StoredInstance, now_us};
use crate::jobs::store::to_json;
use crate::storage::{InstanceId, InstanceOwner, JobId, SeriesId, UploadId};

impl Database {
    /// Index `rows` as belonging to `owner`, in one transaction; for a job, also mark it indexed, first:
    /// false (and nothing written) when the job's results were indexed already, so they are indexed once.
    pub async fn insert_instances(
        &self,
        owner: InstanceOwner,
        rows: &[NewInstance],
    ) -> Result<bool, DbError> {
        Ok(self.insert_rows(owner, rows, false).await?.is_some())
    }

    /// Index received `rows` of upload `upload` (pending assembly when `pending`: STOW-RS), in one
    /// transaction, each replacing the received copies of its SOP Instance UID indexed before, so that the
    /// index holds one received copy per SOP Instance UID; the copies replaced, whose files are the caller's
    /// to remove.
    pub async fn insert_received(
        &self,
        upload: UploadId,
        rows: &[NewInstance],
        pending: bool,
    ) -> Result<Vec<ReplacedCopy>, DbError> {
        Ok(self
            .insert_rows(InstanceOwner::Upload(upload), rows, pending)
            .await?
            .unwrap_or_default())
    }

    /// The received copies (rows owned by an upload) of the SOP Instance UIDs `sop_uids`, newest first.
    pub async fn received_copies(
        &self,
        sop_uids: &[String],
    ) -> Result<Vec<StoredInstance>, DbError> {
        let mut out = Vec::new();
        for chunk in sop_uids.chunks(500) {
            let sql = format!(
                "SELECT {INSTANCE_COLUMNS} FROM instances
                 WHERE upload_id IS NOT NULL AND sop_instance_uid IN {}
                 ORDER BY created_us DESC, id DESC",
                self.dialect().json_strings(1)
            );
            let rows = assembled(sql)
                .bind(to_json(&chunk))
                .fetch_all(&self.pool)
                .await?;
            for r in &rows {
                out.push(stored_instance(r)?);
            }
        }
        out.sort_by_key(|r| std::cmp::Reverse(r.created_us));
        Ok(out)
    }

    async fn insert_rows(
        &self,
        owner: InstanceOwner,
        rows: &[NewInstance],
        pending: bool,
    ) -> Result<Option<Vec<ReplacedCopy>>, DbError> {
        let mut tx = self.pool.begin().await?;
        let (upload, job) = match owner {
            InstanceOwner::Upload(u) => (Some(u.to_string()), None),
            InstanceOwner::Job(j) => (None, Some(j.to_string())),
        };
        let now = now_us();
        if let Some(job) = &job {
            let r = query(
                "INSERT INTO indexed_jobs (job_id, instances, created_us) VALUES ($1, $2, $3)
                 ON CONFLICT (job_id) DO NOTHING",
            )
            .bind(job)
            .bind(rows.len() as i64)
            .bind(now)
            .execute(&mut tx)
            .await?;
            if r.rows_affected() != 1 {
                tx.rollback().await?;
                return Ok(None);
            }
        }
        let mut replaced = Vec::new();
        for r in rows {
            let i = &r.instance;
            if upload.is_some() {
                let gone = query(
                    "DELETE FROM instances WHERE sop_instance_uid = $1 AND upload_id IS NOT NULL
                     RETURNING id, upload_id",
                )
                .bind(&i.sop_instance_uid)
                .fetch_all(&mut tx)
                .await?;
                for g in &gone {
                    replaced.push(replaced_copy(g)?);
                }
            }
            query(
                "INSERT INTO instances (id, upload_id, series_id, job_id, sop_class_uid, sop_instance_uid,
                 transfer_syntax, study_uid, series_uid, patient_id, patient_name, patient_birth_date,
                 patient_sex, study_date, study_time, accession_number, study_description,
                 referring_physician, study_id, modality, series_number, series_description, body_part,
                 instance_number, bytes, created_us, pending, sha256)
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11, $12, $13, $14, $15, $16, $17, $18, $19, $20, $21, $22, $23, $24, $25, $26, $27, $28)",
            )
            .bind(r.id.to_string())
            .bind(&upload)
            .bind(r.series_id.map(|s| s.to_string()))
            .bind(&job)
            .bind(&i.sop_class_uid)
            .bind(&i.sop_instance_uid)
            .bind(&i.transfer_syntax)
            .bind(&i.study_uid)
            .bind(&i.series_uid)
            .bind(&i.patient_id)
            .bind(&i.patient_name)
            .bind(&i.patient_birth_date)
            .bind(&i.patient_sex)
            .bind(&i.study_date)
            .bind(&i.study_time)
            .bind(&i.accession_number)
            .bind(&i.study_description)
            .bind(&i.referring_physician)
            .bind(&i.study_id)
            .bind(&i.modality)
            .bind(i.series_number)
            .bind(&i.series_description)
            .bind(&i.body_part)
            .bind(i.instance_number)
            .bind(i.bytes as i64)
            .bind(now)
            .bind(pending as i64)
            .bind(&r.sha256)
            .execute(&mut tx)
            .await?;
        }
        tx.commit().await?;
        Ok(Some(replaced))
    }

    /// The indexed instances in `scope`, newest first.
    pub async fn indexed_instances(
        &self,
        scope: &IndexScope,
    ) -> Result<Vec<StoredInstance>, DbError> {
        let sql = format!(
            "SELECT {INSTANCE_COLUMNS} FROM instances
             WHERE (CAST($1 AS TEXT) IS NULL OR study_uid = $1)
               AND (CAST($2 AS TEXT) IS NULL OR series_uid = $2)
             ORDER BY created_us DESC, id DESC"
        );
        let rows = assembled(sql)
            .bind(&scope.study_uid)
            .bind(&scope.series_uid)
            .fetch_all(&self.pool)
            .await?;
        rows.iter().map(stored_instance).collect()
    }

    /// Succeeded volume jobs whose DICOM results are not indexed yet, oldest first.
    pub async fn jobs_to_index(&self) -> Result<Vec<JobId>, DbError> {
        let rows = query(
            "SELECT id FROM jobs WHERE status = 'succeeded' AND kind = 'volume'
             AND NOT EXISTS (SELECT 1 FROM indexed_jobs x WHERE x.job_id = jobs.id) ORDER BY id",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| r.parsed("id", "jobs", JobId::parse))
            .collect()
    }

    /// Whether a job's results were indexed.
    pub async fn job_indexed(&self, id: JobId) -> Result<bool, DbError> {
        let row = query("SELECT 1 FROM indexed_jobs WHERE job_id = $1")
            .bind(id.to_string())
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.is_some())
    }

    /// Mark a job as indexed without instances (its results carry no patient); false when it was already.
    pub async fn mark_job_indexed(&self, id: JobId) -> Result<bool, DbError> {
        self.insert_instances(InstanceOwner::Job(id), &[]).await
    }

    /// Series (UID, study UID) with received instances not yet assembled, oldest first.
    pub async fn pending_series(&self) -> Result<Vec<(String, String)>, DbError> {
        let rows = query(
            "SELECT series_uid, MIN(study_uid) AS study_uid FROM instances WHERE pending = 1
             GROUP BY series_uid ORDER BY MIN(created_us)",
        )
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("series_uid")?, r.try_get("study_uid")?)))
            .collect()
    }

    /// Claim the received instances of series `series_uid` pending assembly that nobody holds (no claim, or
    /// one ended before `now`) for the caller until `claimed_until_us`; their ids. Empty when there are none
    /// or another assembly holds them all: then this one has nothing to assemble.
    pub async fn claim_pending_instances(
        &self,
        series_uid: &str,
        now: i64,
        claimed_until_us: i64,
    ) -> Result<Vec<InstanceId>, DbError> {
        let rows = query(
            "UPDATE instances SET claimed_until_us = $1
             WHERE series_uid = $2 AND pending = 1 AND (claimed_until_us IS NULL OR claimed_until_us < $3)
             RETURNING id",
        )
        .bind(claimed_until_us)
        .bind(series_uid)
        .bind(now)
        .fetch_all(&self.pool)
        .await?;
        let mut ids = rows
            .iter()
            .map(|r| r.parsed("id", "instances", InstanceId::parse))
            .collect::<Result<Vec<_>, DbError>>()?;
        ids.sort_by_key(|i| i.to_string());
        Ok(ids)
    }

    /// At start: on SQLite, release the claims on pending instances (they were this process's, before a
    /// stop); on a shared database nothing (claims of lost processes end by themselves).
    pub async fn release_instance_claims(&self) -> Result<u64, DbError> {
        if self.is_shared() {
            return Ok(0);
        }
        let r = query(
            "UPDATE instances SET claimed_until_us = NULL WHERE pending = 1 AND claimed_until_us IS NOT NULL",
        )
        .execute(&self.pool)
        .await?;
        Ok(r.rows_affected())
    }

    /// Received instances `ids` were assembled: no longer pending nor claimed, and members of `series` when
    /// one was made. Setting the same values again changes nothing, so settling twice is harmless.
    pub async fn settle_instances(
        &self,
        ids: &[InstanceId],
        series: Option<SeriesId>,
    ) -> Result<(), DbError> {
        let ids: Vec<String> = ids.iter().map(|i| i.to_string()).collect();
        let sql = format!(
            "UPDATE instances SET pending = 0, claimed_until_us = NULL,
                 series_id = COALESCE($1, series_id) WHERE id IN {}",
            self.dialect().json_strings(2)
        );
        assembled(sql)
            .bind(series.map(|s| s.to_string()))
            .bind(to_json(&ids))
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Uploads that own indexed instances (for pairing `instances/<upload>/` folders with rows).
    pub async fn uploads_with_instances(&self) -> Result<Vec<UploadId>, DbError> {
        let rows = query("SELECT DISTINCT upload_id FROM instances WHERE upload_id IS NOT NULL")
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| r.parsed("upload_id", "instances", UploadId::parse))
            .collect()
    }
}
