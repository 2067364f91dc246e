//! What the viewer builds on, against the real server on a random port: `GET /v1/limits` answers the
//! validators' own constants and settings, and each bound is accepted while one past it is refused;
//! refusals name the request's fields by JSON Pointer (`errors`) on the simulation, job and rule routes;
//! `GET /v1/events` streams every job's creation, status, progress and deletion in order, resumes after a
//! `Last-Event-ID`, asks for a reload when it cannot and ends after `?seconds=`; `GET /v1/protocols` lists
//! the protocols the rules run, each a volume job body the API takes, and a rule and the listed body make
//! the same job.

use crate::common;
use crate::sse;

use serde_json::{Value, json};

use common::{TestApp, assert_problem, cone_geometry, parallel_geometry, spawn_app_with};
use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::jobs::model::MAX_RENDER_FRAMES;
use ctrecon::jobs::model::ProductSpec;
use ctrecon::jobs::model::{MAX_CURVE_POINTS, MAX_ITEMS, MAX_ROTATING_FRAMES, MAX_SIGMA_MM};
use ctrecon::jobs::rules::{JobTemplate, Protocol};
use ctrecon::recon::geometry::angles::MAX_VIEWS;
use ctrecon::recon::grid::MAX_AXIS;
use ctrecon::recon::iterative::params::{MAX_ITERATIONS, MAX_TV_ITERATIONS};
use ctrecon::recon::phantom::{MAX_BODIES, MAX_INCIDENT_PHOTONS};
use ctrecon::volume::MAX_SIDE;
use ctrecon::volume::{Frame, Volume};
use sse::{Ev, Sse};

const BUDGET: u64 = 3 << 28;

#[tokio::test]
async fn limits_are_the_validators_constants_and_the_configured_settings() {
    let app = spawn_app_with(|s| {
        s.memory_budget_bytes = BUDGET;
        s.render_max_side = 777;
        s.max_upload_bytes = 12_345_678;
        s.max_json_bytes = 54_321;
    })
    .await;
    let r = app.get("/v1/limits").await;
    assert_eq!(r.status(), 200);
    let l: Value = r.json().await.expect("json");
    let want = json!({
        "geometry": {"max_detector_elements": MAX_AXIS, "max_views": MAX_VIEWS},
        "grid": {"max_side": MAX_AXIS},
        "algorithm": {"max_iterations": MAX_ITERATIONS, "max_tv_iterations": MAX_TV_ITERATIONS},
        "simulation": {"max_bodies": MAX_BODIES, "max_incident_photons": MAX_INCIDENT_PHOTONS,
                       "max_values": BUDGET / 4},
        "volume_job": {"max_steps": MAX_ITEMS, "max_products": MAX_ITEMS, "max_sigma_mm": MAX_SIGMA_MM,
                       "max_rotating_frames": MAX_ROTATING_FRAMES, "max_render_frames": MAX_RENDER_FRAMES,
                       "max_render_side": 777, "max_image_side": MAX_SIDE,
                       "max_curve_points": MAX_CURVE_POINTS},
        "uploads": {"max_upload_bytes": 12_345_678, "max_json_bytes": 54_321},
        "memory_budget_bytes": BUDGET,
    });
    assert_eq!(l, want);
}

/// POST a simulation of `geometry` (and `noise` photons when given); returns the response.
async fn simulation(app: &TestApp, geometry: Value, noise: Option<f64>) -> reqwest::Response {
    let mut body =
        json!({"phantom": {"table": "shepp_logan", "scale_mm": 0.4}, "geometry": geometry});
    if let Some(i0) = noise {
        body["noise"] = json!({"incident_photons": i0, "seed": 1});
    }
    app.post_json("/v1/simulations", &body).await
}

/// Assert a refusal with `status`/`code` whose `errors` name exactly `pointer`, with the problem's detail.
async fn refused_at(r: reqwest::Response, status: u16, code: &str, pointer: &str) -> Value {
    let p = assert_problem(r, status, code).await;
    assert_eq!(
        p["errors"],
        json!([{"pointer": pointer, "detail": p["detail"]}]),
        "{p}"
    );
    p
}

