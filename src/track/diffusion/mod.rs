//! The diffusion coefficient D from trajectories of a point-scanning
//! microscope (`docs/tracking.md`), per track and for the ensemble, by
//! three estimators:
//!
//! - [`cve`]: the covariance-based estimator (Vestergaard, Blainey &
//!   Flyvbjerg, PRE 89, 022726, 2014), with its variance formula;
//! - [`msd`]: an unweighted fit of the mean squared displacement with the
//!   number of points that minimises the error of D (Michalet, PRE 82,
//!   041914, 2010), computed exactly for the track rather than read off a
//!   chart;
//! - [`ml`]: maximum likelihood with the tridiagonal covariance of the
//!   steps (Berglund, PRE 82, 011917, 2010), generalised to each
//!   localisation's own time stamp, blur and (when given) error; 95 %
//!   intervals from the likelihood ratio.
//!
//! Every estimator takes [`Series`]: a track's positions in µm with each
//! localisation's time stamp and blur time from the scan ([`scan`]). The
//! ensemble estimate is the same estimator over all series at once (pooled
//! moments, a pooled MSD curve, a joint likelihood), so tracks weigh in by
//! how much they tell.
//!
//! Per axis, consecutive localisations `i`, `i+1` of a free Brownian
//! particle have steps with `Var(Δᵢ) = 2D(Δtᵢ − τᵢ − τᵢ₊₁) + σᵢ² + σᵢ₊₁²`
//! and `Cov(Δᵢ, Δᵢ₊₁) = 2Dτᵢ₊₁ − σᵢ₊₁²` (τ the blur time, σ² the
//! localisation variance). x and y are independent and share D.

pub mod cve;
pub mod ml;
pub mod msd;
pub mod scan;

pub use scan::{Exposure, ScanGeometry};

use crate::types::Track;

/// The quantile of the standard normal for two-sided 95 % intervals.
pub const Z_95: f64 = 1.959_963_984_540_054;

/// A track prepared for estimation.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    /// Frame of each localisation, increasing.
    pub frames: Vec<usize>,
    /// Positions along x and y, µm.
    pub axes: [Vec<f64>; 2],
    /// Time stamp of each localisation, s.
    pub times: Vec<f64>,
    /// Blur time τ of each localisation, s.
    pub blur: Vec<f64>,
    /// Localisation variance along x and y of each localisation, µm², when
    /// every localisation of the track has one.
    pub variances: Option<[Vec<f64>; 2]>,
    /// The field along x and y, µm (`[−a/2, (W − 1/2)·a]`, in the units of
    /// `axes`): localisations exist only inside it, which selects the
    /// steps (see [`fit_weight`]).
    pub field: [(f64, f64); 2],
}

impl Series {
    /// `track` (ordered by frame, one localisation per frame) with each
    /// localisation's time stamp and blur from `geometry` under `exposure`;
    /// a `time` the table gave replaces the scan's time stamp.
    pub fn new(track: &Track, geometry: &ScanGeometry, exposure: Exposure) -> Self {
        let a = geometry.pixel_size_um;
        let n = track.points.len();
        let mut series = Series {
            frames: Vec::with_capacity(n),
            axes: [Vec::with_capacity(n), Vec::with_capacity(n)],
            times: Vec::with_capacity(n),
            blur: Vec::with_capacity(n),
            variances: None,
            field: [
                (-0.5 * a, (geometry.width as f64 - 0.5) * a),
                (-0.5 * a, (geometry.height as f64 - 0.5) * a),
            ],
        };
        let all_sigma = track.points.iter().all(|p| p.sigma.is_some());
        let mut variances = [Vec::new(), Vec::new()];
        for point in &track.points {
            let (time, blur) = geometry.stamp(exposure, point.frame, point.x, point.y);
            series.frames.push(point.frame);
            series.axes[0].push(point.x * a);
            series.axes[1].push(point.y * a);
            series.times.push(point.time_s.unwrap_or(time));
            series.blur.push(blur);
            if let (true, Some((sx, sy))) = (all_sigma, point.sigma) {
                variances[0].push((sx * a).powi(2));
                variances[1].push((sy * a).powi(2));
            }
        }
        if all_sigma && n > 0 {
            series.variances = Some(variances);
        }
        series
    }

    /// Number of localisations.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the series has no localisation.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
}

