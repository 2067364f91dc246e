//! The ZIP ingest on arbitrary bytes: unpacked member by member under bomb limits, each member decoded, the
//! series assembled. It must return, never panic, and never allocate by a declared size.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ctrecon::dicom::fuzz_zip_entry(data);
});
