//! DICOM ingest: the 133-slice LIDC-IDRI-0001 series (70 MB, `.testdata/lidc`, see `scripts/fetch-test-data.sh`)
//! decoded in parallel and assembled into an HU volume, on a 2-thread pool (the target machine has 2 cores).
//! Target: ≤ 1 s. Without the data the benchmark prints a skip notice.

use std::path::Path;

use criterion::{Criterion, criterion_group, criterion_main};
use ctrecon::dicom::{ReadLimits, SeriesMeta, read_upload, write_ct_series};
use ctrecon::recon::control::unattended;
use ctrecon::series::AssemblyOptions;

fn load() -> Option<Vec<(String, Vec<u8>)>> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join(".testdata/lidc");
    let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "dcm"))
        .filter_map(|p| {
            Some((
                p.file_name()?.to_string_lossy().into_owned(),
                std::fs::read(&p).ok()?,
            ))
        })
        .collect();
    files.sort();
    (files.len() == 133).then_some(files)
}

fn ingest(files: &[(String, Vec<u8>)]) -> ctrecon::volume::Volume {
    let mut up = read_upload(files, &ReadLimits::default(), unattended()).unwrap();
    let g = up.series.remove(0);
    g.assemble(&AssemblyOptions::default(), true, unattended())
        .expect("LIDC assembles")
        .volume
}

fn bench(c: &mut Criterion) {
    let Some(files) = load() else {
        eprintln!("SKIPPED: .testdata/lidc is missing (run scripts/fetch-test-data.sh)");
        return;
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .expect("thread pool");
    let mut g = c.benchmark_group("dicom");
    g.sample_size(10);
    g.bench_function("lidc_133_slices_bytes_to_hu_volume", |b| {
        b.iter(|| pool.install(|| ingest(&files)))
    });
    g.bench_function("lidc_133_slices_files_to_hu_volume", |b| {
        b.iter(|| {
            pool.install(|| {
                let files = load().expect("LIDC files");
                ingest(&files)
            })
        })
    });
    let vol = pool.install(|| ingest(&files));
    g.bench_function("lidc_volume_to_derived_ct_series", |b| {
        b.iter(|| pool.install(|| write_ct_series(&vol, &SeriesMeta::default()).expect("writes")))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
