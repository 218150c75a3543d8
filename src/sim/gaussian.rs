//! Standard normal variates from one 32-bit draw each: the ziggurat method
//! of Marsaglia & Tsang, "The Ziggurat Method for Generating Random
//! Variables", J. Stat. Softw. 5(8), 2000, with 128 layers.
//!
//! Why not `rand_distr::StandardNormal`: the random walk draws three normals
//! per PSF sample (1,800 per paper frame), the simulator's largest cost.
//! rand_distr's ziggurat spends a 64-bit draw and f64 arithmetic on each
//! even when an f32 is asked for. Brownian steps need no more than single
//! precision, so this one takes 32 bits per variate: the low 7 bits pick
//! the layer and the upper 25 (signed) the abscissa, which avoids the
//! layer/abscissa correlation of the original code (Doornik, "An Improved
//! Ziggurat Method", 2005). Abscissae are resolved to 2^−24 of the layer
//! width, finer than an f32 mantissa.

use std::sync::OnceLock;

use rand::{Rng, RngExt};

const LAYERS: usize = 128;
/// Start of the tail, and the area of each layer, for 128 layers.
const TAIL_START: f64 = 3.442_619_855_899;
const LAYER_AREA: f64 = 9.912_563_035_262_17e-3;
/// Scale of the signed 25-bit abscissa: |hz| < 2^24.
const SCALE: f64 = (1u32 << 24) as f64;

struct Tables {
    /// Acceptance thresholds on |hz| for the fast path.
    k: [u32; LAYERS],
    /// Abscissa per unit of hz.
    w: [f64; LAYERS],
    /// Density at each layer's edge.
    f: [f64; LAYERS],
}

fn tables() -> &'static Tables {
    static TABLES: OnceLock<Tables> = OnceLock::new();
    TABLES.get_or_init(|| {
        let mut k = [0u32; LAYERS];
        let mut w = [0.0; LAYERS];
        let mut f = [0.0; LAYERS];
        let mut edge = TAIL_START;
        let mut previous = edge;
        let q = LAYER_AREA / (-0.5 * edge * edge).exp();
        k[0] = ((edge / q) * SCALE) as u32;
        k[1] = 0;
        w[0] = q / SCALE;
        w[LAYERS - 1] = edge / SCALE;
        f[0] = 1.0;
        f[LAYERS - 1] = (-0.5 * edge * edge).exp();
        for i in (1..LAYERS - 1).rev() {
            edge = (-2.0 * (LAYER_AREA / edge + (-0.5 * edge * edge).exp()).ln()).sqrt();
            k[i + 1] = ((edge / previous) * SCALE) as u32;
            previous = edge;
            f[i] = (-0.5 * edge * edge).exp();
            w[i] = edge / SCALE;
        }
        Tables { k, w, f }
    })
}

/// A standard normal variate (mean 0, variance 1) from the ziggurat (the
/// simulator draws through [`standard_normal_from_bits`]; this serves the
/// tests).
#[cfg(test)]
pub(crate) fn standard_normal<R: Rng + ?Sized>(rng: &mut R) -> f64 {
    let bits = rng.next_u32();
    standard_normal_from_bits(bits, rng)
}

/// A standard normal variate whose first 32 random bits were drawn in bulk
/// beforehand (filling a buffer is several times cheaper per word than
/// single draws). In the rare rejections (about 1.5 %) further bits come
/// from `rng`.
#[inline]
pub(crate) fn standard_normal_from_bits<R: Rng + ?Sized>(bits: u32, rng: &mut R) -> f64 {
    let tables = tables();
    let layer = (bits & 0x7f) as usize;
    // Arithmetic shift: a signed 25-bit abscissa from the upper bits.
    let hz = (bits as i32) >> 7;
    if hz.unsigned_abs() < tables.k[layer] {
        return f64::from(hz) * tables.w[layer];
    }
    slow_path(rng, tables, hz, layer)
}

#[cold]
fn slow_path<R: Rng + ?Sized>(rng: &mut R, tables: &Tables, mut hz: i32, mut layer: usize) -> f64 {
    loop {
        let x = f64::from(hz) * tables.w[layer];
        if layer == 0 {
            // The tail beyond TAIL_START (Marsaglia 1964).
            loop {
                let u1: f64 = 1.0 - rng.random::<f64>();
                let u2: f64 = 1.0 - rng.random::<f64>();
                let tail_x = -u1.ln() / TAIL_START;
                let tail_y = -u2.ln();
                if tail_y + tail_y >= tail_x * tail_x {
                    return if hz > 0 {
                        TAIL_START + tail_x
                    } else {
                        -TAIL_START - tail_x
                    };
                }
            }
        }
        let u: f64 = rng.random();
        if tables.f[layer] + u * (tables.f[layer - 1] - tables.f[layer]) < (-0.5 * x * x).exp() {
            return x;
        }
        let bits = rng.next_u32();
        layer = (bits & 0x7f) as usize;
        hz = (bits as i32) >> 7;
        if hz.unsigned_abs() < tables.k[layer] {
            return f64::from(hz) * tables.w[layer];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn moments_and_tails_match_the_standard_normal() {
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let n = 2_000_000;
        let (mut m1, mut m2, mut m4) = (0.0, 0.0, 0.0);
        let mut beyond_two = 0usize;
        let mut beyond_tail = 0usize;
        let mut below_half = 0usize;
        for _ in 0..n {
            let x = standard_normal(&mut rng);
            m1 += x;
            m2 += x * x;
            m4 += x * x * x * x;
            beyond_two += usize::from(x.abs() > 2.0);
            beyond_tail += usize::from(x.abs() > TAIL_START);
            below_half += usize::from(x < 0.5);
        }
        let n_f = n as f64;
        // Standard errors at n = 2e6: mean 7e−4, variance 1e−3, fourth
        // moment 6.6e−3 (√(96/n)); proportions √(p(1−p)/n). Allow 5.
        assert!((m1 / n_f).abs() < 5.0 * (1.0 / n_f).sqrt());
        assert!((m2 / n_f - 1.0).abs() < 5.0 * (2.0 / n_f).sqrt());
        assert!((m4 / n_f - 3.0).abs() < 5.0 * (96.0 / n_f).sqrt());
        let check = |count: usize, p: f64| {
            let observed = count as f64 / n_f;
            assert!(
                (observed - p).abs() < 5.0 * (p * (1.0 - p) / n_f).sqrt(),
                "observed {observed}, expected {p}"
            );
        };
        check(beyond_two, 0.045_500_263_896_358_4);
        check(beyond_tail, 5.761_168_605_196_7e-4);
        check(below_half, 0.691_462_461_274_013_1);
    }
}
