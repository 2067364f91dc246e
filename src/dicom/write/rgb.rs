//! RGB Secondary Capture: one rendered frame as Secondary Capture Image Storage, several (a rotating sequence)
//! as Multi-frame True Color Secondary Capture, in the study and frame of reference of the source, with a
//! DerivationDescription that names what the picture shows (preset, camera).

use dicom_core::value::PrimitiveValue;
use dicom_core::{DataElement, VR};
use dicom_dictionary_std::{tags, uids};

use super::{Builder, Identity, new_uid};
use crate::dicom::{DicomError, SeriesMeta};
use crate::volume::ScreenSides;

/// Equally sized 8-bit RGB frames (`rows × columns × 3` bytes each, row by row, RGB interleaved).
pub struct RgbFrames<'a> {
    pub rows: usize,
    pub columns: usize,
    pub frames: &'a [&'a [u8]],
    /// Milliseconds between frames of a sequence.
    pub frame_time_ms: f64,
}

/// Write `img` as an RGB Secondary Capture instance (multi-frame when it has several frames). `sides` become
/// Patient Orientation (directions of the rows and columns, H/F for head and feet); `derivation` is written as
/// DerivationDescription. Returns the SOP Instance UID and the file.
pub fn write_secondary_capture_rgb(
    img: &RgbFrames<'_>,
    meta: &SeriesMeta,
    derivation: &str,
    sides: Option<&ScreenSides>,
) -> Result<(String, Vec<u8>), DicomError> {
    let meta = &*crate::dicom::uid::valid_meta(meta);
    let (h, w, n) = (img.rows, img.columns, img.frames.len());
    if h == 0 || w == 0 || h > 65535 || w > 65535 || n == 0 || n > 10_000 {
        return Err(DicomError::Write(format!(
            "{n} frame(s) of {h}×{w} cannot be written"
        )));
    }
    if img.frames.iter().any(|f| f.len() != h * w * 3) {
        return Err(DicomError::Write("an RGB frame has the wrong size".into()));
    }
    let multi = n > 1;
    let study_uid = meta.study_uid.clone().unwrap_or_else(new_uid);
    let sop = new_uid();
    let mut b = Builder::new();
    b.identity(
        Identity {
            sop_class: if multi {
                uids::MULTI_FRAME_TRUE_COLOR_SECONDARY_CAPTURE_IMAGE_STORAGE
            } else {
                uids::SECONDARY_CAPTURE_IMAGE_STORAGE
            },
            sop_instance: &sop,
            modality: "OT",
            study_uid: &study_uid,
            series_uid: &new_uid(),
            instance_number: 1,
        },
        meta,
    )
    .strs(
        tags::IMAGE_TYPE,
        VR::CS,
        &["DERIVED".into(), "SECONDARY".into()],
    )
    .str(tags::CONVERSION_TYPE, VR::CS, "WSD")
    .str(tags::BURNED_IN_ANNOTATION, VR::CS, "NO")
    .str(tags::DERIVATION_DESCRIPTION, VR::ST, derivation);
    if let Some(for_uid) = &meta.frame_of_reference_uid {
        b.str(tags::FRAME_OF_REFERENCE_UID, VR::UI, for_uid);
    }
    if let Some(s) = sides {
        let dicom = |s: &str| s.replace('S', "H").replace('I', "F");
        b.strs(
            tags::PATIENT_ORIENTATION,
            VR::CS,
            &[dicom(&s.right), dicom(&s.bottom)],
        );
    }
    b.us(tags::SAMPLES_PER_PIXEL, 3)
        .str(tags::PHOTOMETRIC_INTERPRETATION, VR::CS, "RGB")
        .us(tags::PLANAR_CONFIGURATION, 0)
        .us(tags::ROWS, h as u16)
        .us(tags::COLUMNS, w as u16)
        .us(tags::BITS_ALLOCATED, 8)
        .us(tags::BITS_STORED, 8)
        .us(tags::HIGH_BIT, 7)
        .us(tags::PIXEL_REPRESENTATION, 0);
    if multi {
        b.str(tags::NUMBER_OF_FRAMES, VR::IS, &n.to_string())
            .dss(tags::FRAME_TIME, &[img.frame_time_ms]);
        b.0.put(DataElement::new(
            tags::FRAME_INCREMENT_POINTER,
            VR::AT,
            PrimitiveValue::Tags([tags::FRAME_TIME].into_iter().collect()),
        ));
    }
    let pixels: Vec<u8> = img.frames.concat();
    b.bytes(tags::PIXEL_DATA, VR::OB, pixels);
    Ok((sop, b.finish()?))
}
