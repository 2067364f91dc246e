//! Geometry JSON as a client sends it: parsed, validated and turned into views. It must return, never panic,
//! and never allocate by a declared count.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ctrecon::recon::geometry::fuzz_entry(data);
});