#[tokio::test]
async fn each_bound_of_the_limits_is_accepted_and_one_past_it_is_refused_at_its_field() {
    let app = spawn_app_with(|_| {}).await;
    let l: Value = app.get("/v1/limits").await.json().await.expect("json");
    let max_views = l["geometry"]["max_views"].as_u64().expect("n") as usize;
    let max_det = l["geometry"]["max_detector_elements"].as_u64().expect("n") as usize;
    let max_i0 = l["simulation"]["max_incident_photons"].as_f64().expect("x");
    let max_iter = l["algorithm"]["max_iterations"].as_u64().expect("n");
    let max_side = l["grid"]["max_side"].as_u64().expect("n");

    // Views and detector elements (a 1-element detector, and a single view, keep the arrays small).
    let r = simulation(&app, parallel_geometry(max_views, 1, 1.0), None).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let r = simulation(&app, parallel_geometry(max_views + 1, 1, 1.0), None).await;
    refused_at(r, 422, "invalid_geometry", "/geometry/angles/count").await;
    let r = simulation(&app, parallel_geometry(1, max_det, 0.01), None).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let r = simulation(&app, parallel_geometry(1, max_det + 1, 0.01), None).await;
    refused_at(r, 422, "invalid_geometry", "/geometry/det_count").await;
    let cone = json!({"type": "cone", "angles": {"count": 1}, "dso_mm": 400, "dsd_mm": 600,
                      "detector": {"nu": 1, "nv": max_det + 1, "du_mm": 1.0, "dv_mm": 0.01}});
    refused_at(
        simulation(&app, cone, None).await,
        422,
        "invalid_geometry",
        "/geometry/detector/nv",
    )
    .await;
    // Incident photons.
    let r = simulation(&app, parallel_geometry(4, 8, 1.0), Some(max_i0)).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let r = simulation(&app, parallel_geometry(4, 8, 1.0), Some(max_i0 * 1.001)).await;
    refused_at(r, 422, "invalid_parameter", "/noise/incident_photons").await;

    // Iterations and the grid side, on a reconstruction job.
    let input = app.simulate(parallel_geometry(8, 16, 1.0), 4.0).await;
    let sirt = |n: u64| {
        json!({"input": input, "algorithm": {"name": "sirt", "iterations": n},
               "grid": {"nx": 8, "ny": 8, "dx_mm": 1.0, "dy_mm": 1.0}})
    };
    let j = app.submit(&sirt(max_iter)).await;
    assert_eq!(j["algorithm"]["iterations"], max_iter);
    let r = app.post_json("/v1/jobs", &sirt(max_iter + 1)).await;
    refused_at(r, 422, "invalid_parameter", "/algorithm/iterations").await;
    let fbp = |nx: u64| {
        json!({"input": input, "algorithm": {"name": "fbp"},
               "grid": {"nx": nx, "ny": 1, "dx_mm": 0.0005, "dy_mm": 0.0005}})
    };
    let j = app.submit(&fbp(max_side)).await;
    assert_eq!(j["grid"]["nx"], max_side);
    let r = app.post_json("/v1/jobs", &fbp(max_side + 1)).await;
    refused_at(r, 422, "invalid_parameter", "/grid/nx").await;

    // The projections' values against the memory budget (413, as the array limits are).
    let small = spawn_app_with(|s| s.memory_budget_bytes = 4 * 6000).await;
    let l: Value = small.get("/v1/limits").await.json().await.expect("json");
    assert_eq!(l["simulation"]["max_values"], 6000);
    let r = simulation(&small, parallel_geometry(60, 100, 1.0), None).await;
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let r = simulation(&small, parallel_geometry(60, 101, 1.0), None).await;
    refused_at(r, 413, "array_too_large", "/geometry").await;
}

