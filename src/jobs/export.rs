//! The DICOM results of a succeeded volume job, written once to `results/<job>/dicom/` for delivery:
//! planar stacks of several frames (reformats, slabs) as a derived CT series in HU, other images (a MIP,
//! the frames of a rotating MIP) as 8-bit Secondary Capture instances of one series each, renderings as
//! RGB Secondary Capture, meshes as Encapsulated STL, and on request the whole volume as a derived CT
//! series. Every file keeps the source series' study, frame of reference and patient and references the
//! source series (Referenced Series Sequence) with a Derivation Description naming the product.
//!
//! The folder is built in a scratch directory and renamed into place with its manifest, so it is complete
//! or absent. Runs on the worker pool (blocking).

use std::path::{Path, PathBuf};

use ndarray::{Array2, Array3, Ix3};
use serde::{Deserialize, Serialize};

use super::ingest::dicom_problem;
use super::model::{JobResult, JobSpec, ProductResult, SeriesRecord, VolumeUnits};
use super::views::{ProductFormat, ProductQuery, RenderContext};
use crate::dicom::{
    ScOrientation, SeriesMeta, new_uid, read_part10, write_ct_series, write_encapsulated_stl,
    write_secondary_capture_frame,
};
use crate::error_code::Problem;
use crate::storage::npy::decode_f32;
use crate::storage::{BlobStore, JobId, ResultName};
use crate::volume::{Frame, Volume, Window, WindowPreset, mu_to_hu};

/// How a job's results become DICOM.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExportOptions {
    /// Window of 8-bit Secondary Capture images; `None`: each image's 0.5–99.5 percentile range.
    pub window: Option<WindowPreset>,
    /// Also write the job's volume as a derived CT series.
    pub send_volume: bool,
    /// μ of water (1/mm), to convert reconstructions to HU.
    pub mu_water: f64,
}

/// One exported instance.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExportedFile {
    /// File name in the export folder.
    pub file: String,
    pub sop_class_uid: String,
    pub sop_instance_uid: String,
}

const MANIFEST: &str = "manifest.json";

/// The export folder of a job.
pub fn export_dir(store: &BlobStore, job: JobId) -> PathBuf {
    store.result_dir(job).join("dicom")
}

fn io_problem(e: std::io::Error) -> Problem {
    tracing::error!(error = %e, "DICOM export failed");
    Problem::internal()
}

/// The job's DICOM results, exported now unless they already were.
pub fn export_job(
    store: &BlobStore,
    job: JobId,
    spec: &JobSpec,
    result: &JobResult,
    source: Option<&SeriesRecord>,
    opts: &ExportOptions,
) -> Result<Vec<ExportedFile>, Problem> {
    let dir = export_dir(store, job);
    if let Some(files) = read_manifest(&dir) {
        return Ok(files);
    }
    let scratch = store.scratch().map_err(io_problem)?;
    let mut out = Writer {
        dir: scratch.path().to_path_buf(),
        files: Vec::new(),
    };
    let specs: Vec<serde_json::Value> = match spec {
        JobSpec::Volume(v) => v
            .products
            .iter()
            .map(|p| serde_json::to_value(p).unwrap_or_default())
            .collect(),
        JobSpec::Reconstruction(_) => Vec::new(),
    };
    let ctx = RenderContext {
        frame: result.frame(),
        units: result.units,
        mu_water: opts.mu_water,
        meta: meta(source, "derived", String::new(), 900),
        patient: source.is_some(),
    };
    for p in &result.products {
        let what = specs
            .get(p.index)
            .map(|s| s.to_string())
            .unwrap_or_else(|| p.kind.clone());
        let m = meta(
            source,
            &p.kind,
            format!("ctrecon volume job {job}, product {}: {what}", p.index),
            901 + p.index as i32,
        );
        let ext = if p.is_mesh() { "stl" } else { "npy" };
        let bytes = store
            .local(&store.result_path(
                job,
                &ResultName::Product {
                    index: p.index,
                    ext,
                },
            ))
            .and_then(std::fs::read)
            .map_err(io_problem)?;
        export_product(&mut out, &bytes, p, &m, &ctx, opts)?;
    }
    if opts.send_volume || result.products.is_empty() {
        let bytes = store
            .local(&store.result_path(job, &ResultName::Volume))
            .and_then(std::fs::read)
            .map_err(io_problem)?;
        let processed = format!("ctrecon volume job {job}: the processed volume");
        let derivation = match &result.derivation {
            Some(d) => format!("{d}; {processed}")
                .chars()
                .take(crate::jobs::model::MAX_DERIVATION_CHARS)
                .collect(),
            None => processed,
        };
        let m = meta(source, "volume", derivation, 900);
        let data = to_hu(decode_stack(&bytes)?, &ctx);
        let series = write_ct_series(
            &Volume {
                data,
                frame: result.frame(),
            },
            &m,
        )
        .map_err(|e| dicom_problem(&e))?;
        for (_, b) in series.files {
            out.add(&b)?;
        }
    }
    let manifest =
        serde_json::to_vec(&out.files).map_err(|e| io_problem(std::io::Error::other(e)))?;
    std::fs::write(out.dir.join(MANIFEST), manifest).map_err(io_problem)?;
    match std::fs::rename(scratch.path(), &dir) {
        Ok(()) => Ok(out.files),
        // Another export won the race: use its files.
        Err(_) if read_manifest(&dir).is_some() => Ok(read_manifest(&dir).unwrap_or_default()),
        Err(e) => Err(io_problem(e)),
    }
}

