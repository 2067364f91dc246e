//! The panic hook of the targets that read DICOM: libFuzzer's hook aborts on every panic, also one that
//! ctrecon catches inside a third-party parser or codec and answers as an error of the file
//! (`ctrecon::dicom::panic_is_contained`). Those are let through; every other panic still aborts, and one that
//! escapes to the target is caught by libFuzzer's wrapper and aborts there.

pub fn let_contained_panics_through() {
    let libfuzzer_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if ctrecon::dicom::panic_is_contained() {
            eprintln!("contained: {info}");
        } else {
            libfuzzer_hook(info);
        }
    }));
}
