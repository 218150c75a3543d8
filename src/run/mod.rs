//! The orchestrator: executes a [`Plan`] over a [`Registry`], skipping
//! every step whose artefact is already stored intact, and records the run.
//!
//! For every step whose key is stored, the blobs are re-hashed (all at once,
//! in parallel): if they are intact the step is `cached` and its artefact is
//! loaded only if a later step needs it; if a blob is missing or damaged it
//! is reported and the step is `rebuilt`, never used as is. Other steps are
//! `computed`. With `force`, every step is computed and its blobs must come
//! out identical to the stored ones, or the run fails as a check.
//!
//! A run is recorded as `running` before its first step, each step as it
//! finishes, and `done` or `failed` (with the error) at the end; a run whose
//! process dies stays `running` until the next run on the same host marks
//! it `unfinished`.

pub(crate) mod artefacts;
pub(crate) mod calibrate;
mod compute;
pub mod cross_validation;
mod descriptions;
mod details;
mod execution;
pub(crate) mod plan;
pub(crate) mod reproduce;
mod rows;
mod stored;
pub(crate) mod table;
pub(crate) mod test_sets;
pub mod track_recording;

use std::time::Instant;

use anyhow::Context;
use serde::Serialize;

pub use artefacts::Artefact;
pub use compute::subset;
pub use execution::score_rows;
pub use plan::{Action, Plan, Step};
pub use rows::{EmptyFramesRow, EstimatorRow, TrackingRow};
pub use stored::{RecordedTracking, load_artefact, read_blobs, recorded_tracking};

use crate::error::CheckFailed;
use crate::manifest::Manifest;
use crate::registry::hashing::sha256_hex;
use crate::registry::{
    AucRow, CrossValidationPlan, Registry, RunKind, RunStart, RunStatus, StepCounts, StepRecord,
    host_name, utc_now,
};
use execution::Execution;

/// How to run.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Recompute every step and check the results equal the stored ones.
    pub force: bool,
    /// Recorded as the run's kind.
    pub kind: RunKind,
    /// The run this one derives from (e.g. the run being reproduced).
    pub parent_run: Option<String>,
    /// For a cross-validation, its plan (recorded with the run).
    pub cross_validation: Option<CrossValidationPlan>,
}

/// What a run did.
#[derive(Debug, Clone, Serialize)]
pub struct RunOutcome {
    pub run: String,
    pub manifest: String,
    pub status: RunStatus,
    /// The AUC table, one row per (detector, dataset, ε), in plan order.
    pub auc: Vec<AucRow>,
    /// The localisations on empty frames (frames without ground truth),
    /// one row per evaluation of a set that has some, in plan order: a set
    /// of empty frames has no AUC row, only this.
    pub empty_frames: Vec<EmptyFramesRow>,
    /// The tracking pipelines' figures, in plan order.
    pub tracking: Vec<TrackingRow>,
    /// Steps cached, computed, and rebuilt (made again because a stored
    /// blob was missing or damaged).
    #[serde(flatten)]
    pub counts: StepCounts,
    pub steps: Vec<StepRecord>,
    /// Blobs found missing or damaged (and rebuilt).
    pub damaged_blobs: Vec<String>,
    pub seconds: f64,
}

/// A new run id: UTC start time plus 8 hex digits that differ between
/// runs started in the same second (hash of time, process and host).
pub(crate) fn new_run_id() -> String {
    let now = utc_now();
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let counter = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let salt =
        sha256_hex(format!("{nanos}/{}/{}/{counter}", std::process::id(), host_name()).as_bytes());
    // 2026-11-22T23:05:00.123Z → 20261122T230500Z
    let compact: String = now[..19]
        .chars()
        .filter(|c| *c != '-' && *c != ':')
        .collect();
    format!("{compact}Z-{}", &salt[..8])
}

/// Runs `manifest` (its [`Plan::from_manifest`]) on `registry` and records it.
pub(crate) fn run_manifest(
    registry: &mut Registry,
    manifest: &Manifest,
    options: &RunOptions,
) -> anyhow::Result<RunOutcome> {
    let plan = Plan::from_manifest(manifest)?;
    execute(registry, manifest, &plan, options)
}

/// A progress line on standard error, for people watching a terminal.
fn log(message: impl AsRef<str>) {
    crate::progress::note_on_terminal(message.as_ref());
}