fn read_manifest(dir: &Path) -> Option<Vec<ExportedFile>> {
    let bytes = std::fs::read(dir.join(MANIFEST)).ok()?;
    serde_json::from_slice(&bytes).ok()
}

struct Writer {
    dir: PathBuf,
    files: Vec<ExportedFile>,
}

impl Writer {
    /// Write one Part 10 file and note its SOP class and instance.
    fn add(&mut self, bytes: &[u8]) -> Result<(), Problem> {
        let file = format!("{:05}.dcm", self.files.len() + 1);
        let path = self.dir.join(&file);
        std::fs::write(&path, bytes).map_err(io_problem)?;
        let p10 = read_part10(&path).map_err(|e| dicom_problem(&e))?;
        self.files.push(ExportedFile {
            file,
            sop_class_uid: p10.sop_class_uid,
            sop_instance_uid: p10.sop_instance_uid,
        });
        Ok(())
    }
}

/// Labels of a derived series: the source's study, frame of reference and patient, a reference to the
/// source series and how the result was derived.
fn meta(source: Option<&SeriesRecord>, what: &str, derivation: String, number: i32) -> SeriesMeta {
    let description = |s: Option<&str>| -> String {
        format!("ctrecon {what} {}", s.unwrap_or(""))
            .trim()
            .chars()
            .take(64)
            .collect()
    };
    let derivation = (!derivation.is_empty()).then_some(derivation);
    match source {
        Some(s) => SeriesMeta {
            study_uid: s.study_uid.clone(),
            frame_of_reference_uid: s.frame_of_reference_uid.clone(),
            patient_name: s.patient_name.clone(),
            patient_id: s.patient_id.clone(),
            series_description: description(s.description.as_deref()),
            series_number: number,
            source_series_uid: Some(s.series_uid.clone()),
            derivation_description: derivation,
        },
        None => SeriesMeta {
            series_description: description(None),
            series_number: number,
            derivation_description: derivation,
            ..SeriesMeta::default()
        },
    }
}

fn decode_stack(bytes: &[u8]) -> Result<Array3<f32>, Problem> {
    decode_f32(bytes)
        .ok()
        .and_then(|a| a.into_dimensionality::<Ix3>().ok())
        .ok_or_else(Problem::internal)
}

fn to_hu<D: ndarray::Dimension>(
    a: ndarray::Array<f32, D>,
    ctx: &RenderContext,
) -> ndarray::Array<f32, D> {
    match ctx.units {
        VolumeUnits::Hu => a,
        VolumeUnits::MuPerMm => a.mapv(|v| mu_to_hu(v, ctx.mu_water)),
    }
}

/// The frame of a planar stack of several frames, as a volume's frame (columns, rows, frames).
fn stack_frame(p: &ProductResult) -> Option<Frame> {
    let plane = p.plane?;
    let step = p.frame_spacing_mm.filter(|s| s.is_finite() && *s != 0.0)?;
    let [r, c] = [plane.row_direction, plane.column_direction];
    let n = [
        r[1] * c[2] - r[2] * c[1],
        r[2] * c[0] - r[0] * c[2],
        r[0] * c[1] - r[1] * c[0],
    ];
    let sign = step.signum();
    Some(Frame {
        spacing_mm: [plane.pixel_mm[1], plane.pixel_mm[0], step.abs()],
        origin_mm: plane.first_pixel_mm,
        direction: [r, c, n.map(|v| v * sign)],
    })
}

fn export_product(
    out: &mut Writer,
    bytes: &[u8],
    p: &ProductResult,
    m: &SeriesMeta,
    ctx: &RenderContext,
    opts: &ExportOptions,
) -> Result<(), Problem> {
    if p.is_mesh() {
        let title = m.series_description.clone();
        let (_, b) = write_encapsulated_stl(bytes, m, &title).map_err(|e| dicom_problem(&e))?;
        return out.add(&b);
    }
    if super::views::rgb::is_rendering(p) {
        let q = ProductQuery {
            format: Some(ProductFormat::Dicom),
            frame: None,
            preset: None,
            ww: None,
            wl: None,
            units: Default::default(),
            depth: None,
            delay_ms: None,
        };
        let ctx = RenderContext {
            meta: m.clone(),
            ..ctx.clone()
        };
        let b = super::views::rgb::render_rgb_product(bytes, p, &q, ProductFormat::Dicom, &ctx)?;
        return out.add(&b);
    }
    let stack = to_hu(decode_stack(bytes)?, ctx);
    let frames = stack.dim().0;
    if let (true, Some(frame), true) = (frames > 1, stack_frame(p), ctx.patient) {
        let series =
            write_ct_series(&Volume { data: stack, frame }, m).map_err(|e| dicom_problem(&e))?;
        for (_, b) in series.files {
            out.add(&b)?;
        }
        return Ok(());
    }
    let series_uid = new_uid();
    for k in 0..frames {
        let img: Array2<f32> = stack.index_axis(ndarray::Axis(0), k).to_owned();
        let window = match opts.window {
            Some(w) => w.window(),
            None => Window::auto(img.view()),
        };
        let placement = p
            .frame_sides(k, ctx.patient)
            .filter(|_| ctx.patient)
            .map(|sides| ScOrientation {
                sides,
                plane: p.frame_plane(k),
            });
        let (_, b) = write_secondary_capture_frame(
            img.view(),
            window,
            m,
            Some(&series_uid),
            k + 1,
            placement.as_ref(),
        )
        .map_err(|e| dicom_problem(&e))?;
        out.add(&b)?;
    }
    Ok(())
}
