//! The tracking sections (`docs/tracking.md`, "The tracking experiment"):
//! `recordings` (name → frames, overrides of the microscope, the volume's
//! settings), `linkers` (name → one linker kind) and `tracking` (how tracks
//! are scored, which detector and linker run on which recordings).

use super::microscope::apply_sim_overrides;
use crate::error::{FieldError, Segment};
use crate::manifest::raw::RawTracking;
use crate::manifest::serde_adapters::{Named, SingletonMap};
use crate::manifest::{
    DatasetSpec, DetectorEntry, LinkerEntry, RecordingSpec, TrackingEvaluationSpec, TrackingSpec,
};
use crate::sim::SimParams;
use crate::sim::recording::{Blinking, RecordingParams};
use crate::track::pipeline::LinkerSpec;
use crate::types::derive_seed;

/// A recording's own fields, beside the microscope's.
const RECORDING_FIELDS: [&str; 8] = [
    "frames",
    "qd_density",
    "qd_count",
    "lateral_margin_um",
    "half_depth_um",
    "dead_time_ms",
    "blink_on_ms",
    "blink_off_ms",
];

/// The microscope's fields that a recording does not use, and why.
const NOT_FOR_RECORDINGS: [(&str, &str); 3] = [
    ("emitters", "its QDs come from qd_density or qd_count"),
    (
        "margin_px",
        "its volume reaches lateral_margin_um beyond the field",
    ),
    ("z_start", "its QDs start spread through the volume"),
];

/// Every recording, in manifest order; names are shared with the datasets.
pub(super) fn resolve_recordings(
    section: &Named<serde_yaml::Mapping>,
    microscope: &SimParams,
    master_seed: u64,
    datasets: &[DatasetSpec],
) -> Result<Vec<RecordingSpec>, FieldError> {
    section
        .0
        .iter()
        .map(|(name, entry)| {
            let path = super::path_of(&["recordings", name]);
            super::check_name(&path, name)?;
            if datasets.iter().any(|d| &d.name == name) {
                return Err(FieldError::at(
                    &path,
                    format!("`{name}` is already a dataset (recordings and datasets share names)"),
                ));
            }
            resolve_recording(&path, name, entry, microscope, master_seed)
        })
        .collect()
}

fn resolve_recording(
    path: &[Segment],
    name: &str,
    entry: &serde_yaml::Mapping,
    microscope: &SimParams,
    master_seed: u64,
) -> Result<RecordingSpec, FieldError> {
    let number = |field: &str, default: Option<f64>| -> Result<Option<f64>, FieldError> {
        match entry.get(field) {
            None => Ok(default),
            Some(value) => value
                .as_f64()
                .map(Some)
                .ok_or_else(|| FieldError::at(&super::field(path, field), "must be a number")),
        }
    };
    let frames = match entry.get("frames") {
        None => {
            return Err(FieldError::at(
                path,
                "missing field `frames` (the number of frames)",
            ));
        }
        Some(value) => crate::limits::check_frame_count("frames", value.as_u64().unwrap_or(0))
            .map_err(|e| e.under(path))?,
    };
    let blinking = match (number("blink_on_ms", None)?, number("blink_off_ms", None)?) {
        (Some(on_ms), Some(off_ms)) => Some(Blinking { on_ms, off_ms }),
        (None, None) => None,
        (Some(_), None) => {
            return Err(FieldError::at(
                &super::field(path, "blink_off_ms"),
                "missing: blink_on_ms and blink_off_ms come together",
            ));
        }
        (None, Some(_)) => {
            return Err(FieldError::at(
                &super::field(path, "blink_on_ms"),
                "missing: blink_on_ms and blink_off_ms come together",
            ));
        }
    };
    // Fields of a dataset that a recording does not use, and a density
    // beside a set count (the CLI refuses --qd-density with --qd-count):
    // an error, never silently ignored.
    for (field, reason) in NOT_FOR_RECORDINGS {
        if entry.contains_key(field) {
            return Err(FieldError::at(
                &super::field(path, field),
                format!("not used by a recording ({reason})"),
            ));
        }
    }
    if entry.contains_key("qd_density") && entry.contains_key("qd_count") {
        return Err(FieldError::at(
            &super::field(path, "qd_density"),
            "not used beside qd_count (give one of them)",
        ));
    }
    let params = RecordingParams {
        microscope: apply_sim_overrides(path, microscope, entry, &RECORDING_FIELDS)?,
        frames,
        density_per_um3: number("qd_density", Some(0.05))?.unwrap_or_default(),
        qd_count: match entry.get("qd_count") {
            None => None,
            Some(value) => Some(value.as_u64().ok_or_else(|| {
                FieldError::at(
                    &super::field(path, "qd_count"),
                    "must be a whole number ≥ 0",
                )
            })?),
        },
        lateral_margin_um: number("lateral_margin_um", Some(1.5))?.unwrap_or_default(),
        half_depth_um: number("half_depth_um", Some(4.0))?.unwrap_or_default(),
        blinking,
        dead_time_ms: number("dead_time_ms", Some(0.0))?.unwrap_or_default(),
    };
    params.validate().map_err(|e| e.under(path))?;
    crate::limits::check_dataset_pixels(
        "frames",
        frames,
        params.microscope.height,
        params.microscope.width,
    )
    .map_err(|e| e.under(path))?;
    Ok(RecordingSpec {
        name: name.to_string(),
        seed: derive_seed(master_seed, "dataset", name),
        params,
    })
}

