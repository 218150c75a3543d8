//! `reproduce`: re-execute a recorded run from scratch, into a scratch
//! registry, and compare what comes out with what was recorded, artefact by
//! artefact and number by number.
//!
//! Per step it compares the content key (same inputs, same code?), the
//! sha256 of every blob as recorded, as stored now (re-hashed: an altered
//! stored blob shows up here) and as reproduced; per AUC cell the recorded
//! and reproduced values, bit for bit. Where an evaluation's blob differs,
//! the numbers inside it are compared one by one.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;
use serde_json::Value;

use super::RunOptions;
use crate::error::CheckFailed;
use crate::manifest;
use crate::registry::diff::flatten;
use crate::registry::{
    AucRow, BlobRef, BlobRole, BlobState, Registry, RunKind, RunRecord, RunStart, RunStatus,
    StepCounts, StepId, StepRecord,
};

/// One blob of one artefact, three ways.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct BlobComparison {
    pub role: BlobRole,
    pub recorded: Option<String>,
    /// `intact`, `missing`, or `damaged (hashes to …)`; `-` if not recorded.
    pub stored: StoredBlob,
    pub reproduced: Option<String>,
    pub identical: bool,
}

/// How a recorded blob stands in the main registry now. Written as text:
/// `intact`, `missing`, `damaged (hashes to …)`, or `-` for a blob the
/// run did not record.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum StoredBlob {
    NotRecorded,
    Checked(BlobState),
}

impl std::fmt::Display for StoredBlob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StoredBlob::NotRecorded => f.pad("-"),
            StoredBlob::Checked(BlobState::Intact) => f.pad("intact"),
            StoredBlob::Checked(BlobState::Missing) => f.pad("missing"),
            StoredBlob::Checked(BlobState::Damaged { actual }) => {
                f.pad(&format!("damaged (hashes to {actual})"))
            }
        }
    }
}

impl Serialize for StoredBlob {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

/// One artefact of the run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct ArtefactComparison {
    pub step: StepId,
    pub recorded_key: Option<String>,
    pub reproduced_key: Option<String>,
    pub blobs: Vec<BlobComparison>,
    /// Numbers that differ inside the artefact (evaluations): `field: a → b`.
    pub differing_numbers: Vec<String>,
    pub identical: bool,
}

/// One AUC cell.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct NumberComparison {
    pub detector: String,
    pub dataset: String,
    pub eps_px: f64,
    pub recorded: Option<f64>,
    pub reproduced: Option<f64>,
    pub identical: bool,
}

/// Everything `reproduce` found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct ReproduceReport {
    pub run: String,
    /// The run recorded in the main registry for this reproduction.
    pub reproduction_run: String,
    pub scratch: String,
    pub identical: bool,
    pub artefacts: Vec<ArtefactComparison>,
    pub auc: Vec<NumberComparison>,
    /// Differences in code version or machine (not failures by themselves).
    pub notes: Vec<String>,
}

impl ReproduceReport {
    /// A human-readable summary.
    pub(crate) fn render(&self) -> String {
        let mut out = format!(
            "reproduce {}: {}\n",
            self.run,
            if self.identical {
                "IDENTICAL"
            } else {
                "DIFFERENT"
            }
        );
        for note in &self.notes {
            out.push_str(&format!("note: {note}\n"));
        }
        for artefact in &self.artefacts {
            out.push_str(&format!(
                "  {:<9} {}\n",
                if artefact.identical {
                    "identical"
                } else {
                    "DIFFERS"
                },
                artefact.step
            ));
            if !artefact.identical {
                if artefact.recorded_key != artefact.reproduced_key {
                    out.push_str(&format!(
                        "            key: recorded {} reproduced {}\n",
                        artefact.recorded_key.as_deref().unwrap_or("-"),
                        artefact.reproduced_key.as_deref().unwrap_or("-")
                    ));
                }
                for blob in artefact.blobs.iter().filter(|b| !b.identical) {
                    out.push_str(&format!(
                        "            {}: recorded {} stored {} reproduced {}\n",
                        blob.role,
                        blob.recorded.as_deref().unwrap_or("-"),
                        blob.stored,
                        blob.reproduced.as_deref().unwrap_or("-")
                    ));
                }
                for number in &artefact.differing_numbers {
                    out.push_str(&format!("            {number}\n"));
                }
            }
        }
        for cell in &self.auc {
            out.push_str(&format!(
                "  {:<9} AUC {}@{} ε={}: recorded {} reproduced {}\n",
                if cell.identical {
                    "identical"
                } else {
                    "DIFFERS"
                },
                cell.detector,
                cell.dataset,
                cell.eps_px,
                cell.recorded.map_or("-".into(), |v| format!("{v}")),
                cell.reproduced.map_or("-".into(), |v| format!("{v}"))
            ));
        }
        out
    }
}

