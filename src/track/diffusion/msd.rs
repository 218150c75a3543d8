//! The mean squared displacement (MSD) fit with the optimal number of
//! points (Michalet, PRE 82, 041914, 2010), the conventional reference.
//!
//! `MSD(n)` is the mean of `Δx² + Δy²` over all pairs of localisations `n`
//! frames apart (pooled over the series given), at the pairs' mean time lag
//! `tₙ`, each axis's mean weighted by [`super::fit_weight`] of the extent
//! of the localisations from the pair's first to its last (the stretch of
//! path the field had to hold for the pair to be seen; see there). An
//! unweighted straight line through lags `1..=p`,
//! `MSD = 4D·t + b`, gives `D̂` (slope / 4) and the localisation variance
//! `σ̂² = (b + 8D̂τ̄)/4` (for Brownian motion `MSD(t) = 4D(t − 2τ) + 4σ²`).
//!
//! Michalet showed that the error of D̂ has a minimum at some `p`, which
//! grows with the reduced localisation error `σ²/(DΔt)`. Here `p` is
//! chosen by computing the error exactly: D̂ is a quadratic form `ΔᵀAΔ` of
//! the steps, so under the Gaussian step model
//! (`Var(Δᵢ)`, `Cov(Δᵢ, Δᵢ₊₁)`, see [`super`]) `Var D̂ = 2 tr(AΣAΣ)` per
//! axis, with Σ evaluated at the current estimate. Starting from `p = 2`,
//! the `p` of least variance is taken and the estimate redone, twice. `p`
//! is at most [`MAX_LAGS`] and half the longest track.
//!
//! The 95 % interval is `D̂ ± 1.96·SE`, stated valid as the CVE's (at least
//! [`super::cve::MIN_STEPS`] steps, both axes counted).

use super::{Estimate, Series, Z_95, extent, fit_weight};

/// Most lags fitted.
pub(crate) const MAX_LAGS: usize = 10;

/// A pair of localisations of one series, `i < j`, with its field weight
/// per axis: the inverse chance that the field holds the stretch of path
/// between them, whose extent is that of the localisations `i..=j` (not
/// only the end-to-end distance: a pair is seen only if every localisation
/// between its ends is).
#[derive(Debug, Clone, Copy)]
struct Pair {
    i: usize,
    j: usize,
    weight: [f64; 2],
}

/// The pairs of each lag `1..=max_lag` (frames) of one series, each
/// weighed once for every fit and variance that reads it.
fn pairs_by_lag(series: &Series, max_lag: usize) -> Vec<Vec<Pair>> {
    let mut lags = vec![Vec::new(); max_lag + 1];
    let weight = |axis: usize, i: usize, j: usize| {
        let (low, high) = series.field[axis];
        fit_weight(extent(series.axes[axis][i..=j].iter().copied()), high - low)
    };
    for i in 0..series.len() {
        for j in i + 1..series.len() {
            let lag = series.frames[j] - series.frames[i];
            if lag > max_lag {
                break;
            }
            let weight = [weight(0, i, j), weight(1, i, j)];
            lags[lag].push(Pair { i, j, weight });
        }
    }
    lags
}

/// The fit of lags `1..=p`: its coefficients on each lag's MSD, and the
/// estimates.
struct Fit {
    /// Per lag (index = lag) and axis: the coefficient of one pair's
    /// `fit_weight · Δ²` in D̂.
    pair_weight: Vec<[f64; 2]>,
    d: f64,
    localisation_variance: f64,
}

