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

pub(crate) mod cve;
pub(crate) mod ml;
pub(crate) mod msd;
pub(crate) mod scan;
mod search;
pub mod tables;

pub use scan::{Exposure, ScanGeometry};

use rayon::prelude::*;

use crate::types::Track;

/// The quantile of the standard normal for two-sided 95 % intervals.
pub(crate) const Z_95: f64 = 1.959_963_984_540_054;

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
    /// Where within the field the localiser misses particles, per axis
    /// ([`DetectionProfile`]); `None`: it finds them equally everywhere.
    pub detection: Option<std::sync::Arc<DetectionProfile>>,
    /// Per localisation, the extent along x and y (µm) of the
    /// linker's gate that admitted the step to it from the previous one
    /// (+∞ for the first, and where no gate is known): a step is seen only
    /// inside its gate, and ML conditions on that as on the field.
    pub gates: [Vec<f64>; 2],
}

/// How a localiser's chance of finding a particle falls off towards the
/// field's edges, along x and y: bins of one pixel from the field's low
/// end, each with its detection efficiency relative to the field's middle
/// (≤ 1). A particle near an edge is found less often (its spot is cut by
/// the edge), so a track tends to end when its particle moves towards an
/// edge: the steps seen are selected short, and an estimator conditioned
/// on the field alone reads D low. The maximum-likelihood estimator
/// conditions each localisation on being found ([`ml`]).
///
/// Read off the localisations themselves: particles at steady state are
/// spread uniformly, so the localisations' density along an axis is the
/// efficiency up to a constant (the median over the middle half of the
/// bins, where the localiser is taken to miss nothing for position). Only
/// the runs of bins below [`DetectionProfile::FULL`] from each edge inwards
/// count.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectionProfile {
    /// Per axis, the bins of the edges' runs below full efficiency:
    /// `(low, high, 1 − q)`, in
    /// the units of [`Series::axes`].
    pub shortfalls: [Vec<(f64, f64, f64)>; 2],
}

impl DetectionProfile {
    /// The profile of the localisations of `series` (positions in µm) over
    /// the field `field` in bins of `bin` µm; `None` with fewer than
    /// [`DetectionProfile::MIN_LOCALISATIONS`] localisations.
    pub fn from_localisations(series: &[Series], field: [(f64, f64); 2], bin: f64) -> Option<Self> {
        let total: usize = series.iter().map(Series::len).sum();
        if total < Self::MIN_LOCALISATIONS || bin.is_nan() || bin <= 0.0 {
            return None;
        }
        let mut shortfalls = [Vec::new(), Vec::new()];
        for (axis, shortfall) in shortfalls.iter_mut().enumerate() {
            let (low, high) = field[axis];
            let bins = ((high - low) / bin).round().max(1.0) as usize;
            let mut counts = vec![0usize; bins];
            for value in series.iter().flat_map(|s| s.axes[axis].iter()) {
                let b = ((value - low) / bin).floor();
                if b >= 0.0 && (b as usize) < bins {
                    counts[b as usize] += 1;
                }
            }
            let mut middle: Vec<usize> = counts[bins / 4..bins - bins / 4].to_vec();
            middle.sort_unstable();
            let reference = middle[middle.len() / 2] as f64;
            if reference <= 0.0 {
                return None;
            }
            let efficiency = |b: usize| (counts[b] as f64 / reference).min(1.0);
            // The runs of bins below full efficiency from each edge inwards;
            // the middle's scatter is noise, not the edge's cut.
            let from_low = (0..bins).take_while(|&b| efficiency(b) < Self::FULL);
            let from_high = (0..bins).rev().take_while(|&b| efficiency(b) < Self::FULL);
            let mut edge_bins: Vec<usize> = from_low.chain(from_high).collect();
            edge_bins.sort_unstable();
            edge_bins.dedup();
            for b in edge_bins {
                let from = low + b as f64 * bin;
                let missed = 1.0 - efficiency(b);
                // Neighbouring bins alike (e.g. the empty ones of a field
                // the particles never reach) are one interval: ML pays for
                // each interval at every step.
                match shortfall.last_mut() {
                    Some((_, to, last)) if *to == from && *last == missed => *to = from + bin,
                    _ => shortfall.push((from, from + bin, missed)),
                }
            }
        }
        Some(Self { shortfalls })
    }

    /// An edge bin at this efficiency or above ends the edge's run.
    pub const FULL: f64 = 0.9;