/// The numbers that differ between two JSON documents (at most `limit`).
fn differing_numbers(a: &[u8], b: &[u8], limit: usize) -> Vec<String> {
    let (Ok(a), Ok(b)) = (
        serde_json::from_slice::<Value>(a),
        serde_json::from_slice::<Value>(b),
    ) else {
        return vec!["not comparable: a score.json does not parse".to_string()];
    };
    let (fa, fb) = (flatten(&a), flatten(&b));
    let keys: BTreeSet<&String> = fa.keys().chain(fb.keys()).collect();
    let mut out: Vec<String> = keys
        .into_iter()
        .filter(|k| fa.get(*k) != fb.get(*k))
        .map(|k| {
            format!(
                "{k}: recorded {} reproduced {}",
                fa.get(k).map_or("-".into(), |v| v.to_string()),
                fb.get(k).map_or("-".into(), |v| v.to_string())
            )
        })
        .collect();
    if out.len() > limit {
        let more = out.len() - limit;
        out.truncate(limit);
        out.push(format!("… and {more} more"));
    }
    out
}

/// Re-executes run `run_id` of `registry` from scratch in `scratch` (a
/// folder that must not hold a registry yet) and compares. Records the
/// reproduction as a run of kind `reproduce` in `registry`. Returns the
/// report; the caller decides the exit code from `identical`.
pub(crate) fn reproduce(
    registry: &mut Registry,
    run_id: &str,
    scratch: &Path,
) -> anyhow::Result<ReproduceReport> {
    let record = registry.run_record(run_id)?;
    let source = format!("{} (as recorded by run {run_id})", record.manifest_path);
    let manifest = manifest::parse(&record.manifest_text, &source).map_err(|e| {
        anyhow::Error::new(CheckFailed(format!(
            "the manifest recorded by run {run_id} no longer parses with this scanloc: {e:#}"
        )))
    })?;
    let mut notes = code_notes(&record);
    refuse_incomplete(&record)?;
    let recorded_done = record.status == RunStatus::Done;
    if !recorded_done {
        notes.push(format!(
            "the recorded run is {}: only the steps and AUC values it recorded are compared",
            record.status
        ));
    }
    if record.kind == RunKind::Reproduce {
        notes.push("the recorded run is itself a reproduction".into());
    }
    let (fresh, outcome) = re_execute(&record, &manifest, scratch)?;
    let artefacts = compare_artefacts(registry, &fresh, &record, &outcome)?;
    let auc = compare_auc(&record.auc, &outcome.auc, recorded_done);
    // Identical exactly when every line the report prints says so.
    let identical = artefacts.iter().all(|a| a.identical) && auc.iter().all(|c| c.identical);
    let reproduction_run = record_reproduction(
        registry, &record, &manifest, source, &outcome, &artefacts, identical,
    )?;
    Ok(ReproduceReport {
        run: run_id.to_string(),
        reproduction_run,
        scratch: scratch.display().to_string(),
        identical,
        artefacts,
        auc,
        notes,
    })
}

/// Where the code that recorded the run differs from this one (not a
/// failure by itself).
fn code_notes(record: &RunRecord) -> Vec<String> {
    let current = crate::registry::CodeVersion::current();
    [
        (
            "crate_version",
            &record.code.crate_version,
            &current.crate_version,
        ),
        ("git_commit", &record.code.git_commit, &current.git_commit),
        ("git_dirty", &record.code.git_dirty, &current.git_dirty),
        ("rustc", &record.code.rustc, &current.rustc),
    ]
    .into_iter()
    .filter(|(_, recorded, now)| recorded != now)
    .map(|(field, recorded, now)| format!("{field}: recorded {recorded}, now {now}"))
    .collect()
}

/// Runs the recorded run's plan again in a new registry in `scratch`.
fn re_execute(
    record: &RunRecord,
    manifest: &manifest::Manifest,
    scratch: &Path,
) -> anyhow::Result<(Registry, super::RunOutcome)> {
    if scratch.join(crate::registry::DATABASE_FILE).exists() {
        return Err(crate::error::input_error(format!(
            "{}: already holds a registry; reproduce needs an empty scratch folder",
            scratch.display()
        )));
    }
    let plan = recorded_plan(record, manifest)?;
    let mut fresh = Registry::open(scratch)?;
    let outcome = super::execute(
        &mut fresh,
        manifest,
        &plan,
        &RunOptions {
            kind: RunKind::Reproduce,
            parent_run: Some(record.id.clone()),
            force: false,
            cross_validation: None,
        },
    )
    .context("re-executing the run in the scratch registry")?;
    Ok((fresh, outcome))
}

