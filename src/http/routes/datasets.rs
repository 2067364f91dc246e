//! `POST /v1/simulations`, `POST /v1/sinograms` (multipart or raw `.npy`), `GET` and `DELETE
//! /v1/datasets/{id}`. A dataset's file is renamed into place only after its row is committed.

use axum::extract::{FromRequest, Multipart, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures_util::StreamExt;
use serde::Deserialize;
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{
    ApiJson, ApiQuery, dataset_id, idempotency_key, media_type, parse_json,
};
use super::super::problem::{ApiResult, api_error};
use super::super::upload::{UploadSink, Uploaded, paced};
use crate::app::Replay;
use crate::app::idempotency::settle;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::model::now_us;
use crate::jobs::plan::{admit_simulation, recon_problem};
use crate::jobs::run::simulate;
use crate::jobs::store::Deleted;
use crate::jobs::{Dataset, DatasetKind, IdempotencyKey, Inserted, SimulationRequest};
use crate::recon::geometry::Geometry;
use crate::storage::npy::{StreamLimits, encode_f32, hex};
use crate::storage::sweep::BlobKind;
use crate::storage::{DatasetId, TempBlob};

const ROUTE_SIMULATIONS: &str = "POST /v1/simulations";
const ROUTE_SINOGRAMS: &str = "POST /v1/sinograms";

/// The JSON representation of a dataset.
pub fn dataset_json(d: &Dataset) -> serde_json::Value {
    let mut v = serde_json::to_value(d).unwrap_or_default();
    if let Some(map) = v.as_object_mut() {
        map.insert(
            "created_at".into(),
            crate::jobs::model::rfc3339(d.created_us).into(),
        );
        map.insert(
            "links".into(),
            serde_json::json!({ "self": format!("/v1/datasets/{}", d.id) }),
        );
        if let Some(scan) = &d.scan {
            map.insert("format".into(), scan.format.clone().into());
        }
    }
    v
}

fn created(d: &Dataset) -> Response {
    let mut r = (StatusCode::CREATED, axum::Json(dataset_json(d))).into_response();
    if let Ok(loc) = HeaderValue::from_str(&format!("/v1/datasets/{}", d.id)) {
        r.headers_mut().insert(header::LOCATION, loc);
    }
    r
}

/// The dataset an earlier request with the same Idempotency-Key created, if any; 422 when that request
/// differed.
async fn replay(st: &AppState, key: Option<&IdempotencyKey>) -> ApiResult<Option<Response>> {
    match st.replay(key).await? {
        Replay::New => Ok(None),
        Replay::Existing(id) => existing(st, &id).await.map(Some),
    }
}

pub(super) async fn existing(st: &AppState, id: &str) -> ApiResult<Response> {
    let id = dataset_id(id)?;
    match st.db.get_dataset(id).await? {
        Some(d) => Ok(created(&d)),
        None => Err(api_error(
            ErrorCode::DatasetNotFound,
            "the dataset was removed",
        )),
    }
}

/// Insert `d` under the Idempotency-Key, then move its file (`temp`, synced) into place: temporary file →
/// row → rename, so a crash never leaves a file without its row. On a lost race, answer the winner.
pub(super) async fn insert(
    st: &AppState,
    d: Dataset,
    key: Option<IdempotencyKey>,
    temp: TempBlob,
) -> ApiResult<Response> {
    let inserted = match st.db.insert_dataset(&d, key.as_ref()).await {
        Ok(i) => i,
        Err(e) => {
            temp.discard().await;
            return Err(e.into());
        }
    };
    match inserted {
        Inserted::New => {
            if let Err(e) = st
                .store
                .commit_async(temp, st.store.dataset_path(d.id))
                .await
            {
                tracing::error!(error = %e, dataset_id = %d.id, "moving a dataset into place failed");
                let _ = st.db.delete_dataset(d.id).await;
                return Err(Problem::internal().into());
            }
            tracing::info!(dataset_id = %d.id, kind = d.kind.as_str(), "dataset stored");
            Ok(created(&d))
        }
        existing @ Inserted::Existing { .. } => {
            temp.discard().await;
            match settle(existing, key.as_ref())? {
                Replay::Existing(id) => self::existing(st, &id).await,
                Replay::New => Err(Problem::internal().into()),
            }
        }
    }
}

fn limits(st: &AppState) -> StreamLimits {
    StreamLimits {
        max_file_bytes: st.settings.max_upload_bytes,
        max_elements: crate::app::limits::max_array_values(&st.settings),
    }
}

pub async fn post_simulation(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: ApiJson<SimulationRequest>,
) -> ApiResult<Response> {
    let key = idempotency_key(&headers)?.map(|key| IdempotencyKey {
        route: ROUTE_SIMULATIONS,
        key,
        fingerprint: body.fingerprint.clone(),
    });
    if let Some(r) = replay(&st, key.as_ref()).await? {
        return Ok(r);
    }
    let req = body.value;
    let views = admit_simulation(&req, crate::app::limits::max_array_values(&st.settings))?;
    let id = DatasetId::generate();
    let store = st.store.clone();
    let request = req.clone();
    let (temp, bytes, sha256, shape) = st
        .engine
        .compute(move || {
            let data = simulate(&request, &views)?;
            let encoded = encode_f32(data.view());
            let temp = store.write_temp(&encoded).map_err(|e| {
                tracing::error!(error = %e, "writing a simulation failed");
                Problem::internal()
            })?;
            Ok((
                temp,
                encoded.len() as u64,
                hex(&Sha256::digest(&encoded)),
                data.shape().to_vec(),
            ))
        })
        .await?;
    let d = Dataset {
        id,
        kind: DatasetKind::Simulation,
        geometry: req.geometry,
        shape,
        dtype: "float32".into(),
        bytes,
        sha256,
        phantom: Some(req.phantom),
        noise: req.noise,
        scan: None,
        created_us: now_us(),
    };
    insert(&st, d, key, temp).await
}

/// Query of a raw upload: the geometry JSON, unless sent in the `X-Ctrecon-Geometry` header.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SinogramQuery {
    pub geometry: Option<String>,
}

