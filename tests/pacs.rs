//! The DICOM node and DICOMweb, against Orthanc and DCMTK (one test binary, see `tests/test_binaries.rs`).

mod common;
#[path = "common/dicomweb.rs"]
mod dw;
#[path = "common/orthanc.rs"]
mod orthanc;
#[path = "common/sse.rs"]
mod sse;

mod dicomweb;
mod dicomweb_client;
mod dicomweb_wado;
mod dimse_admission;
mod dimse_node;
mod dimse_pull;
mod dimse_query;
mod dimse_rules;
mod hostile_memory;
mod hostile_uids;
mod resent_instances;
