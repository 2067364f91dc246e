//! The HTTP service, its CLI and viewer, the contract, the documentation's examples and the job and blob
//! stores (one test binary, see `tests/test_binaries.rs`).

#[path = "common/postgres.rs"]
mod cluster;
mod common;
#[path = "common/roles.rs"]
mod roles;
#[path = "common/s3.rs"]
mod s3;
#[path = "common/sse.rs"]
mod sse;

mod api_errors;
mod api_helical;
mod api_hints;
mod api_jobs;
mod api_lifecycle;
mod api_recovery;
#[path = "api_render/main.rs"]
mod api_render;
mod api_series;
mod api_viewer;
mod blob_store;
mod cli;
mod contract_schemathesis;
mod docs_console;
mod docs_examples;
mod fuzz_replay;
mod generated_client;
mod geometry_rtk;
mod hostile_http;
mod job_store;
#[path = "mesh_honest/main.rs"]
mod mesh_honest;
mod node_tables;
#[path = "orientation/main.rs"]
mod orientation;
mod scan_formats;
mod scan_nxtomo;
mod scan_simulated;
mod scan_zeiss;
mod scans_http;
mod scans_prep;
#[path = "viewer/main.rs"]
mod viewer;
