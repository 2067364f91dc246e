//! The CPU features the SIMD kernels need, detected once per process.
//!
//! `is_x86_feature_detected!("avx512f")` was seen reading the environment on every call with the
//! standard library used here (about 5 % of a fan-beam reconstruction that asked once per image row),
//! so the answers are kept here.

use std::sync::OnceLock;

/// True when the CPU has AVX2 and FMA.
pub fn avx2_fma() -> bool {
    static FLAG: OnceLock<bool> = OnceLock::new();
    *FLAG.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// True when the CPU has AVX2, FMA and AVX-512F.
pub fn avx512f() -> bool {
    static FLAG: OnceLock<bool> = OnceLock::new();
    *FLAG.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            avx2_fma() && std::arch::is_x86_feature_detected!("avx512f")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}