/// The estimators (written as their [`Method::name`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    Cve,
    Msd,
    Ml,
}

impl Method {
    pub const ALL: [Method; 3] = [Method::Cve, Method::Msd, Method::Ml];

    /// The name written in tables.
    pub fn name(self) -> &'static str {
        match self {
            Method::Cve => "cve",
            Method::Msd => "msd",
            Method::Ml => "ml",
        }
    }

    /// This estimator over `series` (one track, or all for the ensemble).
    pub fn estimate(self, series: &[&Series]) -> Option<Estimate> {
        match self {
            Method::Cve => cve::estimate(series),
            Method::Msd => msd::estimate(series),
            Method::Ml => ml::estimate(series),
        }
    }
}

/// One estimate of D.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    /// D, µm²/s.
    pub d: f64,
    /// Its standard error, µm²/s.
    pub standard_error: f64,
    /// The 95 % interval, µm²/s (the upper end may be infinite).
    pub low: f64,
    pub high: f64,
    /// The localisation variance per axis, µm²: estimated, or the mean of
    /// the given ones.
    pub localisation_variance: f64,
    /// Steps (displacements between consecutive localisations) used, per axis.
    pub steps: usize,
    /// Whether the estimator's stated condition for its interval holds
    /// (`docs/tracking.md`).
    pub interval_valid: bool,
}

impl Estimate {
    /// Whether the 95 % interval holds `d`.
    pub fn covers(&self, d: f64) -> bool {
        self.low <= d && d <= self.high
    }
}

/// The inverse of the chance that a stretch of path of extent `extent`
/// along an axis fits in a field of length `length` there, relative to a
/// point: `L / (L − extent)`.
///
/// A track exists only while its particle is in the field, so a step (or a
/// pair of steps, or a pair of localisations n frames apart) is seen only
/// if all its localisations are in the field; with particles spread
/// uniformly (the steady state) a stretch of extent `e` lands inside with
/// probability `(L − e)/L`, whatever its shape. Long steps are thus
/// under-represented, which biases moment estimators of D low by about
/// `√(2/π)·s/L` per axis (`s` the step's standard deviation): −11 % at
/// D = 1 µm²/s in the paper's 1.7 µm field. Weighting each stretch by
/// this factor (Horvitz–Thompson) removes the bias. Capped at 20 (an
/// extent above 95 % of the field, which only noise can give).
pub fn fit_weight(extent: f64, length: f64) -> f64 {
    length / (length - extent).max(0.05 * length)
}

/// The extent (largest minus smallest) of `values`.
pub(crate) fn extent(values: impl IntoIterator<Item = f64>) -> f64 {
    let (low, high) = values
        .into_iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    (high - low).max(0.0)
}

/// The standard normal's cumulative distribution function Φ, to a
/// relative error below 1.2·10⁻⁷ (the Chebyshev fit of erfc in Press et
/// al., *Numerical Recipes*, §6.2).
pub fn normal_cdf(x: f64) -> f64 {
    let z = (x / std::f64::consts::SQRT_2).abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let polynomial = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * polynomial.exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

/// Steps of one axis of one series: `(Δ, Δt)` between consecutive
/// localisations, with the frame gap.
pub(crate) fn steps(series: &Series, axis: usize) -> impl Iterator<Item = (f64, f64, usize)> + '_ {
    let values = &series.axes[axis];
    (1..series.len()).map(move |i| {
        (
            values[i] - values[i - 1],
            series.times[i] - series.times[i - 1],
            series.frames[i] - series.frames[i - 1],
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_normal_cdf_and_the_fit_weight_match_hand_values() {
        // The fit's relative error on erfc is below 1.2e-7 (erfc ≤ 2).
        assert!((normal_cdf(0.0) - 0.5).abs() < 1.5e-7);
        assert!((normal_cdf(1.959_963_985) - 0.975).abs() < 1.5e-7);
        assert!((normal_cdf(-1.0) - 0.158_655_254).abs() < 1.5e-7);
        // A step of a quarter of the field fits in 3/4 of the places.
        assert!((fit_weight(0.25, 1.0) - 4.0 / 3.0).abs() < 1e-12);
        assert_eq!(fit_weight(2.0, 1.0), 20.0);
        assert!((extent([0.3, -0.2, 0.1]) - 0.5).abs() < 1e-15);
    }
}
