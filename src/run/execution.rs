//! The step loop of a run: each step's artefact reused if stored intact,
//! otherwise computed and stored (or, with `--force`, compared with the
//! stored one); the AUC rows and empty-frame figures of evaluations
//! collected; every step recorded.

use std::time::Instant;

use super::artefacts::Artefact;
use super::compute::{LoadedArtefacts, compute};
use super::details::details;
use super::log;
use super::plan::{Action, Plan, Step};
use super::rows::{EmptyFramesRow, TrackingRow};
use super::stored::{
    Stored, check_stored_artefact, check_stored_artefacts, decode_step, read_blobs,
};
use crate::metrics::Score;
use crate::registry::hashing::sha256_hex;
use crate::registry::{
    AucRow, BlobRef, BlobRole, NewArtefact, Registry, StepCounts, StepOutcome, StepRecord,
};

/// How often a run waiting for another's step looks again.
const CLAIM_POLL: std::time::Duration = std::time::Duration::from_millis(200);

/// What a run has done so far.
pub(super) struct Execution {
    pub run_id: String,
    pub steps: Vec<StepRecord>,
    /// One line per missing or damaged blob found (its step was rebuilt).
    pub damaged: Vec<String>,
    /// With `--force`: one line per recomputed artefact that differs from
    /// the stored one.
    pub mismatches: Vec<String>,
    pub counts: StepCounts,
    /// The empty-frame figures of the evaluations so far, in plan order.
    pub empty_frames: Vec<EmptyFramesRow>,
    /// The tracking pipelines' figures so far, in plan order.
    pub tracking: Vec<TrackingRow>,
}

/// One step done: how, with which blobs, and its artefact if it was made
/// (a cached artefact is not loaded unless a later step reads it).
struct StepDone {
    outcome: StepOutcome,
    blobs: Vec<BlobRef>,
    detail: Option<String>,
    artefact: Option<Artefact>,
    /// Time spent re-hashing a cached artefact's blobs before the loop.
    verify_seconds: f64,
}

/// With `--force`, how a recomputed artefact compares with the intact one
/// already stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Recomputed {
    Identical,
    Differs,
}

impl Recomputed {
    /// What the step's record says about it.
    fn detail(self) -> &'static str {
        match self {
            Recomputed::Identical => "recomputed: identical to the stored artefact",
            Recomputed::Differs => "recomputed: DIFFERS from the stored artefact",
        }
    }
}

impl Execution {
    pub(super) fn new(run_id: String) -> Self {
        Self {
            run_id,
            steps: Vec::new(),
            damaged: Vec::new(),
            mismatches: Vec::new(),
            counts: StepCounts::default(),
            empty_frames: Vec::new(),
            tracking: Vec::new(),
        }
    }

    /// Runs every step of `plan` in order; returns the AUC table.
    pub(super) fn execute(
        &mut self,
        registry: &mut Registry,
        plan: &Plan,
        force: bool,
    ) -> anyhow::Result<Vec<AucRow>> {
        let stored = check_stored_artefacts(registry, plan)?;
        let mut loaded = LoadedArtefacts::new(plan);
        let mut auc = Vec::new();
        for (index, step) in plan.steps.iter().enumerate() {
            let clock = Instant::now();
            let done = match (&stored[index], force) {
                (Stored::Intact(blobs, seconds), false) => self.reuse(step, blobs, *seconds),
                (Stored::Absent, false) => {
                    // Another run may be computing it: wait, then reuse.
                    match self.claim(registry, step)? {
                        Stored::Intact(blobs, seconds) => {
                            registry.release_claims(&self.run_id, Some(&step.key))?;
                            self.reuse(step, &blobs, seconds)
                        }
                        now => {
                            let made = self.make(registry, plan, index, &now, &mut loaded, clock);
                            registry.release_claims(&self.run_id, Some(&step.key))?;
                            made?
                        }
                    }
                }
                (stored, _) => self.make(registry, plan, index, stored, &mut loaded, clock)?,
            };
            match scored(registry, step, &done)? {
                Some(Artefact::Evaluation(score)) => {
                    auc.extend(score_rows(plan, step, &score));
                    self.empty_frames.extend(empty_frames_row(step, &score));
                }
                Some(Artefact::TrackEvaluation(evaluation)) => {
                    self.tracking.extend(TrackingRow::of(step, &evaluation));
                }
                _ => {}
            }
            if let Some(artefact) = &done.artefact {
                loaded.keep_if_read_later(index, artefact.clone());
            }
            loaded.drop_unread_after(index);
            self.record_step(registry, index, step, done, clock)?;
        }
        Ok(auc)
    }

