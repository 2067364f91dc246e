//! Results of a succeeded job, immutable once written: `volume.npy`, `slice`, `projection`, `mesh.stl`,
//! `series.zip` (a derived CT series), `metrics`, and the `products/{index}` of volume jobs. Views are rendered
//! on the worker pool on first request and cached; every file is served with a strong ETag,
//! `Cache-Control: immutable` and range support. What a view could not honour (a mesh's empty surface or
//! unreached `target_triangles`) is named by its stable codes in the [`WARNINGS`] header, kept beside the
//! cached file so that every answer for the same ETag carries it.

use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderName, HeaderValue};
use axum::response::Response;
use sha2::{Digest, Sha256};

use super::super::AppState;
use super::super::extract::{ApiQuery, job_id};
use super::super::files::{FileMeta, serve_bytes, serve_file, serve_stored};
use super::super::problem::{ApiResult, api_error};
use crate::dicom::SeriesMeta;
use crate::error_code::{ErrorCode, Problem};
use crate::jobs::views::{
    MeshQuery, ProductFormat, ProductQuery, ProjectionQuery, RenderContext, Rendered, SeriesQuery,
    SliceQuery, ViewRequest, render, render_product,
};
use crate::jobs::{JobResult, JobStatus};
use crate::storage::npy::hex;
use crate::storage::{JobId, ResultName};

/// The result of job `id`, or why there is none.
async fn result_of(st: &AppState, id: JobId) -> ApiResult<JobResult> {
    let job = st
        .db
        .get_job(id)
        .await?
        .ok_or_else(|| api_error(ErrorCode::JobNotFound, format!("no job {id}")))?;
    match (job.status, job.result) {
        (JobStatus::Succeeded, Some(r)) => Ok(r),
        (status, _) => Err(api_error(
            ErrorCode::JobNotSucceeded,
            format!(
                "the job is {}; results exist once it has succeeded",
                status.as_str()
            ),
        )),
    }
}

pub async fn volume(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let r = result_of(&st, id).await?;
    serve_stored(
        &headers,
        &st.store,
        FileMeta {
            path: st.store.result_path(id, &ResultName::Volume),
            etag: r.volume.sha256,
            content_type: "application/x-npy",
            filename: Some(format!("{id}.npy")),
        },
    )
    .await
}

pub async fn metrics(
    State(st): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let r = result_of(&st, id).await?;
    let Some(m) = r.metrics else {
        return Err(api_error(
            ErrorCode::ResultUnavailable,
            "this job computed no metrics (request `outputs: [\"volume\", \"metrics\"]` on a simulation)",
        ));
    };
    let body = serde_json::to_vec(&m).unwrap_or_default();
    let etag = hex(&Sha256::digest(&body));
    serve_bytes(&headers, &etag, "application/json", body)
}

/// How DICOM results of `r` are labelled: the source series' study, frame of reference and patient when the
/// volume derives from one.
async fn render_context(st: &AppState, r: &JobResult) -> ApiResult<RenderContext> {
    let source = match r.source_series {
        Some(id) => st.db.get_series(id).await?,
        None => None,
    };
    let meta = match source {
        Some(s) => SeriesMeta {
            study_uid: s.study_uid,
            frame_of_reference_uid: s.frame_of_reference_uid,
            patient_name: s.patient_name,
            patient_id: s.patient_id,
            series_description: format!(
                "ctrecon {}",
                s.description.as_deref().unwrap_or("derived")
            )
            .chars()
            .take(64)
            .collect(),
            series_number: 900,
            source_series_uid: Some(s.series_uid),
            derivation_description: Some("ctrecon: derived from the source series".into()),
        },
        None => SeriesMeta {
            series_description: "ctrecon reconstruction".into(),
            series_number: 900,
            derivation_description: r.derivation.clone(),
            ..SeriesMeta::default()
        },
    };
    Ok(RenderContext {
        frame: r.frame(),
        units: r.units,
        mu_water: st.settings.mu_water_per_mm,
        meta,
        patient: r.source_series.is_some(),
    })
}

/// Response header naming, comma-separated, the stable codes of what a view could not honour (absent when
/// there is nothing to say).
pub const WARNINGS: &str = "x-ctrecon-warnings";

/// Where a derived file and, for views that can warn, the JSON array of its warning codes are kept.
struct Derived {
    path: std::path::PathBuf,
    warnings: Option<std::path::PathBuf>,
}

