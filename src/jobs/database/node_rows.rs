//! Rows of the DICOM node's tables as domain values: deliveries and their instances, indexed instances. The
//! SQLite and PostgreSQL rows hold the same columns with the same meanings (TEXT, and INTEGER / BIGINT read
//! as `i64`).

use super::DbError;
use super::driver::Row;
use crate::jobs::deliveries::{Delivery, DeliveryInstance, DeliveryState, InstanceState};
use crate::jobs::model::{IndexedInstance, ReplacedCopy, StoredInstance};
use crate::jobs::store::corrupt;
use crate::storage::{InstanceId, InstanceOwner, JobId, SeriesId, UploadId};

/// The columns of `instances` that [`stored_instance`] reads.
pub(crate) const INSTANCE_COLUMNS: &str = "id, upload_id, series_id, job_id, sop_class_uid, sop_instance_uid, transfer_syntax, \
     study_uid, series_uid, patient_id, patient_name, patient_birth_date, patient_sex, study_date, \
     study_time, accession_number, study_description, referring_physician, study_id, modality, \
     series_number, series_description, body_part, instance_number, bytes, created_us, sha256";

/// An indexed instance (a row of `instances` with [`INSTANCE_COLUMNS`]).
pub(crate) fn stored_instance(row: &Row) -> Result<StoredInstance, DbError> {
    let bad = |e: crate::storage::BadId| corrupt("instances", e);
    let id: String = row.try_get("id")?;
    let upload: Option<String> = row.try_get("upload_id")?;
    let job: Option<String> = row.try_get("job_id")?;
    let series: Option<String> = row.try_get("series_id")?;
    let owner = match (upload, job) {
        (Some(u), None) => InstanceOwner::Upload(UploadId::parse(&u).map_err(bad)?),
        (None, Some(j)) => InstanceOwner::Job(JobId::parse(&j).map_err(bad)?),
        _ => return Err(corrupt("instances", "an instance needs one owner")),
    };
    let bytes: i64 = row.try_get("bytes")?;
    Ok(StoredInstance {
        id: InstanceId::parse(&id).map_err(bad)?,
        owner,
        series_id: series
            .as_deref()
            .map(SeriesId::parse)
            .transpose()
            .map_err(bad)?,
        created_us: row.try_get("created_us")?,
        instance: IndexedInstance {
            sop_class_uid: row.try_get("sop_class_uid")?,
            sop_instance_uid: row.try_get("sop_instance_uid")?,
            transfer_syntax: row.try_get("transfer_syntax")?,
            study_uid: row.try_get("study_uid")?,
            series_uid: row.try_get("series_uid")?,
            patient_id: row.try_get("patient_id")?,
            patient_name: row.try_get("patient_name")?,
            patient_birth_date: row.try_get("patient_birth_date")?,
            patient_sex: row.try_get("patient_sex")?,
            study_date: row.try_get("study_date")?,
            study_time: row.try_get("study_time")?,
            accession_number: row.try_get("accession_number")?,
            study_description: row.try_get("study_description")?,
            referring_physician: row.try_get("referring_physician")?,
            study_id: row.try_get("study_id")?,
            modality: row.try_get("modality")?,
            series_number: row.try_get("series_number")?,
            series_description: row.try_get("series_description")?,
            body_part: row.try_get("body_part")?,
            instance_number: row.try_get("instance_number")?,
            bytes: bytes.max(0) as u64,
        },
        sha256: row.try_get("sha256")?,
    })
}

/// A received copy replaced by a newer one (the `id` and `upload_id` of a deleted row of `instances`).
pub(crate) fn replaced_copy(row: &Row) -> Result<ReplacedCopy, DbError> {
    let bad = |e: crate::storage::BadId| corrupt("instances", e);
    let id: String = row.try_get("id")?;
    let upload: String = row.try_get("upload_id")?;
    Ok(ReplacedCopy {
        upload: UploadId::parse(&upload).map_err(bad)?,
        id: InstanceId::parse(&id).map_err(bad)?,
    })
}

/// A delivery, without its instances (a row of `deliveries`).
pub(crate) fn delivery(row: &Row) -> Result<Delivery, DbError> {
    let state: String = row.try_get("state")?;
    let job: String = row.try_get("job_id")?;
    let attempts: i64 = row.try_get("attempts")?;
    Ok(Delivery {
        id: row.try_get("id")?,
        job_id: JobId::parse(&job).map_err(|e| corrupt("deliveries", e))?,
        run_id: row.try_get("run_id")?,
        rule_name: row.try_get("rule_name")?,
        destination: row.try_get("destination")?,
        state: DeliveryState::parse(&state).ok_or_else(|| corrupt("deliveries", state))?,
        attempts: attempts.max(0) as u32,
        next_attempt_us: row.try_get("next_attempt_us")?,
        last_error: row.try_get("last_error")?,
        created_us: row.try_get("created_us")?,
        updated_us: row.try_get("updated_us")?,
        finished_us: row.try_get("finished_us")?,
        instances: Vec::new(),
    })
}

/// One instance of a delivery (a row of `delivery_instances`).
pub(crate) fn delivery_instance(row: &Row) -> Result<DeliveryInstance, DbError> {
    let state: String = row.try_get("state")?;
    let status: Option<i64> = row.try_get("status")?;
    Ok(DeliveryInstance {
        file: row.try_get("file")?,
        sop_class_uid: row.try_get("sop_class_uid")?,
        sop_instance_uid: row.try_get("sop_instance_uid")?,
        state: InstanceState::parse(&state).ok_or_else(|| corrupt("delivery_instances", state))?,
        status: status.map(|s| s.clamp(0, 0xFFFF) as u16),
        detail: row.try_get("detail")?,
    })
}
