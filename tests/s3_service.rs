//! The service on S3 object storage: an API process (`serve --workers 0`) and `ctrecon worker` processes,
//! each with a data directory of its own, share a PostgreSQL job database and an S3 server that checks SigV4
//! signatures (s3s-fs). Datasets uploaded to the API reach the workers through the bucket, results made by
//! the workers are served by the API straight from it (ranges too), and deleting a job removes its objects.
//! An open DICOM upload outlives the API host that received its instances: each acknowledged instance is in
//! the bucket, so another API host completes it, and a completed or deleted upload leaves no object. Wrong
//! credentials and a missing bucket stop the start of either role with the reason and take no job; `/readyz`
//! reports an object store that stopped answering. `compose.yaml` names only variables the service reads.
//!
//! Without PostgreSQL or s3s-fs (`scripts/install-peers.sh postgres s3`) a test prints one skip line, unless
//! `CTRECON_REQUIRE_PEERS=1`, where it fails.

use crate::cluster;
use crate::common;
use crate::roles;
use crate::s3;
#[path = "s3_service/uploads.rs"]
mod uploads;

use std::time::{Duration, Instant};

use common::{TestApp, cone_geometry, parallel_geometry};
use roles::{api, fbp, on, worker};
use s3::{BUCKET, S3Server, SECRET_KEY};
use serde_json::Value;

/// The whole body of a GET, asserting `status`.
async fn body(client: &TestApp, path: &str, range: Option<&str>, status: u16) -> Vec<u8> {
    let mut req = client.client.get(client.url(path));
    if let Some(r) = range {
        req = req.header("range", r);
    }
    let r = req.send().await.expect("request");
    assert_eq!(r.status(), status, "GET {path} {range:?}");
    r.bytes().await.expect("body").to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_an_api_and_two_workers_with_their_own_directories_share_datasets_and_results() {
    let test = "s3_api_and_two_workers";
    let Some(url) = cluster::database_url(test) else {
        return;
    };
    let Some(s3) = s3::s3(test) else {
        return;
    };
    let (api_dir, w1_dir, w2_dir) = (
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
    );
    let a = api(s3.serve_to(on(api_dir.path(), &url)));
    let client = common::attach(&a.base);
    let _workers = [
        worker(s3.serve_to(on(w1_dir.path(), &url)), "127.0.0.1"),
        worker(s3.serve_to(on(w2_dir.path(), &url)), "127.0.0.1"),
    ];

    // A dataset made on the API host is in the bucket before its 201.
    let flat = client.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let dataset_key = format!("datasets/{flat}.npy");
    let local = std::fs::read(api_dir.path().join(&dataset_key)).expect("the API's copy");
    let object = std::fs::read(s3.object_file(&dataset_key)).expect("the dataset's object");
    assert_eq!(roles::sha256_hex(&object), roles::sha256_hex(&local));

    // Jobs run on the workers, which fetch the dataset from the bucket into their own directories.
    let mut ids = Vec::new();
    for _ in 0..4 {
        let job = client.submit(&fbp(&flat)).await;
        ids.push(job["id"].as_str().expect("id").to_string());
    }
    let mut first_sha = None;
    for id in &ids {
        let done = client.finish(id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert!(
            done["result"]["metrics"]["rmse"].as_f64().expect("rmse") < 0.1,
            "{done}"
        );
        let sha = done["result"]["volume"]["sha256"]
            .as_str()
            .expect("sha")
            .to_string();
        // The same input and parameters give the same bytes on either worker.
        assert_eq!(first_sha.get_or_insert_with(|| sha.clone()), &sha);
        let key = format!("results/{id}/volume.npy");
        let object = std::fs::read(s3.object_file(&key)).expect("the volume's object");
        assert_eq!(roles::sha256_hex(&object), sha);
        // The API host never had the result: it serves it from the bucket, whole and by range.
        assert!(!api_dir.path().join(&key).exists());
        let whole = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            None,
            200,
        )
        .await;
        assert_eq!(roles::sha256_hex(&whole), sha);
        let part = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            Some("bytes=1000-5095"),
            206,
        )
        .await;
        assert_eq!(part, whole[1000..5096]);
        let tail = body(
            &client,
            &format!("/v1/jobs/{id}/result/volume.npy"),
            Some("bytes=-100"),
            206,
        )
        .await;
        assert_eq!(tail, whole[whole.len() - 100..]);
    }
    let mut fetched_by = 0;
    for d in [&w1_dir, &w2_dir] {
        if d.path().join(&dataset_key).exists() {
            fetched_by += 1;
            let copy = std::fs::read(d.path().join(&dataset_key)).expect("copy");
            assert_eq!(roles::sha256_hex(&copy), roles::sha256_hex(&local));
        }
    }
    assert!(fetched_by >= 1, "a worker fetched the dataset");

    // Deleting a job removes its objects; deleting a dataset removes its object.
    let cone = client.simulate(cone_geometry(30, 16), 10.0).await;
    assert!(s3.object_file(&format!("datasets/{cone}.npy")).is_file());
    let r = client
        .client
        .delete(client.url(&format!("/v1/jobs/{}", ids[0])))
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 204);
    assert!(s3::files_under(&s3.object_file(&format!("results/{}", ids[0]))).is_empty());
    assert!(
        s3.object_file(&format!("results/{}/volume.npy", ids[1]))
            .exists()
    );
    let r = client
        .client
        .delete(client.url(&format!("/v1/datasets/{cone}")))
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 204);
    assert!(!s3.object_file(&format!("datasets/{cone}.npy")).exists());
    assert!(s3.object_file(&dataset_key).exists());
}

