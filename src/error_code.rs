//! The one catalogue of stable API error codes.
//!
//! Every error the service returns, as an RFC 9457 `application/problem+json` body or as the `error` of a
//! failed job, carries one of these snake_case codes. Codes never change meaning once published; the HTTP
//! status and title live here too, so that nothing else decides them. `openapi.yaml` lists every code
//! (a test checks it).

mod pointer;
pub use pointer::{field_pointer, json_pointer};

macro_rules! catalogue {
    ($($variant:ident = ($code:literal, $status:literal, $title:literal)),* $(,)?) => {
        /// A stable API error code.
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum ErrorCode {
            $($variant),*
        }

        impl ErrorCode {
            /// Every code, in catalogue order.
            pub const ALL: &'static [ErrorCode] = &[$(ErrorCode::$variant),*];

            /// The stable snake_case code.
            pub fn code(self) -> &'static str {
                match self {
                    $(ErrorCode::$variant => $code),*
                }
            }

            /// The HTTP status answered with this code.
            pub fn status(self) -> u16 {
                match self {
                    $(ErrorCode::$variant => $status),*
                }
            }

            /// A short, fixed, human-readable summary.
            pub fn title(self) -> &'static str {
                match self {
                    $(ErrorCode::$variant => $title),*
                }
            }
        }
    };
}

