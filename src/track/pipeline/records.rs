//! What a tracking evaluation stores (`score.json`): D estimates, per
//! track and per estimator, and the tracking measures. Their JSON is part
//! of the stored artefacts: change it only with
//! [`TRACK_METRIC_VERSION`](super::TRACK_METRIC_VERSION).

use serde::{Deserialize, Serialize};

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

/// The ML ensemble corrected for a pipeline's bias by simulation
/// ([`BiasCorrection::Simulated`](super::BiasCorrection::Simulated)): the pipeline read `D̂` on the recording
/// and `D̂ₛ` on a simulated one at D = `D̂`, so it reads D high by `D̂ₛ/D̂`
/// there, and the corrected D is `D̂ · D̂/D̂ₛ`, its relative standard error
/// the two estimates' added in quadrature.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CorrectedEnsemble {
    /// The corrected D with its standard error and 95 % interval
    /// (`D ± 1.96 SE`); its localisation variance and steps are the
    /// recording's ensemble's.
    pub estimate: StoredEstimate,
    /// `D/D_true − 1` of the corrected D.
    pub relative_error: f64,
    /// QDs in each simulated recording: as many as give them the
    /// recording's localisations per frame, by a pilot with `pilot_qds`.
    pub simulated_qds: u64,
    pub pilot_qds: u64,
    /// The simulated recordings' frames, all together.
    pub simulated_frames: usize,
    /// The ML ensemble the pipeline read on the simulated recordings' tracks
    /// together, whose true D is the recording's ensemble D̂.
    pub simulated: StoredEstimate,
}

impl CorrectedEnsemble {
    /// The correction of `recording`'s ensemble estimate (true D `true_d`)
    /// by `simulated`, the pipeline's estimate on a recording simulated at
    /// D = `recording.d`; `None` where either is not a positive finite D.
    pub fn new(
        recording: &StoredEstimate,
        simulated: &StoredEstimate,
        true_d: f64,
        qds: (u64, u64),
        simulated_frames: usize,
    ) -> Option<Self> {
        let positive = |e: &StoredEstimate| e.d.is_finite() && e.d > 0.0;
        if !(positive(recording) && positive(simulated)) {
            return None;
        }
        let d = recording.d * recording.d / simulated.d;
        let relative_se =
            (recording.standard_error / recording.d).hypot(simulated.standard_error / simulated.d);
        let standard_error = d * relative_se;
        let half_width = 1.96 * standard_error;
        let estimate = StoredEstimate {
            d,
            standard_error: finite_or_nan(standard_error),
            low: finite_or_nan(d - half_width),
            high: (d + half_width).is_finite().then_some(d + half_width),
            ..*recording
        };
        Some(Self {
            estimate,
            relative_error: d / true_d - 1.0,
            simulated_qds: qds.1,
            pilot_qds: qds.0,
            simulated_frames,
            simulated: *simulated,
        })
    }
}
