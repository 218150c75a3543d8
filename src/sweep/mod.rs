//! Sweeps: a set of independent points, each an ordinary recorded run, then
//! one aggregation step that prints and records the table. Three front
//! ends share it: `scanloc cv` (a point per fold), `scanloc calibrate` (a
//! point per brightness) and `scanloc sweep run` (a point per cell of the
//! manifest's `sweep:` grid, see [`grid`]). Each implements
//! [`FrontEnd`] in its own file ([`cv`], [`calibrate`], [`grid`]): its
//! points and its aggregation's table and JSON; the engine here runs
//! points and collects their states without knowing which front end it runs.
//!
//! Executors ([`Executor`]): `local` runs the points on this machine, one
//! after another in this process or in `--jobs N` processes writing into the
//! registry directly (local SQLite, WAL mode); `slurm` submits one job array
//! with a task per missing point and an aggregation job (see [`slurm`]).
//! Slurm tasks never write to the main registry: each writes a shard, a
//! registry folder of its own under the sweep's folder, seeded read-only
//! with the inputs the main registry already holds; the aggregation
//! imports the shards with a single writer ([`crate::registry::shard`]).
//! Every point is a pure function of the manifest, so where it ran changes
//! no key, no blob and no AUC. The design is documented in `docs/cluster.md`.
//!
//! A sweep's folder is `REGISTRY/sweeps/ID`, with `ID` derived from what is
//! swept (front end, its parameters, the manifest's text): the same sweep
//! submitted again finds the same folder and the registry's cache, and
//! runs only its missing points.

pub(crate) mod calibrate;
pub(crate) mod cv;
pub(crate) mod front_end;
pub(crate) mod grid;
pub mod slurm;
pub(crate) mod state;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use anyhow::Context;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::error::{CheckFailed, input_error};
use crate::manifest::{self, Manifest};
use crate::registry::hashing::{canonical_json, sha256_hex};
use crate::registry::shard::{self, Selection};
use crate::registry::{AucRow, Registry, RunStatus, utc_now};
use crate::run::{
    Action, Plan, RunOptions, RunOutcome, TrackingRow, execute, load_artefact, score_rows,
};
use front_end::Finished;
pub use front_end::FrontEnd;
pub use state::PointStatus;

/// The folder of a registry that holds its sweeps.
pub(crate) const SWEEPS_DIR: &str = "sweeps";
/// A sweep folder's description file.
pub(crate) const SWEEP_FILE: &str = "sweep.json";
/// A sweep folder's result file, written by the aggregation.
pub(crate) const RESULT_FILE: &str = "result.json";

/// What is swept, by which front end.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "front_end", rename_all = "snake_case")]
pub enum SweepKind {
    /// `scanloc cv`: one point per fold.
    Cv { detector: String, folds: usize },
    /// `scanloc calibrate`: one point per brightness value.
    Calibrate {
        detector: String,
        brightness: Vec<f64>,
    },
    /// `scanloc sweep run`: one point per cell of the manifest's grid.
    Grid,
}

/// A sweep: its front end and the manifest it sweeps over.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SweepSpec {
    pub kind: SweepKind,
    /// The manifest's path as given (for messages and run records).
    pub manifest_path: String,
    /// The manifest's text, exactly as read.
    pub manifest_text: String,
}

impl SweepSpec {
    /// The sweep's id: `FRONTEND-` and 12 hex digits of the hash of what is
    /// swept (not of the manifest's path, so a moved manifest is the same
    /// sweep).
    pub fn id(&self) -> anyhow::Result<String> {
        let hash = sha256_hex(
            canonical_json(&json!({"kind": self.kind, "manifest": self.manifest_text}))?.as_bytes(),
        );
        Ok(format!("{}-{}", self.kind.front_end().name(), &hash[..12]))
    }
}

/// One point of a sweep: a run of `plan` (made from `manifest`).
#[derive(Debug, Clone)]
pub struct Point {
    pub index: usize,
    /// `fold 2`, `N_qd=7`, `channels=8 epochs=2`.
    pub label: String,
    pub manifest: Arc<Manifest>,
    pub plan: Plan,
    /// How its run is recorded (kind, and a cross-validation's fold);
    /// `force` is the command's.
    pub run: RunOptions,
}

