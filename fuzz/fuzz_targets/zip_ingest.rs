//! The ZIP ingest on arbitrary bytes: unpacked member by member under bomb limits, each member decoded, the
//! series assembled. It must return, never panic, and never allocate by a declared size.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "contained.rs"]
mod contained;

fuzz_target!(init: contained::let_contained_panics_through(), |data: &[u8]| {
    ctrecon::dicom::fuzz_zip_entry(data);
});
