//! The DICOM reader on arbitrary bytes: it must return, never panic (but inside a contained third-party codec),
//! and never allocate by a declared length.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "contained.rs"]
mod contained;

fuzz_target!(init: contained::let_contained_panics_through(), |data: &[u8]| {
    ctrecon::dicom::fuzz_entry(data);
});
