//! `POST /v1/scans`: a scan as the scanner wrote it — a ZIP of its files, a multipart form of its files (one
//! part per file, the part's file name kept, sub-folders allowed), or one file (`?filename=`) — streamed to
//! temporary files, imported view by view into a float32 dataset (`app::scans`) and answered as that dataset
//! (`kind: "scan"`), usable as a job's `input`.

use axum::extract::{Request, State};
use axum::response::Response;
use serde::Deserialize;
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{ApiQuery, idempotency_key, media_type};
use super::super::problem::{ApiResult, api_error};
use super::datasets::insert;
use super::uploads::{Received, check_length, read_body, read_multipart};
use crate::app::Replay;
use crate::app::uploads::ReceivedFile;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::now_us;
use crate::jobs::{Dataset, DatasetKind, IdempotencyKey};
use crate::recon::prep::PrepPlan;
use crate::scans::calibrate::CentrePolicy;
use crate::storage::DatasetId;
use crate::storage::npy::hex;

const ROUTE_SCANS: &str = "POST /v1/scans";

/// Query of `POST /v1/scans`: the file's name when the body is one file (`application/octet-stream`).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanQuery {
    pub filename: Option<String>,
    /// The centre of rotation: `auto` (default: found from the views unless the scan states one), `find`,
    /// `read`, or a detector u offset in mm.
    pub centre: Option<String>,
}

/// The preprocessing steps asked for in `X-Ctrecon-Preprocessing` (JSON; none when absent).
fn preprocessing(headers: &axum::http::HeaderMap) -> ApiResult<PrepPlan> {
    let Some(value) = headers.get("x-ctrecon-preprocessing") else {
        return Ok(PrepPlan::default());
    };
    let text = value.to_str().map_err(|_| {
        api_error(
            ErrorCode::InvalidParameter,
            "X-Ctrecon-Preprocessing: not visible ASCII",
        )
    })?;
    serde_json::from_str(text).map_err(|e| {
        api_error(
            ErrorCode::InvalidParameter,
            format!(
                "X-Ctrecon-Preprocessing: {e} (a JSON object with any of angles, crop, bin, linearise, stripes)"
            ),
        )
    })
}

pub async fn post_scan(
    State(st): State<AppState>,
    ApiQuery(q): ApiQuery<ScanQuery>,
    req: Request,
) -> ApiResult<Response> {
    let centre = match q.centre.as_deref() {
        None => CentrePolicy::Auto,
        Some(text) => CentrePolicy::parse(text).ok_or_else(|| {
            api_error(
                ErrorCode::InvalidQuery,
                format!("centre={text:?}: give auto, find, read or a detector u offset in mm"),
            )
        })?,
    };
    let plan = preprocessing(req.headers())?;
    check_length(&st, req.headers())?;
    let key = idempotency_key(req.headers())?;
    let media = media_type(req.headers());
    let files: Vec<Received> = match (media.as_str(), &q.filename) {
        ("multipart/form-data", None) => read_multipart(&st, req).await?,
        ("application/zip" | "application/x-zip-compressed", None) => {
            let file = read_body(&st, req).await?;
            let path = file.temp.path().to_path_buf();
            let zip = tokio::task::spawn_blocking(move || crate::dicom::is_zip(&path))
                .await
                .map_err(|_| Problem::internal())??;
            if !zip {
                file.temp.discard().await;
                return Err(api_error(
                    ErrorCode::UnsupportedMediaType,
                    "the body was sent as application/zip but is not a ZIP archive: send the scan's files \
                     as a ZIP, as multipart/form-data parts, or one file as application/octet-stream",
                ));
            }
            vec![Received {
                label: "scan.zip".into(),
                file,
            }]
        }
        ("application/octet-stream", Some(name)) => {
            let file = read_body(&st, req).await?;
            vec![Received {
                label: name.clone(),
                file,
            }]
        }
        ("application/octet-stream", None) => {
            return Err(api_error(
                ErrorCode::InvalidQuery,
                "name the file: POST /v1/scans?filename=scan.tif",
            ));
        }
        (_, Some(_)) => {
            return Err(api_error(
                ErrorCode::InvalidQuery,
                "`filename` names a single application/octet-stream file; forms and ZIPs carry their names",
            ));
        }
        _ => {
            return Err(api_error(
                ErrorCode::UnsupportedMediaType,
                "send the scan's files as application/zip, as multipart/form-data (one part per file), or one \
                 file as application/octet-stream with ?filename=",
            ));
        }
    };
    let key = key.map(|key| {
        let mut h = Sha256::new();
        h.update(media.as_bytes());
        for f in &files {
            h.update(f.label.as_bytes());
            h.update(f.file.sha256);
        }
        h.update(q.centre.as_deref().unwrap_or("auto").as_bytes());
        h.update(serde_json::to_string(&plan).unwrap_or_default().as_bytes());
        IdempotencyKey {
            route: ROUTE_SCANS,
            key,
            fingerprint: hex(&h.finalize()),
        }
    });
    if let Some(key) = &key
        && let Replay::Existing(id) = st.replay(Some(key)).await?
    {
        return super::datasets::existing(&st, &id).await;
    }
    let received = files
        .into_iter()
        .map(|f| ReceivedFile {
            label: f.label,
            temp: f.file.temp,
        })
        .collect();
    let imported = st.import_scan(received, centre, plan).await?;
    let d = Dataset {
        id: DatasetId::generate(),
        kind: DatasetKind::Scan,
        geometry: imported.geometry,
        shape: imported.shape,
        dtype: "float32".into(),
        bytes: imported.bytes,
        sha256: imported.sha256,
        phantom: None,
        noise: None,
        scan: Some(imported.record),
        created_us: now_us(),
    };
    insert(&st, d, key, imported.temp).await
}
