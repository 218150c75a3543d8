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

pub mod artefacts;
pub mod calibrate;
pub mod cross_validation;
pub mod plan;
pub mod reproduce;
pub mod table;

use std::collections::HashMap;
use std::io::IsTerminal;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use rayon::prelude::*;
use serde::Serialize;

pub use artefacts::Artefact;
pub use plan::{Action, Plan, Step};

use crate::error::CheckFailed;
use crate::manifest::{DetectorSpec, Manifest};
use crate::registry::hashing::sha256_hex;
use crate::registry::{
    ArtefactDetails, AucRow, BlobRef, BlobState, CrossValidationPlan, NewArtefact, Registry,
    RunKind, RunStart, RunStatus, StepCounts, StepOutcome, StepRecord, host_name, utc_now,
};

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
pub fn new_run_id() -> String {
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
pub fn run_manifest(
    registry: &mut Registry,
    manifest: &Manifest,
    options: &RunOptions,
) -> anyhow::Result<RunOutcome> {
    let plan = Plan::from_manifest(manifest)?;
    execute(registry, manifest, &plan, options)
}

fn log(message: impl AsRef<str>) {
    if std::io::stderr().is_terminal() {
        eprintln!("{}", message.as_ref());
    }
}

/// Executes `plan` (made from `manifest`) on `registry`, recording the run.
pub fn execute(
    registry: &mut Registry,
    manifest: &Manifest,
    plan: &Plan,
    options: &RunOptions,
) -> anyhow::Result<RunOutcome> {
    let started = Instant::now();
    registry.mark_abandoned_runs()?;
    let run_id = new_run_id();
    let resolved = serde_json::to_string(manifest)?;
    registry.begin_run(&RunStart {
        id: run_id.clone(),
        kind: options.kind,
        parent_run: options.parent_run.clone(),
        manifest_name: manifest.name.clone(),
        manifest_path: manifest.source.clone(),
        manifest_text: manifest.text.clone(),
        manifest_sha256: manifest.manifest_sha256.clone(),
        resolved_json: resolved,
        seeds_json: serde_json::to_string(&plan.seeds())?,
        forced: options.force,
        cross_validation: options.cross_validation.clone(),
    })?;
    let mut state = Execution {
        run_id: run_id.clone(),
        steps: Vec::new(),
        damaged: Vec::new(),
        mismatches: Vec::new(),
        counts: StepCounts::default(),
    };
    let result = state.execute(registry, plan, options.force);
    let auc = match &result {
        Ok(auc) => auc.clone(),
        Err(_) => Vec::new(),
    };
    let (status, error) = match (&result, state.mismatches.is_empty()) {
        (Ok(_), true) => (RunStatus::Done, None),
        (Ok(_), false) => (
            RunStatus::Failed,
            Some(format!(
                "--force: recomputed artefacts differ from the stored ones: {}",
                state.mismatches.join("; ")
            )),
        ),
        (Err(e), _) => (RunStatus::Failed, Some(format!("{e:#}"))),
    };
    registry
        .finish_run(&run_id, status, error.as_deref(), state.counts, &auc)
        .context("recording the end of the run")?;
    result?;
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
        counts: state.counts,
        steps: state.steps,
        damaged_blobs: state.damaged,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// What a stored artefact's blobs looked like when checked.
enum Stored {
    Absent,
    Intact(Vec<BlobRef>, f64),
    Damaged(Vec<String>),
}

struct Execution {
    run_id: String,
    steps: Vec<StepRecord>,
    damaged: Vec<String>,
    mismatches: Vec<String>,
    counts: StepCounts,
}

impl Execution {
    fn execute(
        &mut self,
        registry: &mut Registry,
        plan: &Plan,
        force: bool,
    ) -> anyhow::Result<Vec<AucRow>> {
        // Check every stored artefact's blobs at once, in parallel.
        let stored_blobs: Vec<Option<Vec<BlobRef>>> = plan
            .steps
            .iter()
            .map(|step| Ok(registry.artefact(&step.key)?.map(|a| a.blobs)))
            .collect::<anyhow::Result<_>>()?;
        let store = registry.blobs().clone();
        let stored: Vec<Stored> = stored_blobs
            .into_par_iter()
            .map(|blobs| -> anyhow::Result<Stored> {
                let Some(blobs) = blobs else {
                    return Ok(Stored::Absent);
                };
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
            })
            .collect::<anyhow::Result<_>>()?;

        // When each artefact is last needed, to free memory early.
        let mut last_use = vec![0usize; plan.steps.len()];
        for (index, step) in plan.steps.iter().enumerate() {
            for input in step.inputs() {
                last_use[input] = index;
            }
        }
        let mut loaded: HashMap<usize, Artefact> = HashMap::new();
        let mut auc = Vec::new();
        for (index, step) in plan.steps.iter().enumerate() {
            let clock = Instant::now();
            let mut verify_seconds = 0.0;
            let (outcome, blobs, detail, artefact) = match (&stored[index], force) {
                (Stored::Intact(blobs, seconds), false) => {
                    self.counts.add(StepOutcome::Cached);
                    log(format!("cached    {}", step.id));
                    verify_seconds = *seconds;
                    (
                        StepOutcome::Cached,
                        blobs.clone(),
                        Some(format!("verified in {seconds:.3} s")),
                        None,
                    )
                }
                (existing, _) => {
                    let replace = match existing {
                        Stored::Damaged(problems) => {
                            for problem in problems {
                                let message =
                                    format!("{} ({}): {problem}; rebuilding it", step.id, step.key);
                                eprintln!("warning: {message}");
                                self.damaged.push(message);
                            }
                            true
                        }
                        _ => false,
                    };
                    let artefact = compute(registry, plan, index, &mut loaded)?;
                    let encoded = artefact.encode()?;
                    let mut blobs = Vec::with_capacity(encoded.len());
                    for (role, bytes) in &encoded {
                        blobs.push(BlobRef {
                            role: role.clone(),
                            sha256: sha256_hex(bytes),
                        });
                    }
                    // With --force the artefact may be stored intact: the
                    // recomputation must then match it, and a mismatch keeps
                    // the stored one (it is reported, and the run fails).
                    let mut detail = None;
                    let mut differs = false;
                    if let Stored::Intact(previous, _) = existing {
                        let mut ours = blobs.clone();
                        ours.sort_by(|a, b| a.role.cmp(&b.role));
                        differs = *previous != ours;
                        if differs {
                            let message = format!(
                                "{} ({}): recomputed blobs {:?} differ from the stored {:?}",
                                step.id, step.key, ours, previous
                            );
                            eprintln!("error: {message}");
                            self.mismatches.push(message);
                            detail = Some("recomputed: DIFFERS from the stored artefact".into());
                        } else {
                            detail = Some("recomputed: identical to the stored artefact".into());
                        }
                    }
                    if !differs {
                        for (_, bytes) in &encoded {
                            store.put(bytes)?;
                        }
                        registry.record_artefact(
                            &NewArtefact {
                                key: step.key.clone(),
                                kind: step.kind,
                                name: step.name.clone(),
                                spec: step.spec.clone(),
                                code_version: step.code_version.clone(),
                                run_id: Some(self.run_id.clone()),
                                compute_seconds: clock.elapsed().as_secs_f64(),
                                blobs: blobs.clone(),
                                details: details(plan, index, &artefact),
                            },
                            replace,
                        )?;
                    }
                    let outcome = if replace {
                        StepOutcome::Rebuilt
                    } else {
                        StepOutcome::Computed
                    };
                    self.counts.add(outcome);
                    log(format!(
                        "{outcome:<9} {} in {:.2} s",
                        step.id,
                        clock.elapsed().as_secs_f64()
                    ));
                    (outcome, blobs, detail, Some(artefact))
                }
            };
            if let Action::Score {
                detector,
                dataset_name,
                diffusion,
                ..
            } = &step.action
            {
                let score = match &artefact {
                    Some(artefact) => artefact.evaluation()?.clone(),
                    None => Arc::new(artefacts::decode_score(&read_blobs(registry, &blobs)?)?),
                };
                for per_eps in &score.per_eps {
                    auc.push(AucRow {
                        detector: detector.clone(),
                        dataset: dataset_name.clone(),
                        diffusion: *diffusion,
                        eps_px: per_eps.eps_px,
                        auc: per_eps.auc,
                        evaluation_key: step.key.clone(),
                    });
                }
            }
            if let Some(artefact) = artefact
                && last_use[index] > index
            {
                loaded.insert(index, artefact);
            }
            loaded.retain(|&i, _| last_use[i] > index);
            let record = StepRecord {
                ordinal: index,
                step: step.id.clone(),
                kind: step.kind,
                artefact_key: step.key.clone(),
                outcome,
                // A cached step's time is the re-hashing of its blobs.
                seconds: clock.elapsed().as_secs_f64() + verify_seconds,
                blobs,
                detail,
            };
            registry.record_step(&self.run_id, &record)?;
            self.steps.push(record);
        }
        Ok(auc)
    }
}

/// Reads and re-hashes an artefact's blobs; a missing or damaged blob is an
/// error naming it.
pub fn read_blobs(
    registry: &Registry,
    blobs: &[BlobRef],
) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
    blobs
        .iter()
        .map(|blob| match registry.blobs().get(&blob.sha256)? {
            Ok(bytes) => Ok((blob.role.clone(), bytes)),
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
    Ok(match stored.kind {
        crate::registry::ArtefactKind::Dataset => {
            Artefact::Dataset(Arc::new(artefacts::decode_dataset(&blobs)?))
        }
        crate::registry::ArtefactKind::Model => Artefact::Model(Arc::new(
            blobs.into_iter().next().map(|(_, b)| b).unwrap_or_default(),
        )),
        crate::registry::ArtefactKind::Predictions => {
            Artefact::Predictions(Arc::new(artefacts::decode_predictions(&blobs)?))
        }
        crate::registry::ArtefactKind::Evaluation => {
            Artefact::Evaluation(Arc::new(artefacts::decode_score(&blobs)?))
        }
    })
}

/// The artefact of step `index`, from memory or from the registry.
fn input(
    registry: &Registry,
    plan: &Plan,
    index: usize,
    loaded: &mut HashMap<usize, Artefact>,
) -> anyhow::Result<Artefact> {
    if let Some(artefact) = loaded.get(&index) {
        return Ok(artefact.clone());
    }
    let step = &plan.steps[index];
    let stored = registry
        .artefact(&step.key)?
        .with_context(|| format!("{} ({}) is not in the registry", step.id, step.key))?;
    let blobs =
        read_blobs(registry, &stored.blobs).with_context(|| format!("reading {}", step.id))?;
    let artefact = match step.action {
        Action::Simulate { .. } | Action::Subset { .. } => {
            Artefact::Dataset(Arc::new(artefacts::decode_dataset(&blobs)?))
        }
        Action::Train { .. } => Artefact::Model(Arc::new(
            blobs.into_iter().next().map(|(_, b)| b).unwrap_or_default(),
        )),
        Action::Locate { .. } => {
            Artefact::Predictions(Arc::new(artefacts::decode_predictions(&blobs)?))
        }
        Action::Score { .. } => Artefact::Evaluation(Arc::new(artefacts::decode_score(&blobs)?)),
    };
    loaded.insert(index, artefact.clone());
    Ok(artefact)
}

/// Makes the artefact of step `index`.
fn compute(
    registry: &Registry,
    plan: &Plan,
    index: usize,
    loaded: &mut HashMap<usize, Artefact>,
) -> anyhow::Result<Artefact> {
    let step = &plan.steps[index];
    Ok(match &step.action {
        Action::Simulate { dataset } => {
            let progress = crate::progress::bar(dataset.frames as u64, &dataset.name);
            let made =
                crate::sim::simulate(&dataset.params, dataset.seed, 0..dataset.frames, &progress)
                    .with_context(|| format!("simulating dataset {}", dataset.name))?;
            progress.finish_and_clear();
            Artefact::Dataset(Arc::new(made))
        }
        Action::Subset { source, frames } => {
            let source = input(registry, plan, *source, loaded)?;
            Artefact::Dataset(Arc::new(subset(source.dataset()?, frames)?))
        }
        Action::Train {
            detector,
            training,
            validation,
        } => {
            let training_set = input(registry, plan, *training, loaded)?;
            let training_set = training_set.dataset()?;
            let validation_set = match validation {
                Some(v) => Some(input(registry, plan, *v, loaded)?),
                None => None,
            };
            match &detector.spec {
                DetectorSpec::CrockerGrier(_) => {
                    anyhow::bail!("{}: crocker_grier is not a trained detector", detector.name)
                }
                DetectorSpec::Cnn(spec) => {
                    let progress = crate::progress::bar(0, &format!("train {}", detector.name));
                    let fresh_frames = root_dataset(plan, *training).map(|d| &d.params);
                    let model = match &validation_set {
                        Some(validation_set) => crate::detect::cnn::train_selecting_on(
                            &spec.architecture,
                            &spec.training,
                            training_set,
                            crate::detect::cnn::ValidationSet {
                                dataset: validation_set.dataset()?,
                                score: &crate::metrics::paper_aucs,
                            },
                            fresh_frames,
                            detector.seed,
                            &progress,
                        ),
                        None => crate::detect::cnn::train(
                            &spec.architecture,
                            &spec.training,
                            training_set,
                            fresh_frames,
                            detector.seed,
                            &crate::metrics::paper_aucs,
                            &progress,
                        ),
                    }
                    .with_context(|| format!("training {}", detector.name))?;
                    progress.finish_and_clear();
                    Artefact::Model(Arc::new(model.to_bytes()?))
                }
            }
        }
        Action::Locate {
            detector,
            dataset,
            model,
        } => {
            let dataset = input(registry, plan, *dataset, loaded)?;
            let frames = &dataset.dataset()?.frames;
            let model = match model {
                Some(m) => Some(input(registry, plan, *m, loaded)?),
                None => None,
            };
            let progress = crate::progress::bar(frames.n as u64, &step.name);
            let predictions = match &detector.spec {
                DetectorSpec::CrockerGrier(params) => {
                    let features =
                        crate::detect::crocker_grier::locate_stack(frames, params, &progress)
                            .with_context(|| format!("locating with {}", detector.name))?;
                    crate::detect::crocker_grier::to_predictions(&features)
                }
                DetectorSpec::Cnn(_) => {
                    let bytes = model
                        .as_ref()
                        .context("the cnn detector needs its trained model")?
                        .model()?;
                    crate::detect::cnn::TrainedCnn::from_bytes(bytes)?
                        .locate(frames, &progress)
                        .with_context(|| format!("locating with {}", detector.name))?
                }
            };
            progress.finish_and_clear();
            Artefact::Predictions(Arc::new(predictions))
        }
        Action::Score {
            dataset,
            predictions,
            metrics,
            ..
        } => {
            let dataset = input(registry, plan, *dataset, loaded)?;
            let dataset = dataset.dataset()?;
            let predictions = input(registry, plan, *predictions, loaded)?;
            let score = crate::metrics::score(
                predictions.predictions()?,
                &dataset.truth,
                dataset.frames.n,
                &metrics.eps_px,
                metrics.keep_curves,
            )
            .with_context(|| format!("scoring {}", step.name))?;
            Artefact::Evaluation(Arc::new(score))
        }
    })
}

/// The simulated dataset step `index` comes from (itself, or the source of
/// a subset).
fn root_dataset(plan: &Plan, mut index: usize) -> Option<&crate::manifest::DatasetSpec> {
    while let Action::Subset { source, .. } = &plan.steps[index].action {
        index = *source;
    }
    match &plan.steps[index].action {
        Action::Simulate { dataset } => Some(dataset),
        _ => None,
    }
}

/// Frames `frames` of `source` (renumbered 0, 1, … in the given order) and
/// their truth rows.
pub fn subset(
    source: &crate::types::Dataset,
    frames: &[usize],
) -> anyhow::Result<crate::types::Dataset> {
    let stack = &source.frames;
    let mut data = Vec::with_capacity(frames.len() * stack.frame_len());
    let mut position = vec![None; stack.n];
    for (new, &old) in frames.iter().enumerate() {
        anyhow::ensure!(
            old < stack.n,
            "subset: frame {old} of a {}-frame dataset",
            stack.n
        );
        anyhow::ensure!(position[old].is_none(), "subset: frame {old} twice");
        position[old] = Some(new);
        data.extend_from_slice(stack.frame(old));
    }
    let mut truth: Vec<crate::types::TruthRow> = source
        .truth
        .iter()
        .filter_map(|row| {
            position.get(row.frame).copied().flatten().map(|new| {
                let mut row = *row;
                row.frame = new;
                row
            })
        })
        .collect();
    // Frame order, emitters in their original order within a frame.
    truth.sort_by_key(|row| row.frame);
    Ok(crate::types::Dataset {
        frames: crate::types::FrameStack::from_vec(frames.len(), stack.height, stack.width, data)?,
        truth,
    })
}

/// The typed registry row of step `index`'s new artefact.
fn details(plan: &Plan, index: usize, artefact: &Artefact) -> ArtefactDetails {
    let step = &plan.steps[index];
    match (&step.action, artefact) {
        (Action::Simulate { dataset }, _) => ArtefactDetails::Dataset {
            frames: dataset.frames,
            height: dataset.params.height,
            width: dataset.params.width,
            seed: dataset.seed,
            diffusion: dataset.fixed_diffusion(),
            brightness: dataset.params.brightness,
            params_json: serde_json::to_string(&dataset.params).unwrap_or_default(),
        },
        (Action::Subset { source, frames }, _) => {
            let root = root_dataset(plan, *source);
            let (seed, params) = (root.map_or(0, |d| d.seed), root.map(|d| &d.params));
            ArtefactDetails::Dataset {
                frames: frames.len(),
                height: params.map_or(0, |p| p.height),
                width: params.map_or(0, |p| p.width),
                seed,
                diffusion: None,
                brightness: params.map_or(0.0, |p| p.brightness),
                params_json: step.spec.clone(),
            }
        }
        (
            Action::Train {
                detector, training, ..
            },
            _,
        ) => ArtefactDetails::Model {
            detector: detector.name.clone(),
            detector_kind: detector.spec.kind().to_string(),
            training_dataset_key: plan.steps[*training].key.clone(),
            seed: detector.seed,
        },
        (
            Action::Locate {
                detector,
                dataset,
                model,
            },
            artefact,
        ) => ArtefactDetails::Predictions {
            detector: detector.name.clone(),
            dataset_key: plan.steps[*dataset].key.clone(),
            model_key: model.map(|m| plan.steps[m].key.clone()),
            count: artefact.predictions().map(|p| p.len()).unwrap_or(0),
        },
        (
            Action::Score {
                detector,
                dataset_name,
                dataset,
                predictions,
                ..
            },
            artefact,
        ) => {
            let score = artefact.evaluation().ok();
            ArtefactDetails::Evaluation {
                detector: detector.clone(),
                dataset: dataset_name.clone(),
                dataset_key: plan.steps[*dataset].key.clone(),
                predictions_key: plan.steps[*predictions].key.clone(),
                rmse_top_px: score.and_then(|s| s.rmse_top_px),
                fraction_without_prediction: score
                    .map(|s| s.fraction_without_prediction)
                    .unwrap_or(0.0),
                auc: score
                    .map(|s| {
                        s.per_eps
                            .iter()
                            .map(|e| (e.eps_px, e.auc, e.true_positives, e.false_positives))
                            .collect()
                    })
                    .unwrap_or_default(),
            }
        }
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
