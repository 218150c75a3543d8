//! The `datasets` section: name → frame count and overrides of the
//! microscope.

use super::microscope::apply_sim_overrides;
use crate::error::{FieldError, Segment, display_path};
use crate::manifest::serde_adapters::Named;
use crate::manifest::{DatasetSpec, MAX_DATASET_PIXELS, MAX_FRAMES, derive_seed};
use crate::sim::SimParams;

/// Every dataset, in manifest order, with its microscope and derived seed.
pub(super) fn resolve_datasets(
    section: &Named<serde_yaml::Mapping>,
    microscope: &SimParams,
    master_seed: u64,
) -> Result<Vec<DatasetSpec>, FieldError> {
    if section.0.is_empty() {
        return Err(FieldError::new(
            "datasets",
            "must declare at least one dataset",
        ));
    }
    section
        .0
        .iter()
        .map(|(name, entry)| resolve_dataset(name, entry, microscope, master_seed))
        .collect()
}

fn resolve_dataset(
    name: &str,
    entry: &serde_yaml::Mapping,
    microscope: &SimParams,
    master_seed: u64,
) -> Result<DatasetSpec, FieldError> {
    let path = super::path_of(&["datasets", name]);
    super::check_name(&path, name)?;
    let frames = read_frames(&path, entry.get("frames"))?;
    let params = apply_sim_overrides(&path, microscope, entry, &["frames"])?;
    params
        .validate()
        .map_err(|error| blame_dataset_or_microscope(error, &path, entry))?;
    check_pixel_count(&path, frames, &params)?;
    Ok(DatasetSpec {
        name: name.to_string(),
        frames,
        seed: derive_seed(master_seed, "dataset", name),
        params,
    })
}

/// A failed check of a dataset's parameters belongs to the dataset when it
/// sets the field itself (or the error names no field), and otherwise to
/// the microscope it inherited the value from. The microscope's values
/// passed their own check, so such a value fails only together with the
/// dataset's overrides (a margin too wide for the dataset's narrower
/// frames): the message then names the dataset too.
fn blame_dataset_or_microscope(
    error: FieldError,
    dataset_path: &[Segment],
    overrides: &serde_yaml::Mapping,
) -> FieldError {
    let set_by_dataset = match error.path.first() {
        None => true,
        Some(Segment::Key(top)) => overrides.contains_key(top.as_str()),
        Some(Segment::Index(_)) => false,
    };
    if set_by_dataset {
        return error.under(dataset_path);
    }
    let message = format!(
        "{} (inherited by {})",
        error.message,
        display_path(dataset_path)
    );
    FieldError { message, ..error }.under(&super::path_of(&["microscope"]))
}

/// The dataset's `frames`: a positive integer, at most [`MAX_FRAMES`].
fn read_frames(
    dataset_path: &[Segment],
    value: Option<&serde_yaml::Value>,
) -> Result<usize, FieldError> {
    let Some(value) = value else {
        return Err(FieldError::at(
            dataset_path,
            "missing field `frames` (the number of frames)",
        ));
    };
    let frames_path = super::field(dataset_path, "frames");
    match value.as_u64() {
        Some(0) | None => Err(FieldError::at(&frames_path, "must be a positive integer")),
        Some(n) if n > MAX_FRAMES as u64 => Err(FieldError::at(
            &frames_path,
            format!("must be at most {MAX_FRAMES}, got {n}"),
        )),
        Some(n) => Ok(n as usize),
    }
}

/// Refuses datasets too large to hold in memory ([`MAX_DATASET_PIXELS`]).
fn check_pixel_count(
    dataset_path: &[Segment],
    frames: usize,
    params: &SimParams,
) -> Result<(), FieldError> {
    let pixels = frames
        .checked_mul(params.height)
        .and_then(|p| p.checked_mul(params.width));
    if pixels.is_none_or(|p| p > MAX_DATASET_PIXELS) {
        return Err(FieldError::at(
            &super::field(dataset_path, "frames"),
            format!(
                "{frames} frames of {}×{} pixels exceed the limit of {MAX_DATASET_PIXELS} pixels per dataset",
                params.height, params.width
            ),
        ));
    }
    Ok(())
}