struct ParsedGeometry {
    geometry: Geometry,
    shape: Vec<usize>,
    fingerprint: String,
}

fn parse_geometry(text: &[u8]) -> ApiResult<ParsedGeometry> {
    let (geometry, fingerprint): (Geometry, String) = parse_json(text)?;
    let views = geometry.to_views().map_err(|e| recon_problem(&e.into()))?;
    Ok(ParsedGeometry {
        shape: views.data_shape(),
        geometry,
        fingerprint,
    })
}

pub async fn post_sinogram(
    State(st): State<AppState>,
    ApiQuery(query): ApiQuery<SinogramQuery>,
    req: Request,
) -> ApiResult<Response> {
    let key = idempotency_key(req.headers())?;
    let media = media_type(req.headers());
    if let Some(n) = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
        && n > st
            .settings
            .max_upload_bytes
            .saturating_add(st.settings.max_json_bytes as u64 + 4096)
    {
        return Err(api_error(
            ErrorCode::BodyTooLarge,
            format!(
                "the body has {n} bytes, the limit is {}",
                st.settings.max_upload_bytes
            ),
        ));
    }
    let (geometry, upload) = match media.as_str() {
        "multipart/form-data" => multipart(&st, req).await?,
        "application/x-npy" | "application/octet-stream" => raw(&st, query, req).await?,
        _ => {
            return Err(api_error(
                ErrorCode::UnsupportedMediaType,
                "send multipart/form-data (parts `geometry` and `data`) or application/x-npy",
            ));
        }
    };
    let fingerprint = hex(&Sha256::digest(
        format!("{}:{}", geometry.fingerprint, upload.sha256).as_bytes(),
    ));
    let key = key.map(|key| IdempotencyKey {
        route: ROUTE_SINOGRAMS,
        key,
        fingerprint,
    });
    if let Some(r) = replay(&st, key.as_ref()).await? {
        return Ok(r);
    }
    let id = DatasetId::generate();
    let d = Dataset {
        id,
        kind: DatasetKind::Upload,
        geometry: geometry.geometry,
        shape: upload.header.shape.clone(),
        dtype: upload.header.dtype.name().into(),
        bytes: upload.bytes,
        sha256: upload.sha256,
        phantom: None,
        noise: None,
        scan: None,
        created_us: now_us(),
    };
    insert(&st, d, key, upload.temp).await
}