catalogue! {
    // The request itself.
    MalformedJson = ("malformed_json", 400, "The body is not valid JSON"),
    InvalidRequest = ("invalid_request", 422, "The request does not match its schema"),
    InvalidParameter = ("invalid_parameter", 422, "A parameter is out of range"),
    InvalidGeometry = ("invalid_geometry", 422, "The geometry cannot describe a scanner"),
    InvalidQuery = ("invalid_query", 400, "A query parameter is malformed"),
    InvalidId = ("invalid_id", 400, "The id is malformed"),
    InvalidMultipart = ("invalid_multipart", 400, "The multipart body is malformed or lacks a part"),
    UnsupportedMediaType = ("unsupported_media_type", 415, "The content type is not accepted here"),
    BodyTooLarge = ("body_too_large", 413, "The body exceeds the size limit"),
    // Uploaded arrays.
    MalformedNpy = ("malformed_npy", 400, "The .npy header is malformed"),
    UnsupportedDtype = ("unsupported_dtype", 422, "The array's dtype or layout is not supported"),
    ShapeMismatch = ("shape_mismatch", 422, "The array's shape does not match the geometry"),
    ArrayTooLarge = ("array_too_large", 413, "The declared array exceeds the size limit"),
    TruncatedUpload = ("truncated_upload", 400, "The upload ended before the declared data"),
    NonFiniteData = ("non_finite_data", 422, "The data contain NaN or infinite values"),
    // Resources and their states.
    NotFound = ("not_found", 404, "No such route"),
    MethodNotAllowed = ("method_not_allowed", 405, "The method is not allowed on this route"),
    DatasetNotFound = ("dataset_not_found", 404, "No such dataset"),
    JobNotFound = ("job_not_found", 404, "No such job"),
    JobNotSucceeded = ("job_not_succeeded", 409, "The job has no results: it has not succeeded"),
    JobAlreadyFinished = ("job_already_finished", 409, "The job has already finished"),
    JobActive = ("job_active", 409, "The job is queued or running"),
    ResultUnavailable = ("result_unavailable", 404, "The job did not produce this result"),
    JobTooLarge = ("job_too_large", 422, "The job can never fit the memory budget"),
    RangeNotSatisfiable = ("range_not_satisfiable", 416, "The requested range is outside the file"),
    ResourceInUse = ("resource_in_use", 409, "A queued or running job uses this resource"),
    FileMissing = ("file_missing", 410, "The stored file was lost; upload it again"),
    // Result views (the codes of `VolumeError`).
    SliceOutOfRange = ("slice_out_of_range", 422, "The slice index is outside the volume"),
    InvalidSlab = ("invalid_slab", 422, "The slab is empty or outside the volume"),
    InvalidWindow = ("invalid_window", 422, "The window width or level is invalid"),
    EmptyImage = ("empty_image", 422, "The image is empty"),
    EncodingFailed = ("encoding_failed", 500, "The image could not be encoded"),
    InvalidMeshOptions = ("invalid_mesh_options", 422, "The mesh options are out of range"),
    IsoOutOfRange = ("iso_out_of_range", 422, "The iso-value is above every value of the volume"),
    EmptyTransferFunction = ("empty_transfer_function", 422, "The transfer function has no control point"),
    InvalidClip = ("invalid_clip", 422, "A clip plane has a zero normal or a clip box is degenerate"),
    CameraInsideVolume = ("camera_inside_volume", 422, "An orthographic camera cannot sit inside the volume"),
    InvalidRenderSize = ("invalid_render_size", 422, "The image size is zero or above the configured limit"),
    // Scans as scanners write them (the codes of `ScanError`).
    ScanInvalid = ("scan_invalid", 422, "A scan's files are malformed or contradict each other"),
    ScanNotRecognised = ("scan_not_recognised", 422, "Nothing in the upload is a scan format ctrecon reads"),
    ScanUnsupported = ("scan_unsupported", 422, "A scan uses a feature ctrecon does not read"),
    // DICOM uploads and series (the codes of `DicomError` and `SeriesError`).
    UploadNotFound = ("upload_not_found", 404, "No such upload"),
    UploadClosed = ("upload_closed", 409, "The upload is completed: no more instances"),
    UploadChanged = ("upload_changed", 409, "Instances arrived while the upload was being completed"),
    SeriesNotFound = ("series_not_found", 404, "No such series"),
    DicomNotDicom = ("dicom_not_dicom", 422, "A file is not DICOM"),
    DicomParseError = ("dicom_parse_error", 422, "A DICOM data set cannot be parsed"),
    DicomMissingAttribute = ("dicom_missing_attribute", 422, "A required DICOM attribute is missing"),
    DicomInvalidUid = ("dicom_invalid_uid", 422, "A DICOM UID is malformed"),
    DicomNoPixelData = ("dicom_no_pixel_data", 422, "A DICOM file has no pixel data"),
    DicomUnsupported = ("dicom_unsupported", 422, "A DICOM feature is not supported"),
    DicomUnsupportedTransferSyntax = ("dicom_unsupported_transfer_syntax", 422, "A DICOM transfer syntax cannot be decoded"),
    DicomUnsupportedPhotometric = ("dicom_unsupported_photometric", 422, "A DICOM colour image cannot make a volume of grey values"),
    DicomTooLarge = ("dicom_too_large", 413, "A DICOM image exceeds the size limits"),
    DicomPixelDataShort = ("dicom_pixel_data_short", 422, "The pixel data is shorter than declared"),
    DicomDecodeError = ("dicom_decode_error", 422, "The pixel data cannot be decoded"),
    DicomNotCt = ("dicom_not_ct", 422, "A CT series is required"),
    DicomNoImages = ("dicom_no_images", 422, "The upload contains no DICOM image"),
    ZipInvalid = ("zip_invalid", 400, "The ZIP archive is invalid"),
    ZipLimitsExceeded = ("zip_limits_exceeded", 413, "The ZIP archive exceeds the unpacking limits"),
    SeriesEmpty = ("series_empty", 422, "The series has no image slices"),
    SeriesSizeMismatch = ("series_size_mismatch", 422, "Slices of the series differ in size"),
    SeriesMissingAttribute = ("series_missing_attribute", 422, "A slice lacks the attributes that place it"),
    SeriesInvalidAttribute = ("series_invalid_attribute", 422, "A slice has an invalid placement attribute"),
    SeriesOrientationMismatch = ("series_orientation_mismatch", 422, "Slices of the series differ in orientation"),
    SeriesSpacingMismatch = ("series_spacing_mismatch", 422, "Slices of the series differ in pixel spacing"),
    SeriesDuplicatePosition = ("series_duplicate_position", 422, "Two different slices share a position"),
    SeriesNotCollinear = ("series_not_collinear", 422, "Slice positions do not lie on a line"),
    SeriesMissingSlices = ("series_missing_slices", 422, "Slices are missing from the series"),
    SeriesUnevenSpacing = ("series_uneven_spacing", 422, "The slice spacing is uneven"),
    SeriesSpacingJump = ("series_spacing_jump", 422, "A gap between slices is too wide to interpolate"),
    SeriesTooLarge = ("series_too_large", 413, "The assembled volume exceeds the size limit"),
    // Processing rules, DICOM peers and deliveries.
    RuleNotFound = ("rule_not_found", 404, "No such rule"),
    RuleExists = ("rule_exists", 409, "A rule of that name exists"),
    RuleReadOnly = ("rule_read_only", 409, "The rule comes from the configuration file and cannot be changed here"),
    InvalidRule = ("invalid_rule", 422, "The rule is invalid"),
    InvalidPattern = ("invalid_pattern", 422, "A match pattern is not a valid wildcard pattern"),
    UnknownPeer = ("unknown_peer", 422, "A destination is not a configured DICOM peer"),
    PeerNotFound = ("peer_not_found", 404, "No such DICOM peer"),
    PeerUnreachable = ("peer_unreachable", 502, "The DICOM peer did not answer"),
    DimseUnavailable = ("dimse_unavailable", 503, "ctrecon cannot call DICOM peers in this process"),
    PeerNotPermitted = ("peer_not_permitted", 422, "The DICOM peer is not configured for this use"),
    DicomNodeOff = ("dicom_node_off", 409, "No DICOM node listens here: a series cannot be pulled from a PACS"),
    PullFailed = ("pull_failed", 422, "The series could not be pulled from the PACS"),
    PullSeriesNotFound = ("pull_series_not_found", 422, "The PACS holds no such series"),
    DeliveryNotFound = ("delivery_not_found", 404, "No such delivery"),
    DeliveryNotRetryable = ("delivery_not_retryable", 409, "Only a failed delivery can be retried"),
    // DICOMweb.
    DicomwebNotFound = ("dicomweb_not_found", 404, "No such study, series or instance"),
    NotAcceptable = ("not_acceptable", 406, "None of the media types or transfer syntaxes asked for is offered"),
    // Protocol.
    IdempotencyKeyReused = ("idempotency_key_reused", 422, "The Idempotency-Key was used with another request"),
    InvalidIdempotencyKey = ("invalid_idempotency_key", 400, "The Idempotency-Key header is malformed"),
    Unauthorized = ("unauthorized", 401, "A valid bearer token is required"),
    RequestTimeout = ("request_timeout", 408, "The request took too long"),
    UploadStalled = ("upload_stalled", 408, "The upload sent too little for too long"),
    // Failed jobs.
    ReconstructionFailed = ("reconstruction_failed", 422, "The reconstruction refused its input"),
    AttemptsExhausted = ("attempts_exhausted", 500, "The job was interrupted too many times"),
    // The server.
    Internal = ("internal", 500, "Internal server error"),
    Unavailable = ("unavailable", 503, "The service is not ready"),
    TooManyConnections = ("too_many_connections", 503, "Too many open connections"),
}