/// Executes `plan` (made from `manifest`) on `registry`, recording the run:
/// `running` before the first step, then each step, then `done` or `failed`.
pub fn execute(
    registry: &mut Registry,
    manifest: &Manifest,
    plan: &Plan,
    options: &RunOptions,
) -> anyhow::Result<RunOutcome> {
    let started = Instant::now();
    if registry.is_read_only() {
        refuse_work_on_read_only(registry, plan, options.force)?;
    }
    registry.mark_abandoned_runs()?;
    let run_id = new_run_id();
    record_run_start(registry, &run_id, manifest, plan, options)?;
    let mut execution = Execution::new(run_id.clone());
    let result = execution.execute(registry, plan, options.force);
    let auc = result.as_ref().cloned().unwrap_or_default();
    // Whatever happened, this run computes nothing any more.
    registry.release_claims(&run_id, None)?;
    let (status, error) = verdict(&result, &execution.mismatches);
    registry
        .finish_run(&run_id, status, error.as_deref(), execution.counts, &auc)
        .context("recording the end of the run")?;
    result?;
    if registry.is_read_only() {
        crate::progress::note(format_args!(
            "warning: {} is read-only: every step was served from its cache, but run {run_id} could not be recorded there",
            registry.dir().display()
        ));
    }
    if let Some(error) = error {
        return Err(anyhow::Error::new(CheckFailed(format!(
            "run {run_id}: {error}"
        ))));
    }
    Ok(RunOutcome {
        run: run_id,
        manifest: manifest.source.clone(),
        status,
        auc,
        empty_frames: execution.empty_frames,
        tracking: execution.tracking,
        counts: execution.counts,
        steps: execution.steps,
        damaged_blobs: execution.damaged,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// On a registry that cannot be written, a run can only serve what is
/// stored: refuses (as bad input, before any work) a plan with a step that
/// is not stored intact, or `--force`.
fn refuse_work_on_read_only(registry: &Registry, plan: &Plan, force: bool) -> anyhow::Result<()> {
    let dir = registry.dir().display();
    if force {
        return Err(crate::error::input_error(format!(
            "{dir}: the registry is read-only, so --force cannot store what it recomputes"
        )));
    }
    let stored = stored::check_stored_artefacts(registry, plan)?;
    let missing: Vec<&crate::registry::StepId> = plan
        .steps
        .iter()
        .zip(&stored)
        .filter(|(_, stored)| !matches!(stored, stored::Stored::Intact(..)))
        .map(|(step, _)| &step.id)
        .collect();
    if let Some(first) = missing.first() {
        return Err(crate::error::input_error(format!(
            "{dir}: the registry is read-only and {} of the run's steps are not stored intact there ({first}, …): run on a writable registry (--registry)",
            missing.len()
        )));
    }
    Ok(())
}

/// Records the run as `running`, with its manifest, resolved manifest and
/// seeds, before its first step.
fn record_run_start(
    registry: &mut Registry,
    run_id: &str,
    manifest: &Manifest,
    plan: &Plan,
    options: &RunOptions,
) -> anyhow::Result<()> {
    registry.begin_run(&RunStart {
        id: run_id.to_string(),
        kind: options.kind,
        parent_run: options.parent_run.clone(),
        manifest_name: manifest.name.clone(),
        manifest_path: manifest.source.clone(),
        manifest_text: manifest.text.clone(),
        manifest_sha256: manifest.manifest_sha256.clone(),
        resolved_json: serde_json::to_string(manifest)?,
        seeds_json: serde_json::to_string(&plan.seeds())?,
        forced: options.force,
        cross_validation: options.cross_validation.clone(),
    })
}

/// How the run ended, and the error recorded with it: failed on an error,
/// or (with `--force`) when a recomputed artefact differs from the stored
/// one; done otherwise.
fn verdict(
    result: &anyhow::Result<Vec<AucRow>>,
    mismatches: &[String],
) -> (RunStatus, Option<String>) {
    match result {
        Err(e) => (RunStatus::Failed, Some(format!("{e:#}"))),
        Ok(_) if mismatches.is_empty() => (RunStatus::Done, None),
        Ok(_) => (
            RunStatus::Failed,
            Some(format!(
                "--force: recomputed artefacts differ from the stored ones: {}",
                mismatches.join("; ")
            )),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn subsets_are_artefacts_of_their_own_and_renumber_frames() {
        let text = "name: t\nseed: 9\ndatasets:\n  all:\n    frames: 12\n    emitters: 2\n";
        let manifest = crate::manifest::parse(text, "t.yaml").unwrap();
        let mut plan = Plan::from_manifest(&manifest).unwrap();
        let fold = plan
            .add_subset(
                0,
                "all-fold-1",
                vec![7, 2, 11],
                serde_json::json!({"fold": 1}),
            )
            .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::open(dir.path()).unwrap();
        let first = execute(&mut registry, &manifest, &plan, &RunOptions::default()).unwrap();
        assert_eq!(first.counts.computed, 2);
        let again = execute(&mut registry, &manifest, &plan, &RunOptions::default()).unwrap();
        assert_eq!(again.counts.cached, 2);

        let all = load_artefact(&registry, &plan.steps[0].key).unwrap();
        let part = load_artefact(&registry, &plan.steps[fold].key).unwrap();
        let (all, part) = (all.dataset().unwrap(), part.dataset().unwrap());
        assert_eq!(part.frames.n, 3);
        for (new, old) in [(0, 7), (1, 2), (2, 11)] {
            assert_eq!(part.frames.frame(new), all.frames.frame(old));
            let theirs: Vec<_> = all.truth.iter().filter(|r| r.frame == old).collect();
            let ours: Vec<_> = part.truth.iter().filter(|r| r.frame == new).collect();
            assert_eq!(ours.len(), 2);
            for (a, b) in ours.iter().zip(theirs) {
                assert_eq!((a.x, a.y), (b.x, b.y));
            }
        }
        // Another choice of frames is another artefact.
        let other = plan
            .add_subset(0, "all-fold-2", vec![7, 2], serde_json::json!({"fold": 2}))
            .unwrap();
        assert_ne!(plan.steps[other].key, plan.steps[fold].key);
        assert!(subset(all, &[12]).is_err());
        assert!(subset(all, &[1, 1]).is_err());
    }
}
