//! Open DICOM uploads across API hosts with object storage: every acknowledged instance is in the bucket, so
//! an upload opened on one API process and completed through another (its own data directory) after the
//! first was killed assembles every instance; completing or deleting an upload removes its objects.

use ctrecon::dicom::{SeriesMeta, write_ct_series};
use ctrecon::recon::VolumeGrid;
use ctrecon::volume::{Frame, Volume};
use serde_json::{Value, json};

use crate::common::{self, TestApp, assert_problem};
use crate::roles::{api, on, sha256_hex};
use crate::{cluster, s3};

/// Slices of the test series.
const SLICES: usize = 12;

/// A CT series of `SLICES` slices of 32 × 32 pixels, 2 mm apart: its instances' bytes, in slice order.
fn instances() -> Vec<Vec<u8>> {
    let g = VolumeGrid {
        nx: 32,
        ny: 32,
        nz: SLICES,
        spacing_mm: [1.5, 1.5, 2.0],
        centre_mm: [0.0, 0.0, 0.0],
    };
    let data = ndarray::Array3::from_shape_fn((SLICES, 32, 32), |(z, y, x)| {
        (z * 100 + y * 3 + x) as f32 - 500.0
    });
    let vol = Volume {
        data,
        frame: Frame::from_grid(&g),
    };
    let meta = SeriesMeta {
        series_description: "across hosts".into(),
        series_number: 1,
        ..Default::default()
    };
    write_ct_series(&vol, &meta)
        .expect("a CT series")
        .files
        .into_iter()
        .map(|(_, bytes)| bytes)
        .collect()
}

/// `POST path` with one `application/dicom` instance.
async fn send(client: &TestApp, path: &str, instance: &[u8]) -> reqwest::Response {
    client
        .client
        .post(client.url(path))
        .header("content-type", "application/dicom")
        .body(instance.to_vec())
        .send()
        .await
        .expect("request")
}

/// Open an upload with the first instance: its id.
async fn open(client: &TestApp, instance: &[u8]) -> String {
    let r = send(client, "/v1/series", instance).await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.expect("json");
    v["upload"]["id"].as_str().expect("upload id").to_string()
}

/// Append an instance; the answer counts `count` instances.
async fn append(client: &TestApp, id: &str, instance: &[u8], count: usize) {
    let r = send(client, &format!("/v1/series?upload={id}"), instance).await;
    assert_eq!(r.status(), 200);
    let v: Value = r.json().await.expect("json");
    assert_eq!(v["upload"]["instances"], count, "{v}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn s3_an_upload_opened_on_a_killed_api_host_is_completed_through_another_with_every_instance()
{
    let test = "s3_upload_across_api_hosts";
    let Some(url) = cluster::database_url(test) else {
        return;
    };
    let Some(s3) = s3::s3(test) else {
        return;
    };
    let files = instances();
    let (a_dir, b_dir) = (
        tempfile::tempdir().expect("dir"),
        tempfile::tempdir().expect("dir"),
    );
    let a = api(s3.serve_to(on(a_dir.path(), &url)));
    let b = api(s3.serve_to(on(b_dir.path(), &url)));
    let (ca, cb) = (common::attach(&a.base), common::attach(&b.base));

    // Two thirds of the instances through A: each acknowledged one is in the bucket, byte for byte.
    let id = open(&ca, &files[0]).await;
    let on_a = 2 * SLICES / 3;
    for (k, f) in files.iter().enumerate().take(on_a).skip(1) {
        append(&ca, &id, f, k + 1).await;
    }
    let mut expected: Vec<String> = files[..on_a]
        .iter()
        .map(|f| format!("{}.dcm", sha256_hex(f)))
        .collect();
    expected.sort();
    assert_eq!(s3.objects_under(&format!("uploads/{id}")), expected);
    for name in &expected {
        let object =
            std::fs::read(s3.object_file(&format!("uploads/{id}/{name}"))).expect("object");
        assert_eq!(format!("{}.dcm", sha256_hex(&object)), *name);
    }

    // A dies; the rest goes through B, which completes the upload with what A acknowledged.
    a.signal("KILL");
    drop(a);
    for (k, f) in files.iter().enumerate().skip(on_a) {
        append(&cb, &id, f, k + 1).await;
    }
    let r = cb
        .post_json(&format!("/v1/uploads/{id}/complete"), &json!({}))
        .await;
    assert_eq!(r.status(), 201);
    let v: Value = r.json().await.expect("json");
    assert_eq!(v["upload"]["instances"], SLICES, "{v}");
    assert_eq!(
        v["series"][0]["series"]["shape"],
        json!([SLICES, 32, 32]),
        "{v}"
    );
    let series = v["series"][0]["series"]["id"].as_str().expect("series id");
    // The series is in the bucket; the upload's objects and B's copies of them are gone.
    assert!(s3.object_file(&format!("series/{series}.npy")).is_file());
    assert_eq!(
        s3.objects_under(&format!("uploads/{id}")),
        Vec::<String>::new()
    );
    assert!(!b_dir.path().join("uploads").join(&id).exists());
    assert_eq!(s3.unfinished(), Vec::<String>::new());
    // The volume holds every slice: the last one (sent to B) and the first (sent to A) as written.
    let r = cb.get(&format!("/v1/series/{series}/volume.npy")).await;
    assert_eq!(r.status(), 200);
    let (shape, values) = common::read_npy_f32(&r.bytes().await.expect("volume"));
    assert_eq!(shape, [SLICES, 32, 32]);
    let at = |z: usize, y: usize, x: usize| values[(z * 32 + y) * 32 + x];
    for z in [0, on_a - 1, on_a, SLICES - 1] {
        let want = (z * 100 + 5 * 3 + 7) as f32 - 500.0;
        assert!(
            (at(z, 5, 7) - want).abs() <= 1.0,
            "slice {z}: {} HU",
            at(z, 5, 7)
        );
    }

    // An upload that is deleted leaves no object and no file; appending to it is then refused.
    let other = open(&cb, &files[0]).await;
    append(&cb, &other, &files[1], 2).await;
    assert_eq!(s3.objects_under(&format!("uploads/{other}")).len(), 2);
    let r = cb
        .client
        .delete(cb.url(&format!("/v1/uploads/{other}")))
        .send()
        .await
        .expect("request");
    assert_eq!(r.status(), 204);
    assert_eq!(
        s3.objects_under(&format!("uploads/{other}")),
        Vec::<String>::new()
    );
    assert!(!b_dir.path().join("uploads").join(&other).exists());
    assert_problem(
        cb.get(&format!("/v1/uploads/{other}")).await,
        404,
        "upload_not_found",
    )
    .await;
    assert_problem(
        send(&cb, &format!("/v1/series?upload={other}"), &files[2]).await,
        404,
        "upload_not_found",
    )
    .await;
    // A completed upload is not deleted by itself: it goes with its series.
    let r = cb
        .client
        .delete(cb.url(&format!("/v1/uploads/{id}")))
        .send()
        .await
        .expect("request");
    assert_problem(r, 409, "upload_closed").await;
    assert_eq!(s3.objects_under("uploads"), Vec::<String>::new());
}
