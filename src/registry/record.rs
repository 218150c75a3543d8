//! Runs as the registry records them and reads them back: typed, column by
//! named column. A missing or malformed column is an error naming the run
//! and the column, never a silent default.

use std::collections::BTreeMap;
use std::fmt;

use anyhow::Context;
use rusqlite::types::FromSql;
use rusqlite::{OptionalExtension, Row};
use serde::{Deserialize, Serialize};

use super::{
    ArtefactKind, BlobRef, BlobRole, CodeVersion, Registry, StepId, host_name, process_alive,
};
use crate::error::input_error;

/// For an enum stored in the database by name: `as_str` (the stored
/// name), `parse` (its inverse, `None` for an unknown name) and `Display`
/// (the name, padded as the format asks).
macro_rules! stored_by_name {
    ($type:ident { $($variant:ident => $name:literal),+ $(,)? }) => {
        impl $type {
            /// The name stored in the database.
            pub fn as_str(self) -> &'static str {
                match self {
                    $($type::$variant => $name),+
                }
            }

            /// The value stored as `text` (`None` for an unknown name).
            pub fn parse(text: &str) -> Option<Self> {
                match text {
                    $($name => Some($type::$variant),)+
                    _ => None,
                }
            }
        }

        impl fmt::Display for $type {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.pad(self.as_str())
            }
        }
    };
}

/// What a run was started by.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunKind {
    /// `scanloc run`: a manifest's plan.
    #[default]
    Run,
    /// `scanloc reproduce`: a recorded run re-executed and compared.
    Reproduce,
    /// `scanloc cv`: a cross-validation (its plan is [`CrossValidationPlan`]).
    Cv,
    /// `scanloc calibrate`: one brightness grid point.
    Calibrate,
    /// `scanloc sweep run`: one point of a manifest's `sweep:` grid.
    Sweep,
}

stored_by_name!(RunKind {
    Run => "run",
    Reproduce => "reproduce",
    Cv => "cv",
    Calibrate => "calibrate",
    Sweep => "sweep",
});

/// How a run ended (or not).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RunStatus {
    /// Still going, or killed before it could say otherwise.
    Running,
    Done,
    Failed,
    /// Its process ended without finishing the record (killed).
    Unfinished,
}

stored_by_name!(RunStatus {
    Running => "running",
    Done => "done",
    Failed => "failed",
    Unfinished => "unfinished",
});

impl RunStatus {
    /// The status a run recorded as `self` by process `pid` on `host` has
    /// in effect: a `running` run of this host whose process is gone was
    /// killed before it could record its end, so it is `unfinished`. The
    /// one place this rule is written.
    pub fn in_effect(self, host: &str, pid: i64) -> RunStatus {
        let process_gone =
            || host == host_name() && u32::try_from(pid).is_ok_and(|pid| !process_alive(pid));
        if self == RunStatus::Running && process_gone() {
            RunStatus::Unfinished
        } else {
            self
        }
    }
}

/// What became of one step of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepOutcome {
    /// Stored intact already (its blobs re-hashed), not recomputed.
    Cached,
    /// Made by this run.
    Computed,
    /// Made again because a stored blob was missing or damaged.
    Rebuilt,
}

stored_by_name!(StepOutcome {
    Cached => "cached",
    Computed => "computed",
    Rebuilt => "rebuilt",
});

/// How many steps of a run had each [`StepOutcome`]. Serialised as
/// `cached_steps`, `computed_steps`, `rebuilt_steps` (the `runs` columns).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StepCounts {
    #[serde(rename = "cached_steps")]
    pub cached: usize,
    #[serde(rename = "computed_steps")]
    pub computed: usize,
    #[serde(rename = "rebuilt_steps")]
    pub rebuilt: usize,
}

impl StepCounts {
    /// Counts one more step with `outcome`.
    pub fn add(&mut self, outcome: StepOutcome) {
        match outcome {
            StepOutcome::Cached => self.cached += 1,
            StepOutcome::Computed => self.computed += 1,
            StepOutcome::Rebuilt => self.rebuilt += 1,
        }
    }
}

/// The plan of a cross-validation run, recorded with it: which detector,
/// how many folds, and for `scanloc cv --fold K` the one fold (1-based)
/// that ran. Runs are re-planned from this record, never from names.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CrossValidationPlan {
    pub detector: String,
    pub folds: usize,
    /// The only fold run (1-based); `None` for the whole sweep.
    pub fold: Option<usize>,
}

