//! Scale-out: workers, PostgreSQL, S3, several hosts (one test binary, see `tests/test_binaries.rs`).

#[path = "common/postgres.rs"]
mod cluster;
mod common;
#[path = "common/roles.rs"]
mod roles;
#[path = "common/s3.rs"]
mod s3;
#[path = "common/sse.rs"]
mod sse;

mod multi_host;
mod s3_service;
mod scale_out;
mod workers;
