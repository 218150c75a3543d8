//! The rows a run reports beside its AUC rows: the empty-frame figures of
//! evaluations on scenes and the tracking pipelines' figures, as the run
//! table prints them and `scanloc report` reads them back.

use super::plan::{Action, Step};
use crate::metrics::scenes::EmptyFrames;
use crate::track::pipeline::TrackEvaluation;

/// The localisations of one evaluation on the empty frames (frames
/// without ground truth) of its test set, counted at the detector's score
/// threshold (docs/metric.md, "Scenes"): on a set of empty frames the only
/// figure there is, as it has no AUC.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct EmptyFramesRow {
    pub detector: String,
    pub dataset: String,
    /// A localisation counts if its score is at least this; `None`: every
    /// localisation counts.
    pub threshold: Option<f64>,
    /// The set's empty frames and the localisations on them.
    #[serde(flatten)]
    pub empty_frames: EmptyFrames,
}

/// A tracking pipeline's figures on one recording, as the run table
/// prints them (the per-track estimates stay in the evaluation's
/// `score.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TrackingRow {
    /// `DETECTOR+LINKER`.
    pub pipeline: String,
    pub recording: String,
    /// The recording's true D, µm²/s.
    pub diffusion: f64,
    pub tracking: crate::metrics::tracking::TrackingScore,
    pub estimators: Vec<EstimatorRow>,
    /// The ML ensemble corrected for the pipeline's bias by simulation,
    /// where the scoring asked for it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub corrected_ensemble: Option<crate::track::pipeline::CorrectedEnsemble>,
    pub evaluation_key: String,
}

/// One estimator's D on a recording: the ensemble and the per-track
/// metrics.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct EstimatorRow {
    pub method: crate::track::diffusion::Method,
    pub ensemble: Option<crate::track::pipeline::StoredEstimate>,
    pub ensemble_relative_error: Option<f64>,
    pub per_track: Option<crate::metrics::diffusion::DiffusionScore>,
}

impl TrackingRow {
    /// The row of tracking evaluation step `step` whose evaluation is
    /// `evaluation`; `None` for a step that does not score tracks.
    pub fn of(step: &Step, evaluation: &TrackEvaluation) -> Option<Self> {
        let Action::ScoreTracks {
            pipeline,
            recording_name,
            ..
        } = &step.action
        else {
            return None;
        };
        Some(Self::new(pipeline, recording_name, &step.key, evaluation))
    }

    /// The row of pipeline `pipeline` on recording `recording` whose
    /// evaluation, stored under `evaluation_key`, is `evaluation`.
    pub fn new(
        pipeline: &str,
        recording: &str,
        evaluation_key: &str,
        evaluation: &TrackEvaluation,
    ) -> Self {
        Self {
            pipeline: pipeline.to_string(),
            recording: recording.to_string(),
            diffusion: evaluation.true_diffusion_um2_s,
            tracking: evaluation.tracking.clone(),
            estimators: evaluation
                .diffusion
                .iter()
                .map(|e| EstimatorRow {
                    method: e.method,
                    ensemble: e.ensemble,
                    ensemble_relative_error: e.ensemble_relative_error,
                    per_track: e.per_track,
                })
                .collect(),
            corrected_ensemble: evaluation.corrected_ensemble,
            evaluation_key: evaluation_key.to_string(),
        }
    }
}