/// What a run records when it starts.
#[derive(Debug, Clone)]
pub struct RunStart {
    pub id: String,
    pub kind: RunKind,
    pub parent_run: Option<String>,
    pub manifest_name: String,
    pub manifest_path: String,
    pub manifest_text: String,
    pub manifest_sha256: String,
    pub resolved_json: String,
    pub seeds_json: String,
    pub forced: bool,
    /// For a cross-validation run, its plan.
    pub cross_validation: Option<CrossValidationPlan>,
}

/// One step of a run as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepRecord {
    pub ordinal: usize,
    /// `dataset/train`, `evaluation/trackpy@test-1.00`, …
    pub step: StepId,
    pub kind: ArtefactKind,
    pub artefact_key: String,
    pub outcome: StepOutcome,
    pub seconds: f64,
    pub blobs: Vec<BlobRef>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

/// One cell of a run's AUC table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AucRow {
    pub detector: String,
    pub dataset: String,
    /// The dataset's D in µm²/s, if it is fixed.
    pub diffusion: Option<f64>,
    pub eps_px: f64,
    /// The AUC of every prediction (for ranked lists: the whole lists).
    pub auc: f64,
    /// The AUC of each frame's best guess alone, when the evaluated
    /// predictions are ranked lists (`Prediction::candidate`); `None`
    /// otherwise, and in runs recorded before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub auc_best_per_frame: Option<f64>,
    pub evaluation_key: String,
}

/// A run in full as recorded: what ran, with which code, where, how it
/// ended, each step and the AUC table. Times are UTC ISO 8601.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunRecord {
    pub id: String,
    pub kind: RunKind,
    /// For a reproduction: the run reproduced.
    pub parent_run: Option<String>,
    pub manifest_name: String,
    pub manifest_path: String,
    /// The manifest text exactly as read.
    pub manifest_text: String,
    pub manifest_sha256: String,
    /// The resolved manifest as the run serialised it (defaults filled in,
    /// every seed derived).
    pub resolved: serde_json::Value,
    /// Seed of every seeded step, by step id (`dataset/train`), in decimal.
    pub seeds: BTreeMap<String, String>,
    #[serde(flatten)]
    pub code: CodeVersion,
    pub host: String,
    pub pid: u32,
    pub threads: usize,
    /// Run with `--force`.
    pub forced: bool,
    pub started_at: String,
    pub ended_at: Option<String>,
    /// In effect (see [`RunStatus::in_effect`]).
    pub status: RunStatus,
    pub error: Option<String>,
    #[serde(flatten)]
    pub counts: StepCounts,
    /// For a cross-validation run, its plan (`None` for an old `cv` run
    /// whose plan could not be recovered).
    pub cross_validation: Option<CrossValidationPlan>,
    pub steps: Vec<StepRecord>,
    pub auc: Vec<AucRow>,
}

/// One line of the run listing.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunSummary {
    pub id: String,
    pub kind: RunKind,
    pub manifest_name: String,
    /// In effect (see [`RunStatus::in_effect`]).
    pub status: RunStatus,
    pub started_at: String,
    pub ended_at: Option<String>,
    #[serde(flatten)]
    pub counts: StepCounts,
    pub git_commit: String,
    pub git_dirty: String,
}

/// Reads named columns of one row of `table`, naming the run and the
/// column in every error.
struct Columns<'a, 'row> {
    row: &'a Row<'row>,
    table: &'static str,
    run: &'a str,
}

impl Columns<'_, '_> {
    fn get<T: FromSql>(&self, column: &str) -> anyhow::Result<T> {
        self.row
            .get::<_, T>(column)
            .with_context(|| self.malformed(column))
    }

    fn parse<T>(&self, column: &str, parse: impl Fn(&str) -> Option<T>) -> anyhow::Result<T> {
        let text: String = self.get(column)?;
        parse(&text).with_context(|| format!("{}: unknown value {text:?}", self.malformed(column)))
    }

    fn json<T: serde::de::DeserializeOwned>(&self, column: &str) -> anyhow::Result<T> {
        let text: String = self.get(column)?;
        serde_json::from_str(&text).with_context(|| self.malformed(column))
    }

    fn count(&self, column: &str) -> anyhow::Result<usize> {
        let value: i64 = self.get(column)?;
        usize::try_from(value).with_context(|| self.malformed(column))
    }

    fn malformed(&self, column: &str) -> String {
        format!(
            "run {}: column {}.{column} is missing or malformed",
            self.run, self.table
        )
    }
}

