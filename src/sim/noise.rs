//! Detector noise: Poisson shot noise and the PMT excess-noise model.
//!
//! Counts are returned as `u64` and never clipped: callers decide whether a
//! count fits their storage type and refuse it otherwise.

use rand::{Rng, RngExt};
use rand_distr::{Distribution as _, Gamma, Poisson};

use super::params::DetectorNoise;

/// Below this mean, Poisson variates are drawn by sequential inversion (one
/// uniform draw, about λ + 1 comparisons); above it by rand_distr's PTRS
/// rejection sampler, whose cost does not grow with λ.
const INVERSION_LIMIT: f64 = 30.0;

/// Number of guide-table cells of [`PoissonTable`]: with 1024 cells the
/// guide almost always lands on the answer, so a draw costs one uniform and
/// one well-predicted comparison.
const GUIDE_CELLS: usize = 1024;

/// One Poisson(mean) variate, for any finite `mean ≥ 0` up to
/// rand_distr's limit of 1.8e19 (larger means are refused upstream).
pub fn poisson<R: Rng + ?Sized>(rng: &mut R, mean: f64) -> u64 {
    let uniform: f64 = rng.random();
    poisson_from_uniform(uniform, rng, mean)
}

/// One Poisson(mean) variate whose uniform was drawn beforehand (in bulk);
/// means of 30 and more draw what they need from `rng` instead.
#[inline]
pub(crate) fn poisson_from_uniform<R: Rng + ?Sized>(uniform: f64, rng: &mut R, mean: f64) -> u64 {
    debug_assert!(mean.is_finite() && mean >= 0.0);
    if mean <= 0.0 {
        0
    } else if mean < INVERSION_LIMIT {
        // Squeeze: P(X = 0) = exp(−λ) ≥ 1 − λ, so a uniform at or below
        // 1 − λ gives 0 without evaluating the exponential. Most pixels have
        // λ ≪ 1 signal photons, so this is the common, exact, fast path.
        if uniform <= 1.0 - mean {
            return 0;
        }
        sample_by_inversion(mean, uniform)
    } else {
        match Poisson::new(mean) {
            Ok(poisson) => poisson.sample(rng) as u64,
            Err(_) => u64::MAX,
        }
    }
}

/// `1/k` for small `k`: the inversion recurrence `p_k = p_(k−1) · λ / k`
/// then costs a multiplication instead of a division.
const RECIPROCALS: [f64; 128] = {
    let mut table = [0.0; 128];
    let mut k = 1;
    while k < 128 {
        table[k] = 1.0 / k as f64;
        k += 1;
    }
    table
};

/// `P(X = k)` from `P(X = k − 1)` for Poisson(mean). Every CDF in this
/// module is accumulated with this one recurrence, so table and direct
/// inversion give the same variate for the same uniform.
#[inline]
fn next_probability(previous: f64, mean: f64, k: u64) -> f64 {
    match RECIPROCALS.get(k as usize) {
        Some(reciprocal) => previous * (mean * reciprocal),
        None => previous * (mean / k as f64),
    }
}

/// Sequential inversion: the smallest `k` with `P(X ≤ k) ≥ uniform`.
fn sample_by_inversion(mean: f64, uniform: f64) -> u64 {
    let mut k = 0u64;
    let mut probability = (-mean).exp();
    let mut total = probability;
    while uniform > total {
        k += 1;
        probability = next_probability(probability, mean, k);
        if probability == 0.0 {
            // Rounding left the CDF a hair short of 1: the variate is in the
            // far tail, where the current k is as good as any.
            break;
        }
        total += probability;
    }
    k
}

/// Poisson variates of one fixed mean by table inversion with a guide table
/// (Chen & Asau 1974; Devroye, *Non-Uniform Random Variate Generation*,
/// §III.2.4): one uniform draw and about one comparison per variate.
///
/// Used for the background, which every pixel has: a pixel's count is the
/// sum of an independent Poisson(background) and Poisson(signal) draw, which
/// is exactly Poisson(background + signal).
#[derive(Debug, Clone)]
pub struct PoissonTable {
    mean: f64,
    /// `cdf[k] = P(X ≤ k)`, up to where the tail is below 1e−16.
    cdf: Vec<f64>,
    /// `guide[i]` = smallest `k` with `cdf[k] > i / GUIDE_CELLS`.
    guide: Vec<u32>,
}