/// Least squares through the pooled MSD of lags `1..=p`; `None` with fewer
/// than two lags holding pairs.
fn fit(series: &[&Series], pairs: &[Vec<Vec<Pair>>], p: usize) -> Option<Fit> {
    let mut points = Vec::new(); // (lag, t, msd, weight per axis)
    for lag in 1..=p {
        let (mut sums, mut weights, mut time, mut count) = ([0.0; 2], [0.0; 2], 0.0, 0usize);
        for (s, lags) in series.iter().zip(pairs) {
            for &Pair { i, j, weight } in lags.get(lag).into_iter().flatten() {
                for axis in 0..2 {
                    let delta = s.axes[axis][j] - s.axes[axis][i];
                    sums[axis] += weight[axis] * delta * delta;
                    weights[axis] += weight[axis];
                }
                time += s.times[j] - s.times[i];
                count += 1;
            }
        }
        if count > 0 {
            let msd = sums[0] / weights[0] + sums[1] / weights[1];
            points.push((lag, time / count as f64, msd, weights));
        }
    }
    if points.len() < 2 {
        return None;
    }
    let k = points.len() as f64;
    let mean_t = points.iter().map(|p| p.1).sum::<f64>() / k;
    let mean_msd = points.iter().map(|p| p.2).sum::<f64>() / k;
    let sxx: f64 = points.iter().map(|p| (p.1 - mean_t).powi(2)).sum();
    if sxx.is_nan() || sxx <= 0.0 {
        return None;
    }
    let slope: f64 = points
        .iter()
        .map(|p| (p.1 - mean_t) * (p.2 - mean_msd))
        .sum::<f64>()
        / sxx;
    let intercept = mean_msd - slope * mean_t;
    let d = slope / 4.0;
    let mean_blur = mean_blur(series);
    let mut pair_weight = vec![[0.0; 2]; p + 1];
    for &(lag, t, _, weights) in &points {
        let slope_coefficient = (t - mean_t) / sxx / 4.0;
        pair_weight[lag] = [
            slope_coefficient / weights[0],
            slope_coefficient / weights[1],
        ];
    }
    Some(Fit {
        pair_weight,
        d,
        localisation_variance: (intercept + 8.0 * d * mean_blur) / 4.0,
    })
}

fn mean_blur(series: &[&Series]) -> f64 {
    let count: usize = series.iter().map(|s| s.len()).sum();
    series.iter().flat_map(|s| &s.blur).sum::<f64>() / count.max(1) as f64
}

/// A symmetric band matrix of half-width `w` (entries with `|k − l| ≤ w`).
struct Band {
    n: usize,
    w: usize,
    values: Vec<f64>,
}

impl Band {
    fn new(n: usize, w: usize) -> Self {
        Self {
            n,
            w,
            values: vec![0.0; n * (2 * w + 1)],
        }
    }

    fn get(&self, k: usize, l: usize) -> f64 {
        if k >= self.n || l >= self.n || k.abs_diff(l) > self.w {
            return 0.0;
        }
        self.values[k * (2 * self.w + 1) + l + self.w - k]
    }

    fn add(&mut self, k: usize, l: usize, value: f64) {
        let w = self.w;
        self.values[k * (2 * w + 1) + l + w - k] += value;
    }
}