    /// Fewest localisations the profile is read from.
    pub const MIN_LOCALISATIONS: usize = 1000;
}

/// A recording's estimates by one method ([`estimate_recording`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingEstimates {
    /// Over every series of two localisations or more at once.
    pub ensemble: Option<Estimate>,
    /// One entry per series, in series order: its estimate, `None` when it
    /// has fewer than `min_points` localisations or got none.
    pub per_track: Vec<Option<Estimate>>,
    /// ML: the tracks' dispersion [`ml::dispersion`] (each track's
    /// interval is widened by it where it exceeds 1); `None` for the
    /// other methods, or where it could not be measured.
    pub dispersion: Option<f64>,
    /// ML: the dispersion of the runs the ensemble is estimated over
    /// ([`ml::ensemble`]; its interval is widened by it where it exceeds
    /// 1); `None` for the other methods, or where it could not be measured.
    pub ensemble_dispersion: Option<f64>,
}

/// Prepares a recording's `series` for estimation: each is told where the
/// localiser misses particles ([`DetectionProfile`], read off all the
/// series' localisations in bins of one pixel of `pixel_size_um`; left
/// unset with fewer than [`DetectionProfile::MIN_LOCALISATIONS`]).
pub fn attach_detection_profile(series: &mut [Series], pixel_size_um: f64) {
    let Some(field) = series.first().map(|s| s.field) else {
        return;
    };
    let profile =
        DetectionProfile::from_localisations(series, field, pixel_size_um).map(std::sync::Arc::new);
    for s in series {
        s.detection = profile.clone();
    }
}

/// The share of a link's gate within which the ML ensemble takes its
/// steps ([`within_gates`]): 2/3, i.e. 2 standard deviations of the
/// displacement on each axis under the `lap` linker's default gate of 3.
pub const ENSEMBLE_GATE: f64 = 2.0 / 3.0;

/// The largest share of a link's gate [`within_gates`] takes: up to
/// 1/√2 of the gate's extent on both axes, a displacement is inside the
/// (elliptic) gate, so the narrowed box is all the ensemble is conditioned
/// on.
pub(crate) const MAX_ENSEMBLE_GATE: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// `series` cut where a step leaves `fraction` (at most
/// [`MAX_ENSEMBLE_GATE`]) of the extent of the gate that admitted it, on
/// either axis, each step's gate narrowed to that box (series without
/// gates are kept whole).
///
/// A linker links whatever falls in its gate, so where particles are
/// dense a track that lost its particle takes up another one close by:
/// such a step is the two particles' offset plus a step, and inflates D.
/// Such steps are spread far more widely than the particle's own, so a
/// narrower gate keeps a smaller share of them than of true steps
/// (2 σ: 91 % of a true step's displacements per axis), and ML, conditioned
/// on each step's gate as on the field, reads D from the rest without
/// the truncation's bias (docs/tracking.md, "Wrong links").
pub(crate) fn within_gates(series: &[Series], fraction: f64) -> Vec<Series> {
    let mut pieces = Vec::new();
    for s in series {
        let mut start = 0;
        let mut piece = |from: usize, to: usize| {
            let mut p = s.slice(from, to);
            for gates in &mut p.gates {
                for g in gates.iter_mut() {
                    *g *= fraction;
                }
            }
            pieces.push(p);
        };
        for i in 1..s.len() {
            let outside = (0..2).any(|axis| {
                (s.axes[axis][i] - s.axes[axis][i - 1]).abs() > fraction * s.gates[axis][i]
            });
            if outside {
                piece(start, i);
                start = i;
            }
        }
        if start < s.len() {
            piece(start, s.len());
        }
    }
    pieces
}

/// `series` cut to the box `margin` (µm) inside their field on every
/// side: each run of consecutive localisations inside the box becomes a
/// series whose field is the box (its first step's gate dropped, as it
/// starts afresh). ML conditioned on the box reads D from steps whose
/// ends are away from the edges, where a localiser's chance of finding a
/// particle may depend on how the particle moved (its path leaving the
/// field), which the [`DetectionProfile`], a function of position, does
/// not describe (docs/tracking.md, "Near the field's edges"). A margin
/// of 0 keeps every series whole.
pub(crate) fn within_margin(series: &[Series], margin: f64) -> Vec<Series> {
    if margin <= 0.0 {
        return series.to_vec();
    }
    let mut pieces = Vec::new();
    for s in series {
        let inner = [
            (s.field[0].0 + margin, s.field[0].1 - margin),
            (s.field[1].0 + margin, s.field[1].1 - margin),
        ];
        if inner.iter().any(|(low, high)| low >= high) {
            continue;
        }
        let inside = |i: usize| {
            (0..2).all(|axis| (inner[axis].0..=inner[axis].1).contains(&s.axes[axis][i]))
        };
        let mut i = 0;
        while i < s.len() {
            if !inside(i) {
                i += 1;
                continue;
            }
            let start = i;
            while i < s.len() && inside(i) {
                i += 1;
            }
            let mut piece = s.slice(start, i);
            piece.field = inner;
            pieces.push(piece);
        }
    }
    pieces
}