/// The recorded plan of a cross-validation run from its three columns.
fn cross_validation_plan(columns: &Columns) -> anyhow::Result<Option<CrossValidationPlan>> {
    let Some(detector) = columns.get::<Option<String>>("cv_detector")? else {
        return Ok(None);
    };
    let folds: Option<i64> = columns.get("cv_folds")?;
    let folds = folds
        .and_then(|f| usize::try_from(f).ok())
        .with_context(|| columns.malformed("cv_folds"))?;
    let fold = match columns.get::<Option<i64>>("cv_fold")? {
        None => None,
        Some(fold) => Some(usize::try_from(fold).with_context(|| columns.malformed("cv_fold"))?),
    };
    Ok(Some(CrossValidationPlan {
        detector,
        folds,
        fold,
    }))
}

/// The step counts of a `runs` row.
fn step_counts(columns: &Columns) -> anyhow::Result<StepCounts> {
    Ok(StepCounts {
        cached: columns.count("cached_steps")?,
        computed: columns.count("computed_steps")?,
        rebuilt: columns.count("rebuilt_steps")?,
    })
}

impl Registry {
    /// Every row `sql` (with run `id` as `?1`) returns from `table`, each
    /// read by `read`.
    fn rows_of_run<T>(
        &self,
        table: &'static str,
        id: &str,
        sql: &str,
        read: impl Fn(&Columns) -> anyhow::Result<T>,
    ) -> anyhow::Result<Vec<T>> {
        let mut statement = self
            .conn
            .prepare(sql)
            .with_context(|| format!("run {id}: reading table {table}"))?;
        let mut rows = statement.query([id])?;
        let mut read_rows = Vec::new();
        while let Some(row) = rows.next()? {
            read_rows.push(read(&Columns {
                row,
                table,
                run: id,
            })?);
        }
        Ok(read_rows)
    }

    /// Every run, newest first, with its status in effect.
    pub fn runs(&self) -> anyhow::Result<Vec<RunSummary>> {
        let mut statement = self
            .conn
            .prepare(
                "SELECT id, kind, manifest_name, status, started_at, ended_at, cached_steps,
                    computed_steps, rebuilt_steps, git_commit, git_dirty, host, pid
             FROM runs ORDER BY started_at DESC, id DESC",
            )
            .context("listing the runs")?;
        let mut rows = statement.query([])?;
        let mut runs = Vec::new();
        while let Some(row) = rows.next()? {
            let id: String = row.get("id")?;
            let columns = Columns {
                row,
                table: "runs",
                run: &id,
            };
            let recorded = columns.parse("status", RunStatus::parse)?;
            runs.push(RunSummary {
                kind: columns.parse("kind", RunKind::parse)?,
                manifest_name: columns.get("manifest_name")?,
                status: recorded.in_effect(&columns.get::<String>("host")?, columns.get("pid")?),
                started_at: columns.get("started_at")?,
                ended_at: columns.get("ended_at")?,
                counts: step_counts(&columns)?,
                git_commit: columns.get("git_commit")?,
                git_dirty: columns.get("git_dirty")?,
                id,
            });
        }
        Ok(runs)
    }

    /// The newest run of `kind` that ended `done`, if any.
    pub fn latest_done_run(&self, kind: RunKind) -> anyhow::Result<Option<RunSummary>> {
        Ok(self
            .runs()?
            .into_iter()
            .find(|run| run.kind == kind && run.status == RunStatus::Done))
    }

