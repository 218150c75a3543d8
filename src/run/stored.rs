//! Artefacts already in the registry: checking their blobs before a run,
//! and reading them back.

use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use rayon::prelude::*;

use super::artefacts::{self, Artefact};
use super::plan::{Action, Plan, Step};
use super::rows::TrackingRow;
use crate::registry::{
    ArtefactKind, BlobRef, BlobRole, BlobState, BlobStore, Registry, RunRecord, StepId,
};
use crate::track::pipeline::TrackEvaluation;

/// What a step's stored artefact looked like when its blobs were checked.
pub(super) enum Stored {
    /// Nothing stored under the step's key.
    Absent,
    /// Stored, every blob present with the bytes its hash names; with the
    /// seconds the re-hashing took.
    Intact(Vec<BlobRef>, f64),
    /// Stored, but blobs are missing or damaged: one line per problem.
    Damaged(Vec<String>),
}

/// Checks the stored artefact of every step of `plan`, re-hashing all their
/// blobs at once, in parallel.
pub(super) fn check_stored_artefacts(
    registry: &Registry,
    plan: &Plan,
) -> anyhow::Result<Vec<Stored>> {
    let stored_blobs: Vec<Option<Vec<BlobRef>>> = plan
        .steps
        .iter()
        .map(|step| Ok(registry.artefact(&step.key)?.map(|a| a.blobs)))
        .collect::<anyhow::Result<_>>()?;
    let store = registry.blobs();
    stored_blobs
        .into_par_iter()
        .map(|blobs| match blobs {
            None => Ok(Stored::Absent),
            Some(blobs) => check_blobs(store, blobs),
        })
        .collect()
}

/// Checks the stored artefact of one key (as [`check_stored_artefacts`]).
pub(super) fn check_stored_artefact(registry: &Registry, key: &str) -> anyhow::Result<Stored> {
    match registry.artefact(key)? {
        None => Ok(Stored::Absent),
        Some(artefact) => check_blobs(registry.blobs(), artefact.blobs),
    }
}

/// Re-hashes one artefact's blobs.
fn check_blobs(store: &BlobStore, blobs: Vec<BlobRef>) -> anyhow::Result<Stored> {
    let clock = Instant::now();
    let mut problems = Vec::new();
    for blob in &blobs {
        match store.check(&blob.sha256)? {
            BlobState::Intact => {}
            BlobState::Missing => problems.push(format!(
                "{} blob {} is missing ({})",
                blob.role,
                blob.sha256,
                store.path(&blob.sha256).display()
            )),
            BlobState::Damaged { actual } => problems.push(format!(
                "{} blob {} is damaged: its bytes hash to {actual} ({})",
                blob.role,
                blob.sha256,
                store.path(&blob.sha256).display()
            )),
        }
    }
    Ok(if problems.is_empty() {
        Stored::Intact(blobs, clock.elapsed().as_secs_f64())
    } else {
        Stored::Damaged(problems)
    })
}

/// Reads and re-hashes an artefact's blobs; a missing or damaged blob is an
/// error naming it.
pub fn read_blobs(
    registry: &Registry,
    blobs: &[BlobRef],
) -> anyhow::Result<Vec<(BlobRole, Vec<u8>)>> {
    blobs
        .iter()
        .map(|blob| match registry.blobs().get(&blob.sha256)? {
            Ok(bytes) => Ok((blob.role, bytes)),
            Err(state) => anyhow::bail!(
                "{} blob {} ({}) is {:?}; it will be rebuilt by the next run",
                blob.role,
                blob.sha256,
                registry.blobs().path(&blob.sha256).display(),
                state
            ),
        })
        .collect()
}

/// Loads the artefact stored under `key` (blobs re-hashed; a damaged or
/// missing blob is an error), decoded by its kind. For reports and other
/// readers of past runs: `registry.run_record(id)?.steps` gives the keys.
pub fn load_artefact(registry: &Registry, key: &str) -> anyhow::Result<Artefact> {
    let stored = registry
        .artefact(key)?
        .with_context(|| format!("no artefact {key} in {}", registry.dir().display()))?;
    let blobs = read_blobs(registry, &stored.blobs)
        .with_context(|| format!("reading {} {}", stored.kind.as_str(), stored.name))?;
    decode(stored.kind, blobs)
}

/// A tracking pipeline's evaluation in a recorded run: its row of the
/// run's tracking tables and the whole evaluation (with the per-track
/// estimates).
#[derive(Debug, Clone)]
pub struct RecordedTracking {
    pub row: TrackingRow,
    pub evaluation: Arc<TrackEvaluation>,
}

