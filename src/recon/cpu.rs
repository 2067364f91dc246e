//! The CPU features the SIMD kernels need, detected once per process.
//!
//! `is_x86_feature_detected!("avx512f")` was seen reading the environment on every call with the
//! standard library used here (about 5 % of a fan-beam reconstruction that asked once per image row),
//! so the answers are kept here.
//!
//! A program may cap the kernels before their first use ([`limit`]), to measure or check the paths
//! another CPU would take: the `ctrecon` binary, the examples and the benchmarks read the cap from the
//! environment variable `CTRECON_SIMD` (`avx2`: leave AVX-512F unused; `scalar`: no vector kernels).

use std::sync::OnceLock;

/// The widest kernels the process may use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Simd {
    /// The portable kernels only.
    Scalar,
    /// AVX2 + FMA kernels, never AVX-512F.
    Avx2,
    /// Whatever the CPU has.
    Any,
}

impl Simd {
    /// Parse a cap as `CTRECON_SIMD` spells it: `scalar` (or `none`), `avx2`; anything else (and
    /// nothing) caps nothing.
    pub fn parse(value: Option<&str>) -> Self {
        match value.map(|v| v.trim().to_ascii_lowercase()).as_deref() {
            Some("scalar") | Some("none") => Simd::Scalar,
            Some("avx2") => Simd::Avx2,
            _ => Simd::Any,
        }
    }
}

static CAP: OnceLock<Simd> = OnceLock::new();

/// Cap the kernels for the rest of the process. Only the first cap counts, and only before the first
/// kernel asked for the features; returns whether this one took effect.
pub fn limit(cap: Simd) -> bool {
    CAP.set(cap).is_ok()
}

fn cap() -> Simd {
    *CAP.get_or_init(|| Simd::Any)
}

/// True when the CPU has AVX2 and FMA (and the cap allows them).
pub fn avx2_fma() -> bool {
    static FLAG: OnceLock<bool> = OnceLock::new();
    *FLAG.get_or_init(|| cap() >= Simd::Avx2 && has(Feature::Avx2) && has(Feature::Fma))
}

/// True when the CPU has AVX2, FMA, AVX-512F, BMI2 and POPCNT (and the cap allows AVX-512F).
pub fn avx512f() -> bool {
    static FLAG: OnceLock<bool> = OnceLock::new();
    *FLAG.get_or_init(|| {
        cap() >= Simd::Any
            && avx2_fma()
            && has(Feature::Avx512f)
            && has(Feature::Bmi2)
            && has(Feature::Popcnt)
    })
}

/// The x86-64 features the kernels use.
#[derive(Debug, Clone, Copy)]
enum Feature {
    Avx2,
    Fma,
    Avx512f,
    /// Bit deposit and extract (`pdep`, `pext`), which the AVX-512F loops use beside the vectors;
    /// every CPU with AVX-512F has them.
    Bmi2,
    /// The population count instruction, likewise (without it a bit count is a dozen shifts and
    /// masks).
    Popcnt,
}

/// Whether the CPU has `feature` (never off x86-64).
fn has(feature: Feature) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        match feature {
            Feature::Avx2 => std::arch::is_x86_feature_detected!("avx2"),
            Feature::Fma => std::arch::is_x86_feature_detected!("fma"),
            Feature::Avx512f => std::arch::is_x86_feature_detected!("avx512f"),
            Feature::Bmi2 => std::arch::is_x86_feature_detected!("bmi2"),
            Feature::Popcnt => std::arch::is_x86_feature_detected!("popcnt"),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = feature;
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn caps_are_parsed_case_insensitively_and_unknown_values_cap_nothing() {
        assert_eq!(Simd::parse(None), Simd::Any);
        assert_eq!(Simd::parse(Some("AVX2")), Simd::Avx2);
        assert_eq!(Simd::parse(Some(" scalar ")), Simd::Scalar);
        assert_eq!(Simd::parse(Some("none")), Simd::Scalar);
        assert_eq!(Simd::parse(Some("avx512")), Simd::Any);
        assert_eq!(Simd::parse(Some("")), Simd::Any);
    }

    #[test]
    fn the_first_question_fixes_the_cap_and_avx512f_implies_avx2() {
        let _ = avx2_fma();
        // The features were asked for, so the cap is fixed (to `Any` unless a test set it first).
        assert!(!limit(Simd::Scalar));
        assert!(!avx512f() || avx2_fma());
    }
}
