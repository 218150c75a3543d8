//! What a step's content key is the hash of: one typed description per
//! step kind, serialised (as canonical JSON, [`crate::registry::hashing`])
//! together with the artefact kind it makes, from [`ArtefactKind`].
//!
//! Each struct serialises to exactly the JSON object the planner hashed
//! before they were typed (`tests/it/content_keys.rs` pins every key of
//! `experiments/`): a field that is absent from some keys is an `Option`
//! skipped when `None`; one that is `null` in them is an `Option` kept.

use serde::Serialize;

use crate::manifest::DetectorSpec;
use crate::metrics::ScoreReading;
use crate::registry::ArtefactKind;
use crate::sim::SimParams;
use crate::track::pipeline::{LinkerSpec, TrackScoring};

/// A step's description: the kind of artefact it makes beside what the
/// step itself says.
pub(super) trait Describes: Serialize {
    /// The kind of artefact the step makes (its key's `kind`).
    const KIND: ArtefactKind;
}

/// A description with its `kind`, as it is hashed.
#[derive(Serialize)]
pub(super) struct Keyed<'a, T: Describes> {
    kind: ArtefactKind,
    #[serde(flatten)]
    description: &'a T,
}

impl<'a, T: Describes> Keyed<'a, T> {
    pub(super) fn new(description: &'a T) -> Self {
        Keyed {
            kind: T::KIND,
            description,
        }
    }
}

/// Simulating a dataset.
#[derive(Serialize)]
pub(super) struct SimulateDescription<'a> {
    pub code: &'a str,
    pub params: &'a SimParams,
    pub frames: usize,
    pub seed: u64,
}

impl Describes for SimulateDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Dataset;
}

/// Taking some frames of a dataset as a dataset of their own.
#[derive(Serialize)]
pub(super) struct SubsetDescription<'a> {
    pub code: &'a str,
    /// The source dataset's key.
    pub source: &'a str,
    pub frames: usize,
    /// sha256 of the frame list (decimal, comma-separated).
    pub frames_sha256: String,
    /// How the frames were chosen (`{"first": 300}`, a fold, …).
    pub chosen_by: &'a serde_json::Value,
}

impl Describes for SubsetDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Dataset;
}

/// Training a detector.
#[derive(Serialize)]
pub(super) struct TrainDescription<'a> {
    pub code: &'a str,
    pub detector: &'a DetectorSpec,
    /// The training dataset's key.
    pub training: &'a str,
    pub seed: u64,
    /// The validation dataset's key, only when given (models selected on a
    /// split of their training set keep the keys they always had).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub validation: Option<&'a str>,
    /// `"fresh frames only"` for a fold model whose recipe trains on fresh
    /// frames only (since 2026-12-01); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub trains_on: Option<&'static str>,
}

impl Describes for TrainDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Model;
}

/// Running a detector on a dataset.
#[derive(Serialize)]
pub(super) struct LocateDescription<'a> {
    pub code: &'a str,
    pub detector: &'a DetectorSpec,
    /// The dataset's key.
    pub dataset: &'a str,
    /// The model's key (`null` for an untrained detector).
    pub model: Option<&'a str>,
    /// Only for detectors that draw while locating, so that the others keep
    /// the keys they always had.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

impl Describes for LocateDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Predictions;
}

/// The metric's settings in a score's key.
#[derive(Serialize)]
pub(super) struct MetricDescription<'a> {
    pub eps_px: &'a [f64],
    pub keep_curves: bool,
}

/// Scoring predictions against a dataset's truth.
#[derive(Serialize)]
pub(super) struct ScoreDescription<'a> {
    pub code: &'a str,
    /// The dataset's key.
    pub dataset: &'a str,
    /// The predictions' key.
    pub predictions: &'a str,
    pub metric: MetricDescription<'a>,
    pub reading: ScoreReading,
}

impl Describes for ScoreDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Evaluation;
}

/// Simulating a continuous recording.
#[derive(Serialize)]
pub(super) struct RecordingDescription<'a> {
    pub code: &'a str,
    /// [`crate::manifest::RecordingSpec::params_json`].
    pub recording: serde_json::Value,
    pub seed: u64,
}

impl Describes for RecordingDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Dataset;
}

/// Linking a recording's predictions into tracks.
#[derive(Serialize)]
pub(super) struct LinkDescription<'a> {
    pub code: &'a str,
    pub linker: &'a LinkerSpec,
    /// `null` when every prediction is linked.
    pub min_score: Option<f64>,
    /// The recording's key.
    pub recording: &'a str,
    /// The predictions' key.
    pub predictions: &'a str,
}

impl Describes for LinkDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Predictions;
}

/// Scoring tracks against a recording's truth.
#[derive(Serialize)]
pub(super) struct TrackScoreDescription<'a> {
    pub code: &'a str,
    /// The recording's key.
    pub recording: &'a str,
    /// The tracks' key.
    pub tracks: &'a str,
    pub scoring: &'a TrackScoring,
    /// With a bias correction by simulation only: its code version.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bias_correction_code: Option<&'static str>,
    /// With a bias correction by simulation only: its seed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bias_correction_seed: Option<u64>,
}

impl Describes for TrackScoreDescription<'_> {
    const KIND: ArtefactKind = ArtefactKind::Evaluation;
}