/// A recording's D by `method`: the ensemble estimate over all `series`
/// of two localisations or more, and one per series of at least
/// `min_points`. The ML ensemble takes its steps within `ensemble_gate`
/// (≤ [`MAX_ENSEMBLE_GATE`]) of their links' gates, conditioned on them
/// ([`within_gates`]; 1: every step), and, with `ensemble_margin` > 0
/// (µm), within the box that far inside the field ([`within_margin`]);
/// each track's own estimate, and the moment estimators, use every step
/// as it is.
///
/// Maximum likelihood estimates a series without given variances with the
/// ensemble's localisation variance rather than its own: one localiser on
/// one recording errs alike in every track, and a short track cannot tell
/// σ² from D (on the CNN's tracks of `make tracking` at D = 1, a relative
/// RMSE of 0.47 against 0.64 profiled per track; docs/tracking.md, "The
/// estimators"), and widens each track's interval by the tracks'
/// [`ml::dispersion`] where it exceeds 1; the ensemble's interval is
/// widened by its own runs' dispersion ([`ml::ensemble`]).
pub fn estimate_recording(
    series: &[Series],
    method: Method,
    min_points: usize,
    ensemble_gate: f64,
    ensemble_margin: f64,
) -> RecordingEstimates {
    // A track's own estimate and the moment estimators use every step as
    // it is: the linker's full gate truncates a step's distribution too
    // little to matter (0.5 % per axis at 3 σ), and conditioned on it a
    // short track's likelihood is nearly flat towards large D.
    let whole: Vec<Series> = series.iter().map(Series::ungated).collect();
    let of = |series: &[Series]| -> Option<Estimate> {
        let all: Vec<&Series> = series.iter().filter(|s| s.len() > 1).collect();
        method.estimate(&all)
    };
    let (ensemble, ensemble_dispersion, shared_variance) = match method {
        Method::Ml => {
            let (ensemble, phi) = ml_ensemble(series, ensemble_gate, ensemble_margin).unzip();
            // The tracks' σ² comes from the likelihood of every step of
            // the whole tracks, as each track's own estimate takes them
            // (the ensemble leaves out first steps and steps beyond its
            // box).
            let all: Vec<&Series> = whole.iter().filter(|s| s.len() > 1).collect();
            let shared = ml::localisation_variance(&all).filter(|v| v.is_finite());
            (ensemble, phi.flatten(), shared)
        }
        _ => (of(&whole), None, None),
    };
    // Each track as its own estimate sees it: σ² told where the ensemble
    // gave it.
    let tracks: Vec<Option<Series>> = whole
        .iter()
        .map(|s| {
            (s.len() >= min_points.max(2)).then(|| match shared_variance {
                Some(v) => s.told(v),
                None => s.clone(),
            })
        })
        .collect();
    let dispersion = (method == Method::Ml)
        .then(|| {
            let told: Vec<&Series> = tracks.iter().flatten().collect();
            ml::dispersion(&told)
        })
        .flatten();
    // Each track's fit is its own: in parallel, collected in order.
    let per_track = tracks
        .par_iter()
        .map(|track| {
            let track = track.as_ref()?;
            match (method, dispersion) {
                (Method::Ml, Some(phi)) => ml::estimate_with_dispersion(&[track], phi),
                _ => method.estimate(&[track]),
            }
        })
        .collect();
    RecordingEstimates {
        ensemble,
        per_track,
        dispersion,
        ensemble_dispersion,
    }
}

