//! The `datasets` section: name → frame count and overrides of the
//! microscope.

use super::microscope::apply_sim_overrides;
use crate::error::{FieldError, Segment, display_path};
use crate::manifest::DatasetSpec;
use crate::manifest::serde_adapters::Named;
use crate::sim::SimParams;
use crate::types::derive_seed;

/// Every dataset, in manifest order, with its microscope and derived seed.
pub(super) fn resolve_datasets(
    section: &Named<serde_yaml::Mapping>,
    microscope: &SimParams,
    master_seed: u64,
) -> Result<Vec<DatasetSpec>, FieldError> {
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

/// The dataset's `frames`: a positive integer, at most [`MAX_FRAMES`](crate::limits::MAX_FRAMES).
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
    // The command line's limits (one definition, in `limits`).
    crate::limits::check_frame_count("frames", value.as_u64().unwrap_or(0))
        .map_err(|e| e.under(dataset_path))
}

/// Refuses datasets too large to hold in memory ([`MAX_DATASET_PIXELS`](crate::limits::MAX_DATASET_PIXELS)).
fn check_pixel_count(
    dataset_path: &[Segment],
    frames: usize,
    params: &SimParams,
) -> Result<(), FieldError> {
    crate::limits::check_dataset_pixels("frames", frames, params.height, params.width)
        .map_err(|e| e.under(dataset_path))
}
