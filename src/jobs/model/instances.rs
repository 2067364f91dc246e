//! The instance index's rows as both job database adapters read and write them: an indexed DICOM instance
//! with the attributes queries match, where it is stored and what owns it, and the narrowing of a read.

use crate::storage::{InstanceId, InstanceOwner, SeriesId, UploadId};

/// One indexed instance: its identity, the attributes of its patient, study, series and itself, and where
/// its file is.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct IndexedInstance {
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
    pub transfer_syntax: String,
    pub study_uid: String,
    pub series_uid: String,
    pub patient_id: Option<String>,
    pub patient_name: Option<String>,
    pub patient_birth_date: Option<String>,
    pub patient_sex: Option<String>,
    pub study_date: Option<String>,
    pub study_time: Option<String>,
    pub accession_number: Option<String>,
    pub study_description: Option<String>,
    pub referring_physician: Option<String>,
    pub study_id: Option<String>,
    pub modality: Option<String>,
    pub series_number: Option<i64>,
    pub series_description: Option<String>,
    pub body_part: Option<String>,
    pub instance_number: Option<i64>,
    /// Size of the file (bytes).
    pub bytes: u64,
}

/// An instance as stored: its row id (which names its file), owner, series and time of indexing.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredInstance {
    pub id: InstanceId,
    pub owner: InstanceOwner,
    /// The assembled series it belongs to, when it is a received instance of one.
    pub series_id: Option<SeriesId>,
    pub created_us: i64,
    pub instance: IndexedInstance,
    /// SHA-256 of its file (hex) for a received instance; `None` for rows indexed before it was kept.
    pub sha256: Option<String>,
}

/// A row to insert: the instance, its new id, its series and the SHA-256 of its file (hex).
#[derive(Debug, Clone)]
pub struct NewInstance {
    pub id: InstanceId,
    pub series_id: Option<SeriesId>,
    pub instance: IndexedInstance,
    pub sha256: Option<String>,
}

/// A received copy that indexing a newer copy of the same SOP Instance UID replaced: its row is gone, its
/// file (`instances/<upload>/<id>.dcm`) is the caller's to remove.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReplacedCopy {
    pub upload: UploadId,
    pub id: InstanceId,
}

/// Narrowing of an index read by exact UIDs (taken from single-valued unique keys of a query).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct IndexScope {
    pub study_uid: Option<String>,
    pub series_uid: Option<String>,
}
