//! What a run would refuse only after doing work, refused when the manifest
//! is read: `scanloc check` then says no to every manifest `run` or `cv`
//! would stop on as bad input, and a run never simulates for minutes to fail
//! at its first evaluation.
//!
//! These checks cross fields (a dataset's emitters and the validation or
//! cross-validation that scores it, a training split and its dataset's frame
//! count); the checks of
//! one parameter block stay with its type (`SimParams::validate`,
//! `CrockerGrierParams::validate`, …).

use super::{DetectorSpec, Manifest};
use crate::error::{FieldError, Segment};
use crate::types::DetectorKind;

fn problem(path: &[&str], message: String) -> FieldError {
    let path: Vec<Segment> = path.iter().map(|p| Segment::key(p)).collect();
    FieldError::at(&path, message)
}

/// The first problem of `manifest` that its run would only find by running.
pub(crate) fn check(manifest: &Manifest) -> Result<(), FieldError> {
    // Every dataset that gets scored by its AUC, and by what (for the
    // message). An evaluation is not among them: it scores a set of empty
    // frames by its false localisations (docs/metric.md, "Scenes"), while a
    // CNN's validation and a cross-validation need the AUC, which a set
    // without ground truth does not have.
    let mut scored: Vec<(&str, String)> = Vec::new();
    for detector in &manifest.detectors {
        let DetectorSpec::Cnn(spec) = &detector.spec else {
            continue;
        };
        let Some(training) = manifest.dataset(&spec.training_set) else {
            continue;
        };
        let settings = &spec.training;
        let held_out = settings.held_out_frames(training.frames);
        if held_out == training.frames && settings.fresh_frames_per_epoch == 0 {
            return Err(problem(
                &[
                    "detectors",
                    &detector.name,
                    DetectorKind::Cnn.as_str(),
                    "training",
                    "validation_fraction",
                ],
                format!(
                    "{} holds out all {} frames of `{}` for validation and fresh_frames_per_epoch is 0, so nothing is left to train on",
                    settings.validation_fraction, training.frames, training.name
                ),
            ));
        }
        if settings.teacher_particles > 0
            && let Err(refusal) = crate::detect::likelihood::LikelihoodParams::default()
                .check_microscope(&training.params)
        {
            return Err(problem(
                &[
                    "detectors",
                    &detector.name,
                    DetectorKind::Cnn.as_str(),
                    "training",
                    "teacher_particles",
                ],
                format!("the teacher cannot model `{}`: {refusal}", training.name),
            ));
        }
        if held_out > 0 {
            scored.push((
                training.name.as_str(),
                format!("validation of `{}`", detector.name),
            ));
        }
    }
    if let Some(cv) = &manifest.cross_validation
        && let Some(training) = manifest
            .detector(&cv.detector)
            .and_then(|d| d.spec.training_dataset())
            .and_then(|name| manifest.dataset(name))
    {
        if cv.folds > training.frames {
            return Err(problem(
                &["cross_validation", "folds"],
                format!(
                    "{} folds need at least {} frames, but the training set `{}` has {}",
                    cv.folds, cv.folds, training.name, training.frames
                ),
            ));
        }
        scored.push((
            training.name.as_str(),
            format!("cross-validation of `{}`", cv.detector),
        ));
    }
    for (name, by) in scored {
        let Some(dataset) = manifest.dataset(name) else {
            continue;
        };
        if dataset.params.emitters.always_empty() {
            // Inherited from the microscope unless the microscope has some.
            let path: &[&str] = if manifest.microscope.emitters.always_empty() {
                &["microscope", "emitters"]
            } else {
                &["datasets", name, "emitters"]
            };
            return Err(problem(
                path,
                format!(
                    "0 emitters in `{name}` leave no ground truth for the {by} to be scored against (its AUC needs some)"
                ),
            ));
        }
    }
    Ok(())
}
