//! The covariance-based estimator (CVE; Vestergaard, Blainey & Flyvbjerg,
//! PRE 89, 022726, 2014).
//!
//! From the steps `Δ` between localisations in consecutive frames (a frame
//! gap splits a track into segments; pairs of steps within a segment), per
//! axis and pooled over both axes and all series given:
//!
//! `D̂ = ⟨Δ²⟩/(2Δt) + ⟨ΔᵢΔᵢ₊₁⟩/Δt`, `σ̂² = R⟨Δ²⟩ + (2R − 1)⟨ΔᵢΔᵢ₊₁⟩`,
//!
//! `Δt` the mean step time and `R = τ̄/Δt` the blur coefficient from the
//! scan. D̂ does not depend on R; σ̂² does. The field selects the steps it
//! shows (a track ends when its particle leaves), so each mean is weighted
//! by [`super::fit_weight`] of the stretch it averages (a step, a pair of
//! steps) along its axis, which removes the bias this selection causes. Its variance (their Eq. 16, for
//! N steps of one axis) is `Var D̂ = D²[(6 + 4ε + 2ε²)/N + 4(1 + ε)²/N²]`
//! with `ε = σ²/(DΔt) − 2R`; for K independent segments (axes × segments)
//! pooled into N steps the end term is `4(1 + ε)²·K/N²`.
//!
//! The 95 % interval is `D̂ ± 1.96·SE`, stated valid for at least
//! [`MIN_STEPS`] steps (both axes counted) with `D̂ > 0`: below that the
//! estimate's distribution is too skewed for a normal interval.

use super::{Estimate, Series, Z_95, extent, fit_weight, steps};

/// Fewest steps (both axes counted) for which the normal interval is
/// stated valid.
pub(crate) const MIN_STEPS: usize = 200;

/// Moments pooled over series and axes.
#[derive(Debug, Default)]
struct Moments {
    sum_sq: f64,
    weight_sq: f64,
    steps: usize,
    sum_pair: f64,
    weight_pair: f64,
    pairs: usize,
    sum_dt: f64,
    sum_blur: f64,
    points: usize,
    segments: usize,
}

impl Moments {
    fn add(&mut self, series: &Series) {
        for axis in 0..2 {
            let (low, high) = series.field[axis];
            let length = high - low;
            let values = &series.axes[axis];
            let mut previous: Option<f64> = None;
            let mut in_segment = false;
            for (i, (delta, dt, gap)) in steps(series, axis).enumerate() {
                if gap != 1 {
                    previous = None;
                    in_segment = false;
                    continue;
                }
                if !in_segment {
                    self.segments += 1;
                    in_segment = true;
                }
                let weight = fit_weight(delta.abs(), length);
                self.sum_sq += weight * delta * delta;
                self.weight_sq += weight;
                self.steps += 1;
                self.sum_dt += dt;
                self.sum_blur += series.blur[i + 1];
                self.points += 1;
                if let Some(before) = previous {
                    let weight = fit_weight(extent(values[i - 1..=i + 1].iter().copied()), length);
                    self.sum_pair += weight * before * delta;
                    self.weight_pair += weight;
                    self.pairs += 1;
                }
                previous = Some(delta);
            }
        }
    }
}

/// The CVE over `series` pooled; `None` without two steps in a row.
pub(crate) fn estimate(series: &[&Series]) -> Option<Estimate> {
    let mut moments = Moments::default();
    for s in series {
        moments.add(s);
    }
    if moments.pairs == 0 || moments.sum_dt <= 0.0 {
        return None;
    }
    let n = moments.steps as f64;
    let dt = moments.sum_dt / n;
    let r = moments.sum_blur / moments.points as f64 / dt;
    let mean_sq = moments.sum_sq / moments.weight_sq;
    let mean_pair = moments.sum_pair / moments.weight_pair;
    let d = mean_sq / (2.0 * dt) + mean_pair / dt;
    let localisation_variance = r * mean_sq + (2.0 * r - 1.0) * mean_pair;
    let epsilon = localisation_variance / (d * dt) - 2.0 * r;
    let k = moments.segments as f64;
    let variance = d
        * d
        * ((6.0 + 4.0 * epsilon + 2.0 * epsilon * epsilon) / n
            + 4.0 * (1.0 + epsilon).powi(2) * k / (n * n));
    let standard_error = variance.sqrt();
    Some(Estimate {
        d,
        standard_error,
        low: d - Z_95 * standard_error,
        high: d + Z_95 * standard_error,
        localisation_variance,
        steps: moments.steps / 2,
        interval_valid: moments.steps >= MIN_STEPS && d > 0.0,
    })
}