impl ErrorCode {
    /// The code with this snake_case name.
    pub fn from_code(code: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|c| c.code() == code)
    }

    /// The problem `type` URI of this code (RFC 9457 §3.1.1): a stable URN naming the code.
    pub fn type_uri(self) -> String {
        format!("urn:ctrecon:problem:{}", self.code())
    }
}

/// An RFC 9457 problem: a catalogue code plus a detail for this occurrence. Serialises as the
/// `application/problem+json` body (`type`, `title`, `status`, `detail`, `code`, and `errors` when the
/// problem names fields of the request). A 5xx problem's detail is replaced by its title, so server errors
/// never leak internals.
#[derive(Debug, Clone, PartialEq)]
pub struct Problem {
    pub code: ErrorCode,
    pub detail: String,
    /// The fields of the request body the problem is about (the extension member `errors`).
    pub errors: Vec<FieldError>,
}

/// One field of a refused request body: an RFC 6901 JSON Pointer into the body (`/geometry/dsd_mm`; the
/// empty pointer is the whole body) and what is wrong with it.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldError {
    pub pointer: String,
    pub detail: String,
}

impl Problem {
    pub fn new(code: ErrorCode, detail: impl Into<String>) -> Self {
        Self {
            code,
            detail: detail.into(),
            errors: Vec::new(),
        }
    }
    /// The same problem, naming the field at `pointer` (a JSON Pointer into the request body) with the
    /// problem's detail.
    pub fn at(mut self, pointer: impl Into<String>) -> Self {
        let detail = self.detail.clone();
        self.errors.push(FieldError {
            pointer: pointer.into(),
            detail,
        });
        self
    }
    /// A server error: the detail is logged by the caller, never sent.
    pub fn internal() -> Self {
        Self::new(ErrorCode::Internal, "")
    }
    /// The detail a client may see.
    pub fn public_detail(&self) -> &str {
        if self.code.status() >= 500 || self.detail.is_empty() {
            self.code.title()
        } else {
            &self.detail
        }
    }
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {}", self.code.code(), self.detail)
    }
}

impl std::error::Error for Problem {}

#[derive(serde::Serialize, serde::Deserialize)]
struct ProblemBody {
    #[serde(rename = "type")]
    type_uri: String,
    title: String,
    status: u16,
    detail: String,
    code: String,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    errors: Vec<FieldError>,
}

impl serde::Serialize for Problem {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        ProblemBody {
            type_uri: self.code.type_uri(),
            title: self.code.title().to_string(),
            status: self.code.status(),
            detail: self.public_detail().to_string(),
            code: self.code.code().to_string(),
            errors: if self.code.status() >= 500 {
                Vec::new()
            } else {
                self.errors.clone()
            },
        }
        .serialize(s)
    }
}