/// The ML ensemble over `series` as [`estimate_recording`] takes it: the
/// runs of steps within `ensemble_gate` of each link's gate (every step
/// for a share of 1) and `ensemble_margin` µm inside the field, each
/// conditioned on its box; with the runs' dispersion where it was
/// measured.
pub(crate) fn ml_ensemble(
    series: &[Series],
    ensemble_gate: f64,
    ensemble_margin: f64,
) -> Option<(Estimate, Option<f64>)> {
    let runs = match ensemble_gate <= MAX_ENSEMBLE_GATE {
        true => within_margin(&within_gates(series, ensemble_gate), ensemble_margin),
        false => {
            let whole: Vec<Series> = series.iter().map(Series::ungated).collect();
            within_margin(&whole, ensemble_margin)
        }
    };
    let runs: Vec<&Series> = runs.iter().filter(|s| s.len() > 1).collect();
    let (ensemble, phi) = ml::ensemble(&runs)?;
    Some((ensemble, phi))
}

impl Series {
    /// The series with no gates: every step taken as it is.
    fn ungated(&self) -> Series {
        Series {
            gates: [
                vec![f64::INFINITY; self.len()],
                vec![f64::INFINITY; self.len()],
            ],
            ..self.clone()
        }
    }

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
            detection: None,
            gates: [Vec::with_capacity(n), Vec::with_capacity(n)],
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
            let first = series.frames.len() == 1;
            let (gx, gy) = match point.gate {
                Some((gx, gy)) if !first => (gx * a, gy * a),
                _ => (f64::INFINITY, f64::INFINITY),
            };
            series.gates[0].push(gx);
            series.gates[1].push(gy);
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

    /// Localisations `from..to` of this series, as a series of its own:
    /// its first localisation starts it afresh, so the link into it has no
    /// gate.
    pub fn slice(&self, from: usize, to: usize) -> Series {
        let mut gates = [
            self.gates[0][from..to].to_vec(),
            self.gates[1][from..to].to_vec(),
        ];
        for axis in &mut gates {
            if let Some(first) = axis.first_mut() {
                *first = f64::INFINITY;
            }
        }
        Series {
            frames: self.frames[from..to].to_vec(),
            axes: [
                self.axes[0][from..to].to_vec(),
                self.axes[1][from..to].to_vec(),
            ],
            times: self.times[from..to].to_vec(),
            blur: self.blur[from..to].to_vec(),
            variances: self
                .variances
                .as_ref()
                .map(|v| [v[0][from..to].to_vec(), v[1][from..to].to_vec()]),
            field: self.field,
            detection: self.detection.clone(),
            gates,
        }
    }

    /// This series with every localisation's variance told as `v` (µm²),
    /// unless it has its own.
    pub fn told(&self, v: f64) -> Series {
        Series {
            variances: Some(
                self.variances
                    .clone()
                    .unwrap_or_else(|| [vec![v; self.len()], vec![v; self.len()]]),
            ),
            ..self.clone()
        }
    }

