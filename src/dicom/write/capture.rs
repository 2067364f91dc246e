//! Grey Secondary Capture (a windowed 2D image such as a MIP or a reformat, placed in the patient when it is
//! planar) and Encapsulated STL, in the study and frame of reference of the source.

use dicom_core::value::PrimitiveValue;
use dicom_core::{DataElement, VR};
use dicom_dictionary_std::{tags, uids};
use ndarray::ArrayView2;

use super::{Builder, Identity, grey_pixels, new_uid};
use crate::dicom::{DicomError, SeriesMeta};
use crate::volume::{ImagePlane, ScreenSides, Window};

/// Write a 2D image (e.g. a MIP, `[row][column]`) through `window` as an 8-bit Secondary Capture instance.
/// Returns the file and its SOP Instance UID; the series is new unless `series_uid` is given.
pub fn write_secondary_capture(
    img: ArrayView2<'_, f32>,
    window: Window,
    meta: &SeriesMeta,
    series_uid: Option<&str>,
) -> Result<(String, Vec<u8>), DicomError> {
    write_secondary_capture_placed(img, window, meta, series_uid, None)
}

/// How a Secondary Capture image is oriented in the patient: the screen sides (written as Patient Orientation
/// (0020,0020): the directions of the rows and of the columns, H/F for head and feet) and, for a planar
/// image, its plane (Image Position/Orientation (Patient) and Pixel Spacing, so that a viewer places it and
/// shows its orientation markers).
#[derive(Debug, Clone, PartialEq)]
pub struct ScOrientation {
    pub sides: ScreenSides,
    pub plane: Option<ImagePlane>,
}

/// [`write_secondary_capture`] with the image's orientation in the patient.
pub fn write_secondary_capture_placed(
    img: ArrayView2<'_, f32>,
    window: Window,
    meta: &SeriesMeta,
    series_uid: Option<&str>,
    orientation: Option<&ScOrientation>,
) -> Result<(String, Vec<u8>), DicomError> {
    write_secondary_capture_frame(img, window, meta, series_uid, 1, orientation)
}

/// [`write_secondary_capture_placed`] as instance `instance_number` of a series (e.g. the frames of a
/// rotating MIP, each its own instance of one series).
pub fn write_secondary_capture_frame(
    img: ArrayView2<'_, f32>,
    window: Window,
    meta: &SeriesMeta,
    series_uid: Option<&str>,
    instance_number: usize,
    orientation: Option<&ScOrientation>,
) -> Result<(String, Vec<u8>), DicomError> {
    let meta = &*crate::dicom::uid::valid_meta(meta);
    let (h, w) = img.dim();
    if h == 0 || w == 0 || h > 65535 || w > 65535 {
        return Err(DicomError::Write(format!(
            "a {h}×{w} image cannot be written"
        )));
    }
    let window =
        Window::new(window.width, window.level).map_err(|e| DicomError::Write(e.to_string()))?;
    let study_uid = meta.study_uid.clone().unwrap_or_else(new_uid);
    let series_uid = series_uid.map(str::to_string).unwrap_or_else(new_uid);
    let sop = new_uid();
    let mut b = Builder::new();
    b.identity(
        Identity {
            sop_class: uids::SECONDARY_CAPTURE_IMAGE_STORAGE,
            sop_instance: &sop,
            modality: "OT",
            study_uid: &study_uid,
            series_uid: &series_uid,
            instance_number,
        },
        meta,
    )
    .strs(
        tags::IMAGE_TYPE,
        VR::CS,
        &["DERIVED".into(), "SECONDARY".into()],
    )
    .str(tags::CONVERSION_TYPE, VR::CS, "WSD")
    .str(tags::BURNED_IN_ANNOTATION, VR::CS, "NO");
    if let Some(o) = orientation {
        let dicom = |s: &str| s.replace('S', "H").replace('I', "F");
        b.strs(
            tags::PATIENT_ORIENTATION,
            VR::CS,
            &[dicom(&o.sides.right), dicom(&o.sides.bottom)],
        );
        if let Some(p) = &o.plane {
            let [r, c] = [p.row_direction, p.column_direction];
            b.dss(tags::IMAGE_POSITION_PATIENT, &p.first_pixel_mm)
                .dss(
                    tags::IMAGE_ORIENTATION_PATIENT,
                    &[r[0], r[1], r[2], c[0], c[1], c[2]],
                )
                .dss(tags::PIXEL_SPACING, &p.pixel_mm);
            if let Some(for_uid) = &meta.frame_of_reference_uid {
                b.str(tags::FRAME_OF_REFERENCE_UID, VR::UI, for_uid);
            }
        }
    }
    grey_pixels(&mut b, h, w, 8, false);
    let pixels: Vec<u8> = img
        .iter()
        .map(|&v| (window.unit(v) * 255.0).round() as u8)
        .collect();
    b.bytes(tags::PIXEL_DATA, VR::OB, pixels);
    Ok((sop, b.finish()?))
}

