//! Writers: a volume as a derived CT series or one Enhanced CT file, a 2D image as Secondary Capture, an STL as
//! Encapsulated STL, and a ZIP of named files.

use std::io::{Cursor, Write};

use dicom_core::value::{DataSetSequence, PrimitiveValue};
use dicom_core::{DataElement, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use rayon::prelude::*;

use super::error::DicomError;
use crate::volume::{ImagePlane, Volume};

mod capture;
mod rgb;
pub use capture::{
    ScOrientation, write_encapsulated_stl, write_secondary_capture, write_secondary_capture_frame,
    write_secondary_capture_placed,
};
pub use rgb::{RgbFrames, write_secondary_capture_rgb};

/// Identity and labels of a derived series.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SeriesMeta {
    /// Kept when the source study is known; a new one otherwise.
    pub study_uid: Option<String>,
    /// Kept when the source frame of reference is known; a new one otherwise.
    pub frame_of_reference_uid: Option<String>,
    pub patient_name: Option<String>,
    pub patient_id: Option<String>,
    pub series_description: String,
    pub series_number: i32,
    /// The series the result derives from: written as Referenced Series Sequence (0008,1115) with its
    /// study.
    pub source_series_uid: Option<String>,
    /// How the result was made, written as Derivation Description (0008,2111).
    pub derivation_description: Option<String>,
}

/// A written series: its UIDs, the rescale used and the files (`IM00001.dcm`, …).
#[derive(Debug, Clone, PartialEq)]
pub struct DerivedSeries {
    pub study_uid: String,
    pub series_uid: String,
    pub frame_of_reference_uid: String,
    pub rescale_slope: f64,
    pub rescale_intercept: f64,
    pub files: Vec<(String, Vec<u8>)>,
}

/// A new UID under the UUID root `2.25` (ITU-T X.667).
pub fn new_uid() -> String {
    format!("2.25.{}", uuid::Uuid::new_v4().as_u128())
}

/// A Decimal String of at most 16 characters, as close to `v` as that allows.
fn ds(v: f64) -> String {
    if !v.is_finite() {
        return "0".into();
    }
    let plain = format!("{v}");
    if plain.len() <= 16 {
        return plain;
    }
    for p in (0..=12).rev() {
        let s = format!("{v:.p$}");
        if s.len() <= 16 && s.parse::<f64>().is_ok_and(|x| x != 0.0 || v == 0.0) {
            return s;
        }
    }
    for p in (0..=10).rev() {
        let s = format!("{v:.p$e}");
        if s.len() <= 16 {
            return s;
        }
    }
    "0".into()
}

fn ds_value(v: f64) -> f64 {
    ds(v).parse().unwrap_or(0.0)
}

struct Builder(InMemDicomObject);

/// UIDs, modality and number of one instance.
struct Identity<'a> {
    sop_class: &'a str,
    sop_instance: &'a str,
    modality: &'a str,
    study_uid: &'a str,
    series_uid: &'a str,
    instance_number: usize,
}

