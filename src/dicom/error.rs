//! Errors of DICOM reading and writing, each with a stable snake_case code.

use crate::series::SeriesError;

/// Why a DICOM input was refused or an output could not be written. All but `Write` are the client's input.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DicomError {
    #[error("{label}: not a DICOM Part 10 file (no DICM marker)")]
    NotDicom { label: String },
    #[error("{label}: cannot parse the DICOM data set: {reason}")]
    Parse { label: String, reason: String },
    #[error("{label}: required attribute {what} is missing or invalid")]
    MissingAttribute { label: String, what: &'static str },
    #[error("{label}: {attribute} {value_summary} is not a valid UID: {reason}")]
    InvalidUid {
        label: String,
        attribute: &'static str,
        /// The refused value, shortened and escaped (never the value itself).
        value_summary: String,
        reason: &'static str,
    },
    #[error("{label}: the file has no pixel data")]
    NoPixelData { label: String },
    #[error("{label}: unsupported {what}")]
    Unsupported { label: String, what: String },
    #[error("{label}: transfer syntax {uid} ({name}) cannot be decoded here")]
    UnsupportedTransferSyntax {
        label: String,
        uid: String,
        name: String,
    },
    #[error(
        "{label}: photometric interpretation {photometric} cannot be read as grey values{hint}"
    )]
    UnsupportedPhotometric {
        label: String,
        photometric: String,
        hint: &'static str,
    },
    #[error("{label}: image of {detail} exceeds the limit of {limit}")]
    TooLarge {
        label: String,
        detail: String,
        limit: String,
    },
    #[error("{label}: pixel data holds {got} bytes, {expected} expected")]
    PixelDataShort {
        label: String,
        expected: usize,
        got: usize,
    },
    #[error("{label}: cannot decode pixel data ({transfer_syntax}): {reason}")]
    Decode {
        label: String,
        transfer_syntax: String,
        reason: String,
    },
    #[error("series {series_uid}: modality {modality}, but a CT series is required")]
    NotCt {
        series_uid: String,
        modality: String,
    },
    #[error("invalid ZIP archive: {reason}")]
    Zip { reason: String },
    #[error("ZIP archive refused: {reason}")]
    ZipBomb { reason: String },
    #[error("the upload contains no DICOM image")]
    NoImages,
    #[error("series {series_uid}: {source}")]
    Series {
        series_uid: String,
        #[source]
        source: SeriesError,
    },
    #[error("canceled")]
    Canceled,
    #[error("cannot write DICOM: {0}")]
    Write(String),
}

impl DicomError {
    /// Stable code for the API error catalogue.
    pub fn code(&self) -> &'static str {
        match self {
            DicomError::NotDicom { .. } => "dicom_not_dicom",
            DicomError::Parse { .. } => "dicom_parse_error",
            DicomError::MissingAttribute { .. } => "dicom_missing_attribute",
            DicomError::InvalidUid { .. } => "dicom_invalid_uid",
            DicomError::NoPixelData { .. } => "dicom_no_pixel_data",
            DicomError::Unsupported { .. } => "dicom_unsupported",
            DicomError::UnsupportedTransferSyntax { .. } => "dicom_unsupported_transfer_syntax",
            DicomError::UnsupportedPhotometric { .. } => "dicom_unsupported_photometric",
            DicomError::TooLarge { .. } => "dicom_too_large",
            DicomError::PixelDataShort { .. } => "dicom_pixel_data_short",
            DicomError::Decode { .. } => "dicom_decode_error",
            DicomError::NotCt { .. } => "dicom_not_ct",
            DicomError::Zip { .. } => "zip_invalid",
            DicomError::ZipBomb { .. } => "zip_limits_exceeded",
            DicomError::NoImages => "dicom_no_images",
            DicomError::Series { source, .. } => source.code(),
            DicomError::Canceled => "canceled",
            DicomError::Write(_) => "dicom_write_failed",
        }
    }

    /// Whether the error is the client's input (a 4xx) rather than ours.
    pub fn is_client_error(&self) -> bool {
        !matches!(self, DicomError::Write(_) | DicomError::Canceled)
            && !matches!(
                self,
                DicomError::Series {
                    source: SeriesError::Canceled,
                    ..
                }
            )
    }
}