    /// Run `id` in full: its record, steps and AUC table.
    pub fn run_record(&self, id: &str) -> anyhow::Result<RunRecord> {
        let mut records = self.rows_of_run(
            "runs",
            id,
            "SELECT id, kind, parent_run, manifest_name, manifest_path, manifest_text,
                    manifest_sha256, resolved, seeds, crate_version, git_commit, git_dirty, rustc,
                    host, pid, threads, forced, started_at, ended_at, status, error,
                    cached_steps, computed_steps, rebuilt_steps, cv_detector, cv_folds, cv_fold
             FROM runs WHERE id = ?1",
            |columns| {
                let host: String = columns.get("host")?;
                let pid: i64 = columns.get("pid")?;
                let recorded_status = columns.parse("status", RunStatus::parse)?;
                Ok(RunRecord {
                    id: id.to_string(),
                    kind: columns.parse("kind", RunKind::parse)?,
                    parent_run: columns.get("parent_run")?,
                    manifest_name: columns.get("manifest_name")?,
                    manifest_path: columns.get("manifest_path")?,
                    manifest_text: columns.get("manifest_text")?,
                    manifest_sha256: columns.get("manifest_sha256")?,
                    resolved: columns.json("resolved")?,
                    seeds: columns.json("seeds")?,
                    code: CodeVersion {
                        crate_version: columns.get("crate_version")?,
                        git_commit: columns.get("git_commit")?,
                        git_dirty: columns.get("git_dirty")?,
                        rustc: columns.get("rustc")?,
                    },
                    status: recorded_status.in_effect(&host, pid),
                    pid: u32::try_from(pid).with_context(|| columns.malformed("pid"))?,
                    host,
                    threads: columns.count("threads")?,
                    forced: columns.get("forced")?,
                    started_at: columns.get("started_at")?,
                    ended_at: columns.get("ended_at")?,
                    error: columns.get("error")?,
                    counts: step_counts(columns)?,
                    cross_validation: cross_validation_plan(columns)?,
                    steps: Vec::new(),
                    auc: Vec::new(),
                })
            },
        )?;
        let Some(mut record) = records.pop() else {
            return Err(input_error(format!("{id}: no such run")));
        };
        record.steps = self.rows_of_run(
            "run_steps",
            id,
            "SELECT ordinal, step, kind, artefact_key, outcome, seconds, blobs, detail
             FROM run_steps WHERE run_id = ?1 ORDER BY ordinal",
            |columns| {
                let blobs: BTreeMap<BlobRole, String> = columns.json("blobs")?;
                Ok(StepRecord {
                    ordinal: columns.count("ordinal")?,
                    step: columns.parse("step", |text| text.parse().ok())?,
                    kind: columns.parse("kind", |text| ArtefactKind::parse(text).ok())?,
                    artefact_key: columns.get("artefact_key")?,
                    outcome: columns.parse("outcome", StepOutcome::parse)?,
                    seconds: columns.get("seconds")?,
                    blobs: blobs
                        .into_iter()
                        .map(|(role, sha256)| BlobRef { role, sha256 })
                        .collect(),
                    detail: columns.get("detail")?,
                })
            },
        )?;
        record.auc = self.rows_of_run(
            "run_auc",
            id,
            "SELECT detector, dataset, diffusion, eps_px, auc, auc_best_per_frame, evaluation_key
             FROM run_auc WHERE run_id = ?1 ORDER BY rowid",
            |columns| {
                Ok(AucRow {
                    detector: columns.get("detector")?,
                    dataset: columns.get("dataset")?,
                    diffusion: columns.get("diffusion")?,
                    eps_px: columns.get("eps_px")?,
                    auc: columns.get("auc")?,
                    auc_best_per_frame: columns.get("auc_best_per_frame")?,
                    evaluation_key: columns.get("evaluation_key")?,
                })
            },
        )?;
        Ok(record)
    }

    /// Whether a run with exactly this id exists.
    pub(super) fn run_exists(&self, id: &str) -> anyhow::Result<bool> {
        Ok(self
            .conn
            .query_row("SELECT 1 FROM runs WHERE id = ?1", [id], |_| Ok(()))
            .optional()?
            .is_some())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for kind in [
            RunKind::Run,
            RunKind::Reproduce,
            RunKind::Cv,
            RunKind::Calibrate,
            RunKind::Sweep,
        ] {
            assert_eq!(RunKind::parse(kind.as_str()), Some(kind));
        }
        for outcome in [
            StepOutcome::Cached,
            StepOutcome::Computed,
            StepOutcome::Rebuilt,
        ] {
            assert_eq!(StepOutcome::parse(outcome.as_str()), Some(outcome));
        }
        assert_eq!(RunStatus::parse("done"), Some(RunStatus::Done));
        assert_eq!(RunKind::parse("grid"), None);
        assert_eq!(format!("{:<9}|", StepOutcome::Cached), "cached   |");
    }

    fn start(id: &str, kind: RunKind, cv: Option<CrossValidationPlan>) -> RunStart {
        RunStart {
            id: id.to_string(),
            kind,
            parent_run: None,
            manifest_name: "m".into(),
            manifest_path: "m.yaml".into(),
            manifest_text: "name: m\n".into(),
            manifest_sha256: "00".into(),
            resolved_json: "{}".into(),
            seeds_json: r#"{"dataset/a": "18446744073709551615"}"#.into(),
            forced: false,
            cross_validation: cv,
        }
    }

