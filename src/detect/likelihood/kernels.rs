//! The particle filter's two inner loops over the particles, written so the
//! compiler vectorises them: one PSF sample (position sums and the pixel's
//! signal) and one pixel's Poisson weight. Each has one portable body,
//! compiled also for AVX2 and AVX-512 and picked by what the CPU has; the
//! body uses no fused multiply–add and [`vector_math`]'s exponential and
//! logarithm, so every build returns the same bits.

use super::Particles;
use super::vector_math::{exp, ln, ln_1p};
use crate::detect::cpu::{has_avx2_fma, has_avx512};
use crate::sim::ScanModel;

/// Runs `$body` (a call of an `#[inline(always)]` portable function) in
/// the widest build this CPU has.
macro_rules! dispatch {
    ($name:ident($($arg:ident: $ty:ty),*) => $body:ident) => {
        pub(super) fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                fn wide($($arg: $ty),*) {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2")]
                fn narrow($($arg: $ty),*) {
                    $body($($arg),*)
                }
                if has_avx512() {
                    // SAFETY: the CPU has AVX-512F (checked).
                    return unsafe { wide($($arg),*) };
                }
                if has_avx2_fma() {
                    // SAFETY: the CPU has AVX2 (checked).
                    return unsafe { narrow($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
}

dispatch!(accumulate_sample(scan: &ScanModel, beam_x: f64, beam_y: f64, p: &mut Particles) => accumulate_portable);
dispatch!(weigh_known_background(p: &mut Particles, count: f64, background: f64) => weigh_known_portable);
dispatch!(weigh_own_background(p: &mut Particles, count: f64, reference: f64) => weigh_own_portable);

/// Adds every particle's position to its running sum and the photons of
/// one PSF sample with the beam at `(beam_x, beam_y)` µm to its pixel
/// signal.
#[inline(always)]
fn accumulate_portable(scan: &ScanModel, beam_x: f64, beam_y: f64, p: &mut Particles) {
    let positions = p.x.iter().zip(&p.y).zip(&p.z);
    let accumulators = p.sum_x.iter_mut().zip(&mut p.sum_y).zip(&mut p.signal);
    for (((x, y), z), ((sum_x, sum_y), signal)) in positions.zip(accumulators) {
        *sum_x += x;
        *sum_y += y;
        *signal += scan.sample_photons_with(x - beam_x, y - beam_y, *z, exp);
    }
}

/// Multiplies every weight by P(count | background + s) / P(count |
/// background) for its pixel signal s (scaled by its own N_qd when it has
/// one) and resets the signals; `background` > 0.
#[inline(always)]
fn weigh_known_portable(p: &mut Particles, count: f64, background: f64) {
    let inverse = 1.0 / background;
    scale_signals(p);
    for (weight, signal) in p.weight.iter_mut().zip(&mut p.signal) {
        let s = std::mem::take(signal);
        *weight *= exp(count * ln_1p(s * inverse) - s);
    }
}

/// Multiplies every weight by P(count | b + s) / P(count | `reference`) for
/// its own background b and pixel signal s (scaled by its own N_qd when it
/// has one) and resets the signals; `reference` > 0. An expected 0 photons
/// with photons counted gives weight 0.
#[inline(always)]
fn weigh_own_portable(p: &mut Particles, count: f64, reference: f64) {
    let inverse = 1.0 / reference;
    scale_signals(p);
    let weights = p.weight.iter_mut().zip(&mut p.signal).zip(&p.background);
    for ((weight, signal), background) in weights {
        let mean = background + std::mem::take(signal);
        // ln of a non-positive mean is meaningless; its value is discarded.
        let log_ratio = count * ln(if mean > 0.0 { mean * inverse } else { 1.0 });
        let ratio = exp(log_ratio - (mean - reference));
        *weight *= if mean > 0.0 || count == 0.0 {
            ratio
        } else {
            0.0
        };
    }
}

/// Each particle's pixel signal at its own N_qd, where it has one (the
/// model's signal is at the model's N_qd).
#[inline(always)]
pub(super) fn scale_signals(p: &mut Particles) {
    if !p.brightness_scale.is_empty() {
        for (signal, scale) in p.signal.iter_mut().zip(&p.brightness_scale) {
            *signal *= scale;
        }
    }
}

/// Σw and Σw² in a fixed order (four interleaved partial sums, added at the
/// end), so the result is the same on every CPU and build.
pub(super) fn sum_and_sum_of_squares(weights: &[f64]) -> (f64, f64) {
    let mut sums = [0.0f64; 4];
    let mut squares = [0.0f64; 4];
    let mut chunks = weights.chunks_exact(4);
    for chunk in &mut chunks {
        for lane in 0..4 {
            sums[lane] += chunk[lane];
            squares[lane] += chunk[lane] * chunk[lane];
        }
    }
    for (lane, w) in chunks.remainder().iter().enumerate() {
        sums[lane] += w;
        squares[lane] += w * w;
    }
    (
        (sums[0] + sums[1]) + (sums[2] + sums[3]),
        (squares[0] + squares[1]) + (squares[2] + squares[3]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::SimParams;
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// `n` particles scattered over a paper frame, with signals, weights
    /// and their own backgrounds and brightness scales.
    fn particles(n: usize, seed: u64) -> Particles {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut draw = |low: f64, high: f64| -> Vec<f64> {
            (0..n)
                .map(|_| low + (high - low) * rng.random::<f64>())
                .collect()
        };
        Particles {
            x: draw(-0.5, 2.2),
            y: draw(-0.5, 2.2),
            z: draw(-2.0, 2.0),
            sum_x: draw(0.0, 50.0),
            sum_y: draw(0.0, 50.0),
            signal: draw(0.0, 9.0),
            weight: draw(0.1, 1.0),
            background: draw(2.0, 10.0),
            brightness_scale: draw(0.5, 1.5),
            ..Particles::default()
        }
    }

    fn bits(values: &[f64]) -> Vec<u64> {
        values.iter().map(|v| v.to_bits()).collect()
    }

    /// The vector builds the CPU picks give the portable build's bits, on
    /// particle counts that are and are not multiples of the vector width.
    #[test]
    fn every_build_gives_the_portable_builds_bits() {
        let scan = ScanModel::new(&SimParams::default());
        for n in [1, 7, 64, 501] {
            let (mut vector, mut portable) = (particles(n, 3), particles(n, 3));
            accumulate_sample(&scan, 0.91, 0.42, &mut vector);
            accumulate_portable(&scan, 0.91, 0.42, &mut portable);
            for (a, b) in [
                (&vector.sum_x, &portable.sum_x),
                (&vector.sum_y, &portable.sum_y),
                (&vector.signal, &portable.signal),
            ] {
                assert_eq!(bits(a), bits(b), "{n} particles");
            }
            let (mut vector, mut portable) = (particles(n, 4), particles(n, 4));
            weigh_known_background(&mut vector, 13.0, 8.4);
            weigh_known_portable(&mut portable, 13.0, 8.4);
            assert_eq!(
                bits(&vector.weight),
                bits(&portable.weight),
                "{n} particles"
            );
            let (mut vector, mut portable) = (particles(n, 5), particles(n, 5));
            weigh_own_background(&mut vector, 4.0, 6.0);
            weigh_own_portable(&mut portable, 4.0, 6.0);
            assert_eq!(
                bits(&vector.weight),
                bits(&portable.weight),
                "{n} particles"
            );
        }
    }
}