/// Run `ctrecon ROLE` on the job database `url` against bucket `bucket` with secret `secret`; it must stop
/// at once, saying why, without listening.
fn refused_start(s3: &S3Server, url: &str, role: &[&str], bucket: &str, secret: &str) -> String {
    let dir = tempfile::tempdir().expect("dir");
    let started = Instant::now();
    let mut c = on(dir.path(), url);
    s3.configure(&mut c, bucket, secret);
    let out = c.args(role).output().expect("ctrecon runs");
    assert!(!out.status.success(), "{role:?} must not start");
    assert!(out.stdout.is_empty(), "{role:?} never listened");
    assert!(started.elapsed() < Duration::from_secs(60));
    // Nothing was fetched or made here.
    assert!(s3::files_under(&dir.path().join("results")).is_empty());
    assert!(s3::files_under(&dir.path().join("datasets")).is_empty());
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_wrong_credentials_and_a_missing_bucket_stop_either_role_at_start_and_take_no_job() {
    let test = "s3_bad_configuration";
    let Some(url) = cluster::database_url(test) else {
        return;
    };
    let Some(s3) = s3::s3(test) else {
        return;
    };
    // A job waits in the queue of an API process that runs none.
    let api_dir = tempfile::tempdir().expect("dir");
    let a = api(s3.serve_to(on(api_dir.path(), &url)));
    let client = common::attach(&a.base);
    let flat = client.simulate(parallel_geometry(90, 64, 1.0), 20.0).await;
    let job = client.submit(&fbp(&flat)).await;
    let id = job["id"].as_str().expect("id").to_string();

    let serve = ["serve", "--bind", "127.0.0.1:0"];
    let work = ["worker", "--health-bind", "127.0.0.1:0"];
    for role in [&serve[..], &work[..]] {
        let e = refused_start(&s3, &url, role, BUCKET, "not-the-secret");
        assert!(
            e.contains("object storage") && e.contains("refused the credentials"),
            "{role:?}: {e}"
        );
        let e = refused_start(&s3, &url, role, "no-such-bucket", SECRET_KEY);
        assert!(
            e.contains("object storage") && e.contains("bucket does not exist"),
            "{role:?}: {e}"
        );
        // No process took the job: it is queued as it was, no attempt spent.
        let j = client.job(&id).await;
        assert_eq!(
            (j["status"].as_str(), j["attempts"].as_u64()),
            (Some("queued"), Some(0)),
            "{j}"
        );
    }

    // The API reports the object store ready; a worker with the right settings runs the job at its first
    // attempt.
    let r = client.get("/readyz").await;
    assert_eq!(r.status(), 200);
    let ready: Value = r.json().await.expect("json");
    assert_eq!(ready["object_storage"], "ok", "{ready}");
    let w_dir = tempfile::tempdir().expect("dir");
    let w = worker(s3.serve_to(on(w_dir.path(), &url)), "127.0.0.1");
    let done = client.finish(&id).await;
    assert_eq!(
        (done["status"].as_str(), done["attempts"].as_u64()),
        (Some("succeeded"), Some(1)),
        "{done}"
    );

    // The object store stops answering: both processes say at once that they are not ready (the database
    // and the data directory are fine; the log names the object store).
    drop(s3);
    for base in [&a.base, &w.base] {
        let t = Instant::now();
        let r = common::attach(base).get("/readyz").await;
        common::assert_problem(r, 503, "unavailable").await;
        assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    }
}

#[test]
fn compose_names_only_variables_the_service_reads() {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/compose.yaml"))
        .expect("compose.yaml");
    let names = |prefix: &str| -> Vec<String> {
        let mut out: Vec<String> = text
            .match_indices(prefix)
            .map(|(at, _)| {
                text[at..]
                    .chars()
                    .take_while(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || *c == '_')
                    .collect()
            })
            .collect();
        out.sort();
        out.dedup();
        out
    };
    let ours = names("CTRECON_");
    for needed in [
        "CTRECON_DATABASE_URL",
        "CTRECON_STORAGE_URL",
        "CTRECON_STORAGE_ENDPOINT",
        "CTRECON_DATA_DIR",
    ] {
        assert!(ours.iter().any(|n| n == needed), "{needed} in {ours:?}");
    }
    for name in &ours {
        let value = match name.as_str() {
            "CTRECON_BIND" => "0.0.0.0:8080",
            "CTRECON_DATABASE_URL" => "postgres://ctrecon@postgres:5432/ctrecon",
            "CTRECON_STORAGE_URL" => "s3://ctrecon/site",
            "CTRECON_STORAGE_ENDPOINT" => "http://s3:9000",
            "CTRECON_ALLOW_INSECURE" => "true",
            "CTRECON_DATA_DIR" => "/data",
            _ => "1",
        };
        let s = ctrecon::config::Settings::load(None, [(name.clone(), value.to_string())]);
        assert!(s.is_ok(), "{name}: {:?}", s.err());
    }
    #[cfg(feature = "s3")]
    for name in names("AWS_") {
        assert!(
            ctrecon::storage::object::AWS_VARIABLES.contains(&name.as_str()),
            "{name} is not read by the S3 adapter"
        );
    }
}