/// The points of `spec`, with the manifest they come from. Bad input
/// (manifest, detector, folds, grid) is reported here, before anything runs.
pub fn points(spec: &SweepSpec) -> anyhow::Result<(Arc<Manifest>, Vec<Point>)> {
    let base = Arc::new(manifest::parse(&spec.manifest_text, &spec.manifest_path)?);
    let points = spec.kind.front_end().points(&base, spec)?;
    Ok((base, points))
}

/// Runs point `point` of a sweep into `registry`, recorded as its front
/// end says (a run of kind `cv`, `calibrate` or `sweep`).
pub(crate) fn run_point(
    registry: &mut Registry,
    point: &Point,
    force: bool,
) -> anyhow::Result<RunOutcome> {
    execute(
        registry,
        &point.manifest,
        &point.plan,
        &RunOptions {
            force,
            ..point.run.clone()
        },
    )
}

/// Whether every artefact of `point` is stored in `registry` (rows only:
/// the blobs are re-hashed when a run uses them).
pub(crate) fn point_is_stored(registry: &Registry, point: &Point) -> anyhow::Result<bool> {
    for step in &point.plan.steps {
        if registry.artefact(&step.key)?.is_none() {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The AUC table of `point` read from the stored evaluations (rows in plan
/// order, as the point's run records them).
pub(crate) fn point_auc(registry: &Registry, point: &Point) -> anyhow::Result<Vec<AucRow>> {
    let mut rows = Vec::new();
    for step in &point.plan.steps {
        if matches!(step.action, Action::Score { .. }) {
            let score = load_artefact(registry, &step.key)?;
            rows.extend(score_rows(&point.plan, step, score.evaluation()?));
        }
    }
    Ok(rows)
}

/// The tracking rows of `point` (its tracking pipelines' figures, as its
/// run prints them) read from the stored evaluations, in plan order.
pub(crate) fn point_tracking(
    registry: &Registry,
    point: &Point,
) -> anyhow::Result<Vec<TrackingRow>> {
    let mut rows = Vec::new();
    for step in &point.plan.steps {
        if matches!(step.action, Action::ScoreTracks { .. }) {
            let evaluation = load_artefact(registry, &step.key)?;
            rows.extend(TrackingRow::of(step, evaluation.track_evaluation()?));
        }
    }
    Ok(rows)
}

/// Where sweeps run.
#[derive(Debug, Clone, PartialEq)]
pub enum Executor {
    /// This machine: `jobs` points at a time (1: in this process).
    Local { jobs: usize },
    /// A Slurm cluster: one job array and an aggregation job.
    Slurm(slurm::SlurmOptions),
}

/// A sweep's folder and description file.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepFile {
    pub id: String,
    pub spec: SweepSpec,
    /// The main registry (absolute).
    pub registry: PathBuf,
    /// The scanloc binary the batch scripts run (absolute).
    pub scanloc: PathBuf,
    /// Point labels, by index.
    pub points: Vec<String>,
    /// Every submission to Slurm, oldest first.
    #[serde(default)]
    pub submissions: Vec<slurm::Submission>,
}

impl SweepFile {
    /// The sweep's folder.
    pub fn dir(&self) -> PathBuf {
        self.registry.join(SWEEPS_DIR).join(&self.id)
    }

    /// Point `index`'s shard (a registry folder).
    pub fn shard(&self, index: usize) -> PathBuf {
        self.dir().join("shards").join(index.to_string())
    }

    /// Point `index`'s log (Slurm's output of its task, or a local job's).
    pub fn log(&self, index: usize) -> PathBuf {
        self.dir().join("logs").join(format!("task-{index}.out"))
    }

    /// Writes `sweep.json` (atomically: a reader never sees half of it).
    pub fn save(&self) -> anyhow::Result<()> {
        write_atomically(
            &self.dir().join(SWEEP_FILE),
            serde_json::to_string_pretty(self)?.as_bytes(),
        )
    }

    /// Reads the sweep folder `dir`.
    pub fn load(dir: &Path) -> anyhow::Result<Self> {
        let path = dir.join(SWEEP_FILE);
        let text = std::fs::read_to_string(&path)
            .map_err(|e| input_error(format!("{}: not a sweep folder: {e}", path.display())))?;
        serde_json::from_str(&text)
            .map_err(|e| input_error(format!("{}: damaged sweep file: {e}", path.display())))
    }
}

fn write_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let folder = path.parent().context("a file in a folder")?;
    std::fs::create_dir_all(folder)?;
    // The one output writer (special destinations refused, umask honoured).
    crate::io::write_bytes_atomically(path, bytes)
}

/// Creates (or finds) the folder of sweep `spec` in the registry `registry`
/// and returns its description, with the points.
pub fn prepare(
    registry: &Registry,
    spec: &SweepSpec,
) -> anyhow::Result<(SweepFile, Arc<Manifest>, Vec<Point>)> {
    let (base, points) = points(spec)?;
    let id = spec.id()?;
    let registry_dir = std::fs::canonicalize(registry.dir())
        .with_context(|| format!("resolving {}", registry.dir().display()))?;
    let dir = registry_dir.join(SWEEPS_DIR).join(&id);
    let file = if dir.join(SWEEP_FILE).is_file() {
        let mut file = SweepFile::load(&dir)?;
        file.registry = registry_dir;
        file.scanloc = std::env::current_exe().context("locating the scanloc binary")?;
        file
    } else {
        SweepFile {
            id,
            spec: spec.clone(),
            registry: registry_dir,
            scanloc: std::env::current_exe().context("locating the scanloc binary")?,
            points: points.iter().map(|p| p.label.clone()).collect(),
            submissions: Vec::new(),
        }
    };
    std::fs::create_dir_all(dir.join("logs"))?;
    file.save()?;
    Ok((file, base, points))
}

/// The folder of sweep `id` (a folder path, a sweep id or a unique prefix
/// of one) in the registry `registry_dir`.
pub fn find(registry_dir: &Path, id: &str) -> anyhow::Result<PathBuf> {
    let as_path = Path::new(id);
    if as_path.join(SWEEP_FILE).is_file() {
        return Ok(as_path.to_path_buf());
    }
    let sweeps = registry_dir.join(SWEEPS_DIR);
    let mut matches: Vec<PathBuf> = std::fs::read_dir(&sweeps)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with(id))
        .map(|e| e.path())
        .filter(|p| p.join(SWEEP_FILE).is_file())
        .collect();
    matches.sort();
    match matches.len() {
        1 => Ok(matches.remove(0)),
        0 => Err(input_error(format!(
            "{}: no sweep {id} (sweeps are listed in {})",
            registry_dir.display(),
            sweeps.display()
        ))),
        n => Err(input_error(format!(
            "{id}: matches {n} sweeps in {}; give more of the id",
            sweeps.display()
        ))),
    }
}

/// Where one point stands.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointState {
    pub index: usize,
    pub label: String,
    /// `done` (every artefact in the main registry), `failed`, `missing`
    /// (never ran, or its results are lost), or a Slurm state while queued
    /// or running (`pending`, `running`), or `in shard` (finished, not yet
    /// imported).
    pub status: PointStatus,
    /// The run that computed it, when known.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub run: Option<String>,
    /// Why it failed.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Its task's log, if there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub log: Option<String>,
    #[serde(default)]
    pub cached_steps: usize,
    #[serde(default)]
    pub computed_steps: usize,
}

