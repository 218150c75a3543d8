//! The optional `cross_validation` section: k-fold cross-validation of a
//! trained detector over its training set.

use crate::error::FieldError;
use crate::manifest::{CrossValidation, DetectorEntry};

/// Checks the fold count (2 to 50) and that the detector exists and is
/// trained.
pub(super) fn check_cross_validation(
    cross_validation: &CrossValidation,
    detectors: &[DetectorEntry],
) -> Result<(), FieldError> {
    CrossValidation::check_folds(cross_validation.folds)
        .map_err(|message| FieldError::new("cross_validation.folds", message))?;
    let detector_path = super::path_of(&["cross_validation", "detector"]);
    let detector = super::require_detector(detectors, &detector_path, &cross_validation.detector)?;
    if detector.spec.training_dataset().is_none() {
        return Err(FieldError::at(
            &detector_path,
            format!(
                "`{}` is not trained, so there is nothing to cross-validate",
                cross_validation.detector
            ),
        ));
    }
    Ok(())
}