impl Builder {
    fn new() -> Self {
        Self(InMemDicomObject::new_empty())
    }
    fn str(&mut self, tag: Tag, vr: VR, v: &str) -> &mut Self {
        self.0
            .put(DataElement::new(tag, vr, PrimitiveValue::from(v)));
        self
    }
    fn strs(&mut self, tag: Tag, vr: VR, v: &[String]) -> &mut Self {
        self.0.put(DataElement::new(
            tag,
            vr,
            PrimitiveValue::Strs(v.iter().cloned().collect()),
        ));
        self
    }
    fn dss(&mut self, tag: Tag, v: &[f64]) -> &mut Self {
        let s: Vec<String> = v.iter().map(|x| ds(*x)).collect();
        self.strs(tag, VR::DS, &s)
    }
    fn us(&mut self, tag: Tag, v: u16) -> &mut Self {
        self.0.put(DataElement::new(
            tag,
            VR::US,
            PrimitiveValue::U16([v].into_iter().collect()),
        ));
        self
    }
    fn seq(&mut self, tag: Tag, items: Vec<InMemDicomObject>) -> &mut Self {
        self.0
            .put(DataElement::new(tag, VR::SQ, DataSetSequence::from(items)));
        self
    }
    fn bytes(&mut self, tag: Tag, vr: VR, mut v: Vec<u8>) -> &mut Self {
        if v.len() % 2 == 1 {
            v.push(0);
        }
        self.0
            .put(DataElement::new(tag, vr, PrimitiveValue::U8(v.into())));
        self
    }
    /// Patient, study, series and instance identity shared by all writers.
    fn identity(&mut self, id: Identity<'_>, meta: &SeriesMeta) -> &mut Self {
        let Identity {
            sop_class,
            sop_instance,
            modality,
            study_uid,
            series_uid,
            instance_number,
        } = id;
        self.str(tags::SPECIFIC_CHARACTER_SET, VR::CS, "ISO_IR 192")
            .str(tags::SOP_CLASS_UID, VR::UI, sop_class)
            .str(tags::SOP_INSTANCE_UID, VR::UI, sop_instance)
            .str(tags::STUDY_DATE, VR::DA, "")
            .str(tags::STUDY_TIME, VR::TM, "")
            .str(tags::ACCESSION_NUMBER, VR::SH, "")
            .str(tags::MODALITY, VR::CS, modality)
            .str(tags::MANUFACTURER, VR::LO, "ctrecon")
            .str(tags::REFERRING_PHYSICIAN_NAME, VR::PN, "")
            .str(tags::SERIES_DESCRIPTION, VR::LO, &meta.series_description)
            .str(
                tags::PATIENT_NAME,
                VR::PN,
                meta.patient_name.as_deref().unwrap_or(""),
            )
            .str(
                tags::PATIENT_ID,
                VR::LO,
                meta.patient_id.as_deref().unwrap_or(""),
            )
            .str(tags::PATIENT_BIRTH_DATE, VR::DA, "")
            .str(tags::PATIENT_SEX, VR::CS, "")
            .str(tags::STUDY_INSTANCE_UID, VR::UI, study_uid)
            .str(tags::SERIES_INSTANCE_UID, VR::UI, series_uid)
            .str(tags::STUDY_ID, VR::SH, "")
            .str(tags::SERIES_NUMBER, VR::IS, &meta.series_number.to_string())
            .str(tags::INSTANCE_NUMBER, VR::IS, &instance_number.to_string());
        self.provenance(meta)
    }
    /// Where the result comes from: the source series (Referenced Series Sequence, with the study in
    /// each item), the source frame of reference, and how it was derived.
    fn provenance(&mut self, meta: &SeriesMeta) -> &mut Self {
        if let Some(series) = &meta.source_series_uid {
            let mut item = Builder::new();
            item.str(tags::SERIES_INSTANCE_UID, VR::UI, series);
            if let Some(study) = &meta.study_uid {
                item.str(tags::STUDY_INSTANCE_UID, VR::UI, study);
            }
            self.seq(tags::REFERENCED_SERIES_SEQUENCE, vec![item.0]);
        }
        if let Some(for_uid) = &meta.frame_of_reference_uid {
            self.str(tags::FRAME_OF_REFERENCE_UID, VR::UI, for_uid);
        }
        if let Some(d) = &meta.derivation_description {
            let d: String = d.chars().take(1024).collect();
            self.str(tags::DERIVATION_DESCRIPTION, VR::ST, &d);
        }
        self
    }
    fn finish(self) -> Result<Vec<u8>, DicomError> {
        let werr = |e: &dyn std::fmt::Display| DicomError::Write(e.to_string());
        let file = self
            .0
            .with_meta(FileMetaTableBuilder::new().transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN))
            .map_err(|e| werr(&e))?;
        let mut out = Vec::new();
        file.write_all(&mut out).map_err(|e| werr(&e))?;
        Ok(out)
    }
}