/// A sweep's aggregated result (`result.json` in its folder).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SweepResult {
    pub sweep: String,
    pub folder: String,
    pub finished_at: String,
    pub points: Vec<PointState>,
    /// The front end's table as text (what the command prints).
    pub text: String,
    /// The front end's result as JSON (what the command prints with --json).
    pub json: Value,
}

impl SweepResult {
    /// The points that did not finish.
    pub fn failed(&self) -> Vec<&PointState> {
        self.points.iter().filter(|p| !p.status.is_done()).collect()
    }

    /// The failures as an error for the exit code (1), or `Ok` if every
    /// point is done.
    pub fn check(&self) -> anyhow::Result<()> {
        let failed = self.failed();
        if failed.is_empty() {
            return Ok(());
        }
        Err(anyhow::Error::new(CheckFailed(format!(
            "sweep {}: {} of {} points did not finish: {}; submit the same sweep again to run only these",
            self.sweep,
            failed.len(),
            self.points.len(),
            failed
                .iter()
                .map(|p| format!(
                    "{} ({}{})",
                    p.label,
                    p.error.clone().unwrap_or_else(|| p.status.to_string()),
                    p.log
                        .as_ref()
                        .map(|l| format!(", log {l}"))
                        .unwrap_or_default()
                ))
                .collect::<Vec<_>>()
                .join("; ")
        ))))
    }
}