/// The tracking evaluations of recorded run `record`, in step order: every
/// `evaluation/PIPELINE@RECORDING` step whose `score.json` is a
/// [`TrackEvaluation`] (told apart by content, as a run tells it). For
/// reports and `registry show`, which rebuild the tables `scanloc run`
/// printed; an evaluation with AUC rows is no tracking evaluation and is
/// not read.
pub fn recorded_tracking(
    registry: &Registry,
    record: &RunRecord,
) -> anyhow::Result<Vec<RecordedTracking>> {
    let mut seen: Vec<&str> = record
        .auc
        .iter()
        .map(|row| row.evaluation_key.as_str())
        .collect();
    let mut found = Vec::new();
    for step in &record.steps {
        let StepId::Evaluation { detector, dataset } = &step.step else {
            continue;
        };
        if seen.contains(&step.artefact_key.as_str()) {
            continue;
        }
        seen.push(&step.artefact_key);
        if let Artefact::TrackEvaluation(evaluation) = load_artefact(registry, &step.artefact_key)?
        {
            found.push(RecordedTracking {
                row: TrackingRow::new(detector, dataset, &step.artefact_key, &evaluation),
                evaluation,
            });
        }
    }
    Ok(found)
}

/// The artefact of step `index` of `plan`, read from the registry.
pub(super) fn load_step_artefact(
    registry: &Registry,
    plan: &Plan,
    index: usize,
) -> anyhow::Result<Artefact> {
    let step = &plan.steps[index];
    let stored = registry
        .artefact(&step.key)?
        .with_context(|| format!("{} ({}) is not in the registry", step.id, step.key))?;
    let blobs =
        read_blobs(registry, &stored.blobs).with_context(|| format!("reading {}", step.id))?;
    decode_step(step, blobs)
}

/// The artefact of `step` from its blobs: the step's action says which of
/// the formats sharing its registry kind they hold.
pub(super) fn decode_step(
    step: &Step,
    blobs: Vec<(BlobRole, Vec<u8>)>,
) -> anyhow::Result<Artefact> {
    Ok(match step.action {
        Action::SimulateRecording { .. } => {
            Artefact::Recording(Arc::new(artefacts::decode_recording(&blobs)?))
        }
        Action::Link { .. } => Artefact::Tracks(Arc::new(artefacts::decode_tracks(&blobs)?)),
        Action::ScoreTracks { .. } => {
            Artefact::TrackEvaluation(Arc::new(artefacts::decode_track_evaluation(&blobs)?))
        }
        _ => decode_plain(step.kind(), blobs)?,
    })
}

/// An artefact of kind `kind` from its blobs, known by its key alone.
fn decode(kind: ArtefactKind, blobs: Vec<(BlobRole, Vec<u8>)>) -> anyhow::Result<Artefact> {
    // Recordings, tracks and tracking evaluations share the registry's
    // kinds with datasets, predictions and evaluations; without the step
    // that made them, their formats tell them apart.
    Ok(match kind {
        ArtefactKind::Dataset if artefacts::holds_recording(&blobs) => {
            Artefact::Recording(Arc::new(artefacts::decode_recording(&blobs)?))
        }
        ArtefactKind::Predictions if artefacts::holds_tracks(&blobs) => {
            Artefact::Tracks(Arc::new(artefacts::decode_tracks(&blobs)?))
        }
        ArtefactKind::Evaluation if artefacts::holds_track_evaluation(&blobs) => {
            Artefact::TrackEvaluation(Arc::new(artefacts::decode_track_evaluation(&blobs)?))
        }
        _ => decode_plain(kind, blobs)?,
    })
}

/// A dataset, model, predictions or evaluation (of the AUC) from its blobs.
fn decode_plain(kind: ArtefactKind, blobs: Vec<(BlobRole, Vec<u8>)>) -> anyhow::Result<Artefact> {
    Ok(match kind {
        ArtefactKind::Dataset => Artefact::Dataset(Arc::new(artefacts::decode_dataset(&blobs)?)),
        ArtefactKind::Model => Artefact::Model(Arc::new(
            blobs.into_iter().next().map(|(_, b)| b).unwrap_or_default(),
        )),
        ArtefactKind::Predictions => {
            Artefact::Predictions(Arc::new(artefacts::decode_predictions(&blobs)?))
        }
        ArtefactKind::Evaluation => {
            Artefact::Evaluation(Arc::new(artefacts::decode_score(&blobs)?))
        }
    })
}
