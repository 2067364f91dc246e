//! Refusals that say what to do. Each case is a mistake a new user makes in the first hour (the README's
//! "Troubleshooting" section lists them): the answer keeps its stable code and its detail names the fix. The
//! README's table quotes each answer; this test sends every case and checks the quote against the answer,
//! so that the section cannot drift.

use crate::common;

use common::{TestApp, parallel_geometry, spawn_app_with};
use ctrecon::dicom::{SeriesMeta, write_ct_series, write_zip};
use ctrecon::volume::{Frame, Volume};
use serde_json::{Value, json};

/// One mistake: the request that makes it, the status and code it gets, and a phrase of the detail that
/// names the fix (the README quotes it).
struct Case {
    name: &'static str,
    status: u16,
    code: &'static str,
    phrase: &'static str,
}

const CASES: &[Case] = &[
    Case {
        name: "a series id given to a reconstruction",
        status: 404,
        code: "dataset_not_found",
        phrase: "is a DICOM series, not a projection dataset: volume jobs take series and job volumes — add \"kind\": \"volume\"",
    },
    Case {
        name: "volume-job fields without a kind",
        status: 422,
        code: "invalid_request",
        phrase: "`products` belongs to volume jobs: add \"kind\": \"volume\"",
    },
    Case {
        name: "a dataset id given to a volume job",
        status: 404,
        code: "series_not_found",
        phrase: "is a projection dataset, not a volume: reconstruct it first",
    },
    Case {
        name: "a grid of the wrong shape",
        status: 422,
        code: "invalid_request",
        phrase: "a grid: {\"nx\", \"ny\", \"dx_mm\", \"dy_mm\"} for a 2D geometry, or {\"nx\", \"ny\", \"nz\", \"spacing_mm\": [x, y, z]} (three numbers) for a cone beam",
    },
    Case {
        name: "angles of the wrong shape",
        status: 422,
        code: "invalid_request",
        phrase: "angles: {\"count\": N} with optional \"start_deg\" and \"range_deg\" (equally spaced)",
    },
    Case {
        name: "an image posted as a ZIP",
        status: 415,
        code: "unsupported_media_type",
        phrase: "the body was sent as application/zip but is a PNG image",
    },
    Case {
        name: "a DICOM file posted as a ZIP",
        status: 415,
        code: "unsupported_media_type",
        phrase: "is a DICOM file: send one instance as application/dicom",
    },
    Case {
        name: "a series id asked of the jobs",
        status: 404,
        code: "job_not_found",
        phrase: "is a DICOM series (GET /v1/series/",
    },
    Case {
        name: "results of a job that has not succeeded",
        status: 409,
        code: "job_not_succeeded",
        phrase: "results exist once it has succeeded",
    },
    Case {
        name: "a job that can never fit the memory budget",
        status: 422,
        code: "job_too_large",
        phrase: "reconstruct onto a smaller grid (or from fewer views), or raise the service's memory_budget_bytes",
    },
];

/// A small CT series uploaded as a ZIP; returns its id.
async fn series(app: &TestApp) -> String {
    let data = ndarray::Array3::from_shape_fn((4, 16, 16), |(z, y, x)| (z + y + x) as f32 - 1000.0);
    let vol = Volume {
        data,
        frame: Frame {
            origin_mm: [0.0, 0.0, 0.0],
            spacing_mm: [1.0, 1.0, 2.0],
            direction: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        },
    };
    let s = write_ct_series(&vol, &SeriesMeta::default()).expect("a series");
    let r = post(
        app,
        "/v1/series",
        "application/zip",
        write_zip(&s.files).expect("zip"),
    )
    .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.expect("json");
    v["series"][0]["series"]["id"]
        .as_str()
        .expect("series id")
        .to_string()
}

async fn post(app: &TestApp, path: &str, media: &str, body: Vec<u8>) -> reqwest::Response {
    app.client
        .post(app.url(path))
        .header("content-type", media)
        .body(body)
        .send()
        .await
        .expect("answered")
}

