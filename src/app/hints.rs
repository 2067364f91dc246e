//! Refusals of a job submission that say what to do: a field that belongs to the other kind of job, and an
//! input id that names another kind of resource (a series given to a reconstruction, a dataset given to a
//! volume job). serde's own message — an unknown field and the fields expected, or "no dataset <id>" — is
//! true but does not point at the fix.

use super::App;
use super::error::{AppError, AppResult, refused};
use crate::error_code::{ErrorCode, Problem};
use crate::storage::{DatasetId, JobId, SeriesId};

/// Fields only a volume job takes.
const VOLUME_FIELDS: &[&str] = &["steps", "products"];
/// Fields only a reconstruction takes.
const RECONSTRUCTION_FIELDS: &[&str] = &["algorithm", "grid", "outputs", "image_convention"];

/// The refusal of a body whose fields belong to the other kind than `volume` says: the first such field,
/// at its pointer, with the `kind` to give.
pub fn misplaced_fields(body: &serde_json::Value, volume: bool) -> AppResult<()> {
    let Some(fields) = body.as_object() else {
        return Ok(());
    };
    let (other, detail) = if volume {
        (
            RECONSTRUCTION_FIELDS,
            "belongs to reconstruction jobs, not volume jobs: leave out \"kind\": \"volume\" to \
             reconstruct a projection dataset, or give a volume job `steps` and `products`",
        )
    } else {
        (
            VOLUME_FIELDS,
            "belongs to volume jobs: add \"kind\": \"volume\" (a volume job takes a DICOM series or a \
             succeeded job's volume as `input`, with `steps` and `products`)",
        )
    };
    match other.iter().find(|f| fields.contains_key(**f)) {
        Some(field) => Err(AppError::Refused(
            Problem::new(ErrorCode::InvalidRequest, format!("`{field}` {detail}"))
                .at(format!("/{field}")),
        )),
        None => Ok(()),
    }
}

impl App {
    /// `no dataset <id>`, saying what `id` is when it names a series or a job instead.
    pub(super) async fn dataset_not_found(&self, id: DatasetId) -> AppError {
        let text = id.to_string();
        let what = match self.kind_of(&text).await {
            Ok(Some(what)) => what,
            Ok(None) => {
                return refused(
                    ErrorCode::DatasetNotFound,
                    format!(
                        "no dataset {id}: a reconstruction's `input` is a projection dataset, made by \
                         POST /v1/sinograms (an uploaded .npy) or POST /v1/simulations"
                    ),
                );
            }
            Err(e) => return e,
        };
        refused(
            ErrorCode::DatasetNotFound,
            format!(
                "{id} is {what}, not a projection dataset: volume jobs take series and job volumes — \
                 add \"kind\": \"volume\" (with `steps` and `products` instead of `algorithm` and `grid`)"
            ),
        )
    }

    /// A volume job's refusal of `id` (`no series or job <id>`), saying so when `id` is a projection dataset.
    pub(super) async fn volume_input_not_found(&self, id: &str, problem: Problem) -> AppError {
        let Ok(dataset) = DatasetId::parse(id) else {
            return problem.into();
        };
        match self.db.get_dataset(dataset).await {
            Ok(Some(_)) => refused(
                problem.code,
                format!(
                    "{id} is a projection dataset, not a volume: reconstruct it first (a job without \
                     \"kind\": \"volume\"), then give that job's id as the volume job's `input`"
                ),
            ),
            Ok(None) => problem.into(),
            Err(e) => e.into(),
        }
    }

    /// What `id` names besides a dataset: "a DICOM series" or "a job", if anything.
    async fn kind_of(&self, id: &str) -> AppResult<Option<&'static str>> {
        Ok(self.resource_of(id).await?.map(|(what, _)| what))
    }

    /// The resource `id` names, if any: what it is and where it is read.
    async fn resource_of(&self, id: &str) -> AppResult<Option<(&'static str, &'static str)>> {
        if let Ok(series) = SeriesId::parse(id)
            && self.db.get_series(series).await?.is_some()
        {
            return Ok(Some(("a DICOM series", "/v1/series/")));
        }
        if let Ok(job) = JobId::parse(id)
            && self.db.get_job(job).await?.is_some()
        {
            return Ok(Some(("a job", "/v1/jobs/")));
        }
        if let Ok(dataset) = DatasetId::parse(id)
            && self.db.get_dataset(dataset).await?.is_some()
        {
            return Ok(Some(("a projection dataset", "/v1/datasets/")));
        }
        Ok(None)
    }

    /// `code` with `detail`, followed by what `id` is when it names another kind of resource (a series id
    /// asked of `/v1/jobs`, say) and where that is read.
    pub(super) async fn not_found(&self, code: ErrorCode, detail: String, id: &str) -> AppError {
        match self.resource_of(id).await {
            Ok(Some((what, route))) => {
                refused(code, format!("{detail}: {id} is {what} (GET {route}{id})"))
            }
            Ok(None) => refused(code, detail),
            Err(e) => e,
        }
    }
}