    /// Number of localisations.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether the series has no localisation.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The first step (index of its first localisation) whose time is not
    /// longer than its two localisations' blur, `Δtᵢ ≤ τᵢ + τᵢ₊₁`: its
    /// displacement would have a variance `2D(Δtᵢ − τᵢ − τᵢ₊₁) ≤ 0`, which
    /// no estimator can use. The scan's own stamps never give one (a
    /// frame's blur is at most a sixth of its period); a table's `time`
    /// column can (time stamps that do not increase, or not in seconds).
    pub fn first_step_shorter_than_blur(&self) -> Option<usize> {
        (1..self.len()).map(|i| i - 1).find(|&i| {
            let step = self.times[i + 1] - self.times[i];
            step.is_nan() || step <= self.blur[i] + self.blur[i + 1]
        })
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
pub(crate) fn fit_weight(extent: f64, length: f64) -> f64 {
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
pub(crate) fn normal_cdf(x: f64) -> f64 {
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

    /// One series holding `counts[b]` localisations at the centre of bin
    /// `b` (1 µm bins from 0) along both axes.
    fn series_with_counts(counts: &[usize]) -> Series {
        let values: Vec<f64> = counts
            .iter()
            .enumerate()
            .flat_map(|(b, &n)| std::iter::repeat_n(b as f64 + 0.5, n))
            .collect();
        let n = values.len();
        Series {
            frames: (0..n).collect(),
            axes: [values.clone(), values],
            times: (0..n).map(|i| i as f64).collect(),
            blur: vec![0.0; n],
            variances: None,
            field: [(0.0, counts.len() as f64); 2],
            detection: None,
            gates: [vec![f64::INFINITY; n], vec![f64::INFINITY; n]],
        }
    }

    #[test]
    fn within_gates_cuts_where_a_step_leaves_the_narrowed_gate() {
        // Steps of 1, 3 and 1 along x, each admitted by a gate of extent 4:
        // 2/3 of it (2.67) keeps the first and last steps, in two pieces,
        // each conditioned on its narrowed gate; a series without gates
        // stays whole.
        let mut series = series_with_counts(&[1, 1, 1, 1]);
        series.axes[0] = vec![0.0, 1.0, 4.0, 5.0];
        series.gates = [
            vec![f64::INFINITY, 4.0, 4.0, 4.0],
            vec![f64::INFINITY, 4.0, 4.0, 4.0],
        ];
        let pieces = within_gates(std::slice::from_ref(&series), 2.0 / 3.0);
        assert_eq!(pieces.len(), 2);
        assert_eq!(pieces[0].axes[0], [0.0, 1.0]);
        assert_eq!(pieces[1].axes[0], [4.0, 5.0]);
        assert_eq!(pieces[1].frames, [2, 3]);
        for piece in &pieces {
            assert_eq!(piece.gates[0][0], f64::INFINITY);
            assert!((piece.gates[0][1] - 8.0 / 3.0).abs() < 1e-12);
        }
        let ungated = series_with_counts(&[1, 1, 1, 1]);
        let whole = within_gates(std::slice::from_ref(&ungated), 2.0 / 3.0);
        assert_eq!(whole, [ungated]);
    }

    #[test]
    fn within_margin_keeps_the_runs_inside_the_inner_box_conditioned_on_it() {
        // A field [0, 10] on both axes, a margin of 2: x = 1 and x = 9 are
        // outside the box [2, 8], so the series falls into the runs
        // before, between and after them.
        let mut series = series_with_counts(&[1, 1, 1, 1, 1, 1, 1, 1, 1, 1]);
        series.axes[0] = vec![3.0, 4.0, 1.0, 5.0, 6.0, 7.0, 9.0, 5.0, 5.5, 6.0];
        series.axes[1] = vec![5.0; 10];
        series.gates = [vec![4.0; 10], vec![4.0; 10]];
        let pieces = within_margin(std::slice::from_ref(&series), 2.0);
        let runs: Vec<&[usize]> = pieces.iter().map(|p| p.frames.as_slice()).collect();
        assert_eq!(runs, [&[0, 1][..], &[3, 4, 5], &[7, 8, 9]]);
        for piece in &pieces {
            assert_eq!(piece.field, [(2.0, 8.0), (2.0, 8.0)]);
            assert_eq!(piece.gates[0][0], f64::INFINITY);
            assert_eq!(piece.gates[0][1], 4.0);
        }
        // No margin: whole; a margin leaving no box: nothing.
        assert_eq!(
            within_margin(std::slice::from_ref(&series), 0.0),
            [series.clone()]
        );
        assert!(within_margin(std::slice::from_ref(&series), 5.0).is_empty());
    }

    #[test]
    fn the_detection_profile_is_the_edges_runs_below_full_density() {
        // Edges at 20 % and 60 % of the middle's density, a dip in the
        // middle (noise, not an edge's cut) ignored, the bin at 95 % ending
        // the high edge's run.
        let counts = [40, 120, 200, 200, 200, 100, 200, 200, 200, 190, 80];
        let mut series = [series_with_counts(&counts)];
        attach_detection_profile(&mut series, 1.0);
        let profile = series[0].detection.clone().expect("a profile");
        for axis in 0..2 {
            let got: Vec<(f64, f64, f64)> = profile.shortfalls[axis]
                .iter()
                .map(|&(a, b, s)| (a, b, (s * 100.0).round() / 100.0))
                .collect();
            assert_eq!(got, [(0.0, 1.0, 0.8), (1.0, 2.0, 0.4), (10.0, 11.0, 0.6)]);
        }
        // Neighbouring edge bins alike are one interval.
        let mut empty_edges = [series_with_counts(&[
            0, 0, 0, 100, 400, 400, 400, 400, 0, 0,
        ])];
        attach_detection_profile(&mut empty_edges, 1.0);
        let profile = empty_edges[0].detection.clone().expect("a profile");
        assert_eq!(
            profile.shortfalls[0],
            [(0.0, 3.0, 1.0), (3.0, 4.0, 0.75), (8.0, 10.0, 1.0)]
        );
        // Too few localisations: no profile.
        let mut sparse = [series_with_counts(&[1, 2, 3, 4])];
        attach_detection_profile(&mut sparse, 1.0);
        assert!(sparse[0].detection.is_none());
    }

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
