//! The `evaluations` section: which detectors are scored on which datasets.

use crate::error::FieldError;
use crate::manifest::raw::RawEvaluation;
use crate::manifest::{DatasetSpec, DetectorEntry, DetectorSpec, EvaluationSpec};

/// Every (detector, dataset) pair to score, in manifest order; each named
/// detector and dataset must exist, and no pair may come twice with the
/// same frames (a detector may be scored on a whole set and, beside that,
/// on its first N frames: the two are different sets of frames).
pub(super) fn resolve_evaluations(
    section: &[RawEvaluation],
    datasets: &[DatasetSpec],
    detectors: &[DetectorEntry],
) -> Result<Vec<EvaluationSpec>, FieldError> {
    let mut evaluations: Vec<EvaluationSpec> = Vec::new();
    for (index, evaluation) in section.iter().enumerate() {
        let path = super::item(&super::path_of(&["evaluations"]), index);
        super::require_detector(
            detectors,
            &super::field(&path, "detector"),
            &evaluation.detector,
        )?;
        let datasets_path = super::field(&path, "datasets");
        if evaluation.datasets.is_empty() {
            return Err(FieldError::at(
                &datasets_path,
                "must list at least one dataset",
            ));
        }
        for (position, dataset) in evaluation.datasets.iter().enumerate() {
            let dataset_path = super::item(&datasets_path, position);
            super::require_dataset(datasets, &dataset_path, dataset)?;
            let spec = datasets
                .iter()
                .find(|d| &d.name == dataset)
                .expect("required above");
            let frames = match evaluation.frames {
                None => None,
                Some(0) => {
                    return Err(FieldError::at(
                        &super::field(&path, "frames"),
                        "must be a positive integer",
                    ));
                }
                // All of them: the plain evaluation, with its usual keys.
                Some(frames) if frames >= spec.frames => {
                    if frames > spec.frames {
                        return Err(FieldError::at(
                            &super::field(&path, "frames"),
                            format!(
                                "{frames} frames asked of `{dataset}`, which has {}",
                                spec.frames
                            ),
                        ));
                    }
                    None
                }
                Some(frames) => Some(frames),
            };
            check_detector_models(detectors, &evaluation.detector, spec, &dataset_path)?;
            let pair = EvaluationSpec {
                detector: evaluation.detector.clone(),
                dataset: dataset.clone(),
                frames,
            };
            if evaluations.iter().any(|e| {
                e.detector == pair.detector && e.dataset == pair.dataset && e.frames == pair.frames
            }) {
                let which = match frames {
                    Some(frames) => format!("the first {frames} frames of `{dataset}`"),
                    None => format!("`{dataset}`"),
                };
                return Err(FieldError::at(
                    &dataset_path,
                    format!("`{}` is already evaluated on {which}", evaluation.detector),
                ));
            }
            evaluations.push(pair);
        }
    }
    Ok(evaluations)
}

/// Whether detector `name` can model the frames of `dataset`, named at
/// `path` (the likelihood detector models Poisson counts only).
fn check_detector_models(
    detectors: &[DetectorEntry],
    name: &str,
    dataset: &DatasetSpec,
    path: &[crate::error::Segment],
) -> Result<(), FieldError> {
    match detectors.iter().find(|d| d.name == name).map(|d| &d.spec) {
        Some(DetectorSpec::Likelihood(params)) => params
            .check_microscope(&params.assumed_microscope(&dataset.params))
            .map_err(|e| {
                FieldError::at(
                    path,
                    format!("`{name}` cannot model `{}`: {}", dataset.name, e),
                )
            }),
        _ => Ok(()),
    }
}