impl<'de> serde::Deserialize<'de> for Problem {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let body = ProblemBody::deserialize(d)?;
        let code = ErrorCode::from_code(&body.code)
            .ok_or_else(|| serde::de::Error::custom(format!("unknown code {}", body.code)))?;
        Ok(Problem {
            errors: body.errors,
            ..Problem::new(code, body.detail)
        })
    }
}

// Each layer's error enum to its catalogue code: the one table, matched exhaustively (a new variant does not
// compile until it has a code; no lookup by string).

impl From<&crate::volume::VolumeError> for ErrorCode {
    fn from(e: &crate::volume::VolumeError) -> Self {
        use crate::volume::VolumeError as E;
        match e {
            E::IndexOutOfRange { .. } => ErrorCode::SliceOutOfRange,
            E::BadSlab { .. } => ErrorCode::InvalidSlab,
            E::BadWindow { .. } => ErrorCode::InvalidWindow,
            E::Empty => ErrorCode::EmptyImage,
            E::InvalidParameter { .. } => ErrorCode::InvalidParameter,
            E::Encode(_) => ErrorCode::EncodingFailed,
        }
    }
}

impl From<&crate::series::SeriesError> for ErrorCode {
    /// A canceled assembly is no client fault: `internal` (the job or request reports the cancel itself).
    fn from(e: &crate::series::SeriesError) -> Self {
        use crate::series::SeriesError as E;
        match e {
            E::Empty => ErrorCode::SeriesEmpty,
            E::SizeMismatch { .. } => ErrorCode::SeriesSizeMismatch,
            E::MissingAttribute { .. } => ErrorCode::SeriesMissingAttribute,
            E::InvalidAttribute { .. } => ErrorCode::SeriesInvalidAttribute,
            E::OrientationMismatch { .. } => ErrorCode::SeriesOrientationMismatch,
            E::SpacingMismatch { .. } => ErrorCode::SeriesSpacingMismatch,
            E::DuplicatePosition { .. } => ErrorCode::SeriesDuplicatePosition,
            E::NotCollinear { .. } => ErrorCode::SeriesNotCollinear,
            E::MissingSlices { .. } => ErrorCode::SeriesMissingSlices,
            E::UnevenSpacing { .. } => ErrorCode::SeriesUnevenSpacing,
            E::SpacingJump { .. } => ErrorCode::SeriesSpacingJump,
            E::TooLarge { .. } | E::OverBudget { .. } => ErrorCode::SeriesTooLarge,
            E::Canceled => ErrorCode::Internal,
        }
    }
}

impl From<&crate::dicom::DicomError> for ErrorCode {
    /// Writing failures and cancels are ours, not the client's: `internal`.
    fn from(e: &crate::dicom::DicomError) -> Self {
        use crate::dicom::DicomError as E;
        match e {
            E::NotDicom { .. } => ErrorCode::DicomNotDicom,
            E::Parse { .. } => ErrorCode::DicomParseError,
            E::MissingAttribute { .. } => ErrorCode::DicomMissingAttribute,
            E::InvalidUid { .. } => ErrorCode::DicomInvalidUid,
            E::NoPixelData { .. } => ErrorCode::DicomNoPixelData,
            E::Unsupported { .. } => ErrorCode::DicomUnsupported,
            E::UnsupportedTransferSyntax { .. } => ErrorCode::DicomUnsupportedTransferSyntax,
            E::UnsupportedPhotometric { .. } => ErrorCode::DicomUnsupportedPhotometric,
            E::TooLarge { .. } => ErrorCode::DicomTooLarge,
            E::PixelDataShort { .. } => ErrorCode::DicomPixelDataShort,
            E::Decode { .. } => ErrorCode::DicomDecodeError,
            E::NotCt { .. } => ErrorCode::DicomNotCt,
            E::Zip { .. } => ErrorCode::ZipInvalid,
            E::ZipBomb { .. } => ErrorCode::ZipLimitsExceeded,
            E::NoImages => ErrorCode::DicomNoImages,
            E::Series { source, .. } => source.into(),
            E::Canceled | E::Write(_) => ErrorCode::Internal,
        }
    }
}

impl From<&crate::mesh::MeshError> for ErrorCode {
    fn from(e: &crate::mesh::MeshError) -> Self {
        use crate::mesh::MeshError as E;
        match e {
            E::InvalidOption { .. } => ErrorCode::InvalidMeshOptions,
            E::Clip(_) => ErrorCode::InvalidClip,
        }
    }
}