    #[test]
    fn a_run_reads_back_as_recorded() {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::open(dir.path()).unwrap();
        let cv = CrossValidationPlan {
            detector: "cnn".into(),
            folds: 3,
            fold: Some(2),
        };
        registry
            .begin_run(&start("r1", RunKind::Cv, Some(cv.clone())))
            .unwrap();
        let step = StepRecord {
            ordinal: 0,
            step: StepId::Dataset("a".into()),
            kind: ArtefactKind::Dataset,
            artefact_key: "k".into(),
            outcome: StepOutcome::Rebuilt,
            seconds: 0.5,
            blobs: vec![BlobRef {
                role: BlobRole::Frames,
                sha256: "ab".into(),
            }],
            detail: None,
        };
        registry.record_step("r1", &step).unwrap();
        let counts = StepCounts {
            cached: 0,
            computed: 0,
            rebuilt: 1,
        };
        let auc = AucRow {
            detector: "cnn-cv2of3".into(),
            dataset: "x-held-out".into(),
            diffusion: Some(0.75),
            eps_px: 1.0,
            auc: 0.25,
            auc_best_per_frame: Some(0.125),
            evaluation_key: "e".into(),
        };
        registry
            .finish_run(
                "r1",
                RunStatus::Done,
                None,
                counts,
                std::slice::from_ref(&auc),
            )
            .unwrap();
        let record = registry.run_record("r1").unwrap();
        assert_eq!(record.kind, RunKind::Cv);
        assert_eq!(record.status, RunStatus::Done);
        assert_eq!(record.cross_validation, Some(cv));
        assert_eq!(record.counts, counts);
        assert_eq!(record.steps, [step]);
        assert_eq!(record.auc, [auc]);
        assert_eq!(record.seeds["dataset/a"], u64::MAX.to_string());
        let summary = &registry.runs().unwrap()[0];
        assert_eq!((summary.kind, summary.counts), (RunKind::Cv, counts));

        // A plain run has no plan.
        registry
            .begin_run(&start("r2", RunKind::Run, None))
            .unwrap();
        assert_eq!(registry.run_record("r2").unwrap().cross_validation, None);
    }

    #[test]
    fn a_malformed_column_is_an_error_naming_the_run_and_the_column() {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::open(dir.path()).unwrap();
        registry
            .begin_run(&start("r1", RunKind::Run, None))
            .unwrap();
        for (sql, column) in [
            ("UPDATE runs SET seeds = 'not json'", "runs.seeds"),
            ("UPDATE runs SET kind = 'grid'", "runs.kind"),
            ("UPDATE runs SET threads = -1", "runs.threads"),
            ("UPDATE runs SET cv_detector = 'cnn'", "runs.cv_folds"),
        ] {
            let fresh = tempfile::tempdir().unwrap();
            let mut copy = Registry::open(fresh.path()).unwrap();
            copy.begin_run(&start("r1", RunKind::Run, None)).unwrap();
            copy.connection().execute_batch(sql).unwrap();
            let error = format!("{:#}", copy.run_record("r1").unwrap_err());
            assert!(
                error.contains("run r1") && error.contains(column),
                "{sql}: {error}"
            );
        }
        registry
            .record_step(
                "r1",
                &StepRecord {
                    ordinal: 0,
                    step: StepId::Dataset("a".into()),
                    kind: ArtefactKind::Dataset,
                    artefact_key: "k".into(),
                    outcome: StepOutcome::Computed,
                    seconds: 1.0,
                    blobs: Vec::new(),
                    detail: None,
                },
            )
            .unwrap();
        // The schema's CHECK keeps outcomes valid; a renamed column is
        // what a reader must not paper over.
        registry
            .connection()
            .execute_batch("ALTER TABLE run_steps RENAME COLUMN seconds TO duration")
            .unwrap();
        let error = format!("{:#}", registry.run_record("r1").unwrap_err());
        assert!(error.contains("run r1"), "{error}");
    }

    #[test]
    fn only_a_running_run_of_a_dead_process_here_is_unfinished() {
        let here = host_name();
        let own = i64::from(std::process::id());
        // No process has a pid this large on Linux (pid_max ≤ 2²²).
        let dead = i64::from(u32::MAX);
        assert_eq!(RunStatus::Running.in_effect(&here, own), RunStatus::Running);
        assert_eq!(
            RunStatus::Running.in_effect(&here, dead),
            if std::path::Path::new("/proc/self").exists() {
                RunStatus::Unfinished
            } else {
                RunStatus::Running
            }
        );
        assert_eq!(
            RunStatus::Running.in_effect("another-host.invalid", dead),
            RunStatus::Running
        );
        assert_eq!(RunStatus::Done.in_effect(&here, dead), RunStatus::Done);
    }
}
