//! The `.npy` reader (whole-file decode and the streamed validator) on arbitrary bytes.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    ctrecon::storage::npy::fuzz_entry(data);
});