/// Runs sweep `spec` with `executor` on the registry `registry`. With the
/// local executor, or Slurm with `wait`, returns the aggregated result;
/// with Slurm without `wait`, the submission (the result is `None`).
pub fn run(
    registry: &mut Registry,
    spec: &SweepSpec,
    executor: &Executor,
    force: bool,
) -> anyhow::Result<(SweepFile, Option<SweepResult>)> {
    let (file, base, points) = prepare(registry, spec)?;
    match executor {
        Executor::Local { jobs } => {
            let mut states = Vec::new();
            if *jobs <= 1 {
                for point in &points {
                    states.push(match run_point(registry, point, force) {
                        Ok(outcome) => state_of_run(point, &outcome),
                        Err(error) => {
                            // Input errors stop the sweep; a point that fails
                            // while running is reported with the others.
                            if crate::error::exit_code(&error) == 2 {
                                return Err(error);
                            }
                            failed_state(point, format!("{error:#}"), None)
                        }
                    });
                }
            } else {
                states = run_local_processes(&file, &points, *jobs, force)?;
            }
            let result = aggregate(registry, &file, &base, &points, Some(states))?;
            Ok((file, Some(result)))
        }
        Executor::Slurm(options) => {
            if force {
                return Err(input_error(
                    "--force: only with the local executor (a forced point recomputes and compares in one registry)",
                ));
            }
            slurm::submit(registry, file, &base, &points, options)
        }
    }
}

fn state_of_run(point: &Point, outcome: &RunOutcome) -> PointState {
    PointState {
        index: point.index,
        label: point.label.clone(),
        status: PointStatus::DONE,
        run: Some(outcome.run.clone()),
        error: None,
        log: None,
        cached_steps: outcome.counts.cached,
        computed_steps: outcome.counts.computed + outcome.counts.rebuilt,
    }
}

fn failed_state(point: &Point, error: String, log: Option<&Path>) -> PointState {
    PointState {
        index: point.index,
        label: point.label.clone(),
        status: PointStatus::FAILED,
        run: None,
        error: Some(error),
        log: log.map(|l| l.display().to_string()),
        cached_steps: 0,
        computed_steps: 0,
    }
}

/// The local executor with `jobs` processes: each point is `scanloc sweep
/// task --direct`, writing into the main registry (local SQLite, WAL); the
/// machine's threads are shared out between them.
fn run_local_processes(
    file: &SweepFile,
    points: &[Point],
    jobs: usize,
    force: bool,
) -> anyhow::Result<Vec<PointState>> {
    let threads = (std::thread::available_parallelism().map_or(1, |n| n.get()) / jobs).max(1);
    let mut queue = points.iter();
    let mut running: Vec<(&Point, std::process::Child, PathBuf)> = Vec::new();
    let mut states = Vec::new();
    loop {
        while running.len() < jobs {
            let Some(point) = queue.next() else { break };
            let log_path = file.log(point.index);
            let log = std::fs::File::create(&log_path)
                .with_context(|| format!("creating {}", log_path.display()))?;
            let mut command = Command::new(&file.scanloc);
            command
                .args(["sweep", "task"])
                .arg(file.dir())
                .arg(point.index.to_string())
                .arg("--direct")
                .env(crate::env_vars::RAYON_NUM_THREADS, threads.to_string())
                .stdout(log.try_clone()?)
                .stderr(log);
            if force {
                command.arg("--force");
            }
            let child = command
                .spawn()
                .with_context(|| format!("starting {}", file.scanloc.display()))?;
            running.push((point, child, log_path));
        }
        if running.is_empty() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
        let mut still = Vec::new();
        for (point, mut child, log) in running {
            match child.try_wait()? {
                None => still.push((point, child, log)),
                Some(status) if status.success() => states.push(PointState {
                    log: Some(log.display().to_string()),
                    ..task_state(&log, point)
                }),
                Some(status) => states.push(failed_state(
                    point,
                    format!("its process exited with {status}"),
                    Some(&log),
                )),
            }
        }
        running = still;
    }
    states.sort_by_key(|s| s.index);
    Ok(states)
}

/// The last line a `sweep task` prints is its run's summary as JSON.
fn task_state(log: &Path, point: &Point) -> PointState {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let summary: Option<TaskSummary> = text
        .lines()
        .rev()
        .find_map(|line| serde_json::from_str(line).ok());
    PointState {
        index: point.index,
        label: point.label.clone(),
        status: PointStatus::DONE,
        run: summary.as_ref().map(|s| s.run.clone()),
        error: None,
        log: None,
        cached_steps: summary.as_ref().map_or(0, |s| s.cached_steps),
        computed_steps: summary.map_or(0, |s| s.computed_steps),
    }
}

