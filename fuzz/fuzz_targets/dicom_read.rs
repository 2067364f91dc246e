//! The DICOM reader on arbitrary bytes: it must return, never panic, and never allocate by a declared length.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ctrecon::dicom::fuzz_entry(data);
});