/// `Var(ΔᵀAΔ) = 2 tr(AΣAΣ)` for one axis of `series`, `A` the fit's
/// quadratic form and Σ the steps' covariance at `(d, v)` (the series'
/// own variances where given).
fn axis_variance(series: &Series, axis: usize, lags: &[Vec<Pair>], fit: &Fit, v: f64) -> f64 {
    let steps = series.len() - 1;
    let w = lags.len().max(1);
    let mut a = Band::new(steps, w);
    for (lag, pairs) in lags.iter().enumerate().skip(1) {
        let coefficient = fit.pair_weight.get(lag).map_or(0.0, |c| c[axis]);
        if coefficient == 0.0 {
            continue;
        }
        // Pair (i, j) covers steps i..j: (Σ Δ)² adds its weight to each
        // entry (the field weights taken as given).
        for &Pair { i, j, weight } in pairs {
            let weight = coefficient * weight[axis];
            for k in i..j {
                for l in i..j {
                    if l >= k {
                        a.add(k, l, weight);
                    }
                }
            }
        }
    }
    for k in 0..steps {
        for l in k + 1..(k + w + 1).min(steps) {
            let value = a.get(k, l);
            a.add(l, k, value);
        }
    }
    let variance = |i: usize| match &series.variances {
        Some(given) => given[axis][i],
        None => v,
    };
    let d = fit.d.max(0.0);
    let diag = |k: usize| {
        let dt = series.times[k + 1] - series.times[k];
        2.0 * d * (dt - series.blur[k] - series.blur[k + 1]) + variance(k) + variance(k + 1)
    };
    let off = |k: usize| 2.0 * d * series.blur[k + 1] - variance(k + 1);
    let sigma = |k: usize, l: usize| match (k, l) {
        _ if k == l => diag(k),
        _ if l == k + 1 => off(k),
        _ if k == l + 1 => off(l),
        _ => 0.0,
    };
    // M = AΣ (band w + 1); tr(M²) = Σ M_kl M_lk.
    let m = |k: usize, l: usize| {
        let mut value = a.get(k, l) * sigma(l, l);
        if l > 0 {
            value += a.get(k, l - 1) * sigma(l - 1, l);
        }
        if l + 1 < steps {
            value += a.get(k, l + 1) * sigma(l + 1, l);
        }
        value
    };
    let mut trace = 0.0;
    for k in 0..steps {
        let first = k.saturating_sub(w + 1);
        for l in first..(k + w + 2).min(steps) {
            trace += m(k, l) * m(l, k);
        }
    }
    2.0 * trace
}

/// The variance of the fit's D̂ over all series and both axes.
fn variance(series: &[&Series], pairs: &[Vec<Vec<Pair>>], fit: &Fit) -> f64 {
    let v = fit.localisation_variance.max(0.0);
    series
        .iter()
        .zip(pairs)
        .filter(|(s, _)| s.len() > 1)
        .map(|(s, lags)| axis_variance(s, 0, lags, fit, v) + axis_variance(s, 1, lags, fit, v))
        .sum()
}

/// The MSD fit over `series` pooled with the optimal number of lags;
/// `None` without two lags holding pairs.
pub(crate) fn estimate(series: &[&Series]) -> Option<Estimate> {
    let longest = series.iter().map(|s| s.len()).max()?;
    let max_lag = MAX_LAGS.min(longest / 2).max(2);
    let pairs: Vec<Vec<Vec<Pair>>> = series.iter().map(|s| pairs_by_lag(s, max_lag)).collect();
    let mut best = fit(series, &pairs, 2)?;
    let mut best_variance = variance(series, &pairs, &best);
    for _ in 0..2 {
        // The variance of each p at the current estimate of D and σ².
        let plug_in = Fit {
            pair_weight: Vec::new(),
            ..best
        };
        let mut chosen = 2;
        let mut least = f64::INFINITY;
        for p in 2..=max_lag {
            let Some(candidate) = fit(series, &pairs, p) else {
                continue;
            };
            let at_plug_in = Fit {
                d: plug_in.d,
                localisation_variance: plug_in.localisation_variance,
                ..candidate
            };
            let variance = variance(series, &pairs, &at_plug_in);
            if variance < least {
                least = variance;
                chosen = p;
            }
        }
        best = fit(series, &pairs, chosen)?;
        best_variance = variance(series, &pairs, &best);
    }
    let steps: usize = series.iter().map(|s| s.len().saturating_sub(1)).sum();
    let standard_error = best_variance.max(0.0).sqrt();
    Some(Estimate {
        d: best.d,
        standard_error,
        low: best.d - Z_95 * standard_error,
        high: best.d + Z_95 * standard_error,
        localisation_variance: best.localisation_variance,
        steps,
        interval_valid: 2 * steps >= super::cve::MIN_STEPS && best.d > 0.0,
    })
}