/// What `scanloc sweep task` prints last (one JSON line).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TaskSummary {
    pub sweep: String,
    pub point: usize,
    pub label: String,
    pub run: String,
    pub registry: String,
    pub cached_steps: usize,
    pub computed_steps: usize,
    /// Artefacts copied from the main registry into the shard first.
    pub seeded_artefacts: usize,
    pub seconds: f64,
}

/// One task: point `index` of the sweep in folder `dir`. Into its shard
/// (seeded read-only from the main registry with the point's artefacts it
/// already holds), or with `direct` into the main registry itself.
pub fn task(dir: &Path, index: usize, direct: bool, force: bool) -> anyhow::Result<TaskSummary> {
    let clock = std::time::Instant::now();
    let file = SweepFile::load(dir)?;
    let (_, points) = points(&file.spec)?;
    let point = points.get(index).ok_or_else(|| {
        input_error(format!(
            "{}: point {index}: the sweep has {} points",
            dir.display(),
            points.len()
        ))
    })?;
    let target = if direct {
        file.registry.clone()
    } else {
        file.shard(index)
    };
    let mut registry = Registry::open_to_write(&target, "sweep task")?;
    let mut seeded = 0;
    if !direct {
        let keys: Vec<String> = point.plan.steps.iter().map(|s| s.key.clone()).collect();
        match shard::copy(&mut registry, &file.registry, &Selection::Artefacts(keys)) {
            Ok(report) => seeded = report.new_artefacts,
            // Inputs are recomputed when the main registry cannot give them.
            Err(error) => crate::progress::note(format_args!(
                "warning: reading inputs from {}: {error:#}; computing them here",
                file.registry.display()
            )),
        }
    }
    crate::progress::note(format_args!(
        "sweep {} point {index} ({}) into {} on {}",
        file.id,
        point.label,
        target.display(),
        crate::registry::host_name()
    ));
    let outcome = run_point(&mut registry, point, force)?;
    Ok(TaskSummary {
        sweep: file.id.clone(),
        point: index,
        label: point.label.clone(),
        run: outcome.run,
        registry: target.display().to_string(),
        cached_steps: outcome.counts.cached,
        computed_steps: outcome.counts.computed + outcome.counts.rebuilt,
        seeded_artefacts: seeded,
        seconds: clock.elapsed().as_secs_f64(),
    })
}

/// Imports the shards in the sweep's folder into `registry` (the single
/// writer): a missing or damaged shard is reported, the others imported.
/// A shard whose point is then complete is removed (its blobs were re-hashed
/// into the main registry); the others stay for `sweep status` to explain.
/// Returns (point, error) for the shards that could not be imported.
pub(crate) fn import_shards(
    registry: &mut Registry,
    file: &SweepFile,
    points: &[Point],
) -> anyhow::Result<Vec<(usize, String)>> {
    let mut problems = Vec::new();
    for point in points {
        let shard = file.shard(point.index);
        if !shard.exists() {
            continue;
        }
        match shard::copy(registry, &shard, &Selection::Everything) {
            Ok(report) => {
                crate::progress::note(format_args!("imported {}", report.summary()));
                if !report.conflicts.is_empty() {
                    problems.push((point.index, report.summary()));
                } else if point_is_stored(registry, point)? {
                    std::fs::remove_dir_all(&shard)
                        .with_context(|| format!("removing {}", shard.display()))?;
                }
            }
            Err(error) => {
                crate::progress::note(format_args!("error: shard {}: {error:#}", shard.display()));
                problems.push((point.index, format!("shard {}: {error:#}", shard.display())));
            }
        }
    }
    Ok(problems)
}

/// The last run recorded in point `index`'s shard: (id, status, error).
/// A status this scanloc does not know reads as no run.
fn shard_run(file: &SweepFile, index: usize) -> Option<(String, RunStatus, Option<String>)> {
    let conn = shard::open_read_only(&file.shard(index)).ok()?;
    let (id, status, error): (String, String, Option<String>) = conn
        .query_row(
            "SELECT id, status, error FROM runs ORDER BY started_at DESC, id DESC LIMIT 1",
            [],
            |row| Ok((row.get(0)?, row.get(1)?, row.get(2)?)),
        )
        .ok()?;
    Some((id, RunStatus::parse(&status)?, error))
}