/// Every linker, in manifest order.
pub(super) fn resolve_linkers(
    section: Named<SingletonMap<LinkerSpec>>,
) -> Result<Vec<LinkerEntry>, FieldError> {
    section
        .0
        .into_iter()
        .map(|(name, SingletonMap(spec))| {
            let path = super::path_of(&["linkers", &name]);
            super::check_name(&path, &name)?;
            spec.validate()
                .map_err(|e| e.under(&super::field(&path, spec.kind_name())))?;
            Ok(LinkerEntry { name, spec })
        })
        .collect()
}

/// The `tracking` section: each named detector, linker and recording must
/// exist, and no pipeline may run twice on one recording.
pub(super) fn resolve_tracking(
    section: RawTracking,
    detectors: &[DetectorEntry],
    linkers: &[LinkerEntry],
    recordings: &[RecordingSpec],
) -> Result<TrackingSpec, FieldError> {
    let path = super::path_of(&["tracking"]);
    section
        .scoring
        .validate()
        .map_err(|e| e.under(&super::field(&path, "scoring")))?;
    let list_path = super::field(&path, "evaluations");
    if section.evaluations.is_empty() {
        return Err(FieldError::at(
            &list_path,
            "must list at least one pipeline",
        ));
    }
    let mut evaluations: Vec<TrackingEvaluationSpec> = Vec::new();
    for (index, entry) in section.evaluations.into_iter().enumerate() {
        let entry_path = super::item(&list_path, index);
        super::require_detector(
            detectors,
            &super::field(&entry_path, "detector"),
            &entry.detector,
        )?;
        if !linkers.iter().any(|l| l.name == entry.linker) {
            return Err(FieldError::at(
                &super::field(&entry_path, "linker"),
                format!("`{}` is not a linker of this manifest", entry.linker),
            ));
        }
        if let Some(correction) = entry.bias_correction {
            correction.validate().map_err(|e| e.under(&entry_path))?;
        }
        if let Some(score) = entry.min_score
            && !score.is_finite()
        {
            return Err(FieldError::at(
                &super::field(&entry_path, "min_score"),
                format!("must be a finite number, got {score}"),
            ));
        }
        let recordings_path = super::field(&entry_path, "recordings");
        if entry.recordings.is_empty() {
            return Err(FieldError::at(
                &recordings_path,
                "must list at least one recording",
            ));
        }
        for (position, recording) in entry.recordings.iter().enumerate() {
            let recording_path = super::item(&recordings_path, position);
            let Some(found) = recordings.iter().find(|r| &r.name == recording) else {
                return Err(FieldError::at(
                    &recording_path,
                    format!("`{recording}` is not a recording of this manifest"),
                ));
            };
            let field = &found.params.microscope;
            crate::track::pipeline::check_ensemble_margin(
                section.scoring.ensemble_margin_px,
                field.height,
                field.width,
            )
            .map_err(|e| {
                FieldError::at(
                    &super::field(&super::field(&path, "scoring"), "ensemble_margin_px"),
                    format!("{e}, recording `{recording}`"),
                )
            })?;
            let spec = TrackingEvaluationSpec {
                detector: entry.detector.clone(),
                linker: entry.linker.clone(),
                recording: recording.clone(),
                min_score: entry.min_score,
                bias_correction: entry.bias_correction,
            };
            if evaluations
                .iter()
                .any(|e| e.pipeline() == spec.pipeline() && e.recording == spec.recording)
            {
                return Err(FieldError::at(
                    &recording_path,
                    format!("`{}` already runs on `{recording}`", spec.pipeline()),
                ));
            }
            evaluations.push(spec);
        }
    }
    Ok(TrackingSpec {
        scoring: section.scoring,
        evaluations,
    })
}