impl From<&crate::render::RenderError> for ErrorCode {
    /// A degenerate volume is the request's (its source volume), not ours: `invalid_parameter`.
    fn from(e: &crate::render::RenderError) -> Self {
        use crate::render::RenderError as E;
        match e {
            E::EmptyTransferFunction => ErrorCode::EmptyTransferFunction,
            E::ZeroClipNormal(_) | E::BadClip(_) => ErrorCode::InvalidClip,
            E::CameraInsideVolume => ErrorCode::CameraInsideVolume,
            E::BadSize { .. } => ErrorCode::InvalidRenderSize,
            E::InvalidParameter { .. } | E::BadVolume => ErrorCode::InvalidParameter,
            E::Encode(_) => ErrorCode::EncodingFailed,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_paths_become_json_pointers_with_escapes() {
        assert_eq!(field_pointer("/geometry", "dso_mm"), "/geometry/dso_mm");
        assert_eq!(
            field_pointer("/geometry", "detector.nu"),
            "/geometry/detector/nu"
        );
        assert_eq!(field_pointer("/grid", "centre_mm[1]"), "/grid/centre_mm/1");
        assert_eq!(
            field_pointer("/geometry", "angles.degrees[12]"),
            "/geometry/angles/degrees/12"
        );
        assert_eq!(field_pointer("", ""), "");
        assert_eq!(json_pointer("/rules", ["a/b", "c~d"]), "/rules/a~1b/c~0d");
    }

    #[test]
    fn field_errors_are_serialised_for_client_errors_only() {
        let p = Problem::new(ErrorCode::InvalidGeometry, "bad").at("/geometry/dsd_mm");
        let v = serde_json::to_value(&p).expect("json");
        assert_eq!(
            v["errors"],
            serde_json::json!([{"pointer": "/geometry/dsd_mm", "detail": "bad"}])
        );
        let back: Problem = serde_json::from_value(v).expect("problem");
        assert_eq!(back, p);
        let plain =
            serde_json::to_value(Problem::new(ErrorCode::InvalidGeometry, "bad")).expect("json");
        assert!(plain.get("errors").is_none());
        let internal = serde_json::to_value(Problem::internal().at("/x")).expect("json");
        assert!(internal.get("errors").is_none());
    }

    #[test]
    fn codes_are_unique_snake_case_and_their_statuses_are_errors() {
        let mut seen = std::collections::HashSet::new();
        for c in ErrorCode::ALL {
            assert!(seen.insert(c.code()), "duplicate code {}", c.code());
            assert!(
                c.code()
                    .chars()
                    .all(|ch| ch.is_ascii_lowercase() || ch == '_'),
                "{}",
                c.code()
            );
            assert!((400..600).contains(&c.status()), "{}", c.code());
        }
    }

    #[test]
    fn layer_errors_keep_the_codes_they_name_themselves() {
        use crate::dicom::DicomError;
        use crate::series::SeriesError;
        use crate::volume::VolumeError;
        let v = VolumeError::BadWindow {
            width: 0.0,
            level: 0.0,
        };
        assert_eq!(ErrorCode::from(&v).code(), v.code());
        let s = SeriesError::TooLarge {
            voxels: 9,
            limit: 1,
        };
        assert_eq!(ErrorCode::from(&s).code(), s.code());
        let d = DicomError::Series {
            series_uid: "1.2".into(),
            source: s,
        };
        assert_eq!(ErrorCode::from(&d), ErrorCode::SeriesTooLarge);
        let z = DicomError::ZipBomb { reason: "x".into() };
        assert_eq!(ErrorCode::from(&z).code(), z.code());
    }

    #[test]
    fn mesh_and_render_errors_map_to_the_codes_they_name_themselves() {
        use crate::mesh::MeshError;
        use crate::render::RenderError;
        for e in [
            MeshError::InvalidOption {
                name: "iso",
                reason: "x".into(),
            },
            MeshError::Clip("x".into()),
        ] {
            assert_eq!(ErrorCode::from(&e).code(), e.code(), "{e}");
        }
        for e in [
            RenderError::EmptyTransferFunction,
            RenderError::ZeroClipNormal(0),
            RenderError::BadClip("x".into()),
            RenderError::CameraInsideVolume,
            RenderError::BadSize {
                width: 0,
                height: 1,
                max: 2,
            },
            RenderError::InvalidParameter {
                name: "x",
                reason: "y".into(),
            },
            RenderError::BadVolume,
            RenderError::Encode("x".into()),
        ] {
            assert_eq!(ErrorCode::from(&e).code(), e.code(), "{e}");
        }
    }
}
