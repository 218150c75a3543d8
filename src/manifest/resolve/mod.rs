//! From the manifest as written ([`RawManifest`]) to the resolved
//! [`Manifest`]: names checked, references followed, defaults filled in,
//! seeds derived.
//!
//! One submodule per section, resolved in the order sections refer to each
//! other: the microscope, the datasets (which override it), the detectors
//! (trained on datasets), then the metrics, evaluations, cross-validation
//! and reference rows (which name datasets and detectors). Every check
//! returns a [`FieldError`] whose path starts at the top of the document
//! (`detectors.cnn.cnn.training.epochs`); [`super::parse`] adds the file and
//! the line.

mod cross_validation;
mod datasets;
mod detectors;
mod evaluations;
mod metrics;
mod microscope;
mod reference;
mod tracking;

use sha2::{Digest, Sha256};

use super::raw::RawManifest;
use super::{DatasetSpec, DetectorEntry, MAX_NAME_LEN, Manifest};
use crate::error::{FieldError, Segment};

/// Resolves `raw`, read from `text`; `source` names the file in the result.
pub(super) fn resolve(raw: RawManifest, text: &str, source: &str) -> Result<Manifest, FieldError> {
    if raw.name.trim().is_empty() {
        return Err(FieldError::new("name", "must not be empty"));
    }
    let microscope = microscope::resolve_microscope(&raw.microscope)?;
    let datasets = datasets::resolve_datasets(&raw.datasets, &microscope, raw.seed)?;
    let recordings =
        tracking::resolve_recordings(&raw.recordings, &microscope, raw.seed, &datasets)?;
    if datasets.is_empty() && recordings.is_empty() {
        return Err(FieldError::new(
            "datasets",
            "must declare at least one dataset (or recording)",
        ));
    }
    let detectors = detectors::resolve_detectors(raw.detectors, raw.seed, &datasets)?;
    let linkers = tracking::resolve_linkers(raw.linkers)?;
    let tracking = raw
        .tracking
        .map(|section| tracking::resolve_tracking(section, &detectors, &linkers, &recordings))
        .transpose()?;
    metrics::check_metrics(&raw.metrics, &detectors)?;
    let evaluations = evaluations::resolve_evaluations(&raw.evaluations, &datasets, &detectors)?;
    if let Some(cross_validation) = &raw.cross_validation {
        cross_validation::check_cross_validation(cross_validation, &detectors)?;
    }
    let reference = raw
        .reference
        .map(|reference| {
            reference::resolve_reference(reference, &raw.metrics.eps_px, &datasets, &detectors)
        })
        .transpose()?;
    let manifest = Manifest {
        source: source.to_string(),
        manifest_sha256: hex::encode(Sha256::digest(text.as_bytes())),
        name: raw.name,
        description: raw.description,
        seed: raw.seed,
        microscope,
        datasets,
        detectors,
        metrics: raw.metrics,
        evaluations,
        cross_validation: raw.cross_validation,
        reference,
        recordings,
        linkers,
        tracking,
        text: text.to_string(),
    };
    super::feasibility::check(&manifest)?;
    Ok(manifest)
}

/// The `microscope` section `section` on top of `base` (a command's
/// defaults rather than the paper's), its fields checked one by one as a
/// manifest's are; not yet validated as a whole.
pub(super) fn microscope_over(
    section: &serde_yaml::Mapping,
    base: &crate::sim::SimParams,
) -> Result<crate::sim::SimParams, FieldError> {
    microscope::apply_sim_overrides(&path_of(&["microscope"]), base, section, &[])
}

/// The path through the mappings `keys` from the top of the document
/// (`["datasets", name]`).
fn path_of(keys: &[&str]) -> Vec<Segment> {
    keys.iter().map(|k| Segment::key(k)).collect()
}

/// The path of field `name` of the mapping at `path`.
fn field(path: &[Segment], name: &str) -> Vec<Segment> {
    let mut path = path.to_vec();
    path.push(Segment::key(name));
    path
}

/// The path of item `index` of the list at `path`.
fn item(path: &[Segment], index: usize) -> Vec<Segment> {
    let mut path = path.to_vec();
    path.push(Segment::Index(index));
    path
}

/// Checks the name of a dataset or detector declared at `path`: names
/// become parts of artefact names and file names, so they are kept plain.
fn check_name(path: &[Segment], name: &str) -> Result<(), FieldError> {
    let valid = super::is_plain_name(name, MAX_NAME_LEN);
    if valid {
        Ok(())
    } else {
        Err(FieldError::at(
            path,
            format!(
                "invalid name {name:?}: use 1 to {MAX_NAME_LEN} letters, digits, '.', '_' or '-', starting with a letter or digit"
            ),
        ))
    }
}

/// Checks that `name`, given at `path`, is a dataset of the manifest.
fn require_dataset(
    datasets: &[DatasetSpec],
    path: &[Segment],
    name: &str,
) -> Result<(), FieldError> {
    if datasets.iter().any(|d| d.name == name) {
        Ok(())
    } else {
        Err(FieldError::at(
            path,
            format!("`{name}` is not a dataset of this manifest"),
        ))
    }
}

/// The detector `name`, given at `path`, of the manifest.
fn require_detector<'a>(
    detectors: &'a [DetectorEntry],
    path: &[Segment],
    name: &str,
) -> Result<&'a DetectorEntry, FieldError> {
    detectors
        .iter()
        .find(|d| d.name == name)
        .ok_or_else(|| FieldError::at(path, format!("`{name}` is not a detector of this manifest")))
}
