//! The typed registry row recorded with each new artefact.

use super::artefacts::Artefact;
use super::compute::root_dataset;
use super::plan::{Action, Plan};
use crate::registry::{ArtefactDetails, EvaluationAuc};

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
            let root = root_dataset(plan, *source);
            let (seed, params) = (root.map_or(0, |d| d.seed), root.map(|d| &d.params));
            ArtefactDetails::Dataset {
                frames: frames.len(),
                height: params.map_or(0, |p| p.height),
                width: params.map_or(0, |p| p.width),
                seed,
                diffusion: None,
                brightness: params.map_or(0.0.into(), |p| p.brightness),
                params_json: step.spec.clone(),
            }
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
        ) => {
            let score = artefact.evaluation().ok();
            ArtefactDetails::Evaluation {
                detector: detector.clone(),
                dataset: dataset_name.clone(),
                dataset_key: plan.steps[*dataset].key.clone(),
                predictions_key: plan.steps[*predictions].key.clone(),
                rmse_top_px: score.and_then(|s| s.rmse_top_px),
                fraction_without_prediction: score
                    .map(|s| s.fraction_without_prediction)
                    .unwrap_or(0.0),
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
        (Action::SimulateRecording { recording }, _) => {
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
        (
            Action::Link {
                pipeline,
                recording,
                predictions,
                ..
            },
            artefact,
        ) => ArtefactDetails::Predictions {
            detector: pipeline.clone(),
            dataset_key: plan.steps[*recording].key.clone(),
            // The localiser's model, if it is trained.
            model_key: match &plan.steps[*predictions].action {
                Action::Locate { model, .. } => model.map(|m| plan.steps[m].key.clone()),
                _ => None,
            },
            count: artefact
                .tracks()
                .map(|tracks| tracks.iter().map(|t| t.points.len()).sum())
                .unwrap_or(0),
        },
        (
            Action::ScoreTracks {
                pipeline,
                recording_name,
                recording,
                tracks,
                ..
            },
            artefact,
        ) => {
            // No AUC: the tracking measures are in score.json. The share of
            // truth points no track point matched stands for the frames
            // without a prediction.
            let missed = artefact.track_evaluation().ok().map(|e| {
                let t = &e.tracking;
                if t.truth_points == 0 {
                    0.0
                } else {
                    t.missed_points as f64 / t.truth_points as f64
                }
            });
            ArtefactDetails::Evaluation {
                detector: pipeline.clone(),
                dataset: recording_name.clone(),
                dataset_key: plan.steps[*recording].key.clone(),
                predictions_key: plan.steps[*tracks].key.clone(),
                rmse_top_px: None,
                fraction_without_prediction: missed.unwrap_or(0.0),
                auc: Vec::new(),
            }
        }
    }
}
