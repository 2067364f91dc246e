//! Bad input is answered with a 4xx `application/problem+json` and its catalogue code, never a panic or
//! a 5xx; bearer tokens; the OpenAPI contract lists every route and every error code.

use crate::common;

use common::{assert_problem, cone_geometry, npy, parallel_geometry, spawn_app, spawn_app_with};
use ctrecon::error_code::ErrorCode;
use serde_json::{Value, json};

const GOOD_ID: &str = "0192d1f2-7a3b-7c4d-8e5f-60718293a4b5";

/// Send only the headers of a POST declaring `length` body bytes; returns the status line and the body.
async fn raw_post_headers_only(app: &common::TestApp, path: &str, length: u64) -> (String, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let addr = app.base.trim_start_matches("http://");
    let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!(
        "POST {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/x-npy\r\n\
         X-Ctrecon-Geometry: {}\r\nContent-Length: {length}\r\nConnection: close\r\n\r\n",
        parallel_geometry(4, 3, 1.0)
    );
    s.write_all(req.as_bytes()).await.unwrap();
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out).await;
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text.lines().next().unwrap_or("").to_string();
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("").to_string();
    (status, body)
}

fn percent(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

fn f32s(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// Raw upload of `body` for a parallel geometry of 4 views × 3 detector elements.
async fn upload(app: &common::TestApp, body: Vec<u8>) -> reqwest::Response {
    let geometry = parallel_geometry(4, 3, 1.0).to_string();
    app.client
        .post(app.url("/v1/sinograms"))
        .header("content-type", "application/x-npy")
        .header("x-ctrecon-geometry", geometry)
        .body(body)
        .send()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_accept_float32_float64_and_uint16_and_refuse_every_malformed_array() {
    let app = spawn_app_with(|s| s.max_upload_bytes = 1 << 20).await;
    // Accepted: the three dtypes, raw and multipart.
    let r = upload(&app, npy("<f4", "(4, 3)", &f32s(&[0.5; 12]))).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(
        (v["shape"].clone(), v["dtype"].clone()),
        (json!([4, 3]), json!("float32"))
    );
    assert_eq!(v["sha256"].as_str().unwrap().len(), 64);
    let d64: Vec<u8> = [0.25f64; 12].iter().flat_map(|v| v.to_le_bytes()).collect();
    let r = upload(&app, npy("<f8", "(4, 3)", &d64)).await;
    assert_eq!(r.status(), 201);
    let form = reqwest::multipart::Form::new()
        .text("geometry", parallel_geometry(4, 3, 1.0).to_string())
        .part(
            "data",
            reqwest::multipart::Part::bytes(npy("<u2", "(4, 3)", &[1u8; 24])).file_name("s.npy"),
        );
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.unwrap();
    assert_eq!(v["dtype"], "uint16");
    let id = v["id"].as_str().unwrap();
    assert_eq!(app.get(&format!("/v1/datasets/{id}")).await.status(), 200);

    // Refused.
    let good = f32s(&[0.5; 12]);
    let mut bad_magic = npy("<f4", "(4, 3)", &good);
    bad_magic[1] = b'X';
    assert_problem(upload(&app, bad_magic).await, 400, "malformed_npy").await;
    assert_problem(
        upload(&app, npy("<f4", "(4, 3", &good)).await,
        400,
        "malformed_npy",
    )
    .await;
    assert_problem(
        upload(&app, npy("<i8", "(4, 3)", &[0; 96])).await,
        422,
        "unsupported_dtype",
    )
    .await;
    assert_problem(
        upload(&app, npy("<f4", "(3, 4)", &good)).await,
        422,
        "shape_mismatch",
    )
    .await;
    let mut nan = [0.5f32; 12];
    nan[7] = f32::NAN;
    assert_problem(
        upload(&app, npy("<f4", "(4, 3)", &f32s(&nan))).await,
        422,
        "non_finite_data",
    )
    .await;
    assert_problem(
        upload(&app, npy("<f4", "(4, 3)", &good[..40])).await,
        400,
        "truncated_upload",
    )
    .await;
    let mut long = npy("<f4", "(4, 3)", &good);
    long.extend_from_slice(&[0; 4]);
    assert_problem(upload(&app, long).await, 400, "malformed_npy").await;
    // A declared shape beyond the limit is refused from the header alone.
    let app_big = spawn_app_with(|s| s.max_upload_bytes = 1 << 20).await;
    let geometry = parallel_geometry(4000, 3000, 0.1).to_string();
    let r = app_big
        .client
        .post(app_big.url("/v1/sinograms"))
        .header("content-type", "application/x-npy")
        .header("x-ctrecon-geometry", geometry)
        .body(npy("<f4", "(4000, 3000)", &[0; 64]))
        .send()
        .await
        .unwrap();
    assert_problem(r, 413, "array_too_large").await;
    // A body over the upload limit is refused from its declared length, before it is sent: raw HTTP,
    // so that the client reads the answer instead of failing to write the rest.
    let (status, body) = raw_post_headers_only(&app, "/v1/sinograms", 10_000_000).await;
    assert!(status.contains(" 413 "), "{status}");
    assert!(body.contains("\"code\":\"body_too_large\""), "{body}");
    // Wrong content type, missing geometry, missing parts.
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .header("content-type", "text/plain")
        .body("hello")
        .send()
        .await
        .unwrap();
    assert_problem(r, 415, "unsupported_media_type").await;
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .header("content-type", "application/x-npy")
        .body(npy("<f4", "(4, 3)", &good))
        .send()
        .await
        .unwrap();
    assert_problem(r, 422, "invalid_request").await;
    let form =
        reqwest::multipart::Form::new().text("geometry", parallel_geometry(4, 3, 1.0).to_string());
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .multipart(form)
        .send()
        .await
        .unwrap();
    assert_problem(r, 400, "invalid_multipart").await;
    // A geometry that cannot exist.
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .header("content-type", "application/x-npy")
        .header(
            "x-ctrecon-geometry",
            parallel_geometry(4, 3, -1.0).to_string(),
        )
        .body(npy("<f4", "(4, 3)", &good))
        .send()
        .await
        .unwrap();
    assert_problem(r, 422, "invalid_geometry").await;
    // Nothing half-written was kept.
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("tmp"))
            .unwrap()
            .count(),
        0
    );
    assert_eq!(
        std::fs::read_dir(app.dir.path().join("datasets"))
            .unwrap()
            .count(),
        3
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn json_requests_with_bad_syntax_fields_or_values_are_refused_with_their_codes() {
    let app = spawn_app().await;
    let sim =
        |g: Value| json!({"phantom": {"table": "shepp_logan", "scale_mm": 20}, "geometry": g});
    let r = app
        .client
        .post(app.url("/v1/simulations"))
        .header("content-type", "application/json")
        .body("{\"phantom\": ")
        .send()
        .await
        .unwrap();
    assert_problem(r, 400, "malformed_json").await;
    let r = app
        .client
        .post(app.url("/v1/simulations"))
        .body(sim(cone_geometry(8, 16)).to_string())
        .send()
        .await
        .unwrap();
    assert_problem(r, 415, "unsupported_media_type").await;
    let mut unknown = sim(cone_geometry(8, 16));
    unknown["colour"] = json!("red");
    assert_problem(
        app.post_json("/v1/simulations", &unknown).await,
        422,
        "invalid_request",
    )
    .await;
    let zero_views = sim(
        json!({"type": "cone", "angles": {"count": 0}, "dso_mm": 400, "dsd_mm": 600,
        "detector": {"nu": 16, "nv": 16, "du_mm": 1, "dv_mm": 1}}),
    );
    assert_problem(
        app.post_json("/v1/simulations", &zero_views).await,
        422,
        "invalid_geometry",
    )
    .await;
    let mut noisy = sim(cone_geometry(8, 16));
    noisy["noise"] = json!({"incident_photons": -5});
    assert_problem(
        app.post_json("/v1/simulations", &noisy).await,
        422,
        "invalid_parameter",
    )
    .await;
    let big = sim(cone_geometry(4000, 4000));
    assert_problem(
        app.post_json("/v1/simulations", &big).await,
        413,
        "array_too_large",
    )
    .await;
    let r = app
        .client
        .post(app.url("/v1/jobs"))
        .header("content-type", "application/json")
        .body(format!("{{\"pad\": \"{}\"}}", "x".repeat(100_000)))
        .send()
        .await
        .unwrap();
    assert_problem(r, 413, "body_too_large").await;

    let input = app.simulate(cone_geometry(16, 32), 20.0).await;
    let job = |alg: Value, grid: Value| json!({"input": input, "algorithm": alg, "grid": grid});
    let cube = json!({"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1, 1, 1]});
    // NaN is not JSON; negative, zero and out-of-range parameters are refused before queueing.
    let r = app
        .client
        .post(app.url("/v1/jobs"))
        .header("content-type", "application/json")
        .body(format!(
            "{{\"input\": \"{input}\", \"algorithm\": {{\"name\": \"fdk\", \"cutoff\": NaN}}, \"grid\": {cube}}}"
        ))
        .send()
        .await
        .unwrap();
    assert_problem(r, 400, "malformed_json").await;
    for (alg, grid) in [
        (json!({"name": "fdk", "cutoff": -0.5}), cube.clone()),
        (json!({"name": "fdk", "cutoff": 0}), cube.clone()),
        (json!({"name": "sirt", "iterations": 0}), cube.clone()),
        (json!({"name": "sirt", "relaxation": -1}), cube.clone()),
        (json!({"name": "os_sart", "subsets": 0}), cube.clone()),
        // Rows of 32 samples are filtered with padding in [2·32 − 1, 2²⁰]: checked here, not when the job runs.
        (json!({"name": "fdk", "padded_len": 2097152}), cube.clone()),
        (json!({"name": "fdk", "padded_len": 40}), cube.clone()),
        (
            json!({"name": "fdk"}),
            json!({"nx": 0, "ny": 16, "nz": 16, "spacing_mm": [1, 1, 1]}),
        ),
        (
            json!({"name": "fdk"}),
            json!({"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1, -1, 1]}),
        ),
        (
            json!({"name": "fdk"}),
            json!({"nx": 16, "ny": 16, "dx_mm": 1, "dy_mm": 1}),
        ),
    ] {
        let body = job(alg.clone(), grid.clone());
        assert_problem(
            app.post_json("/v1/jobs", &body).await,
            422,
            "invalid_parameter",
        )
        .await;
    }
    // FBP refuses a parallel beam over 90°: at submission, also for an iterative method that starts from it.
    let narrow = app
        .simulate(
            json!({"type": "parallel", "angles": {"count": 8, "range_deg": 90},
                   "det_count": 16, "det_spacing_mm": 1.0}),
            5.0,
        )
        .await;
    // The voxel-driven back projector takes cone beams only.
    for alg in [
        json!({"name": "fbp"}),
        json!({"name": "sirt", "initial": "fbp"}),
        json!({"name": "cgls", "back_projector": "voxel"}),
    ] {
        let body = json!({"input": narrow, "algorithm": alg,
                          "grid": {"nx": 8, "ny": 8, "dx_mm": 1, "dy_mm": 1}});
        assert_problem(
            app.post_json("/v1/jobs", &body).await,
            422,
            "invalid_parameter",
        )
        .await;
    }
    let unknown_value = job(
        json!({"name": "cgls", "back_projector": "joseph"}),
        cube.clone(),
    );
    assert_problem(
        app.post_json("/v1/jobs", &unknown_value).await,
        422,
        "invalid_request",
    )
    .await;
    let unknown_param = job(json!({"name": "fdk", "iterations": 3}), cube.clone());
    assert_problem(
        app.post_json("/v1/jobs", &unknown_param).await,
        422,
        "invalid_request",
    )
    .await;
    let metrics_on_upload = {
        let r = app
            .client
            .post(app.url(&format!(
                "/v1/sinograms?geometry={}",
                percent(&parallel_geometry(4, 3, 1.0).to_string())
            )))
            .header("content-type", "application/x-npy")
            .body(npy("<f4", "(4, 3)", &f32s(&[0.0; 12])))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 201);
        let v: Value = r.json().await.unwrap();
        json!({"input": v["id"], "algorithm": {"name": "fbp"},
               "grid": {"nx": 4, "ny": 4, "dx_mm": 1, "dy_mm": 1}, "outputs": ["metrics"]})
    };
    assert_problem(
        app.post_json("/v1/jobs", &metrics_on_upload).await,
        422,
        "invalid_parameter",
    )
    .await;
    // A job that can never fit the memory budget (1 GiB) is refused at submission.
    let huge = job(
        json!({"name": "fdk"}),
        json!({"nx": 2048, "ny": 2048, "nz": 2048, "spacing_mm": [0.01, 0.01, 0.01]}),
    );
    assert_problem(app.post_json("/v1/jobs", &huge).await, 422, "job_too_large").await;
    let nothing = json!({"input": GOOD_ID, "algorithm": {"name": "fdk"}, "grid": cube});
    assert_problem(
        app.post_json("/v1/jobs", &nothing).await,
        404,
        "dataset_not_found",
    )
    .await;
    let r = app
        .client
        .post(app.url("/v1/jobs"))
        .header("idempotency-key", "")
        .json(&nothing)
        .send()
        .await
        .unwrap();
    assert_problem(r, 400, "invalid_idempotency_key").await;
    // Nothing was queued by any of these.
    let list: Value = app.get("/v1/jobs").await.json().await.unwrap();
    assert_eq!(list["jobs"], json!([]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_ids_routes_queries_and_illegal_transitions_are_4xx_problems() {
    let app = spawn_app().await;
    assert_problem(
        app.get(&format!("/v1/jobs/{GOOD_ID}")).await,
        404,
        "job_not_found",
    )
    .await;
    assert_problem(app.get("/v1/jobs/..%2F..%2Fetc").await, 400, "invalid_id").await;
    assert_problem(
        app.get("/v1/jobs/not-an-id/result/volume.npy").await,
        400,
        "invalid_id",
    )
    .await;
    assert_problem(
        app.get(&format!("/v1/datasets/{GOOD_ID}")).await,
        404,
        "dataset_not_found",
    )
    .await;
    assert_problem(
        app.get(&format!("/v1/jobs/{GOOD_ID}/events")).await,
        404,
        "job_not_found",
    )
    .await;
    assert_problem(
        app.post_json(&format!("/v1/jobs/{GOOD_ID}/cancel"), &json!({}))
            .await,
        404,
        "job_not_found",
    )
    .await;
    assert_problem(app.get("/v1/nothing").await, 404, "not_found").await;
    let r = app.client.put(app.url("/v1/jobs")).send().await.unwrap();
    assert_problem(r, 405, "method_not_allowed").await;
    assert_problem(
        app.get("/v1/jobs?status=sleeping").await,
        400,
        "invalid_query",
    )
    .await;
    assert_problem(app.get("/v1/jobs?limit=0").await, 400, "invalid_query").await;
    assert_problem(app.get("/v1/jobs?cursor=abc").await, 400, "invalid_query").await;
    assert_problem(
        app.get("/v1/jobs?created_after=yesterday").await,
        400,
        "invalid_query",
    )
    .await;
    assert_problem(app.get("/v1/jobs?colour=red").await, 400, "invalid_query").await;

    // A finished job: cancel is 409, results of a failed job are 409, bad view parameters are 4xx.
    let input = app.simulate(cone_geometry(24, 32), 14.0).await;
    let cube = json!({"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1, 1, 1]});
    let job = app
        .submit(&json!({"input": input, "algorithm": {"name": "fdk"}, "grid": cube}))
        .await;
    let id = job["id"].as_str().unwrap();
    let done = app.finish(id).await;
    assert!(
        matches!(done["status"].as_str(), Some("succeeded" | "failed")),
        "{done}"
    );
    assert_problem(
        app.post_json(&format!("/v1/jobs/{id}/cancel"), &json!({}))
            .await,
        409,
        "job_already_finished",
    )
    .await;
    if done["status"] == "succeeded" {
        let base = format!("/v1/jobs/{id}/result");
        assert_problem(
            app.get(&format!("{base}/slice?index=99")).await,
            422,
            "slice_out_of_range",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/slice?axis=oblique")).await,
            400,
            "invalid_query",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/slice?ww=-1&wl=0")).await,
            422,
            "invalid_window",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/slice?ww=1")).await,
            422,
            "invalid_parameter",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/slice?preset=bone&ww=1&wl=0"))
                .await,
            422,
            "invalid_parameter",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/slice?depth=12")).await,
            422,
            "invalid_parameter",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/projection?slab_start=10&slab_end=5"))
                .await,
            422,
            "invalid_slab",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/mesh.stl")).await,
            400,
            "invalid_query",
        )
        .await;
        assert_problem(
            app.get(&format!("{base}/metrics")).await,
            404,
            "result_unavailable",
        )
        .await;
        let r = app
            .client
            .get(app.url(&format!("{base}/volume.npy")))
            .header("range", "bytes=999999999-")
            .send()
            .await
            .unwrap();
        assert_problem(r, 416, "range_not_satisfiable").await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_tokens_configured_only_bearers_of_a_valid_token_get_in() {
    let app = spawn_app_with(|s| s.api_tokens = vec!["correct-horse-battery".into()]).await;
    assert_eq!(app.get("/healthz").await.status(), 200);
    assert_eq!(app.get("/readyz").await.status(), 200);
    assert_problem(app.get("/v1/jobs").await, 401, "unauthorized").await;
    let r = app
        .client
        .get(app.url("/v1/jobs"))
        .bearer_auth("correct-horse-batter")
        .send()
        .await
        .unwrap();
    assert_problem(r, 401, "unauthorized").await;
    let r = app
        .client
        .get(app.url("/v1/jobs"))
        .bearer_auth("correct-horse-battery")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    // The scheme is case-insensitive (RFC 9110), the token is not.
    for (value, status) in [
        ("bearer correct-horse-battery", 200),
        ("BEARER  correct-horse-battery", 200),
        ("bearer CORRECT-HORSE-BATTERY", 401),
        ("Basic correct-horse-battery", 401),
    ] {
        let r = app
            .client
            .get(app.url("/v1/jobs"))
            .header("authorization", value)
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), status, "{value}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_service_reports_metrics_and_echoes_request_ids() {
    let app = spawn_app().await;
    let r = app.get("/healthz").await;
    assert!(r.headers().contains_key("x-request-id"));
    let text = app.get("/metrics").await.text().await.unwrap();
    assert!(text.contains("ctrecon_jobs{status=\"queued\"}"), "{text}");
    assert!(text.contains("ctrecon_queue_depth"));
    assert!(text.contains("ctrecon_http_requests_total"));
}

/// `(method, path)` of every route the router declares, read from its source.
fn declared_routes() -> Vec<(String, String)> {
    // Whitespace-normalised, so that a `.route(` call that rustfmt wraps over lines still reads as one.
    let src = include_str!("../src/http/mod.rs")
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ");
    let mut out = Vec::new();
    for call in src.split(".route(").skip(1) {
        let Some(rest) = call.trim_start().strip_prefix('"') else {
            continue;
        };
        let path = rest.split('"').next().unwrap().to_string();
        // The handlers of this call: up to its closing parenthesis (one level of nesting).
        let args = rest.split("))").next().unwrap_or("");
        for m in ["get", "post", "delete", "put", "patch"] {
            if args.contains(&format!("{m}(")) {
                out.push((m.to_string(), path.clone()));
            }
        }
    }
    out
}

/// `(method, path)` of every operation in the OpenAPI document (2-space path keys, 4-space methods).
fn documented_routes(yaml: &str) -> Vec<(String, String)> {
    operations(yaml)
        .into_iter()
        .map(|(route, _)| route)
        .collect()
}

/// Every operation of the OpenAPI document with its `operationId` (`None` where it has none).
pub(crate) fn operations(yaml: &str) -> Vec<((String, String), Option<String>)> {
    let mut out: Vec<((String, String), Option<String>)> = Vec::new();
    let mut in_paths = false;
    let mut path = None;
    for line in yaml.lines() {
        if line == "paths:" {
            in_paths = true;
            continue;
        }
        if in_paths && !line.starts_with(' ') && !line.is_empty() {
            in_paths = false;
        }
        if !in_paths {
            continue;
        }
        if let Some(p) = line.strip_prefix("  /") {
            path = Some(format!("/{}", p.trim_end_matches(':')));
        } else if let Some(m) = line.strip_prefix("    ")
            && !m.starts_with(' ')
            && let Some(m) = m.strip_suffix(':')
            && ["get", "post", "delete", "put", "patch"].contains(&m)
            && let Some(p) = &path
        {
            out.push(((m.to_string(), p.clone()), None));
        } else if let Some(id) = line.strip_prefix("      operationId: ")
            && let Some((_, slot)) = out.last_mut()
        {
            *slot = Some(id.trim().to_string());
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_openapi_document_describes_every_route_and_every_error_code() {
    let yaml = include_str!("../openapi.yaml");
    assert!(yaml.starts_with("openapi: 3.1"), "OpenAPI 3.1");
    let declared = declared_routes();
    assert!(declared.len() >= 15, "{declared:?}");
    let documented = documented_routes(yaml);
    for route in &declared {
        assert!(
            documented.contains(route),
            "{route:?} is not in openapi.yaml"
        );
    }
    for route in &documented {
        assert!(
            declared.contains(route),
            "openapi.yaml documents {route:?}, which does not exist"
        );
    }
    for code in ErrorCode::ALL {
        assert!(
            yaml.contains(&format!("- {}\n", code.code())),
            "error code {} is not in openapi.yaml",
            code.code()
        );
    }
    let app = spawn_app().await;
    let served = app.get("/openapi.yaml").await.text().await.unwrap();
    assert_eq!(served, yaml);
}

/// Client generators name their functions by `operationId` (openapi-typescript's `operations`, progenitor,
/// openapi-generator): every operation has one, unique, in lowerCamelCase, so that a new route without one
/// fails here.
#[test]
fn every_operation_has_a_stable_unique_operation_id() {
    let yaml = include_str!("../openapi.yaml");
    let ops = operations(yaml);
    assert!(ops.len() >= 50, "{} operations", ops.len());
    let mut seen = std::collections::HashSet::new();
    for ((method, path), id) in &ops {
        let Some(id) = id else {
            panic!("{method} {path} has no operationId in openapi.yaml");
        };
        assert!(
            id.starts_with(|c: char| c.is_ascii_lowercase())
                && id.chars().all(|c| c.is_ascii_alphanumeric()),
            "{method} {path}: operationId {id:?} is not lowerCamelCase"
        );
        assert!(seen.insert(id.clone()), "operationId {id} is used twice");
    }
    for route in declared_routes() {
        assert!(
            ops.iter().any(|(r, id)| *r == route && id.is_some()),
            "{route:?} has no documented operation with an operationId"
        );
    }
}

/// A 3D parallel beam simulates, reconstructs slice by slice through a job, and is refused as every other
/// geometry when it cannot exist: 422 `invalid_geometry` for an upload and for a simulation.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn parallel3d_scans_simulate_and_reconstruct_and_bad_ones_are_invalid_geometry() {
    let app = spawn_app().await;
    let geometry = |du: f64| {
        json!({"type": "parallel3d", "angles": {"count": 90},
               "detector": {"nu": 64, "nv": 24, "du_mm": du, "dv_mm": 1.0}})
    };
    // The phantom (scale 20 mm) reaches 18.4 mm in x and y: 64 elements of 0.75 mm cover ±24 mm.
    let input = app.simulate(geometry(0.75), 20.0).await;
    let job = app
        .submit(
            &json!({"input": input, "algorithm": {"name": "fbp", "filter": "hann"},
               "grid": {"nx": 48, "ny": 48, "nz": 8, "spacing_mm": [1.0, 1.0, 1.0]},
               "outputs": ["volume", "metrics"]}),
        )
        .await;
    let id = job["id"].as_str().unwrap();
    let done = app.finish(id).await;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["result"]["shape"], json!([8, 48, 48]));
    let m: Value = app
        .get(&format!("/v1/jobs/{id}/result/metrics"))
        .await
        .json()
        .await
        .unwrap();
    let rmse = m["rmse"].as_f64().unwrap();
    assert!(rmse < 0.1, "RMSE {rmse}: {m}");
    let data: Vec<u8> = std::iter::repeat_n(0f32.to_le_bytes(), 4 * 2 * 3)
        .flatten()
        .collect();
    let r = app
        .client
        .post(app.url("/v1/sinograms"))
        .header("content-type", "application/x-npy")
        .header(
            "x-ctrecon-geometry",
            json!({"type": "parallel3d", "angles": {"count": 4},
                   "detector": {"nu": 3, "nv": 2, "du_mm": -1.0, "dv_mm": 1.0}})
            .to_string(),
        )
        .body(npy("<f4", "(4, 2, 3)", &data))
        .send()
        .await
        .unwrap();
    assert_problem(r, 422, "invalid_geometry").await;
    let r = app
        .post_json(
            "/v1/simulations",
            &json!({"phantom": {"table": "shepp_logan", "scale_mm": 20}, "geometry": geometry(0.0)}),
        )
        .await;
    assert_problem(r, 422, "invalid_geometry").await;
}
