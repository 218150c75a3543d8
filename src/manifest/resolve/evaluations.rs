//! The `evaluations` section: which detectors are scored on which datasets.

use crate::error::FieldError;
use crate::manifest::raw::RawEvaluation;
use crate::manifest::{DatasetSpec, DetectorEntry, EvaluationSpec};

/// Every (detector, dataset) pair to score, in manifest order; each named
/// detector and dataset must exist, and no pair may come twice.
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
            let pair = EvaluationSpec {
                detector: evaluation.detector.clone(),
                dataset: dataset.clone(),
            };
            if evaluations.contains(&pair) {
                return Err(FieldError::at(
                    &dataset_path,
                    format!(
                        "`{}` is already evaluated on `{dataset}`",
                        evaluation.detector
                    ),
                ));
            }
            evaluations.push(pair);
        }
    }
    Ok(evaluations)
}
