//! DICOMweb (PS3.18) under `/dicom-web`: QIDO-RS (`GET …/studies`, `…/series`, `…/instances`) answered in
//! `application/dicom+json`; WADO-RS retrieval of a study, series or instance as `multipart/related;
//! type="application/dicom"` streamed from the stored files (one part per instance, each with its
//! Content-Type, Content-Length and Content-Location), `/metadata` in `application/dicom+json`, and
//! `/rendered` frames as PNG or JPEG (`quality`, `window`, `viewport`). STOW-RS is in [`super::stow`].
//!
//! `Accept` is honoured: a request that accepts none of what a route offers gets 406. On retrieval,
//! `transfer-syntax=*` sends each instance in its stored syntax; `transfer-syntax=1.2.840.10008.1.2.1`
//! (explicit VR little endian), which is also what no parameter means, re-encodes every other syntax,
//! compressed pixel data decoded. RetrieveURLs and Content-Locations (on each part, `/metadata` and
//! `/rendered`) are absolute, on the host the request named.
//!
//! `negotiation` holds `Accept` handling shared by the routes (and STOW-RS); `qido`, `retrieve`,
//! `metadata` and `rendered` one resource family each.

mod metadata;
mod negotiation;
mod qido;
mod rendered;
mod retrieve;

pub use metadata::{instance_metadata, series_metadata, study_metadata};
pub use negotiation::{DICOM_JSON, accepted, base_url, dicom_json_response};
pub use qido::{
    search_all_instances, search_all_series, search_instances, search_series, search_studies,
    search_study_instances,
};
pub use rendered::{RenderedQuery, frame_rendered, instance_rendered};
pub use retrieve::{retrieve_instance, retrieve_series, retrieve_study};
