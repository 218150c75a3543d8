//! What the CPU can run: the vector kernels (the CNN's convolutions, the
//! likelihood detector's particle loops, Crocker–Grier's filters) pick
//! their build from it. Every build gives the same bits; only the speed
//! differs.

/// Whether the CPU has every feature named: `is_x86_feature_detected!`,
/// which detects once and keeps the answer; false off x86-64.
macro_rules! detected {
    ($($feature:tt),+) => {{
        #[cfg(target_arch = "x86_64")]
        {
            true $(&& std::arch::is_x86_feature_detected!($feature))+
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }};
}

/// Whether this CPU has AVX-512 (the `avx512f` subset).
pub(crate) fn has_avx512() -> bool {
    detected!("avx512f")
}

/// Whether this CPU has AVX2 and FMA.
pub(crate) fn has_avx2_fma() -> bool {
    detected!("avx2", "fma")
}

/// Whether this CPU has AVX2.
pub(crate) fn has_avx2() -> bool {
    detected!("avx2")
}
