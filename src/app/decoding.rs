//! Memory for decoding one DICOM file on its own — an instance appended to an open upload (checked as it
//! arrives), a stored instance rendered or sent uncompressed by DICOMweb: reserved from what the file's
//! header declares (`dicom::declared`) before anything is decoded, and refused (`dicom_too_large`) when it
//! could never fit the memory budget. A compressed file's size on disk says nothing of what it decodes to.

use std::path::PathBuf;

use super::{App, AppResult};
use crate::dicom::{Declared, DicomError, ReadLimits, declared};
use crate::error_code::Problem;
use crate::jobs::engine::Reservation;
use crate::jobs::ingest::dicom_problem;

impl App {
    /// Reserve what decoding the file at `path` holds at its peak — [`Declared::decoding_bytes`], its stored
    /// values, and `beyond` (what the caller makes of them) — or refuse it when that exceeds the budget.
    pub(super) async fn reserve_decoding(
        &self,
        path: PathBuf,
        label: &str,
        beyond: fn(&Declared) -> u64,
    ) -> AppResult<Reservation> {
        let owned = label.to_string();
        let read =
            tokio::task::spawn_blocking(move || declared(&path, &owned, &ReadLimits::default()))
                .await
                .map_err(|_| Problem::internal())?;
        let d = read.map_err(|e| dicom_problem(&e))?;
        let need = d
            .decoding_bytes()
            .saturating_add(d.kept_bytes())
            .saturating_add(beyond(&d));
        let budget = self.settings.memory_budget_bytes;
        if need > budget {
            let e = DicomError::TooLarge {
                label: label.to_string(),
                detail: format!(
                    "pixels that take about {} MiB to decode",
                    need.div_ceil(1 << 20)
                ),
                limit: format!(
                    "the memory budget of {} MiB (memory_budget_bytes)",
                    budget >> 20
                ),
            };
            return Err(dicom_problem(&e).into());
        }
        Ok(self.engine.reserve_memory(need).await)
    }
}
