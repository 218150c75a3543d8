//! A tracking pipeline (`docs/tracking.md`, "The tracking experiment"): a
//! detector's localisations on a recording, linked by a [`LinkerSpec`]
//! into tracks ([`link`]), scored against the recording's truth
//! ([`evaluate`](mod@evaluate)): the tracking measures of
//! [`metrics::tracking`](crate::metrics::tracking) and, per estimator, D
//! for the ensemble and per track with the D metrics of
//! [`metrics::diffusion`](crate::metrics::diffusion); the ML ensemble
//! corrected for the pipeline's bias by simulation ([`bias`]).
//!
//! - [`config`]: the settings a manifest names, checked;
//! - [`link`]: predictions into tracks;
//! - [`records`]: the evaluation as stored;
//! - [`evaluate`](mod@evaluate): tracks scored against the truth;
//! - [`bias`]: the bias correction's procedure, generic over the localiser.

pub(crate) mod bias;
pub(crate) mod config;
pub mod evaluate;
pub(crate) mod link;
pub(crate) mod records;

pub use bias::{
    BIAS_CORRECTION_VERSION, BiasSetup, Localiser, SimulatedBias, correct_ensemble, measure_bias,
    recording_geometry,
};
pub use config::{
    BiasCorrection, LINK_VERSION, LapSettings, LinkerSpec, MAX_BIAS_RECORDINGS,
    TRACK_METRIC_VERSION, TrackScoring, TrackpySettings, check_ensemble_margin, check_min_points,
    valid_ensemble_gate,
};
pub use evaluate::{evaluate, ml_ensemble_of};
pub use link::{link_predictions, scores_at_least, series_of, tracks_of};
pub use records::CorrectedEnsemble;
pub use records::{EstimatorScore, StoredEstimate, TrackEstimate, TrackEvaluation};
