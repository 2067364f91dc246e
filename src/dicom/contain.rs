//! Third-party parsers and codecs run on hostile bytes inside [`contained`]: a panic in one of them becomes an
//! error of the file being read, never a crash of the request or the job. The depth of containment is kept per
//! thread so that the fuzz targets can tell a contained panic (reported as an error of the input) from one that
//! escapes ([`panic_is_contained`]).

use std::cell::Cell;
use std::panic::{AssertUnwindSafe, catch_unwind};

thread_local! {
    static DEPTH: Cell<u32> = const { Cell::new(0) };
}

/// The call marked as contained while it runs.
struct Inside;

impl Inside {
    fn enter() -> Self {
        DEPTH.with(|d| d.set(d.get() + 1));
        Inside
    }
}

impl Drop for Inside {
    fn drop(&mut self) {
        DEPTH.with(|d| d.set(d.get().saturating_sub(1)));
    }
}

/// Run `f`; a panic inside it (a third-party decoder failing on malformed data) is `Err(())`.
pub(super) fn contained<T>(f: impl FnOnce() -> T) -> Result<T, ()> {
    let _inside = Inside::enter();
    catch_unwind(AssertUnwindSafe(f)).map_err(|_| ())
}

/// Whether the current thread is inside [`contained`]: a panic raised now is caught and answered as an error
/// of the input. The fuzz targets' panic hook lets these through and aborts on every other panic.
#[doc(hidden)]
pub fn panic_is_contained() -> bool {
    DEPTH.with(|d| d.get() > 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_inside_is_an_error_and_the_depth_returns_to_zero() {
        assert!(!panic_is_contained());
        let seen = contained(panic_is_contained);
        assert_eq!(seen, Ok(true));
        let failed: Result<(), ()> = contained(|| {
            let nested = contained(|| panic!("decoder failure"));
            assert_eq!(nested, Err(()));
            assert!(panic_is_contained());
            panic!("outer failure")
        });
        assert_eq!(failed, Err(()));
        assert!(!panic_is_contained());
    }
}