/// Every recorded step's artefact against its reproduction, blob by blob.
fn compare_artefacts(
    registry: &Registry,
    fresh: &Registry,
    record: &RunRecord,
    outcome: &super::RunOutcome,
) -> anyhow::Result<Vec<ArtefactComparison>> {
    let reproduced: HashMap<&StepId, &StepRecord> =
        outcome.steps.iter().map(|s| (&s.step, s)).collect();
    let mut artefacts = Vec::new();
    for step in &record.steps {
        let recorded_key = Some(step.artefact_key.clone());
        let ours = reproduced.get(&step.step).copied();
        let mut roles: Vec<BlobRole> = step.blobs.iter().map(|b| b.role).collect();
        for blob in ours.iter().flat_map(|o| &o.blobs) {
            if !roles.contains(&blob.role) {
                roles.push(blob.role);
            }
        }
        roles.sort();
        let mut blobs = Vec::new();
        let mut differing = Vec::new();
        for role in roles {
            let blob = compare_blob(registry, role, &step.blobs, ours)?;
            if !blob.identical && role == BlobRole::Score {
                differing.extend(differing_scores(registry, fresh, &blob));
            }
            blobs.push(blob);
        }
        let reproduced_key = ours.map(|o| o.artefact_key.clone());
        let identical =
            ours.is_some() && recorded_key == reproduced_key && blobs.iter().all(|b| b.identical);
        artefacts.push(ArtefactComparison {
            step: step.step.clone(),
            recorded_key,
            reproduced_key,
            blobs,
            differing_numbers: differing,
            identical,
        });
    }
    Ok(artefacts)
}

/// Blob `role` as recorded (`recorded`), as stored now (re-hashed) and as
/// reproduced (`ours`).
fn compare_blob(
    registry: &Registry,
    role: BlobRole,
    recorded: &[BlobRef],
    ours: Option<&StepRecord>,
) -> anyhow::Result<BlobComparison> {
    let recorded = recorded
        .iter()
        .find(|b| b.role == role)
        .map(|b| b.sha256.clone());
    let reproduced = ours
        .and_then(|o| o.blobs.iter().find(|b| b.role == role))
        .map(|b| b.sha256.clone());
    let stored = match &recorded {
        None => StoredBlob::NotRecorded,
        Some(sha) => StoredBlob::Checked(registry.blobs().check(sha)?),
    };
    let identical = recorded.is_some()
        && recorded == reproduced
        && stored == StoredBlob::Checked(BlobState::Intact);
    Ok(BlobComparison {
        role,
        recorded,
        stored,
        reproduced,
        identical,
    })
}

/// The numbers that differ inside a score blob: the stored bytes as they
/// are now (even if altered) against the reproduction.
fn differing_scores(registry: &Registry, fresh: &Registry, blob: &BlobComparison) -> Vec<String> {
    let stored_bytes = blob
        .recorded
        .as_ref()
        .and_then(|sha| std::fs::read(registry.blobs().path(sha)).ok());
    let ours_bytes = blob
        .reproduced
        .as_ref()
        .and_then(|sha| fresh.blobs().get(sha).ok().and_then(|r| r.ok()));
    match (stored_bytes, ours_bytes) {
        (Some(a), Some(b)) => differing_numbers(&a, &b, 20),
        _ => Vec::new(),
    }
}

/// Every AUC cell recorded (and, for a run that finished, every cell
/// reproduced), compared bit for bit.
fn compare_auc(
    recorded: &[AucRow],
    reproduced: &[AucRow],
    recorded_done: bool,
) -> Vec<NumberComparison> {
    let mut cells: Vec<(String, String, f64)> = recorded
        .iter()
        .map(|row| (row.detector.clone(), row.dataset.clone(), row.eps_px))
        .collect();
    // A run that failed recorded no AUC table: there is nothing to compare
    // the reproduced values with, which is not a difference.
    for row in reproduced.iter().filter(|_| recorded_done) {
        if !cells
            .iter()
            .any(|(d, s, e)| *d == row.detector && *s == row.dataset && *e == row.eps_px)
        {
            cells.push((row.detector.clone(), row.dataset.clone(), row.eps_px));
        }
    }
    let value = |rows: &[AucRow], detector: &str, dataset: &str, eps_px: f64| {
        rows.iter()
            .find(|r| r.detector == detector && r.dataset == dataset && r.eps_px == eps_px)
            .map(|r| r.auc)
    };
    cells
        .into_iter()
        .map(|(detector, dataset, eps_px)| {
            let recorded = value(recorded, &detector, &dataset, eps_px);
            let reproduced = value(reproduced, &detector, &dataset, eps_px);
            let identical =
                matches!((recorded, reproduced), (Some(a), Some(b)) if a.to_bits() == b.to_bits());
            NumberComparison {
                detector,
                dataset,
                eps_px,
                recorded,
                reproduced,
                identical,
            }
        })
        .collect()
}