/// Render a derived file from `source` on the worker pool, unless it is already there (results are immutable,
/// so a rendering never goes stale); returns its warning codes. The warnings are written before the file, so a
/// cached file always has them.
async fn render_once<F>(
    st: &AppState,
    r: &JobResult,
    out: &Derived,
    make: F,
    source: std::path::PathBuf,
) -> ApiResult<Vec<String>>
where
    F: FnOnce(&[u8], &RenderContext) -> Result<Rendered, Problem> + Send + 'static,
{
    if tokio::fs::try_exists(&out.path).await.unwrap_or(false) {
        let Some(w) = &out.warnings else {
            return Ok(Vec::new());
        };
        if let Ok(text) = tokio::fs::read(w).await
            && let Ok(codes) = serde_json::from_slice::<Vec<String>>(&text)
        {
            return Ok(codes);
        }
    }
    let ctx = render_context(st, r).await?;
    let store = st.store.clone();
    let dest = out.path.clone();
    let warnings = out.warnings.clone();
    let codes = st
        .engine
        .compute(move || {
            let io = |e: std::io::Error| {
                tracing::error!(error = %e, "rendering a result failed");
                Problem::internal()
            };
            let bytes = store.local(&source).and_then(std::fs::read).map_err(io)?;
            let out = make(&bytes, &ctx)?;
            if let Some(w) = &warnings {
                let text = serde_json::to_vec(&out.warnings).map_err(|_| Problem::internal())?;
                store.write_atomic(w, &text).map_err(io)?;
            }
            store.write_atomic(&dest, &out.bytes).map_err(io)?;
            Ok(out.warnings)
        })
        .await?;
    Ok(codes)
}

async fn view(
    st: AppState,
    id: String,
    req: ViewRequest,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    req.validate()?;
    let r = result_of(&st, id).await?;
    let mu_water = st.settings.mu_water_per_mm;
    let key = req.key(mu_water);
    let (ext, content_type) = req.media();
    let derived = |ext| {
        st.store.result_path(
            id,
            &ResultName::Derived {
                key_hex: key.clone(),
                ext,
            },
        )
    };
    let out = Derived {
        path: derived(ext),
        warnings: req.warns().then(|| derived("warnings.json")),
    };
    let source = st.store.result_path(id, &ResultName::Volume);
    let codes = render_once(
        &st,
        &r,
        &out,
        move |bytes, ctx| render(bytes, ctx, &req),
        source,
    )
    .await?;
    let mut resp = serve_file(
        &headers,
        FileMeta {
            path: out.path,
            etag: key,
            content_type,
            filename: Some(format!("{id}.{ext}")),
        },
    )
    .await?;
    if !codes.is_empty()
        && let Ok(v) = HeaderValue::from_str(&codes.join(", "))
    {
        resp.headers_mut()
            .insert(HeaderName::from_static(WARNINGS), v);
    }
    Ok(resp)
}

pub async fn series_zip(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<SeriesQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    view(st, id, ViewRequest::Series(q), headers).await
}

pub async fn product(
    State(st): State<AppState>,
    Path((id, index)): Path<(String, String)>,
    ApiQuery(q): ApiQuery<ProductQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let id = job_id(&id)?;
    let index: usize = index.parse().map_err(|_| {
        api_error(
            ErrorCode::InvalidId,
            "a product index is a non-negative integer",
        )
    })?;
    q.validate()?;
    let r = result_of(&st, id).await?;
    let Some(p) = r.products.iter().find(|p| p.index == index).cloned() else {
        return Err(api_error(
            ErrorCode::ResultUnavailable,
            format!(
                "the job has {} product(s); there is no product {index}",
                r.products.len()
            ),
        ));
    };
    let format = q.format_for(&p)?;
    let stored_ext = if p.is_mesh() { "stl" } else { "npy" };
    let stored = st.store.result_path(
        id,
        &ResultName::Product {
            index,
            ext: stored_ext,
        },
    );
    let (ext, content_type) = format.media();
    if matches!(format, ProductFormat::Npy | ProductFormat::Stl) {
        return serve_stored(
            &headers,
            &st.store,
            FileMeta {
                path: stored,
                etag: p.file.sha256,
                content_type,
                filename: Some(format!("{id}-{index}.{ext}")),
            },
        )
        .await;
    }
    let key = q.key(index, format, st.settings.mu_water_per_mm);
    let out = Derived {
        path: st.store.result_path(
            id,
            &ResultName::Derived {
                key_hex: key.clone(),
                ext,
            },
        ),
        warnings: None,
    };
    render_once(
        &st,
        &r,
        &out,
        move |bytes, ctx| render_product(bytes, &p, &q, format, ctx).map(Rendered::from),
        stored,
    )
    .await?;
    serve_file(
        &headers,
        FileMeta {
            path: out.path,
            etag: key,
            content_type,
            filename: Some(format!("{id}-{index}.{ext}")),
        },
    )
    .await
}

pub async fn slice(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<SliceQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    view(st, id, ViewRequest::Slice(q), headers).await
}

pub async fn projection(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<ProjectionQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    view(st, id, ViewRequest::Projection(q), headers).await
}

pub async fn mesh(
    State(st): State<AppState>,
    Path(id): Path<String>,
    ApiQuery(q): ApiQuery<MeshQuery>,
    headers: HeaderMap,
) -> ApiResult<Response> {
    q.validate()?;
    view(st, id, ViewRequest::Mesh(q), headers).await
}