/// Make the mistake `name`; the answer.
async fn make(app: &TestApp, name: &str, series: &str, dataset: &str) -> reqwest::Response {
    let fbp = |input: &str| {
        json!({"input": input, "algorithm": {"name": "fbp"},
               "grid": {"nx": 32, "ny": 32, "dx_mm": 1.0, "dy_mm": 1.0}})
    };
    match name {
        "a series id given to a reconstruction" => app.post_json("/v1/jobs", &fbp(series)).await,
        "volume-job fields without a kind" => {
            let body = json!({"input": series,
                              "products": [{"type": "projection", "axis": "coronal", "kind": "mip"}]});
            app.post_json("/v1/jobs", &body).await
        }
        "a dataset id given to a volume job" => {
            let body = json!({"kind": "volume", "input": dataset,
                              "products": [{"type": "projection", "axis": "coronal", "kind": "mip"}]});
            app.post_json("/v1/jobs", &body).await
        }
        "a grid of the wrong shape" => {
            let mut body = fbp(dataset);
            body["grid"] = json!({"nx": 32, "ny": 32, "nz": 32, "spacing_mm": 3});
            app.post_json("/v1/jobs", &body).await
        }
        "angles of the wrong shape" => {
            let mut geometry = parallel_geometry(8, 8, 1.0);
            geometry["angles"] = json!({"views": 8});
            let body = json!({"phantom": {"table": "modified_shepp_logan", "scale_mm": 20.0},
                              "geometry": geometry});
            app.post_json("/v1/simulations", &body).await
        }
        "an image posted as a ZIP" => {
            let png = b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR".to_vec();
            post(app, "/v1/series", "application/zip", png).await
        }
        "a DICOM file posted as a ZIP" => {
            let mut dicom = vec![0u8; 128];
            dicom.extend_from_slice(b"DICM\x02\x00\x00\x00UL\x04\x00\x00\x00\x00\x00");
            post(app, "/v1/series", "application/zip", dicom).await
        }
        "a series id asked of the jobs" => app.get(&format!("/v1/jobs/{series}")).await,
        "results of a job that has not succeeded" => {
            // Queued behind the long job that holds the one job slot.
            let job = app.submit(&fbp(dataset)).await;
            let id = job["id"].as_str().expect("id");
            app.get(&format!("/v1/jobs/{id}/result/volume.npy")).await
        }
        "a job that can never fit the memory budget" => {
            let mut body = fbp(dataset);
            body["grid"] = json!({"nx": 4096, "ny": 4096, "dx_mm": 0.01, "dy_mm": 0.01});
            app.post_json("/v1/jobs", &body).await
        }
        other => panic!("no such case {other}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_first_hours_mistakes_are_answered_with_their_fix_and_the_readme_quotes_them() {
    // A small budget, so that a large grid can never fit; one job at a time, a slow iterative method
    // keeps the canceled job from finishing first.
    let app = spawn_app_with(|s| {
        s.memory_budget_bytes = 64 << 20;
        s.max_concurrent_jobs = 1;
    })
    .await;
    let series = series(&app).await;
    let dataset = app.simulate(parallel_geometry(90, 48, 1.0), 20.0).await;
    // Occupy the one job slot so that the job canceled in one case is still queued.
    let long = app
        .submit(
            &json!({"input": dataset, "algorithm": {"name": "sirt", "iterations": 100000},
                        "grid": {"nx": 32, "ny": 32, "dx_mm": 1.0, "dy_mm": 1.0}}),
        )
        .await;
    let readme = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/README.md"))
        .expect("README.md");
    let section = readme
        .split("## Troubleshooting")
        .nth(1)
        .expect("a Troubleshooting section")
        .split("\n## ")
        .next()
        .unwrap_or_default()
        .to_string();
    for case in CASES {
        let r = make(&app, case.name, &series, &dataset).await;
        let status = r.status().as_u16();
        let body: Value = r.json().await.expect("a problem");
        assert_eq!(
            (status, body["code"].as_str()),
            (case.status, Some(case.code)),
            "{}: {body}",
            case.name
        );
        let detail = body["detail"].as_str().unwrap_or_default();
        assert!(
            detail.contains(case.phrase),
            "{}: the detail {detail:?} does not say {:?}",
            case.name,
            case.phrase
        );
        // The README quotes the code and the phrase (JSON-escaped quotes aside).
        let quoted = case.phrase.replace('|', "\\|");
        assert!(
            section.contains(case.code) && section.contains(&quoted),
            "README's Troubleshooting does not quote {} `{}`: {quoted}",
            case.name,
            case.code
        );
    }
    let id = long["id"].as_str().expect("id");
    let _ = app
        .client
        .post(app.url(&format!("/v1/jobs/{id}/cancel")))
        .send()
        .await;
}