/// Records the reproduction in the main registry: a run of kind
/// `reproduce`, done if everything is `identical`, failed otherwise, with
/// the reproduced AUC table. Returns its id.
fn record_reproduction(
    registry: &mut Registry,
    record: &RunRecord,
    manifest: &manifest::Manifest,
    source: String,
    outcome: &super::RunOutcome,
    artefacts: &[ArtefactComparison],
    identical: bool,
) -> anyhow::Result<String> {
    let run_id = &record.id;
    let reproduction_run = super::new_run_id();
    let summary = if identical {
        None
    } else {
        let differing: Vec<String> = artefacts
            .iter()
            .filter(|a| !a.identical)
            .map(|a| a.step.to_string())
            .collect();
        Some(format!(
            "reproduction of {run_id} differs: {}",
            if differing.is_empty() {
                "AUC values".to_string()
            } else {
                differing.join(", ")
            }
        ))
    };
    registry.begin_run(&RunStart {
        id: reproduction_run.clone(),
        kind: RunKind::Reproduce,
        parent_run: Some(run_id.to_string()),
        manifest_name: manifest.name.clone(),
        manifest_path: source,
        manifest_text: manifest.text.clone(),
        manifest_sha256: manifest.manifest_sha256.clone(),
        resolved_json: serde_json::to_string(&manifest)?,
        seeds_json: serde_json::to_string(&record.seeds)?,
        forced: false,
        cross_validation: None,
    })?;
    registry.finish_run(
        &reproduction_run,
        if identical {
            RunStatus::Done
        } else {
            RunStatus::Failed
        },
        summary.as_deref(),
        StepCounts {
            computed: outcome.counts.computed,
            ..StepCounts::default()
        },
        &outcome.auc,
    )?;
    Ok(reproduction_run)
}

/// Refuses (as bad input) a run that has no complete record to compare
/// with: one still running, and one whose process ended before it finished
/// (killed), or that recorded no step at all.
fn refuse_incomplete(record: &RunRecord) -> anyhow::Result<()> {
    let (run_id, who) = (&record.id, format!("pid {} on {}", record.pid, record.host));
    match record.status {
        RunStatus::Running => Err(crate::error::input_error(format!(
            "run {run_id} has not finished ({who} is still running it, or was killed on another \
             machine): reproduce it once it is done"
        ))),
        RunStatus::Unfinished => Err(crate::error::input_error(format!(
            "run {run_id} is unfinished: its process ({who}) ended before the run did, so there \
             is no complete record to compare with; rerun its manifest with `scanloc run` (the \
             finished steps are reused) and reproduce that run"
        ))),
        _ if record.steps.is_empty() => Err(crate::error::input_error(format!(
            "run {run_id} recorded no step, so there is nothing to reproduce"
        ))),
        _ => Ok(()),
    }
}

/// The plan a recorded run executed: its manifest's, or for a
/// cross-validation the plan it recorded (detector, folds, and the one fold
/// of a `cv --fold K` run).
fn recorded_plan(record: &RunRecord, manifest: &manifest::Manifest) -> anyhow::Result<super::Plan> {
    if record.kind != RunKind::Cv {
        return super::Plan::from_manifest(manifest);
    }
    let cv = record.cross_validation.as_ref().ok_or_else(|| {
        CheckFailed(format!(
            "run {} is a cross-validation that recorded no plan (an interrupted run made \
             before scanloc recorded plans): rerun it with `scanloc cv`, then reproduce that run",
            record.id
        ))
    })?;
    super::cross_validation::plan(manifest, cv)
}

/// A scratch folder for a reproduction: `dir` if given, else a new
/// temporary folder (removed when the returned guard drops, unless kept).
pub(crate) fn scratch_dir(
    dir: Option<&Path>,
) -> anyhow::Result<(PathBuf, Option<tempfile::TempDir>)> {
    match dir {
        Some(dir) => Ok((dir.to_path_buf(), None)),
        None => {
            let temp = tempfile::Builder::new()
                .prefix("scanloc-reproduce-")
                .tempdir()
                .context("creating a scratch folder")?;
            Ok((temp.path().to_path_buf(), Some(temp)))
        }
    }
}