impl PoissonTable {
    /// A table for `mean`; means outside `[0, 30)` (or not finite) get no
    /// table and are drawn by [`poisson`].
    pub fn new(mean: f64) -> Self {
        let mut cdf = Vec::new();
        let mut guide = Vec::new();
        if mean.is_finite() && mean > 0.0 && mean < INVERSION_LIMIT {
            // The same recurrence as `sample_by_inversion`, so a table draw
            // equals an inversion draw of the same uniform.
            let mut probability = (-mean).exp();
            let mut total = probability;
            cdf.push(total);
            let mut k = 0u64;
            while 1.0 - total > 1e-16 && cdf.len() < 1000 {
                k += 1;
                probability = next_probability(probability, mean, k);
                total += probability;
                cdf.push(total);
            }
            let mut k = 0usize;
            for cell in 0..GUIDE_CELLS {
                let threshold = cell as f64 / GUIDE_CELLS as f64;
                while k + 1 < cdf.len() && cdf[k] < threshold {
                    k += 1;
                }
                guide.push(k as u32);
            }
        }
        Self { mean, cdf, guide }
    }

    /// One Poisson(mean) variate for the table's mean.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> u64 {
        let uniform: f64 = rng.random();
        self.sample_from_uniform(uniform, rng)
    }

    /// One variate from a uniform drawn beforehand.
    #[inline]
    pub fn sample_from_uniform<R: Rng + ?Sized>(&self, uniform: f64, rng: &mut R) -> u64 {
        if self.cdf.is_empty() {
            return poisson_from_uniform(uniform, rng, self.mean);
        }
        // `cdf[guide[cell]] ≥ cell / G` is the largest bound below `uniform`
        // known without a search; walk up from there.
        let mut k = self.guide[(uniform * GUIDE_CELLS as f64) as usize] as usize;
        while uniform > self.cdf[k] {
            k += 1;
            if k == self.cdf.len() {
                // Beyond the table (probability < 1e−16): exact inversion.
                return sample_by_inversion(self.mean, uniform);
            }
        }
        k as u64
    }
}

/// Applies the detector model to a pixel's expected photons: a fixed
/// background plus the pixel's own signal.
#[derive(Debug, Clone)]
pub(crate) struct Detector {
    background: PoissonTable,
    noise: DetectorNoise,
}

impl Detector {
    /// A detector for scenes with `background` expected photons per pixel.
    pub(crate) fn new(noise: DetectorNoise, background: f64) -> Self {
        Self {
            background: PoissonTable::new(background),
            noise,
        }
    }

    /// The recorded count of a pixel with expected `signal` photons (finite,
    /// ≥ 0) on top of the background, the two uniforms of the Poisson stage
    /// (the background's, the signal's) drawn beforehand in bulk. Photons
    /// are drawn as Poisson(background) + Poisson(signal), i.e.
    /// Poisson(background + signal); a pixel without signal costs one table
    /// look-up.
    #[inline]
    pub(crate) fn record_from_uniforms<R: Rng + ?Sized>(
        &self,
        uniforms: [f64; 2],
        rng: &mut R,
        signal: f64,
    ) -> u64 {
        let background = self.background.sample_from_uniform(uniforms[0], rng);
        let photons = if signal > 0.0 {
            background.saturating_add(poisson_from_uniform(uniforms[1], rng, signal))
        } else {
            background
        };
        match self.noise {
            DetectorNoise::Poisson => photons,
            DetectorNoise::Pmt {
                excess_noise_factor,
            } => {
                if photons == 0 {
                    return 0;
                }
                // Sum of `photons` unit-mean gamma gains of variance F² − 1.
                let scale = excess_noise_factor - 1.0;
                match Gamma::new(photons as f64 / scale, scale) {
                    Ok(gamma) => gamma.sample(rng).round() as u64,
                    Err(_) => photons,
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn table_and_direct_inversion_agree_draw_for_draw() {
        // The same uniform gives the same variate whichever path is taken.
        let table = PoissonTable::new(8.4);
        let mut a = ChaCha8Rng::seed_from_u64(3);
        let mut b = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..100_000 {
            let uniform: f64 = b.random();
            assert_eq!(table.sample(&mut a), sample_by_inversion(8.4, uniform));
        }
    }
}
