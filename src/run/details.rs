//! The typed registry row recorded with each new artefact.

use super::artefacts::Artefact;
use super::compute::root_dataset;
use super::plan::{Action, Plan};
use crate::manifest::RecordingSpec;
use crate::metrics::Score;
use crate::registry::{ArtefactDetails, EvaluationAuc};
use crate::track::pipeline::TrackEvaluation;

/// The typed registry row of step `index`'s new artefact.
pub(super) fn details(plan: &Plan, index: usize, artefact: &Artefact) -> ArtefactDetails {
    let step = &plan.steps[index];
    match (&step.action, artefact) {
        (Action::Simulate { dataset }, _) => ArtefactDetails::Dataset {
            frames: dataset.frames,
            height: dataset.params.height,
            width: dataset.params.width,
            seed: dataset.seed,
            diffusion: dataset.fixed_diffusion(),
            brightness: dataset.params.brightness,
            params_json: serde_json::to_string(&dataset.params).unwrap_or_default(),
        },
        (Action::Subset { source, frames }, _) => {
            subset_details(plan, *source, frames.len(), &step.spec)
        }
        (
            Action::Train {
                detector, training, ..
            },
            _,
        ) => ArtefactDetails::Model {
            detector: detector.name.clone(),
            detector_kind: detector.spec.kind(),
            training_dataset_key: plan.steps[*training].key.clone(),
            seed: detector.seed,
        },
        (
            Action::Locate {
                detector,
                dataset,
                model,
            },
            artefact,
        ) => ArtefactDetails::Predictions {
            detector: detector.name.clone(),
            dataset_key: plan.steps[*dataset].key.clone(),
            model_key: model.map(|m| plan.steps[m].key.clone()),
            count: artefact.predictions().map(|p| p.len()).unwrap_or(0),
        },
        (
            Action::Score {
                detector,
                dataset_name,
                dataset,
                predictions,
                ..
            },
            artefact,
        ) => evaluation_details(
            detector,
            dataset_name,
            &plan.steps[*dataset].key,
            &plan.steps[*predictions].key,
            artefact.evaluation().ok().map(|s| &**s),
        ),
        (Action::SimulateRecording { recording }, _) => recording_details(recording),
        (
            Action::Link {
                pipeline,
                recording,
                predictions,
                ..
            },
            artefact,
        ) => link_details(plan, pipeline, *recording, *predictions, artefact),
        (
            Action::ScoreTracks {
                pipeline,
                recording_name,
                recording,
                tracks,
                ..
            },
            artefact,
        ) => ArtefactDetails::Evaluation {
            detector: pipeline.clone(),
            dataset: recording_name.clone(),
            dataset_key: plan.steps[*recording].key.clone(),
            predictions_key: plan.steps[*tracks].key.clone(),
            rmse_top_px: None,
            fraction_without_prediction: artefact
                .track_evaluation()
                .ok()
                .map_or(0.0, |e| missed_share(e)),
            auc: Vec::new(),
        },
    }
}

/// A tracking evaluation has no AUC (its measures are in score.json): the
/// share of truth points no track point matched stands for the frames
/// without a prediction.
fn missed_share(evaluation: &TrackEvaluation) -> f64 {
    let t = &evaluation.tracking;
    if t.truth_points == 0 {
        0.0
    } else {
        t.missed_points as f64 / t.truth_points as f64
    }
}

/// The row of a scoring step's evaluation: `detector`'s predictions (key
/// `predictions_key`) scored on dataset `dataset` (key `dataset_key`),
/// with its figures from `score` (none if the artefact holds no score).
fn evaluation_details(
    detector: &str,
    dataset: &str,
    dataset_key: &str,
    predictions_key: &str,
    score: Option<&Score>,
) -> ArtefactDetails {
    ArtefactDetails::Evaluation {
        detector: detector.to_string(),
        dataset: dataset.to_string(),
        dataset_key: dataset_key.to_string(),
        predictions_key: predictions_key.to_string(),
        rmse_top_px: score.and_then(|s| s.rmse_top_px),
        fraction_without_prediction: score.map(|s| s.fraction_without_prediction).unwrap_or(0.0),
        auc: score
            .map(|s| {
                s.per_eps
                    .iter()
                    .map(|e| EvaluationAuc {
                        eps_px: e.eps_px,
                        auc: e.auc,
                        auc_best_per_frame: e.auc_best_per_frame,
                        true_positives: e.true_positives,
                        false_positives: e.false_positives,
                    })
                    .collect()
            })
            .unwrap_or_default(),
    }
}

/// The row of a subset of the dataset of step `source`: `frames` of it,
/// with the size, seed and brightness of the simulated dataset it comes
/// from, and the step's description `spec` as its parameters.
fn subset_details(plan: &Plan, source: usize, frames: usize, spec: &str) -> ArtefactDetails {
    let root = root_dataset(plan, source);
    let (seed, params) = (root.map_or(0, |d| d.seed), root.map(|d| &d.params));
    ArtefactDetails::Dataset {
        frames,
        height: params.map_or(0, |p| p.height),
        width: params.map_or(0, |p| p.width),
        seed,
        diffusion: None,
        brightness: params.map_or(0.0.into(), |p| p.brightness),
        params_json: spec.to_string(),
    }
}

/// The row of a simulated recording.
fn recording_details(recording: &RecordingSpec) -> ArtefactDetails {
    let m = &recording.params.microscope;
    ArtefactDetails::Dataset {
        frames: recording.params.frames,
        height: m.height,
        width: m.width,
        seed: recording.seed,
        diffusion: m.diffusion_um2_s.fixed(),
        brightness: m.brightness,
        params_json: recording.params_json().to_string(),
    }
}

/// The row of the tracks pipeline `pipeline` linked from the predictions of
/// step `predictions` on the recording of step `recording`: the
/// localiser's model, if it is trained, and the track points' count.
fn link_details(
    plan: &Plan,
    pipeline: &str,
    recording: usize,
    predictions: usize,
    artefact: &Artefact,
) -> ArtefactDetails {
    ArtefactDetails::Predictions {
        detector: pipeline.to_string(),
        dataset_key: plan.steps[recording].key.clone(),
        model_key: match &plan.steps[predictions].action {
            Action::Locate { model, .. } => model.map(|m| plan.steps[m].key.clone()),
            _ => None,
        },
        count: artefact
            .tracks()
            .map(|tracks| tracks.iter().map(|t| t.points.len()).sum())
            .unwrap_or(0),
    }
}