    /// Claims `step` for this run, first waiting while a live run on this
    /// host computes it (saying whose claim it waits for), and returns what
    /// is stored under its key once the claim is ours.
    fn claim(&mut self, registry: &mut Registry, step: &Step) -> anyhow::Result<Stored> {
        let mut waited = false;
        while let Some(holder) = registry.claim_step(&step.key, &self.run_id)? {
            if !waited {
                crate::progress::note(format_args!(
                    "waiting for {}: run {} (pid {} on {}) is computing it",
                    step.id, holder.run_id, holder.pid, holder.host
                ));
                waited = true;
            }
            std::thread::sleep(CLAIM_POLL);
        }
        check_stored_artefact(registry, &step.key)
    }

    /// A step whose artefact is stored intact: nothing to do.
    fn reuse(&mut self, step: &Step, blobs: &[BlobRef], verify_seconds: f64) -> StepDone {
        self.counts.add(StepOutcome::Cached);
        log(format!("cached    {}", step.id));
        StepDone {
            outcome: StepOutcome::Cached,
            blobs: blobs.to_vec(),
            detail: Some(format!("verified in {verify_seconds:.3} s")),
            artefact: None,
            verify_seconds,
        }
    }

    /// Computes step `index`'s artefact and stores it, unless `--force`
    /// recomputed an intact stored artefact and got different blobs (then
    /// the stored one is kept and the mismatch reported).
    fn make(
        &mut self,
        registry: &mut Registry,
        plan: &Plan,
        index: usize,
        stored: &Stored,
        loaded: &mut LoadedArtefacts,
        clock: Instant,
    ) -> anyhow::Result<StepDone> {
        let step = &plan.steps[index];
        let replace = match stored {
            Stored::Damaged(problems) => {
                self.report_damage(step, problems);
                true
            }
            Stored::Absent | Stored::Intact(..) => false,
        };
        let artefact = compute(registry, plan, index, loaded)?;
        let encoded = artefact.encode()?;
        let blobs = blob_refs(&encoded);
        // With --force the artefact may be stored intact: the recomputation
        // must then match it, and a mismatch keeps the stored one.
        let recomputed = match stored {
            Stored::Intact(previous, _) => Some(self.compare_with_stored(step, &blobs, previous)),
            Stored::Absent | Stored::Damaged(_) => None,
        };
        if recomputed != Some(Recomputed::Differs) {
            // Blobs first: a row never names a blob that is not there.
            for (_, bytes) in &encoded {
                registry.blobs().put(bytes)?;
            }
            let row = NewArtefact {
                key: step.key.clone(),
                kind: step.kind(),
                name: step.name(),
                spec: step.spec.clone(),
                code_version: step.code_version.clone(),
                run_id: Some(self.run_id.clone()),
                compute_seconds: clock.elapsed().as_secs_f64(),
                blobs: blobs.clone(),
                details: details(plan, index, &artefact),
            };
            registry.record_artefact(&row, replace)?;
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
        Ok(StepDone {
            outcome,
            blobs,
            detail: recomputed.map(|r| r.detail().to_string()),
            artefact: Some(artefact),
            verify_seconds: 0.0,
        })
    }

    /// Warns about each missing or damaged blob of `step`'s stored artefact
    /// and remembers it for the run's outcome.
    fn report_damage(&mut self, step: &Step, problems: &[String]) {
        for problem in problems {
            let message = format!("{} ({}): {problem}; rebuilding it", step.id, step.key);
            crate::progress::note(format_args!("warning: {message}"));
            self.damaged.push(message);
        }
    }

    /// `--force`: compares the recomputed `blobs` with the `stored` ones
    /// (which are in role order); a difference is reported and fails the
    /// run at its end.
    fn compare_with_stored(
        &mut self,
        step: &Step,
        blobs: &[BlobRef],
        stored: &[BlobRef],
    ) -> Recomputed {
        let mut ours = blobs.to_vec();
        ours.sort_by_key(|r| r.role);
        if ours == stored {
            return Recomputed::Identical;
        }
        let message = format!(
            "{} ({}): recomputed blobs {:?} differ from the stored {:?}",
            step.id, step.key, ours, stored
        );
        crate::progress::note(format_args!("error: {message}"));
        self.mismatches.push(message);
        Recomputed::Differs
    }

    /// Records step `index` of the run, in the registry and in memory.
    fn record_step(
        &mut self,
        registry: &mut Registry,
        index: usize,
        step: &Step,
        done: StepDone,
        clock: Instant,
    ) -> anyhow::Result<()> {
        let record = StepRecord {
            ordinal: index,
            step: step.id.clone(),
            kind: step.kind(),
            artefact_key: step.key.clone(),
            outcome: done.outcome,
            // A cached step's time is the re-hashing of its blobs.
            seconds: clock.elapsed().as_secs_f64() + done.verify_seconds,
            blobs: done.blobs,
            detail: done.detail,
        };
        registry.record_step(&self.run_id, &record)?;
        self.steps.push(record);
        Ok(())
    }
}

/// The blob references of encoded blobs: (role, sha256), in the same order.
fn blob_refs(encoded: &[(BlobRole, Vec<u8>)]) -> Vec<BlobRef> {
    encoded
        .iter()
        .map(|(role, bytes)| BlobRef {
            role: *role,
            sha256: sha256_hex(bytes),
        })
        .collect()
}

/// The evaluation a scoring step made (of the AUC, or of tracks), `None`
/// for other steps. A cached evaluation is read from its `score.json` blob.
fn scored(registry: &Registry, step: &Step, done: &StepDone) -> anyhow::Result<Option<Artefact>> {
    if !matches!(
        step.action,
        Action::Score { .. } | Action::ScoreTracks { .. }
    ) {
        return Ok(None);
    }
    let artefact = match &done.artefact {
        Some(artefact) => artefact.clone(),
        None => decode_step(step, read_blobs(registry, &done.blobs)?)?,
    };
    Ok(Some(artefact))
}

/// The empty-frame figures of scoring step `step` whose evaluation is
/// `score`; none for a step that does not score, a set without empty
/// frames, or an evaluation stored before the figures existed.
fn empty_frames_row(step: &Step, score: &Score) -> Option<EmptyFramesRow> {
    let Action::Score {
        detector,
        dataset_name,
        reading,
        ..
    } = &step.action
    else {
        return None;
    };
    let empty_frames = score.empty_frames.filter(|e| e.frames > 0)?;
    Some(EmptyFramesRow {
        detector: detector.clone(),
        dataset: dataset_name.clone(),
        threshold: reading.threshold,
        empty_frames,
    })
}

/// The AUC table rows (one per ε) of scoring step `step` of `plan` whose
/// evaluation is `score`; none for a step that does not score. Each frame's
/// best-guess AUC is kept only where the scored predictions are ranked
/// lists (the table prints it only for them).
pub fn score_rows(plan: &Plan, step: &Step, score: &Score) -> Vec<AucRow> {
    let Action::Score {
        detector,
        dataset_name,
        diffusion,
        predictions,
        ..
    } = &step.action
    else {
        return Vec::new();
    };
    let ranked = matches!(
        plan.steps.get(*predictions).map(|s| &s.action),
        Some(Action::Locate { detector, .. }) if detector.spec.ranks_candidates()
    );
    score
        .per_eps
        .iter()
        .map(|per_eps| AucRow {
            detector: detector.clone(),
            dataset: dataset_name.clone(),
            diffusion: *diffusion,
            eps_px: per_eps.eps_px,
            auc: per_eps.auc,
            auc_best_per_frame: per_eps.auc_best_per_frame.filter(|_| ranked),
            evaluation_key: step.key.clone(),
        })
        .collect()
}
