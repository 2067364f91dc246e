//! Series assembly on slices placed by arbitrary bytes (NaN, infinite, parallel, repeated positions and
//! orientations): it must return, never panic, and never allocate by what the slices declare.
#![no_main]

use libfuzzer_sys::fuzz_target;

#[path = "contained.rs"]
mod contained;

fuzz_target!(init: contained::let_contained_panics_through(), |data: &[u8]| {
    ctrecon::series::fuzz_entry(data);
});
