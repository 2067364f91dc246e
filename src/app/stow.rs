//! STOW-RS (PS3.18 §10.5) as a front door of the same receive path as C-STORE: each part (already written to
//! a temporary file by the front door, within its size limits) is checked like a C-STORE data set (its
//! header read by the same reader, a storable SOP class, the study of the request's path), and the accepted
//! ones are recorded through [`App::ingest_received_from`] and [`App::index_received`] — assembled into
//! series, rules fired, instances indexed for QIDO-RS, WADO-RS, C-FIND and C-MOVE. A refused part is
//! removed; nothing of it is kept.

use std::path::PathBuf;

use super::{App, AppError, AppResult};
use crate::dicom::{STORABLE_SOP_CLASSES, UploadFile, read_header};

/// PS3.18 / PS3.4 failure reasons (0008,1197) a STOW-RS answer gives.
pub mod reason {
    /// Processing failure (as Orthanc answers an instance of another study).
    pub const PROCESSING_FAILURE: u16 = 0x0110;
    /// SOP class not supported.
    pub const SOP_CLASS_NOT_SUPPORTED: u16 = 0x0122;
    /// Out of resources (a part over the size limit, or storage failed).
    pub const OUT_OF_RESOURCES: u16 = 0xA700;
    /// Cannot understand (not DICOM, or its header cannot be read).
    pub const CANNOT_UNDERSTAND: u16 = 0xC000;
}

/// One part of a STOW-RS body as the front door received it.
#[derive(Debug)]
pub enum StowPart {
    /// A DICOM part written whole to `path` (a temporary file the caller removes when it is still there).
    File { path: PathBuf, bytes: u64 },
    /// A part refused while it arrived (too large, another media type): reason and why.
    Refused { reason: u16, why: String },
}

/// What became of one part.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StowOutcome {
    pub sop_class_uid: Option<String>,
    pub sop_instance_uid: Option<String>,
    pub study_uid: Option<String>,
    pub series_uid: Option<String>,
    /// `None` when stored; the failure reason otherwise.
    pub failure: Option<u16>,
    pub why: String,
}

impl StowOutcome {
    fn failed(reason: u16, why: impl Into<String>) -> Self {
        StowOutcome {
            sop_class_uid: None,
            sop_instance_uid: None,
            study_uid: None,
            series_uid: None,
            failure: Some(reason),
            why: why.into(),
        }
    }
}

impl App {
    /// Store the parts of a STOW-RS request (to `study` when its path names one); one outcome per part, in
    /// order.
    pub async fn stow(
        &self,
        parts: Vec<StowPart>,
        study: Option<&str>,
    ) -> AppResult<Vec<StowOutcome>> {
        self.db
            .node_tables()
            .map_err(|e| super::dicomweb::index_problem(AppError::Db(e)))?;
        let max = self
            .settings
            .dicom
            .max_instance_bytes
            .saturating_add(64 << 10);
        let study = study.map(str::to_string);
        let checked = tokio::task::spawn_blocking(move || {
            parts
                .into_iter()
                .map(|p| match p {
                    StowPart::Refused { reason, why } => (StowOutcome::failed(reason, why), None),
                    StowPart::File { path, bytes } => {
                        let h = match read_header(&path, max) {
                            Ok(h) => h,
                            Err(e) => {
                                return (
                                    StowOutcome::failed(reason::CANNOT_UNDERSTAND, e.to_string()),
                                    None,
                                );
                            }
                        };
                        let mut o = StowOutcome {
                            sop_class_uid: Some(h.sop_class_uid.clone()),
                            sop_instance_uid: Some(h.sop_instance_uid.clone()),
                            study_uid: Some(h.study_uid.clone()),
                            series_uid: Some(h.series_uid.clone()),
                            failure: None,
                            why: String::new(),
                        };
                        if !STORABLE_SOP_CLASSES.contains(&h.sop_class_uid.as_str()) {
                            o.failure = Some(reason::SOP_CLASS_NOT_SUPPORTED);
                            o.why = format!("SOP class {} is not stored here", h.sop_class_uid);
                            return (o, None);
                        }
                        if let Some(s) = &study
                            && *s != h.study_uid
                        {
                            o.failure = Some(reason::PROCESSING_FAILURE);
                            o.why =
                                format!("the instance belongs to study {}, not {s}", h.study_uid);
                            return (o, None);
                        }
                        (o, Some((path, bytes)))
                    }
                })
                .collect::<Vec<_>>()
        })
        .await
        .map_err(|e| AppError::Storage(std::io::Error::other(e)))?;
        let accepted: Vec<(usize, PathBuf, u64)> = checked
            .iter()
            .enumerate()
            .filter_map(|(i, (_, f))| f.clone().map(|(p, b)| (i, p, b)))
            .collect();
        let mut outcomes: Vec<StowOutcome> = checked.into_iter().map(|(o, _)| o).collect();
        if accepted.is_empty() {
            return Ok(outcomes);
        }
        let bytes: u64 = accepted.iter().map(|(_, _, b)| b).sum();
        // Each instance is named by its SOP Instance UID in the upload's report, as HTTP uploads name theirs.
        let files: Vec<UploadFile> = accepted
            .iter()
            .map(|(i, p, _)| UploadFile {
                label: outcomes[*i]
                    .sop_instance_uid
                    .clone()
                    .unwrap_or_else(|| format!("part {}", i + 1)),
                path: p.clone(),
            })
            .collect();
        let paths: Vec<PathBuf> = accepted.iter().map(|(_, p, _)| p.clone()).collect();
        match self.ingest_received_from(files, bytes, None).await {
            Ok(r) => {
                let records: Vec<_> = r.ingested.ready().cloned().collect();
                self.index_received(r.upload_id, paths, &records).await?;
                tracing::info!(upload_id = %r.upload_id, instances = accepted.len(), "STOW-RS instances stored");
            }
            Err(AppError::Refused(p)) => {
                for (i, _, _) in &accepted {
                    outcomes[*i].failure = Some(reason::CANNOT_UNDERSTAND);
                    outcomes[*i].why = p.detail.clone();
                }
            }
            Err(e) => return Err(e),
        }
        Ok(outcomes)
    }
}
