//! What a tracking evaluation stores (`score.json`): D estimates, per
//! track and per estimator, and the tracking measures. Their JSON is part
//! of the stored artefacts: change it only with
//! [`TRACK_METRIC_VERSION`](super::TRACK_METRIC_VERSION).

use serde::{Deserialize, Serialize};

use super::bias::CorrectedEnsemble;
use super::config::TrackScoring;
use crate::metrics::diffusion::{DiffusionInterval, DiffusionScore};
use crate::metrics::tracking::TrackingScore;
use crate::track::diffusion::{Estimate, Method};

/// One estimate of D as stored: µm²/s and µm². A value that is not a
/// finite number (the standard error of an unbounded interval) is stored
/// as `null` and read back as NaN, and is NaN in memory from the start, so
/// a stored evaluation reads back equal to the one computed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StoredEstimate {
    #[serde(deserialize_with = "null_as_nan")]
    pub d: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub standard_error: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub low: f64,
    /// `None` for an unbounded interval (JSON has no infinity).
    pub high: Option<f64>,
    #[serde(deserialize_with = "null_as_nan")]
    pub localisation_variance: f64,
    pub steps: usize,
    pub interval_valid: bool,
}

/// `null` (how JSON writes a number that is not finite) as NaN.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// `value` if finite, else NaN (what it reads back as from JSON).
pub(super) fn finite_or_nan(value: f64) -> f64 {
    if value.is_finite() { value } else { f64::NAN }
}

impl From<Estimate> for StoredEstimate {
    fn from(e: Estimate) -> Self {
        Self {
            d: finite_or_nan(e.d),
            standard_error: finite_or_nan(e.standard_error),
            low: finite_or_nan(e.low),
            high: e.high.is_finite().then_some(e.high),
            localisation_variance: finite_or_nan(e.localisation_variance),
            steps: e.steps,
            interval_valid: e.interval_valid,
        }
    }
}

impl StoredEstimate {
    pub(super) fn interval(&self) -> DiffusionInterval {
        DiffusionInterval {
            d: self.d,
            low: self.low,
            high: self.high.unwrap_or(f64::INFINITY),
        }
    }
}

/// One track's estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackEstimate {
    pub particle: i64,
    pub points: usize,
    pub estimate: StoredEstimate,
}

/// One estimator's D over a recording's tracks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimatorScore {
    pub method: Method,
    /// The estimator over all tracks at once; `None` if it gave none.
    pub ensemble: Option<StoredEstimate>,
    /// `D̂/D − 1` of the ensemble estimate.
    pub ensemble_relative_error: Option<f64>,
    /// The D metrics over the tracks of at least `min_points` whose
    /// estimate's stated condition holds; `None` when there is none.
    pub per_track: Option<DiffusionScore>,
    /// Every track of at least `min_points` localisations that got an
    /// estimate, by particle.
    pub tracks: Vec<TrackEstimate>,
    /// ML: how much more the tracks' estimates scatter than the likelihood
    /// says (each track's interval is widened by it where it exceeds 1;
    /// docs/tracking.md, "The estimators"). Absent for the other methods,
    /// and in evaluations made before `scanloc-track-metric/4`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dispersion: Option<f64>,
    /// ML: how much more the ensemble's runs scatter than the likelihood
    /// says (the ensemble's interval is widened by it where it exceeds 1).
    /// Absent for the other methods, and in evaluations made before
    /// `scanloc-track-metric/5`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble_dispersion: Option<f64>,
}

/// A tracking pipeline's scores on one recording (`score.json` of a
/// tracking evaluation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackEvaluation {
    /// The tracking measures against the selected truth.
    pub tracking: TrackingScore,
    /// The recording's true D, µm²/s.
    pub true_diffusion_um2_s: f64,
    pub scoring: TrackScoring,
    /// One entry per estimator (CVE, MSD fit, ML).
    pub diffusion: Vec<EstimatorScore>,
    /// The ML ensemble corrected for the pipeline's bias, with
    /// [`BiasCorrection::Simulated`] (absent otherwise, and where the
    /// pipeline gave no ensemble).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub corrected_ensemble: Option<CorrectedEnsemble>,
}

impl TrackEvaluation {
    /// The entry of estimator `method`.
    pub fn estimator(&self, method: Method) -> Option<&EstimatorScore> {
        self.diffusion.iter().find(|e| e.method == method)
    }
}