async fn raw(
    st: &AppState,
    query: SinogramQuery,
    req: Request,
) -> ApiResult<(ParsedGeometry, Uploaded)> {
    let text = match (req.headers().get("x-ctrecon-geometry"), &query.geometry) {
        (Some(h), None) => h.as_bytes().to_vec(),
        (None, Some(q)) => q.as_bytes().to_vec(),
        _ => {
            return Err(api_error(
                ErrorCode::InvalidRequest,
                "give the geometry JSON in the X-Ctrecon-Geometry header or the `geometry` query parameter (exactly one)",
            ));
        }
    };
    let geometry = parse_geometry(&text)?;
    let mut sink = UploadSink::create(&st.store, limits(st), Some(geometry.shape.clone())).await?;
    let mut body = req.into_body().into_data_stream();
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| api_error(ErrorCode::TruncatedUpload, e.to_string()))?;
        sink.write(&chunk).await?;
    }
    Ok((geometry, sink.finish().await?))
}

async fn multipart(st: &AppState, req: Request) -> ApiResult<(ParsedGeometry, Uploaded)> {
    let bad = |m: String| api_error(ErrorCode::InvalidMultipart, m);
    let mut form = Multipart::from_request(paced(req), st)
        .await
        .map_err(|e| bad(e.body_text()))?;
    let mut geometry: Option<ParsedGeometry> = None;
    let mut upload: Option<Uploaded> = None;
    while let Some(mut field) = form.next_field().await.map_err(|e| bad(e.body_text()))? {
        match field.name() {
            Some("geometry") if geometry.is_none() => {
                let mut text = Vec::new();
                while let Some(chunk) = field.chunk().await.map_err(|e| bad(e.body_text()))? {
                    text.extend_from_slice(&chunk);
                    if text.len() > st.settings.max_json_bytes {
                        return Err(api_error(
                            ErrorCode::BodyTooLarge,
                            "the geometry part exceeds the JSON size limit",
                        ));
                    }
                }
                let g = parse_geometry(&text)?;
                if let Some(u) = &upload
                    && u.header.shape != g.shape
                {
                    return Err(api_error(
                        ErrorCode::ShapeMismatch,
                        format!(
                            "the array has shape {:?}, the geometry expects {:?}",
                            u.header.shape, g.shape
                        ),
                    ));
                }
                geometry = Some(g);
            }
            Some("data") if upload.is_none() => {
                let expected = geometry.as_ref().map(|g| g.shape.clone());
                let mut sink = UploadSink::create(&st.store, limits(st), expected).await?;
                while let Some(chunk) = field
                    .chunk()
                    .await
                    .map_err(|e| api_error(ErrorCode::TruncatedUpload, e.body_text()))?
                {
                    sink.write(&chunk).await?;
                }
                upload = Some(sink.finish().await?);
            }
            other => {
                return Err(bad(format!(
                    "unexpected or repeated part {:?}: send one `geometry` and one `data` part",
                    other.unwrap_or("")
                )));
            }
        }
    }
    match (geometry, upload) {
        (Some(g), Some(u)) => Ok((g, u)),
        (None, _) => Err(bad("the `geometry` part is missing".into())),
        (_, None) => Err(bad("the `data` part is missing".into())),
    }
}

pub async fn get_dataset(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = dataset_id(&id)?;
    match st.db.get_dataset(id).await? {
        Some(d) => {
            let missing = st
                .db
                .blob_missing(BlobKind::Dataset, &id.to_string())
                .await?;
            let mut view = dataset_json(&d);
            view["available"] = serde_json::json!(!missing);
            Ok(axum::Json(view).into_response())
        }
        None => Err(api_error(
            ErrorCode::DatasetNotFound,
            format!("no dataset {id}"),
        )),
    }
}

/// `DELETE /v1/datasets/{id}`: 204, the row and then the file removed; 409 while a queued or running job
/// reads it.
pub async fn delete_dataset(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Response> {
    let id = dataset_id(&id)?;
    match st.db.delete_dataset(id).await? {
        Deleted::Done => {
            // A crash before this removal leaves an orphan file, which the start-up sweep removes.
            if let Err(e) = st.store.remove_blob_async(&st.store.dataset_path(id)).await {
                tracing::warn!(error = %e, dataset_id = %id, "removing a deleted dataset's file failed");
            }
            tracing::info!(dataset_id = %id, "dataset deleted");
            Ok(StatusCode::NO_CONTENT.into_response())
        }
        Deleted::InUse => Err(api_error(
            ErrorCode::ResourceInUse,
            format!("dataset {id} is the input of a queued or running job; cancel it or wait"),
        )),
        Deleted::NotFound => Err(api_error(
            ErrorCode::DatasetNotFound,
            format!("no dataset {id}"),
        )),
    }
}