#[tokio::test]
async fn refusals_name_their_fields_on_the_simulation_job_and_rule_routes() {
    let app = spawn_app_with(|_| {}).await;
    // The core's geometry checks.
    let fan = json!({"type": "fan", "angles": {"count": 30}, "dso_mm": 300, "dsd_mm": 200,
                     "detector": {"shape": "flat", "count": 32, "spacing_mm": 1.0}});
    let p = refused_at(
        simulation(&app, fan, None).await,
        422,
        "invalid_geometry",
        "/geometry/dsd_mm",
    )
    .await;
    assert!(
        p["detail"].as_str().is_some_and(|d| d.contains("200 mm")),
        "{p}"
    );
    // A schema mismatch names the field itself.
    let r = app
        .post_json(
            "/v1/simulations",
            &json!({"phantom": {"table": "shepp_logan", "scale_mm": "big"},
                    "geometry": parallel_geometry(8, 8, 1.0)}),
        )
        .await;
    refused_at(r, 422, "invalid_request", "/phantom/scale_mm").await;

    // Reconstruction jobs: the algorithm's parameters, the grid against the orbit, a wrong type.
    let fan = json!({"type": "fan", "angles": {"count": 30}, "dso_mm": 300, "dsd_mm": 450,
                     "detector": {"shape": "flat", "count": 32, "spacing_mm": 1.0}});
    let input = app.simulate(fan, 10.0).await;
    let r = app
        .post_json(
            "/v1/jobs",
            &json!({"input": input, "algorithm": {"name": "sirt", "iterations": 0},
                    "grid": {"nx": 8, "ny": 8, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await;
    refused_at(r, 422, "invalid_parameter", "/algorithm/iterations").await;
    let r = app
        .post_json(
            "/v1/jobs",
            &json!({"input": input, "algorithm": {"name": "fbp"},
                    "grid": {"nx": 500, "ny": 500, "dx_mm": 1.25, "dy_mm": 1.25}}),
        )
        .await;
    refused_at(r, 422, "invalid_geometry", "/grid").await;
    let r = app
        .post_json(
            "/v1/jobs",
            &json!({"input": input, "algorithm": {"name": "fbp"}, "outputs": 5,
                    "grid": {"nx": 8, "ny": 8, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await;
    refused_at(r, 422, "invalid_request", "/outputs").await;

    // Volume jobs: a product's field, a step's field.
    let cone = app.simulate(cone_geometry(24, 24), 10.0).await;
    let fdk = app
        .submit(&json!({"input": cone, "algorithm": {"name": "fdk"},
                        "grid": {"nx": 16, "ny": 16, "nz": 16, "spacing_mm": [1, 1, 1]}}))
        .await;
    let fdk = fdk["id"].as_str().expect("id").to_string();
    assert_eq!(app.finish(&fdk).await["status"], "succeeded");
    let volume = |steps: Value, products: Value| json!({"kind": "volume", "input": fdk, "steps": steps, "products": products});
    let r = app
        .post_json(
            "/v1/jobs",
            &volume(
                json!([]),
                json!([{"type": "projection"}, {"type": "rotating", "frames": MAX_ROTATING_FRAMES + 1}]),
            ),
        )
        .await;
    refused_at(r, 422, "invalid_parameter", "/products/1/frames").await;
    let r = app
        .post_json(
            "/v1/jobs",
            &volume(
                json!([{"op": "median"}, {"op": "gaussian", "sigma_mm": MAX_SIGMA_MM + 1.0}]),
                json!([{"type": "projection"}]),
            ),
        )
        .await;
    refused_at(r, 422, "invalid_parameter", "/steps/1/sigma_mm").await;
    let ok = app
        .submit(&volume(
            json!([{"op": "gaussian", "sigma_mm": MAX_SIGMA_MM}]),
            json!([{"type": "rotating", "frames": 4}]),
        ))
        .await;
    assert_eq!(ok["kind"], "volume");

    // Rules: the name, a match pattern, a destination.
    let r = app
        .post_json(
            "/v1/rules",
            &json!({"name": "Bad Name", "protocol": "spine"}),
        )
        .await;
    refused_at(r, 422, "invalid_rule", "/name").await;
    let r = app
        .post_json(
            "/v1/rules",
            &json!({"name": "spine", "protocol": "spine", "match": {"modality": "C[T]"}}),
        )
        .await;
    refused_at(r, 422, "invalid_pattern", "/match/modality").await;
    let r = app
        .post_json(
            "/v1/rules",
            &json!({"name": "spine", "protocol": "spine", "destinations": ["NOWHERE"]}),
        )
        .await;
    refused_at(r, 422, "unknown_peer", "/destinations/0").await;
}

fn seq(id: &str) -> u64 {
    id.rsplit('-')
        .next()
        .and_then(|s| s.parse().ok())
        .expect("an id `{boot}-{seq}`")
}

#[tokio::test]
async fn one_stream_tells_every_jobs_creation_status_progress_and_deletion_in_order() {
    let app = spawn_app_with(|s| s.max_concurrent_jobs = 1).await;
    let input = app.simulate(parallel_geometry(60, 64, 1.0), 28.0).await;
    let mut sse = Sse::open(&app.client, &app.url("/v1/events"), None).await;
    let ready = sse.next(10).await;
    assert_eq!(ready.name, "ready");

    // A short job runs to the end; a long one is queued behind a second long one, canceled while queued,
    // the running one canceled; then the short one is deleted.
    let fbp = app
        .submit(
            &json!({"input": input, "algorithm": {"name": "sirt", "iterations": 400},
                        "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await["id"]
        .as_str()
        .expect("id")
        .to_string();
    let evs = sse
        .until(120, |e| {
            e.name == "status" && e.data["status"] == "succeeded"
        })
        .await;
    let mine: Vec<(&str, &str, u64)> = evs
        .iter()
        .map(|e| {
            assert_eq!(e.data["id"], fbp.as_str(), "{e:?}");
            (
                e.name.as_str(),
                e.data["status"].as_str().unwrap_or(""),
                e.data["progress"].as_u64().unwrap_or(0),
            )
        })
        .collect();
    assert_eq!(mine[0], ("created", "queued", 0), "{mine:?}");
    assert_eq!(evs[0].data["kind"], "reconstruction");
    assert_eq!(evs[0].data["links"]["self"], format!("/v1/jobs/{fbp}"));
    assert_eq!(mine[1], ("status", "running", 0), "{mine:?}");
    assert_eq!(mine.last(), Some(&("status", "succeeded", 100)));
    let middle = &mine[2..mine.len() - 1];
    assert!(!middle.is_empty(), "progress while running: {mine:?}");
    assert!(
        middle
            .iter()
            .all(|(n, s, _)| *n == "progress" && *s == "running"),
        "{mine:?}"
    );
    assert!(
        middle.windows(2).all(|w| w[0].2 <= w[1].2),
        "progress only grows: {mine:?}"
    );
    let ids: Vec<u64> = std::iter::once(&ready)
        .chain(&evs)
        .map(|e| seq(&e.id))
        .collect();
    assert!(
        ids.windows(2).all(|w| w[1] == w[0] + 1),
        "consecutive ids: {ids:?}"
    );

    let endless = json!({"input": input, "algorithm": {"name": "sirt", "iterations": 100000},
                         "grid": {"nx": 64, "ny": 64, "dx_mm": 1.0, "dy_mm": 1.0}});
    let running = app.submit(&endless).await["id"]
        .as_str()
        .expect("id")
        .to_string();
    sse.until(60, |e| {
        e.name == "status" && e.data["id"] == running.as_str() && e.data["status"] == "running"
    })
    .await;
    let queued = app.submit(&endless).await["id"]
        .as_str()
        .expect("id")
        .to_string();
    // The running job's progress may come first.
    let created = sse
        .until(10, |e| e.name == "created")
        .await
        .pop()
        .expect("event");
    assert_eq!(created.data["id"], queued.as_str());
    assert_eq!(created.data["status"], "queued");
    assert_eq!(
        app.post_json(&format!("/v1/jobs/{queued}/cancel"), &json!({}))
            .await
            .status(),
        202
    );
    let mut after = sse.until(10, |e| e.data["id"] == queued.as_str()).await;
    let last = after.last().expect("event");
    assert_eq!(
        (last.name.as_str(), &last.data["status"]),
        ("status", &json!("canceled"))
    );
    assert_eq!(
        app.post_json(&format!("/v1/jobs/{running}/cancel"), &json!({}))
            .await
            .status(),
        202
    );
    after.extend(
        sse.until(30, |e| {
            e.name == "status" && e.data["id"] == running.as_str() && e.data["status"] == "canceled"
        })
        .await,
    );
    let r = app
        .client
        .delete(app.url(&format!("/v1/jobs/{fbp}")))
        .send()
        .await
        .expect("delete");
    assert_eq!(r.status(), 204);
    let deleted = sse.next(10).await;
    assert_eq!(
        (deleted.name.as_str(), &deleted.data),
        ("deleted", &json!({"id": fbp}))
    );
    after.push(deleted);

    // Resuming after the `created` of the queued job replays what followed it, in the same order.
    let mut again = Sse::open(&app.client, &app.url("/v1/events"), Some(&created.id)).await;
    let replay = again.until(10, |e| e.name == "deleted").await;
    let names = |v: &[Ev]| {
        v.iter()
            .map(|e| (e.name.clone(), e.id.clone(), e.data.clone()))
            .collect::<Vec<_>>()
    };
    assert_eq!(names(&replay), names(&after));
    assert_eq!(seq(&replay[0].id), seq(&created.id) + 1);
    // An id from another process is not resumed: the client is told to reload.
    let mut stranger = Sse::open(&app.client, &app.url("/v1/events"), Some("1-1")).await;
    assert_eq!(stranger.next(10).await.name, "resync");
}

#[tokio::test]
async fn a_stream_asked_to_last_n_seconds_ends_then_and_a_bad_n_is_refused() {
    let app = spawn_app_with(|_| {}).await;
    let started = std::time::Instant::now();
    let r = app.get("/v1/events?seconds=1").await;
    assert_eq!(r.status(), 200);
    let body = r.text().await.expect("the stream ends");
    let took = started.elapsed();
    assert!(body.starts_with("event: ready\n"), "{body}");
    assert!(
        took >= std::time::Duration::from_millis(950) && took < std::time::Duration::from_secs(5),
        "ended after {took:?}"
    );
    // `0`: `ready` alone.
    let r = app.get("/v1/events?seconds=0").await;
    assert_eq!(r.status(), 200);
    let body = r.text().await.expect("the stream ends");
    assert!(body.starts_with("event: ready\n"), "{body}");
    assert_eq!(body.matches("event:").count(), 1, "{body}");
    for bad in ["86401", "-1", "x", "1.5"] {
        assert_problem(
            app.get(&format!("/v1/events?seconds={bad}")).await,
            400,
            "invalid_query",
        )
        .await;
    }
    assert_problem(app.get("/v1/events?second=5").await, 400, "invalid_query").await;
}

/// The products of a job as the API shows it, typed (defaults filled in, so two spellings compare equal).
fn products_of(job: &Value) -> Vec<ProductSpec> {
    serde_json::from_value(job["products"].clone()).unwrap_or_else(|e| panic!("{e}: {job}"))
}

#[tokio::test]
async fn protocols_are_the_ones_rules_run_and_each_is_a_volume_job_the_api_takes() {
    let token = "protocols-test-token-0123456789abcdef";
    let app = spawn_app_with(|s| s.api_tokens = vec![token.into()]).await;
    let get = |path: &str| app.client.get(app.url(path)).bearer_auth(token).send();
    let post = |path: &str, body: Value| {
        app.client
            .post(app.url(path))
            .bearer_auth(token)
            .json(&body)
            .send()
    };
    // Behind the token, as the rest of /v1.
    assert_eq!(app.get("/v1/protocols").await.status(), 401);
    let r = get("/v1/protocols").await.expect("request");
    assert_eq!(r.status(), 200);
    let listed: Value = r.json().await.expect("json");
    let listed = listed["protocols"].as_array().expect("protocols").clone();
    let names: Vec<&str> = listed.iter().filter_map(|p| p["name"].as_str()).collect();
    assert_eq!(names, ["spine", "bone_stl", "lung"]);
    for (p, shipped) in listed.iter().zip(Protocol::ALL) {
        // Exactly the steps and products a rule naming the protocol runs, and its window.
        let t: JobTemplate =
            serde_json::from_value(json!({"steps": p["steps"], "products": p["products"]}))
                .unwrap_or_else(|e| panic!("{e}: {p}"));
        assert_eq!(t, shipped.template(), "{p}");
        assert_eq!(p["window"], json!(shipped.window()), "{p}");
        assert_eq!(p["description"], shipped.description());
    }
    assert_eq!(listed[2]["window"], "lung");
    assert_eq!(listed[1]["products"][0]["target_triangles"], 200000);

    // A rule naming `lung`, then a series (a 32 × 32 × 12 ramp of 1 × 1 × 2 mm): the rule's job and the
    // listed body sent as a volume job (what the viewer's preset sends) make the same products.
    let r = post(
        "/v1/rules",
        json!({"name": "lung-ct", "protocol": "lung", "match": {"modality": "CT"}}),
    )
    .await
    .expect("request");
    assert_eq!(r.status(), 201, "{}", r.text().await.unwrap_or_default());
    let data = ndarray::Array3::from_shape_fn((12, 32, 32), |(k, j, i)| {
        (k * 100 + j * 10 + i) as f32 - 1000.0
    });
    let frame = Frame {
        origin_mm: [-16.0, -16.0, 0.0],
        spacing_mm: [1.0, 1.0, 2.0],
        direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
    };
    let meta = SeriesMeta {
        series_description: "protocols".into(),
        series_number: 3,
        ..Default::default()
    };
    let files = write_ct_series(&Volume { data, frame }, &meta)
        .expect("a CT series")
        .files;
    let r = app
        .client
        .post(app.url("/v1/series"))
        .bearer_auth(token)
        .header("content-type", "application/zip")
        .body(write_zip(&files).expect("zip"))
        .send()
        .await
        .expect("upload");
    assert_eq!(r.status(), 201);
    let up: Value = r.json().await.expect("json");
    let series = up["series"][0]["series"]["id"]
        .as_str()
        .expect("series id")
        .to_string();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    let rule_job = loop {
        let rule: Value = get("/v1/rules/lung-ct")
            .await
            .expect("request")
            .json()
            .await
            .expect("json");
        if let Some(id) = rule["runs"][0]["job_id"].as_str() {
            break id.to_string();
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the rule never ran: {rule}"
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    };
    let job_of = |id: String| {
        let get = &get;
        async move {
            let r = get(&format!("/v1/jobs/{id}")).await.expect("request");
            assert_eq!(r.status(), 200);
            r.json::<Value>().await.expect("json")
        }
    };
    let by_rule = job_of(rule_job).await;
    for p in &listed {
        let body = json!({"kind": "volume", "input": series, "steps": p["steps"],
                          "products": p["products"]});
        let r = post("/v1/jobs", body).await.expect("request");
        assert_eq!(
            r.status(),
            202,
            "{p}: {}",
            r.text().await.unwrap_or_default()
        );
        let job: Value = r.json().await.expect("json");
        let want: Vec<ProductSpec> =
            serde_json::from_value(p["products"].clone()).expect("products");
        assert_eq!(products_of(&job), want, "{p}");
        if p["name"] == "lung" {
            assert_eq!(products_of(&job), products_of(&by_rule), "{by_rule}");
            let id = job["id"].as_str().expect("id").to_string();
            let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
            let done = loop {
                let j = job_of(id.clone()).await;
                if j["status"] != "queued" && j["status"] != "running" {
                    break j;
                }
                assert!(std::time::Instant::now() < deadline, "{j}");
                tokio::time::sleep(std::time::Duration::from_millis(50)).await;
            };
            assert_eq!(done["status"], "succeeded", "{done}");
            // A coronal MinIP (one 12 × 32 image) and 10 mm axial MIP slabs every 10 mm.
            let products = done["result"]["products"].as_array().expect("products");
            assert_eq!(products[0]["shape"], json!([1, 12, 32]), "{done}");
            assert_eq!(products[1]["type"], "mpr", "{done}");
        }
    }
}