/// Why point `index` has no result, as its shard tells (read after its
/// task ended).
fn shard_failure(file: &SweepFile, index: usize) -> String {
    match shard_run(file, index) {
        Some((run, RunStatus::Running | RunStatus::Unfinished, _)) => format!(
            "run {run} did not finish: its task was killed (time limit, cancellation, preemption or node failure)"
        ),
        Some((run, status, error)) => format!(
            "run {run} {status}{}",
            error.map(|e| format!(": {e}")).unwrap_or_default()
        ),
        None if file.shard(index).exists() => "its shard holds no run".to_string(),
        None => "no result: the task did not run or did not finish".to_string(),
    }
}

/// Aggregates the sweep: every point's state (from `known` where this
/// process ran it, else from the registry and the shards), the front end's
/// table, recorded in `result.json` (and for cv, as a run of kind `cv`).
/// Does not import: see [`import_shards`].
pub fn aggregate(
    registry: &mut Registry,
    file: &SweepFile,
    base: &Manifest,
    points: &[Point],
    known: Option<Vec<PointState>>,
) -> anyhow::Result<SweepResult> {
    let states = point_states(registry, file, points, known)?;
    let finished = Finished {
        file,
        base,
        points,
        states: &states,
    };
    let (mut text, json) = file.spec.kind.front_end().aggregate(registry, &finished)?;
    for state in states.iter().filter(|s| !s.status.is_done()) {
        text.push_str(&format!(
            "FAILED {}: {}{}\n",
            state.label,
            state
                .error
                .clone()
                .unwrap_or_else(|| state.status.to_string()),
            state
                .log
                .as_ref()
                .map(|l| format!(" (log {l})"))
                .unwrap_or_default()
        ));
    }
    let result = SweepResult {
        sweep: file.id.clone(),
        folder: file.dir().display().to_string(),
        finished_at: utc_now(),
        points: states,
        text,
        json,
    };
    write_atomically(
        &file.dir().join(RESULT_FILE),
        serde_json::to_string_pretty(&result)?.as_bytes(),
    )?;
    Ok(result)
}

/// Every point's state, by index: `known` where this process ran it (or
/// learnt why it failed), else what the registry, the task's log and its
/// shard tell.
fn point_states(
    registry: &Registry,
    file: &SweepFile,
    points: &[Point],
    known: Option<Vec<PointState>>,
) -> anyhow::Result<Vec<PointState>> {
    let mut states = Vec::new();
    for point in points {
        let stored = point_is_stored(registry, point)?;
        let known = known
            .as_ref()
            .and_then(|k| k.iter().find(|s| s.index == point.index).cloned());
        let state = match (stored, known) {
            (true, Some(state)) if state.status.is_done() => state,
            // Ran elsewhere (a Slurm task, or earlier): its log says which run.
            (true, _) => PointState {
                log: None,
                ..task_state(&file.log(point.index), point)
            },
            (false, Some(state)) if !state.status.is_done() => state,
            (false, _) => {
                let log = file.log(point.index);
                let log = log.is_file().then_some(log);
                let error = shard_failure(file, point.index);
                failed_state(point, error, log.as_deref())
            }
        };
        states.push(state);
    }
    Ok(states)
}

/// The aggregation step of a sweep folder (what the Slurm aggregation job
/// runs): imports the shards, then aggregates.
pub(crate) fn import_and_aggregate(
    registry: &mut Registry,
    dir: &Path,
) -> anyhow::Result<SweepResult> {
    let file = SweepFile::load(dir)?;
    let (base, points) = points(&file.spec)?;
    let problems = import_shards(registry, &file, &points)?;
    // A shard that could not be imported explains its point.
    let known = problems
        .into_iter()
        .map(|(index, problem)| failed_state(&points[index], problem, Some(&file.log(index))))
        .collect();
    aggregate(registry, &file, &base, &points, Some(known))
}

impl SweepKind {
    /// The front end that sweeps this kind: the one place a kind is told
    /// apart (the kind itself is what `sweep.json` records).
    pub fn front_end(&self) -> Box<dyn FrontEnd + '_> {
        match self {
            SweepKind::Cv { detector, folds } => Box::new(cv::CvSweep {
                detector,
                folds: *folds,
            }),
            SweepKind::Calibrate {
                detector,
                brightness,
            } => Box::new(calibrate::CalibrateSweep {
                detector,
                brightness,
            }),
            SweepKind::Grid => Box::new(grid::GridSweep),
        }
    }
}
