//! `exp` and `ln` the particle filter's inner loops can vectorise.
//!
//! The filter spends most of its time in two transcendental functions per
//! particle and pixel (the PSF's Gaussian and the Poisson likelihood). The
//! C library's `exp` and `log1p` are calls the compiler cannot vectorise,
//! so these are written out: range reduction by powers of two done on the
//! bits, then a polynomial, with no branches (the loops compile to selects)
//! and no fused multiply–add (Rust never contracts `a * b + c`), so every
//! build — scalar, SSE2, AVX2, AVX-512 — returns the same bits for the same
//! input. Both agree with the C library to within a few units in the last
//! place (checked below), far below anything a weight can show.

/// ln 2 split in two: `N · LN2_HI` is exact for |N| < 2¹¹ (its low bits are
/// zero), `LN2_LO` carries the rest (fdlibm's split).
const LN2_HI: f64 = 0.693_147_180_369_123_8; // bits 0x3fe62e42fee00000
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// 1.5 · 2⁵²: adding it rounds a number of magnitude below 2⁵¹ to an integer
/// (to nearest, ties to even) and leaves that integer in the low bits.
const ROUND_SHIFT: f64 = 6_755_399_441_055_744.0;
const EXPONENT_BIAS: u64 = 1023;
const MANTISSA_BITS: u64 = (1 << 52) - 1;

/// e^x, relative error below 4·10⁻¹⁶. Arguments below −708 or above 709
/// are clamped there (e^−708 ≈ 3·10⁻³⁰⁸, the smallest normal scale the
/// reduction can build); NaN stays NaN.
#[inline(always)]
pub(super) fn exp(x: f64) -> f64 {
    let x = x.clamp(-708.0, 709.0);
    // x = n·ln 2 + r with n an integer and |r| ≤ ln 2 / 2.
    let shifted = x * std::f64::consts::LOG2_E + ROUND_SHIFT;
    let n = shifted - ROUND_SHIFT;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    // e^r by its Taylor series to r¹³/13!: the first term left out is below
    // 5·10⁻¹⁸ for |r| ≤ 0.347.
    let mut p = 1.0 / 6_227_020_800.0;
    p = p * r + 1.0 / 479_001_600.0;
    p = p * r + 1.0 / 39_916_800.0;
    p = p * r + 1.0 / 3_628_800.0;
    p = p * r + 1.0 / 362_880.0;
    p = p * r + 1.0 / 40_320.0;
    p = p * r + 1.0 / 5_040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p = p * r + 1.0;
    // 2ⁿ built from n's bits: the low bits of `shifted` hold n (two's
    // complement), and n + 1023 lies in 1…2046, a normal exponent.
    let n_bits = shifted.to_bits().wrapping_sub(ROUND_SHIFT.to_bits());
    p * f64::from_bits(n_bits.wrapping_add(EXPONENT_BIAS) << 52)
}

/// ln m for a positive, finite, normal m, absolute error below 3·10⁻¹⁶ + a
/// few units in the last place of the result.
#[inline(always)]
pub(super) fn ln(m: f64) -> f64 {
    ln_with_correction(m, 0.0)
}

/// ln(1 + u) for u > −1 (finite), accurate for small u as well: the part
/// of u that rounding 1 + u loses is added back to first order.
#[inline(always)]
pub(super) fn ln_1p(u: f64) -> f64 {
    let m = 1.0 + u;
    ln_with_correction(m, (u - (m - 1.0)) / m)
}

/// ln m + `correction`.
#[inline(always)]
fn ln_with_correction(m: f64, correction: f64) -> f64 {
    let bits = m.to_bits();
    // m = 2^e · f with f in [1, 2), then f in [√½, √2) by moving one factor
    // of 2 over, so that t below stays within ±0.172.
    let exponent_field = f64::from_bits(ROUND_SHIFT.to_bits() | (bits >> 52)) - ROUND_SHIFT;
    let f = f64::from_bits((bits & MANTISSA_BITS) | (EXPONENT_BIAS << 52));
    let large = f > std::f64::consts::SQRT_2;
    let f = if large { 0.5 * f } else { f };
    let e = exponent_field - EXPONENT_BIAS as f64 + if large { 1.0 } else { 0.0 };
    // ln f = 2 atanh t = 2 (t + t³/3 + t⁵/5 + …), t = (f − 1)/(f + 1); the
    // first term left out, 2t²³/23, is below 2·10⁻¹⁹.
    let t = (f - 1.0) / (f + 1.0);
    let t2 = t * t;
    let mut s = 1.0 / 21.0;
    s = s * t2 + 1.0 / 19.0;
    s = s * t2 + 1.0 / 17.0;
    s = s * t2 + 1.0 / 15.0;
    s = s * t2 + 1.0 / 13.0;
    s = s * t2 + 1.0 / 11.0;
    s = s * t2 + 1.0 / 9.0;
    s = s * t2 + 1.0 / 7.0;
    s = s * t2 + 1.0 / 5.0;
    s = s * t2 + 1.0 / 3.0;
    let ln_f = 2.0 * t + 2.0 * t * (t2 * s);
    e * LN2_HI + ((e * LN2_LO + correction) + ln_f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn relative_error(approx: f64, exact: f64) -> f64 {
        ((approx - exact) / exact).abs()
    }

    #[test]
    fn exp_matches_the_c_library() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut worst = 0.0f64;
        for _ in 0..200_000 {
            // The filter's arguments: PSF exponents down to −18, likelihood
            // exponents of either sign; and the whole clamped range.
            for x in [
                -20.0 + 22.0 * rng.random::<f64>(),
                -700.0 + 1400.0 * rng.random::<f64>(),
            ] {
                worst = worst.max(relative_error(exp(x), x.exp()));
            }
        }
        assert!(worst < 4e-16, "worst relative error {worst:e}");
        for x in [
            0.0,
            1.0,
            -1.0,
            1e-300,
            -1e-300,
            0.5 * std::f64::consts::LN_2,
        ] {
            assert!(relative_error(exp(x), x.exp()) < 4e-16, "{x}");
        }
        assert_eq!(exp(0.0), 1.0);
        // The high half of ln 2 has its low 21 bits zero, so n · LN2_HI is exact.
        assert_eq!(LN2_HI.to_bits(), 0x3fe6_2e42_fee0_0000);
        assert!(exp(-1000.0) > 0.0 && exp(-1000.0) < 1e-307);
        assert!(exp(f64::NAN).is_nan());
    }

    #[test]
    fn ln_and_ln_1p_match_the_c_library() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut worst = 0.0f64;
        for _ in 0..200_000 {
            // ln_1p over the filter's signal-to-background ratios, from tiny
            // to large, and ln over ratios either side of 1.
            let u = 10f64.powf(-12.0 + 15.0 * rng.random::<f64>());
            worst = worst.max(relative_error(ln_1p(u), u.ln_1p()));
            let m = 10f64.powf(-3.0 + 6.0 * rng.random::<f64>());
            let exact = m.ln();
            // Relative to |ln m| + 1: near m = 1 the absolute error counts.
            worst = worst.max((ln(m) - exact).abs() / (exact.abs() + 1.0));
        }
        assert!(worst < 5e-16, "worst error {worst:e}");
        assert_eq!(ln_1p(0.0), 0.0);
        assert_eq!(ln(1.0), 0.0);
        assert!(relative_error(ln_1p(-0.5), (-0.5f64).ln_1p()) < 4e-16);
    }
}