/// Wrap a binary STL (millimetres, patient LPS) as an Encapsulated STL instance
/// (SOP Class 1.2.840.10008.5.1.4.1.1.104.3) in the frame of reference of `meta`.
pub fn write_encapsulated_stl(
    stl: &[u8],
    meta: &SeriesMeta,
    title: &str,
) -> Result<(String, Vec<u8>), DicomError> {
    let meta = &*crate::dicom::uid::valid_meta(meta);
    if stl.len() < 84 {
        return Err(DicomError::Write("an STL has at least 84 bytes".into()));
    }
    let study_uid = meta.study_uid.clone().unwrap_or_else(new_uid);
    let for_uid = meta.frame_of_reference_uid.clone().unwrap_or_else(new_uid);
    let sop = new_uid();
    let mut mm = Builder::new();
    mm.str(tags::CODE_VALUE, VR::SH, "mm")
        .str(tags::CODING_SCHEME_DESIGNATOR, VR::SH, "UCUM")
        .str(tags::CODE_MEANING, VR::LO, "mm");
    let mut b = Builder::new();
    b.identity(
        Identity {
            sop_class: uids::ENCAPSULATED_STL_STORAGE,
            sop_instance: &sop,
            modality: "M3D",
            study_uid: &study_uid,
            series_uid: &new_uid(),
            instance_number: 1,
        },
        meta,
    )
    .str(tags::FRAME_OF_REFERENCE_UID, VR::UI, &for_uid)
    .str(tags::POSITION_REFERENCE_INDICATOR, VR::LO, "")
    .str(tags::CONTENT_DATE, VR::DA, "")
    .str(tags::CONTENT_TIME, VR::TM, "")
    .str(tags::ACQUISITION_DATE_TIME, VR::DT, "")
    .str(tags::BURNED_IN_ANNOTATION, VR::CS, "NO")
    .str(tags::DOCUMENT_TITLE, VR::ST, title)
    .seq(tags::CONCEPT_NAME_CODE_SEQUENCE, Vec::new())
    .str(
        tags::MIME_TYPE_OF_ENCAPSULATED_DOCUMENT,
        VR::LO,
        "model/stl",
    )
    .seq(tags::MEASUREMENT_UNITS_CODE_SEQUENCE, vec![mm.0])
    .str(tags::MANUFACTURER_MODEL_NAME, VR::LO, "ctrecon")
    .str(tags::DEVICE_SERIAL_NUMBER, VR::LO, "")
    .str(tags::SOFTWARE_VERSIONS, VR::LO, env!("CARGO_PKG_VERSION"));
    b.0.put(DataElement::new(
        tags::ENCAPSULATED_DOCUMENT_LENGTH,
        VR::UL,
        PrimitiveValue::U32([stl.len() as u32].into_iter().collect()),
    ));
    b.bytes(tags::ENCAPSULATED_DOCUMENT, VR::OB, stl.to_vec());
    Ok((sop, b.finish()?))
}
