//! The `detectors` section: name → one detector kind with its parameters.

use crate::error::FieldError;
use crate::manifest::serde_adapters::{Named, SingletonMap};
use crate::manifest::{DatasetSpec, DetectorEntry, DetectorSpec};
use crate::types::derive_seed;

/// Every detector, in manifest order, with its derived seed; a trained
/// detector's training set must be a dataset of the manifest.
pub(super) fn resolve_detectors(
    section: Named<SingletonMap<DetectorSpec>>,
    master_seed: u64,
    datasets: &[DatasetSpec],
) -> Result<Vec<DetectorEntry>, FieldError> {
    section
        .0
        .into_iter()
        .map(|(name, SingletonMap(spec))| resolve_detector(name, spec, master_seed, datasets))
        .collect()
}

fn resolve_detector(
    name: String,
    spec: DetectorSpec,
    master_seed: u64,
    datasets: &[DatasetSpec],
) -> Result<DetectorEntry, FieldError> {
    let path = super::path_of(&["detectors", &name]);
    super::check_name(&path, &name)?;
    // The parameters sit under the kind's key: `detectors.cnn.cnn.training`.
    let parameters_path = super::field(&path, spec.kind().as_str());
    spec.validate().map_err(|e| e.under(&parameters_path))?;
    if let Some(training_set) = spec.training_dataset() {
        super::require_dataset(
            datasets,
            &super::field(&parameters_path, "training_set"),
            training_set,
        )?;
    }
    Ok(DetectorEntry {
        seed: derive_seed(master_seed, "detector", &name),
        name,
        spec,
    })
}