/// Rescale (slope, intercept) mapping the finite range of `vol` into int16, integer-preserving when possible.
fn quantisation(vol: &Volume) -> Result<(f64, f64), DicomError> {
    let (mut lo, mut hi, mut integral) = (f64::INFINITY, f64::NEG_INFINITY, true);
    for &v in vol.data.iter().filter(|v| v.is_finite()) {
        let v = v as f64;
        lo = lo.min(v);
        hi = hi.max(v);
        integral &= v.fract() == 0.0;
    }
    if !lo.is_finite() {
        return Err(DicomError::Write("the volume has no finite value".into()));
    }
    if integral && lo >= -32768.0 && hi <= 32767.0 {
        return Ok((1.0, 0.0));
    }
    let slope = ds_value(((hi - lo) / 65000.0).max(1e-6) * 1.0001);
    let intercept = ds_value((hi + lo) / 2.0);
    Ok((slope, intercept))
}

fn stored(v: f32, slope: f64, intercept: f64) -> i16 {
    let v = if v.is_finite() { v as f64 } else { intercept };
    ((v - intercept) / slope).round().clamp(-32768.0, 32767.0) as i16
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

/// Spacing of the slice planes along their normal (the slice axis may be tilted).
fn normal_spacing(vol: &Volume) -> f64 {
    let [r, c, s] = vol.frame.direction;
    let n = unit([
        r[1] * c[2] - r[2] * c[1],
        r[2] * c[0] - r[0] * c[2],
        r[0] * c[1] - r[1] * c[0],
    ]);
    (vol.frame.spacing_mm[2] * (s[0] * n[0] + s[1] * n[1] + s[2] * n[2])).abs()
}

fn check_volume(vol: &Volume) -> Result<(usize, usize, usize), DicomError> {
    let (nz, ny, nx) = vol.data.dim();
    if nz == 0 || ny == 0 || nx == 0 || ny > 65535 || nx > 65535 {
        return Err(DicomError::Write(format!(
            "a {nz}×{ny}×{nx} volume cannot be written as DICOM images"
        )));
    }
    Ok((nz, ny, nx))
}

/// Image attributes common to classic and enhanced CT.
fn image_pixel(b: &mut Builder, ny: usize, nx: usize) {
    grey_pixels(b, ny, nx, 16, true);
}

/// The Image Pixel module of a MONOCHROME2 image of `bits` bits, signed or not.
fn grey_pixels(b: &mut Builder, ny: usize, nx: usize, bits: u16, signed: bool) {
    b.us(tags::SAMPLES_PER_PIXEL, 1)
        .str(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, "MONOCHROME2")
        .us(tags::ROWS, ny as u16)
        .us(tags::COLUMNS, nx as u16)
        .us(tags::BITS_ALLOCATED, bits)
        .us(tags::BITS_STORED, bits)
        .us(tags::HIGH_BIT, bits - 1)
        .us(tags::PIXEL_REPRESENTATION, signed as u16);
}

/// Slice `k` as little-endian int16 stored values, in one allocation of its exact size.
fn plane_bytes(vol: &Volume, k: usize, slope: f64, intercept: f64) -> Vec<u8> {
    let plane = vol.data.index_axis(ndarray::Axis(0), k);
    let mut out = vec![0u8; plane.len() * 2];
    for (o, &v) in out.chunks_exact_mut(2).zip(plane.iter()) {
        o.copy_from_slice(&stored(v, slope, intercept).to_le_bytes());
    }
    out
}

/// Write a volume in HU (`[z][y][x]`, convert μ first with `volume::mu_to_hu`) as a derived CT series: one
/// file per slice, new Series/SOP Instance UIDs, study and frame of reference kept when `meta` has them,
/// position/orientation/spacing from the volume's frame, int16 with a rescale to HU. Slices are encoded in
/// parallel.
pub fn write_ct_series(vol: &Volume, meta: &SeriesMeta) -> Result<DerivedSeries, DicomError> {
    let meta = &*super::uid::valid_meta(meta);
    let (nz, ny, nx) = check_volume(vol)?;
    let (slope, intercept) = quantisation(vol)?;
    let study_uid = meta.study_uid.clone().unwrap_or_else(new_uid);
    let series_uid = new_uid();
    let for_uid = meta.frame_of_reference_uid.clone().unwrap_or_else(new_uid);
    let f = vol.frame;
    let orientation = [
        f.direction[0][0],
        f.direction[0][1],
        f.direction[0][2],
        f.direction[1][0],
        f.direction[1][1],
        f.direction[1][2],
    ];
    // Patient Orientation (General Image; optional where the plane is given, but what viewers without
    // plane geometry label the image by): the directions of the rows and of the columns.
    let patient_orientation = ImagePlane {
        first_pixel_mm: f.origin_mm,
        row_direction: f.direction[0],
        column_direction: f.direction[1],
        pixel_mm: [f.spacing_mm[1], f.spacing_mm[0]],
    }
    .patient_orientation();
    let thickness = normal_spacing(vol);
    let files = (0..nz)
        .into_par_iter()
        .map(|k| {
            let mut b = Builder::new();
            b.identity(
                Identity {
                    sop_class: uids::CT_IMAGE_STORAGE,
                    sop_instance: &new_uid(),
                    modality: "CT",
                    study_uid: &study_uid,
                    series_uid: &series_uid,
                    instance_number: k + 1,
                },
                meta,
            )
            .strs(
                tags::IMAGE_TYPE,
                VR::CS,
                &["DERIVED".into(), "SECONDARY".into(), "AXIAL".into()],
            )
            .str(tags::FRAME_OF_REFERENCE_UID, VR::UI, &for_uid)
            .str(tags::POSITION_REFERENCE_INDICATOR, VR::LO, "")
            .str(tags::KVP, VR::DS, "")
            .str(tags::ACQUISITION_NUMBER, VR::IS, "")
            .dss(
                tags::IMAGE_POSITION_PATIENT,
                &f.position(k as f64, 0.0, 0.0),
            )
            .dss(tags::IMAGE_ORIENTATION_PATIENT, &orientation)
            .strs(tags::PATIENT_ORIENTATION, VR::CS, &patient_orientation)
            .dss(tags::SLICE_THICKNESS, &[thickness])
            .dss(tags::SPACING_BETWEEN_SLICES, &[thickness])
            .dss(tags::PIXEL_SPACING, &[f.spacing_mm[1], f.spacing_mm[0]])
            .dss(tags::RESCALE_INTERCEPT, &[intercept])
            .dss(tags::RESCALE_SLOPE, &[slope])
            .str(tags::RESCALE_TYPE, VR::LO, "HU")
            .dss(tags::WINDOW_CENTER, &[40.0])
            .dss(tags::WINDOW_WIDTH, &[400.0]);
            image_pixel(&mut b, ny, nx);
            b.bytes(
                tags::PIXEL_DATA,
                VR::OW,
                plane_bytes(vol, k, slope, intercept),
            );
            Ok((format!("IM{:05}.dcm", k + 1), b.finish()?))
        })
        .collect::<Result<Vec<_>, DicomError>>()?;
    Ok(DerivedSeries {
        study_uid,
        series_uid,
        frame_of_reference_uid: for_uid,
        rescale_slope: slope,
        rescale_intercept: intercept,
        files,
    })
}

/// Write a volume in HU as one multi-frame Enhanced CT file (per-frame plane positions, shared pixel
/// measures, orientation and rescale).
pub fn write_enhanced_ct(vol: &Volume, meta: &SeriesMeta) -> Result<DerivedSeries, DicomError> {
    let meta = &*super::uid::valid_meta(meta);
    let (nz, ny, nx) = check_volume(vol)?;
    let (slope, intercept) = quantisation(vol)?;
    let study_uid = meta.study_uid.clone().unwrap_or_else(new_uid);
    let series_uid = new_uid();
    let for_uid = meta.frame_of_reference_uid.clone().unwrap_or_else(new_uid);
    let f = vol.frame;
    let item = |build: &dyn Fn(&mut Builder)| {
        let mut b = Builder::new();
        build(&mut b);
        b.0
    };
    let thickness = normal_spacing(vol);
    let shared = item(&|b| {
        let measures = item(&|m| {
            m.dss(tags::PIXEL_SPACING, &[f.spacing_mm[1], f.spacing_mm[0]])
                .dss(tags::SLICE_THICKNESS, &[thickness]);
        });
        let orient = item(&|o| {
            o.dss(
                tags::IMAGE_ORIENTATION_PATIENT,
                &[
                    f.direction[0][0],
                    f.direction[0][1],
                    f.direction[0][2],
                    f.direction[1][0],
                    f.direction[1][1],
                    f.direction[1][2],
                ],
            );
        });
        let transform = item(&|t| {
            t.dss(tags::RESCALE_INTERCEPT, &[intercept])
                .dss(tags::RESCALE_SLOPE, &[slope])
                .str(tags::RESCALE_TYPE, VR::LO, "HU");
        });
        b.seq(tags::PIXEL_MEASURES_SEQUENCE, vec![measures])
            .seq(tags::PLANE_ORIENTATION_SEQUENCE, vec![orient])
            .seq(tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE, vec![transform]);
    });
    let per_frame: Vec<InMemDicomObject> = (0..nz)
        .map(|k| {
            item(&|b| {
                let pos = item(&|p| {
                    p.dss(
                        tags::IMAGE_POSITION_PATIENT,
                        &f.position(k as f64, 0.0, 0.0),
                    );
                });
                let content = item(&|c| {
                    c.0.put(DataElement::new(
                        tags::IN_STACK_POSITION_NUMBER,
                        VR::UL,
                        PrimitiveValue::U32([(k + 1) as u32].into_iter().collect()),
                    ));
                });
                b.seq(tags::PLANE_POSITION_SEQUENCE, vec![pos])
                    .seq(tags::FRAME_CONTENT_SEQUENCE, vec![content]);
            })
        })
        .collect();
    let mut b = Builder::new();
    b.identity(
        Identity {
            sop_class: uids::ENHANCED_CT_IMAGE_STORAGE,
            sop_instance: &new_uid(),
            modality: "CT",
            study_uid: &study_uid,
            series_uid: &series_uid,
            instance_number: 1,
        },
        meta,
    )
    .strs(
        tags::IMAGE_TYPE,
        VR::CS,
        &[
            "DERIVED".into(),
            "SECONDARY".into(),
            "AXIAL".into(),
            "NONE".into(),
        ],
    )
    .str(tags::FRAME_OF_REFERENCE_UID, VR::UI, &for_uid)
    .str(tags::NUMBER_OF_FRAMES, VR::IS, &nz.to_string())
    .seq(tags::SHARED_FUNCTIONAL_GROUPS_SEQUENCE, vec![shared])
    .seq(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE, per_frame);
    image_pixel(&mut b, ny, nx);
    let mut pixels: Vec<u8> = Vec::with_capacity(nz * ny * nx * 2);
    for k in 0..nz {
        pixels.extend_from_slice(&plane_bytes(vol, k, slope, intercept));
    }
    b.bytes(tags::PIXEL_DATA, VR::OW, pixels);
    Ok(DerivedSeries {
        study_uid,
        series_uid,
        frame_of_reference_uid: for_uid,
        rescale_slope: slope,
        rescale_intercept: intercept,
        files: vec![("ENHANCED.dcm".into(), b.finish()?)],
    })
}

/// A deflated ZIP of named files (names are ours, e.g. from [`write_ct_series`]).
pub fn write_zip(files: &[(String, Vec<u8>)]) -> Result<Vec<u8>, DicomError> {
    let werr = |e: &dyn std::fmt::Display| DicomError::Write(e.to_string());
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(files.iter().any(|(_, b)| b.len() as u64 >= u32::MAX as u64));
    for (name, bytes) in files {
        zip.start_file(name.as_str(), opts).map_err(|e| werr(&e))?;
        zip.write_all(bytes).map_err(|e| werr(&e))?;
    }
    Ok(zip.finish().map_err(|e| werr(&e))?.into_inner())
}
