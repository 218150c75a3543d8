//! The registry: a SQLite database (`registry.sqlite`) mapping content keys
//! of artefacts to the hashes of their stored bytes, plus the record of
//! every run; blobs live beside it (see [`blobs`]). The schema is in
//! `schema.sql`, `schema_v2.sql` (a cross-validation run's plan) and
//! `schema_v3.sql` (the best-guess-per-frame AUC of ranked lists), and
//! documented in `docs/registry.md`. Writing is here; reading back is in
//! [`record`] (runs, typed), [`sql`] (listings, artefacts, read-only SQL),
//! [`models`] (trained models by run and detector, or by key),
//! [`verify`], [`gc`] and [`diff`].
//!
//! Concurrency: the database is in WAL mode with a long busy timeout and
//! every write is a short `BEGIN IMMEDIATE` transaction, so several runs can
//! share one registry (readers never block, writers queue). Schema
//! migrations run once, inside such a transaction, so concurrent first
//! opens cannot both apply them. Two runs that compute the same artefact at
//! once both write the same blob (identical bytes, atomic rename) and the
//! second insert finds the first.

pub mod blobs;
pub mod dates;
pub mod diff;
pub mod gc;
pub mod hashing;
pub mod models;
pub mod record;
pub mod shard;
pub mod sql;
pub mod sql_guard;
pub mod step_id;
pub mod table;
pub mod verify;
pub mod write_lock;

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use rusqlite::{Connection, OpenFlags, OptionalExtension, params};
use serde::{Deserialize, Serialize};

pub use blobs::{BlobState, BlobStore};
pub use dates::utc_now;
pub use models::{ModelOrigin, StoredModel};
pub use record::{
    AucRow, CrossValidationPlan, RunKind, RunRecord, RunStart, RunStatus, RunSummary, StepCounts,
    StepOutcome, StepRecord,
};
pub use sql::{EvaluationRow, Found};
pub use step_id::{BlobRole, StepId};
pub use table::Table;

use crate::error::input_error;
use write_lock::{Holder, WriteTransaction};

/// The schema version this code writes; see `schema.sql` (version 1),
/// `schema_v2.sql` and `schema_v3.sql` (the migrations to versions 2 and 3).
pub const SCHEMA_VERSION: i64 = 3;
const SCHEMA_V1: &str = include_str!("schema.sql");
const SCHEMA_V2: &str = include_str!("schema_v2.sql");
const SCHEMA_V3: &str = include_str!("schema_v3.sql");

/// The database file name inside a registry folder.
pub const DATABASE_FILE: &str = "registry.sqlite";

/// How long a writer waits for another's transaction before giving up.
const BUSY_TIMEOUT: Duration = Duration::from_secs(300);

/// The kinds of artefact the registry stores.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ArtefactKind {
    Dataset,
    Model,
    Predictions,
    Evaluation,
}

impl ArtefactKind {
    pub fn as_str(self) -> &'static str {
        match self {
            ArtefactKind::Dataset => "dataset",
            ArtefactKind::Model => "model",
            ArtefactKind::Predictions => "predictions",
            ArtefactKind::Evaluation => "evaluation",
        }
    }

    fn parse(text: &str) -> anyhow::Result<Self> {
        Ok(match text {
            "dataset" => ArtefactKind::Dataset,
            "model" => ArtefactKind::Model,
            "predictions" => ArtefactKind::Predictions,
            "evaluation" => ArtefactKind::Evaluation,
            other => anyhow::bail!("unknown artefact kind {other:?} in the registry"),
        })
    }
}

/// One stored blob of an artefact.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BlobRef {
    /// What the blob is within its artefact (`frames.npy`, `score.json`, …).
    pub role: BlobRole,
    pub sha256: String,
}

/// An artefact as the registry knows it.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredArtefact {
    pub key: String,
    pub kind: ArtefactKind,
    pub name: String,
    pub blobs: Vec<BlobRef>,
}

/// The typed facts about a new artefact that go into its kind's table.
#[derive(Debug, Clone)]
pub enum ArtefactDetails {
    Dataset {
        frames: usize,
        height: usize,
        width: usize,
        seed: u64,
        diffusion: Option<f64>,
        /// N_qd: the `brightness` column holds the number when it is fixed
        /// and the distribution's text form (`uniform:5,10`) otherwise.
        brightness: crate::types::Distribution,
        params_json: String,
    },
    Model {
        detector: String,
        detector_kind: crate::types::DetectorKind,
        training_dataset_key: String,
        seed: u64,
    },
    Predictions {
        detector: String,
        dataset_key: String,
        model_key: Option<String>,
        count: usize,
    },
    Evaluation {
        detector: String,
        dataset: String,
        dataset_key: String,
        predictions_key: String,
        rmse_top_px: Option<f64>,
        fraction_without_prediction: f64,
        /// One row of the `auc` table per ε.
        auc: Vec<EvaluationAuc>,
    },
}

/// One ε of an evaluation as the `auc` table holds it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvaluationAuc {
    pub eps_px: f64,
    /// The AUC of every prediction (for ranked lists: the whole lists).
    pub auc: f64,
    /// The AUC of each frame's best prediction alone (`None` in an
    /// evaluation stored before it existed).
    pub auc_best_per_frame: Option<f64>,
    pub true_positives: usize,
    pub false_positives: usize,
}

/// A per-frame simulator parameter as a registry column holds it: a REAL
/// when it is fixed, so existing queries and rows keep their numbers, and
/// the distribution's text form (`uniform:5,10`, as the flags take it)
/// when it is drawn per frame.
fn per_frame_column(value: &crate::types::Distribution) -> rusqlite::types::Value {
    match value.fixed() {
        Some(number) => rusqlite::types::Value::Real(number),
        None => rusqlite::types::Value::Text(value.to_string()),
    }
}

/// A new artefact to record: its blobs must already be in the blob store.
#[derive(Debug, Clone)]
pub struct NewArtefact {
    pub key: String,
    pub kind: ArtefactKind,
    pub name: String,
    /// The canonical JSON `key` is the sha256 of.
    pub spec: String,
    pub code_version: String,
    pub run_id: Option<String>,
    pub compute_seconds: f64,
    pub blobs: Vec<BlobRef>,
    pub details: ArtefactDetails,
}

/// What the build and the machine were: recorded with every run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CodeVersion {
    pub crate_version: String,
    pub git_commit: String,
    pub git_dirty: String,
    pub rustc: String,
}

impl CodeVersion {
    /// The version of this binary (stamped by `build.rs`).
    pub fn current() -> Self {
        Self {
            crate_version: env!("CARGO_PKG_VERSION").to_string(),
            git_commit: env!("SCANLOC_GIT_COMMIT").to_string(),
            git_dirty: env!("SCANLOC_GIT_DIRTY").to_string(),
            rustc: env!("SCANLOC_RUSTC_VERSION").to_string(),
        }
    }
}

/// The host name (`unknown` if the system does not say).
pub fn host_name() -> String {
    for path in ["/proc/sys/kernel/hostname", "/etc/hostname"] {
        if let Ok(name) = std::fs::read_to_string(path) {
            let name = name.trim();
            if !name.is_empty() {
                return name.to_string();
            }
        }
    }
    std::env::var("HOSTNAME")
        .or_else(|_| std::env::var("COMPUTERNAME"))
        .unwrap_or_else(|_| "unknown".to_string())
}

/// Whether process `pid` is alive on this machine (Linux `/proc`; on other
/// systems every process is assumed alive).
pub fn process_alive(pid: u32) -> bool {
    if !Path::new("/proc/self").exists() {
        return true;
    }
    Path::new(&format!("/proc/{pid}")).exists()
}

/// An open registry: database connection plus blob store.
pub struct Registry {
    dir: PathBuf,
    conn: Connection,
    blobs: BlobStore,
    /// Opened from a folder this process cannot write (a read-only mount,
    /// no write permission): artefacts are served, runs are not recorded.
    read_only: bool,
    /// The run this process is recording (from `begin_run` to
    /// `finish_run`), named to writers waiting for the write lock.
    writer_run: Option<String>,
}

impl Registry {
    /// Opens the registry in `dir`, creating it (and applying migrations)
    /// if needed.
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| {
            input_error(format!(
                "{}: cannot create the registry: {e}",
                dir.display()
            ))
        })?;
        if !writable(dir) {
            return Self::connect_read_only(dir);
        }
        Self::connect(dir, Integrity::CheckBeforeWriting)
    }

    /// Opens the registry in `dir`, which cannot be written, read-only (see
    /// [`open_database_read_only`]); blobs are read, nothing is created.
    fn connect_read_only(dir: &Path) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        let path = dir.join(DATABASE_FILE);
        if !path.is_file() {
            return Err(input_error(format!(
                "{}: cannot create a registry here (the folder is read-only)",
                dir.display()
            )));
        }
        let conn = open_database_read_only(dir)?;
        let schema: i64 = conn.query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if schema != SCHEMA_VERSION {
            return Err(input_error(format!(
                "{}: the registry is read-only and its schema (version {schema}) is not this scanloc's ({SCHEMA_VERSION}); open it once where it can be written",
                dir.display()
            )));
        }
        conn.busy_timeout(BUSY_TIMEOUT)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            conn,
            blobs: BlobStore::read_only(dir),
            read_only: true,
            writer_run: None,
        })
    }

    /// Refuses, as bad input, a `command` that needs to write on a
    /// registry opened read-only.
    pub fn refuse_read_only(&self, command: &str) -> anyhow::Result<()> {
        if self.read_only {
            return Err(input_error(format!(
                "the registry at {} is read-only; {command} needs to write",
                self.dir.display()
            )));
        }
        Ok(())
    }

    /// [`Registry::open`] for a `command` that writes: a registry that
    /// cannot be written is refused (see [`Registry::refuse_read_only`]).
    pub fn open_to_write(dir: &Path, command: &str) -> anyhow::Result<Self> {
        let registry = Self::open(dir)?;
        registry.refuse_read_only(command)?;
        Ok(registry)
    }

    /// Begins a write transaction (`BEGIN IMMEDIATE`), waiting for the
    /// write lock and saying whose it is (see [`write_lock`]).
    fn write_transaction(&self) -> anyhow::Result<WriteTransaction<'_>> {
        WriteTransaction::begin(
            &self.conn,
            &self.dir,
            &Holder::this_process(self.writer_run.as_deref()),
            BUSY_TIMEOUT,
        )
    }

    /// Whether this registry was opened read-only (see [`Registry::open`]):
    /// run records are then not kept.
    pub fn is_read_only(&self) -> bool {
        self.read_only
    }

    /// Opens an existing registry; a folder without a database is bad input.
    /// A registry this process cannot write (a read-only mount, no write
    /// permission, or [`SCANLOC_REGISTRY_READ_ONLY`]) is opened read-only,
    /// so every command that only reads works on it (see
    /// [`Registry::refuse_read_only`] for those that write).
    ///
    /// [`SCANLOC_REGISTRY_READ_ONLY`]: crate::env_vars::SCANLOC_REGISTRY_READ_ONLY
    pub fn open_existing(dir: &Path) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        if !dir.join(DATABASE_FILE).is_file() {
            return Err(input_error(format!(
                "{}: no registry here (no {DATABASE_FILE}); `scanloc run` creates one",
                dir.display()
            )));
        }
        if !writable(dir) {
            return Self::connect_read_only(dir);
        }
        Self::connect(dir, Integrity::Unchecked)
    }

    fn connect(dir: &Path, integrity: Integrity) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        let path = dir.join(DATABASE_FILE);
        create_database_file(&path)?;
        let conn = Connection::open(&path).map_err(|e| {
            input_error(format!("{}: cannot open the registry: {e}", path.display()))
        })?;
        conn.busy_timeout(BUSY_TIMEOUT)?;
        // Switching to WAL needs a moment without other connections; retry
        // while a concurrent first open holds the file.
        let mut attempts = 0;
        loop {
            match conn.query_row("PRAGMA journal_mode = WAL", [], |row| {
                row.get::<_, String>(0)
            }) {
                Ok(_) => break,
                Err(e) if attempts < 200 && is_busy(&e) => {
                    attempts += 1;
                    std::thread::sleep(Duration::from_millis(50));
                }
                Err(e) if is_damage(&e) => return Err(damaged(dir, &e.to_string())),
                Err(e) => {
                    return Err(input_error(format!(
                        "{}: cannot open the registry database for shared use: {e}",
                        path.display()
                    )));
                }
            }
        }
        if integrity == Integrity::CheckBeforeWriting {
            // Milliseconds for a registry's database (it holds records, not
            // data); a damaged one would take every later write with it.
            let verdict: String = conn
                .query_row("PRAGMA quick_check(1)", [], |row| row.get(0))
                .or_else(|e| {
                    if is_damage(&e) {
                        Ok(e.to_string())
                    } else {
                        Err(e)
                    }
                })?;
            if verdict != "ok" {
                return Err(damaged(dir, &verdict));
            }
        }
        conn.execute_batch("PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = ON;")?;
        // Who is computing which step now: a table of the moment, not of the
        // record (rows live while a step is computed), so it needs no schema
        // version and older scanloc versions ignore it.
        conn.execute_batch(STEP_CLAIMS)?;
        let mut registry = Self {
            dir: dir.to_path_buf(),
            conn,
            blobs: BlobStore::open(dir)?,
            read_only: false,
            writer_run: None,
        };
        registry.migrate()?;
        Ok(registry)
    }

    /// Applies missing schema migrations, once, under the write lock.
    fn migrate(&mut self) -> anyhow::Result<()> {
        let version: i64 = self
            .conn
            .query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if version == SCHEMA_VERSION {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        // Read again under the lock: another process may have migrated.
        let version: i64 = tx.query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if version > SCHEMA_VERSION {
            return Err(input_error(format!(
                "{}: registry schema version {version} is newer than this scanloc understands ({SCHEMA_VERSION})",
                self.dir.display()
            )));
        }
        if version < 1 {
            tx.execute_batch(SCHEMA_V1)
                .context("creating the registry schema")?;
        }
        if version < 2 {
            tx.execute_batch(SCHEMA_V2)
                .context("migrating the registry schema to version 2")?;
            backfill_cross_validation_plans(&tx)
                .context("recording the plans of earlier cross-validation runs")?;
        }
        if version < 3 {
            tx.execute_batch(SCHEMA_V3)
                .context("migrating the registry schema to version 3")?;
        }
        tx.execute_batch(&format!("PRAGMA user_version = {SCHEMA_VERSION}"))?;
        tx.commit()?;
        Ok(())
    }

    /// The registry folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The blob store.
    pub fn blobs(&self) -> &BlobStore {
        &self.blobs
    }

    /// The raw connection, for queries.
    pub fn connection(&self) -> &Connection {
        &self.conn
    }

    /// The artefact stored under `key`, if any.
    pub fn artefact(&self, key: &str) -> anyhow::Result<Option<StoredArtefact>> {
        let row = self
            .conn
            .query_row(
                "SELECT kind, name FROM artefacts WHERE key = ?1",
                [key],
                |row| Ok((row.get::<_, String>(0)?, row.get::<_, String>(1)?)),
            )
            .optional()?;
        let Some((kind, name)) = row else {
            return Ok(None);
        };
        let mut statement = self.conn.prepare_cached(
            "SELECT role, sha256 FROM artefact_blobs WHERE artefact_key = ?1 ORDER BY role",
        )?;
        let blobs = statement
            .query_map([key], |row| {
                Ok(BlobRef {
                    role: row.get(0)?,
                    sha256: row.get(1)?,
                })
            })?
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Some(StoredArtefact {
            key: key.to_string(),
            kind: ArtefactKind::parse(&kind)?,
            name,
            blobs,
        }))
    }

    /// Records an artefact whose blobs are stored. If the key is already
    /// recorded with the same blobs, nothing changes. If it is recorded with
    /// other blobs, `replace` says the old ones were damaged and are to be
    /// superseded; otherwise that is an error (the step is not
    /// deterministic, or two builds disagree).
    pub fn record_artefact(&mut self, artefact: &NewArtefact, replace: bool) -> anyhow::Result<()> {
        if self.read_only {
            return Err(input_error(format!(
                "{}: the registry is read-only: {} ({}) cannot be stored",
                self.dir.display(),
                artefact.name,
                artefact.key
            )));
        }
        let tx = self.write_transaction()?;
        let now = utc_now();
        insert_blob_rows(&tx, &self.blobs, &artefact.blobs, &now)?;
        let existing: Option<String> = tx
            .query_row(
                "SELECT key FROM artefacts WHERE key = ?1",
                [&artefact.key],
                |row| row.get(0),
            )
            .optional()?;
        if existing.is_some() {
            supersede_blobs_if_changed(&tx, artefact, replace)?;
        } else {
            insert_artefact(&tx, artefact, &now)?;
        }
        tx.commit()?;
        Ok(())
    }

    /// Records as `unfinished` every run whose status in effect is
    /// (see [`RunStatus::in_effect`]).
    pub fn mark_abandoned_runs(&mut self) -> anyhow::Result<usize> {
        if self.read_only {
            return Ok(0);
        }
        let candidates: Vec<(String, String, i64)> = {
            let mut statement = self
                .conn
                .prepare("SELECT id, host, pid FROM runs WHERE status = 'running'")?;
            statement
                .query_map([], |row| {
                    Ok((row.get("id")?, row.get("host")?, row.get("pid")?))
                })?
                .collect::<Result<_, _>>()?
        };
        let mut marked = 0;
        for (id, host, pid) in candidates {
            if RunStatus::Running.in_effect(&host, pid) == RunStatus::Unfinished {
                let tx = self.write_transaction()?;
                marked += tx.execute(
                    "UPDATE runs SET status = 'unfinished',
                       error = 'the process (pid ' || pid || ') ended without finishing the run'
                     WHERE id = ?1 AND status = 'running'",
                    [&id],
                )?;
                tx.commit()?;
            }
        }
        Ok(marked)
    }

    /// Records the start of a run (status `running`).
    pub fn begin_run(&mut self, start: &RunStart) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let code = CodeVersion::current();
        let cv = start.cross_validation.as_ref();
        self.writer_run = Some(start.id.clone());
        let tx = self.write_transaction()?;
        tx.execute(
            "INSERT INTO runs (id, kind, parent_run, manifest_name, manifest_path, manifest_text,
                 manifest_sha256, resolved, seeds, crate_version, git_commit, git_dirty, rustc, host,
                 pid, threads, forced, started_at, status, cv_detector, cv_folds, cv_fold)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18,
                 'running', ?19, ?20, ?21)",
            params![
                start.id,
                start.kind.as_str(),
                start.parent_run,
                start.manifest_name,
                start.manifest_path,
                start.manifest_text,
                start.manifest_sha256,
                start.resolved_json,
                start.seeds_json,
                code.crate_version,
                code.git_commit,
                code.git_dirty,
                code.rustc,
                host_name(),
                std::process::id() as i64,
                rayon::current_num_threads() as i64,
                start.forced,
                utc_now(),
                cv.map(|cv| cv.detector.as_str()),
                cv.map(|cv| cv.folds as i64),
                cv.and_then(|cv| cv.fold).map(|fold| fold as i64),
            ],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Records one finished step of a running run.
    pub fn record_step(&mut self, run_id: &str, step: &StepRecord) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let blobs: serde_json::Map<String, serde_json::Value> = step
            .blobs
            .iter()
            .map(|b| {
                (
                    b.role.to_string(),
                    serde_json::Value::String(b.sha256.clone()),
                )
            })
            .collect();
        let tx = self.write_transaction()?;
        tx.execute(
            "INSERT INTO run_steps (run_id, ordinal, step, kind, artefact_key, outcome, seconds, blobs, detail)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
            params![
                run_id,
                step.ordinal as i64,
                step.step.to_string(),
                step.kind.as_str(),
                step.artefact_key,
                step.outcome.as_str(),
                step.seconds,
                serde_json::Value::Object(blobs).to_string(),
                step.detail
            ],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Records the end of a run: its status, error, step counts and AUC table.
    pub fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        error: Option<&str>,
        counts: StepCounts,
        auc: &[AucRow],
    ) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        tx.execute(
            "UPDATE runs SET status = ?2, error = ?3, ended_at = ?4,
                 cached_steps = ?5, computed_steps = ?6, rebuilt_steps = ?7
             WHERE id = ?1",
            params![
                run_id,
                status.as_str(),
                error,
                utc_now(),
                counts.cached as i64,
                counts.computed as i64,
                counts.rebuilt as i64
            ],
        )?;
        for row in auc {
            tx.execute(
                "INSERT INTO run_auc (run_id, detector, dataset, diffusion, eps_px, auc, auc_best_per_frame, evaluation_key)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
                params![
                    run_id,
                    row.detector,
                    row.dataset,
                    row.diffusion,
                    row.eps_px,
                    row.auc,
                    row.auc_best_per_frame,
                    row.evaluation_key
                ],
            )?;
        }
        tx.commit()?;
        self.writer_run = None;
        Ok(())
    }
}

/// Records the plan of every cross-validation run made before schema 2.
/// Such a run left its plan only in its fold models' names
/// (`DETECTOR-cvKofN`) in its AUC rows; they are read here, once, so that
/// nothing else ever parses names. A run that recorded no AUC rows (it
/// was interrupted) keeps no plan: it is still listed and shown, and
/// `reproduce` says it cannot re-plan it.
fn backfill_cross_validation_plans(tx: &Connection) -> anyhow::Result<()> {
    let runs: Vec<String> = {
        let mut statement =
            tx.prepare("SELECT id FROM runs WHERE kind = 'cv' AND cv_detector IS NULL")?;
        statement
            .query_map([], |row| row.get("id"))?
            .collect::<Result<_, _>>()?
    };
    for run in runs {
        let detectors: Vec<String> = {
            let mut statement =
                tx.prepare("SELECT DISTINCT detector FROM run_auc WHERE run_id = ?1")?;
            statement
                .query_map([&run], |row| row.get("detector"))?
                .collect::<Result<_, _>>()?
        };
        let parsed: Vec<(&str, usize, usize)> = detectors
            .iter()
            .filter_map(|name| {
                let (detector, fold) = name.rsplit_once("-cv")?;
                let (fold, folds) = fold.split_once("of")?;
                Some((detector, fold.parse().ok()?, folds.parse().ok()?))
            })
            .collect();
        let Some(&(detector, _, folds)) = parsed.first() else {
            continue;
        };
        if parsed.iter().any(|&(d, _, n)| d != detector || n != folds) {
            continue;
        }
        let mut scored: Vec<usize> = parsed.iter().map(|&(_, fold, _)| fold).collect();
        scored.sort_unstable();
        scored.dedup();
        // One fold scored out of several: a `cv --fold K` run.
        let only_fold = match scored.as_slice() {
            [fold] if folds > 1 => Some(*fold as i64),
            _ => None,
        };
        tx.execute(
            "UPDATE runs SET cv_detector = ?2, cv_folds = ?3, cv_fold = ?4 WHERE id = ?1",
            params![run, detector, folds as i64, only_fold],
        )?;
    }
    Ok(())
}

/// A `blobs` row for each of `blobs` not recorded yet (its size read from
/// the store), dated `now`.
fn insert_blob_rows(
    tx: &Connection,
    store: &BlobStore,
    blobs: &[BlobRef],
    now: &str,
) -> anyhow::Result<()> {
    for blob in blobs {
        let bytes = std::fs::metadata(store.path(&blob.sha256))
            .map(|m| m.len())
            .unwrap_or(0);
        tx.execute(
            "INSERT OR IGNORE INTO blobs (sha256, bytes, created_at) VALUES (?1, ?2, ?3)",
            params![blob.sha256, bytes as i64, now],
        )?;
    }
    Ok(())
}

/// For an artefact already recorded: nothing if its blobs are the same;
/// else, with `replace` (the old blobs were damaged), records the new ones
/// in their place, and without it refuses (the step is not deterministic).
fn supersede_blobs_if_changed(
    tx: &Connection,
    artefact: &NewArtefact,
    replace: bool,
) -> anyhow::Result<()> {
    let mut statement = tx
        .prepare("SELECT role, sha256 FROM artefact_blobs WHERE artefact_key = ?1 ORDER BY role")?;
    let stored: Vec<BlobRef> = statement
        .query_map([&artefact.key], |row| {
            Ok(BlobRef {
                role: row.get(0)?,
                sha256: row.get(1)?,
            })
        })?
        .collect::<Result<_, _>>()?;
    drop(statement);
    let mut ours = artefact.blobs.clone();
    ours.sort_by_key(|r| r.role);
    if stored == ours {
        return Ok(());
    }
    if !replace {
        anyhow::bail!(
            "artefact {} ({}) is already stored with different content: the step that makes it is not deterministic",
            artefact.name,
            artefact.key
        );
    }
    tx.execute(
        "DELETE FROM artefact_blobs WHERE artefact_key = ?1",
        [&artefact.key],
    )?;
    insert_artefact_blobs(tx, artefact)?;
    Ok(())
}

/// Records a new artefact: its row, its blobs, and the row of its kind's
/// table (`datasets`, `models`, `predictions`, `evaluations` with `auc`).
fn insert_artefact(tx: &Connection, artefact: &NewArtefact, now: &str) -> anyhow::Result<()> {
    tx.execute(
        "INSERT INTO artefacts (key, kind, name, spec, code_version, created_at, created_by_run, compute_seconds)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
        params![
            artefact.key,
            artefact.kind.as_str(),
            artefact.name,
            artefact.spec,
            artefact.code_version,
            now,
            artefact.run_id,
            artefact.compute_seconds
        ],
    )?;
    insert_artefact_blobs(tx, artefact)?;
    insert_details(tx, &artefact.key, &artefact.name, &artefact.details)
}

/// The row of artefact `key` (named `name`) in its kind's table.
fn insert_details(
    tx: &Connection,
    key: &str,
    name: &str,
    details: &ArtefactDetails,
) -> anyhow::Result<()> {
    match details {
        ArtefactDetails::Dataset {
            frames,
            height,
            width,
            seed,
            diffusion,
            brightness,
            params_json,
        } => {
            tx.execute(
                "INSERT INTO datasets (key, name, frames, height, width, seed, diffusion, brightness, params)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
                params![
                    key,
                    name,
                    *frames as i64,
                    *height as i64,
                    *width as i64,
                    seed.to_string(),
                    diffusion,
                    per_frame_column(brightness),
                    params_json
                ],
            )?;
        }
        ArtefactDetails::Model {
            detector,
            detector_kind,
            training_dataset_key,
            seed,
        } => {
            tx.execute(
                "INSERT INTO models (key, detector, detector_kind, training_dataset_key, seed)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
                params![
                    key,
                    detector,
                    detector_kind.as_str(),
                    training_dataset_key,
                    seed.to_string()
                ],
            )?;
        }
        ArtefactDetails::Predictions {
            detector,
            dataset_key,
            model_key,
            count,
        } => {
            tx.execute(
                "INSERT INTO predictions (key, detector, dataset_key, model_key, count)
                 VALUES (?1, ?2, ?3, ?4, ?5)",
                params![key, detector, dataset_key, model_key, *count as i64],
            )?;
        }
        ArtefactDetails::Evaluation {
            detector,
            dataset,
            dataset_key,
            predictions_key,
            rmse_top_px,
            fraction_without_prediction,
            auc,
        } => {
            tx.execute(
                "INSERT INTO evaluations (key, detector, dataset, dataset_key, predictions_key, rmse_top_px, fraction_without_prediction)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7)",
                params![
                    key,
                    detector,
                    dataset,
                    dataset_key,
                    predictions_key,
                    rmse_top_px,
                    fraction_without_prediction
                ],
            )?;
            for row in auc {
                tx.execute(
                    "INSERT INTO auc (evaluation_key, eps_px, auc, auc_best_per_frame, true_positives, false_positives)
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                    params![
                        key,
                        row.eps_px,
                        row.auc,
                        row.auc_best_per_frame,
                        row.true_positives as i64,
                        row.false_positives as i64
                    ],
                )?;
            }
        }
    }
    Ok(())
}

/// Records which blobs make `artefact` (one row per role).
fn insert_artefact_blobs(tx: &Connection, artefact: &NewArtefact) -> rusqlite::Result<()> {
    for blob in &artefact.blobs {
        tx.execute(
            "INSERT INTO artefact_blobs (artefact_key, role, sha256) VALUES (?1, ?2, ?3)",
            params![artefact.key, blob.role, blob.sha256],
        )?;
    }
    Ok(())
}

const STEP_CLAIMS: &str = "CREATE TABLE IF NOT EXISTS step_claims (
    key TEXT PRIMARY KEY,
    run_id TEXT NOT NULL,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    claimed_at TEXT NOT NULL
)";

/// A run computing a step another run needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StepClaim {
    pub run_id: String,
    pub host: String,
    pub pid: i64,
}

impl Registry {
    /// Claims the computation of the artefact `key` for run `run_id` (this
    /// process), or returns the live claim of another run on this host to
    /// wait for. A claim by a process that is gone (the pid/host rule of
    /// unfinished runs) is taken over; one from another host is not waited
    /// for (its liveness cannot be known): both compute, as before claims.
    pub fn claim_step(&mut self, key: &str, run_id: &str) -> anyhow::Result<Option<StepClaim>> {
        if self.read_only {
            return Ok(None);
        }
        let tx = self.write_transaction()?;
        let holder: Option<StepClaim> = tx
            .query_row(
                "SELECT run_id, host, pid FROM step_claims WHERE key = ?1",
                [key],
                |row| {
                    Ok(StepClaim {
                        run_id: row.get(0)?,
                        host: row.get(1)?,
                        pid: row.get(2)?,
                    })
                },
            )
            .optional()?;
        if let Some(holder) = holder
            && holder.run_id != run_id
            && holder.host == host_name()
            && RunStatus::Running.in_effect(&holder.host, holder.pid) == RunStatus::Running
        {
            return Ok(Some(holder));
        }
        tx.execute(
            "INSERT OR REPLACE INTO step_claims (key, run_id, host, pid, claimed_at)
             VALUES (?1, ?2, ?3, ?4, ?5)",
            params![key, run_id, host_name(), std::process::id(), utc_now()],
        )?;
        tx.commit()?;
        Ok(None)
    }

    /// Releases run `run_id`'s claim on `key` (all its claims with `None`).
    pub fn release_claims(&mut self, run_id: &str, key: Option<&str>) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        tx.execute(
            "DELETE FROM step_claims WHERE run_id = ?1 AND (?2 IS NULL OR key = ?2)",
            params![run_id, key],
        )?;
        tx.commit()?;
        Ok(())
    }
}

/// Creates the (empty) database file if missing, with mode 0666 minus the
/// umask like any other file a user makes (SQLite's own default is 0644
/// whatever the umask; its `-wal` and `-shm` files copy the database's
/// mode), so that a group sharing a registry can share its database.
fn create_database_file(path: &Path) -> anyhow::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o666);
    }
    match options.open(path) {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => Err(input_error(format!(
            "{}: cannot create the registry database: {e}",
            path.display()
        ))),
    }
}

/// Whether every registry is to be opened read-only
/// ([`SCANLOC_REGISTRY_READ_ONLY`](crate::env_vars::SCANLOC_REGISTRY_READ_ONLY)
/// is true; a value that is not a boolean, which the CLI refuses, counts as
/// true).
fn read_only_forced() -> bool {
    crate::env_vars::flag(crate::env_vars::SCANLOC_REGISTRY_READ_ONLY).unwrap_or(true)
}

/// Whether this process can create files in `dir` and write its database
/// (tried, not inferred from permission bits, which do not apply to root
/// or to a read-only mount); never for an existing registry when read-only
/// is forced (a new one, such as `reproduce`'s scratch registry, is made).
fn writable(dir: &Path) -> bool {
    if read_only_forced() && dir.join(DATABASE_FILE).is_file() {
        return false;
    }
    let refused = |e: &std::io::Error| {
        matches!(
            e.kind(),
            std::io::ErrorKind::ReadOnlyFilesystem | std::io::ErrorKind::PermissionDenied
        )
    };
    let database = dir.join(DATABASE_FILE);
    if database.is_file()
        && let Err(e) = std::fs::OpenOptions::new().write(true).open(&database)
        && refused(&e)
    {
        return false;
    }
    match tempfile::Builder::new()
        .prefix(".scanloc-write-probe-")
        .tempfile_in(dir)
    {
        Ok(_) => true,
        Err(e) => !refused(&e),
    }
}

/// Opens the database of the registry in `dir` for reading only, creating
/// no file: as a database others may be writing (`mode=ro`) while SQLite
/// can share it so, else (a read-only folder holds no write-ahead-log
/// index for it, and none can be made) as an immutable file. With
/// [`SCANLOC_REGISTRY_READ_ONLY`](crate::env_vars::SCANLOC_REGISTRY_READ_ONLY)
/// it is opened immutable at once (a shared read would create that index).
pub fn open_database_read_only(dir: &Path) -> anyhow::Result<Connection> {
    let path = dir.join(DATABASE_FILE);
    let flags = OpenFlags::SQLITE_OPEN_READ_ONLY
        | OpenFlags::SQLITE_OPEN_URI
        | OpenFlags::SQLITE_OPEN_NO_MUTEX;
    let cannot = |e: rusqlite::Error| {
        input_error(format!("{}: cannot read the registry: {e}", path.display()))
    };
    let readable = |conn: &Connection| {
        conn.query_row("PRAGMA user_version", [], |row| row.get::<_, i64>(0))
            .map(|_| ())
    };
    if !read_only_forced() {
        let conn =
            Connection::open_with_flags(database_uri(&path, "mode=ro"), flags).map_err(cannot)?;
        match readable(&conn) {
            Ok(()) => return Ok(conn),
            // Where the folder can be written, a shared read should work:
            // the error is the database's, not the folder's.
            Err(e) if writable(dir) => return Err(cannot(e)),
            Err(_) => {}
        }
    }
    let conn = Connection::open_with_flags(database_uri(&path, "mode=ro&immutable=1"), flags)
        .map_err(cannot)?;
    readable(&conn).map_err(cannot)?;
    Ok(conn)
}

/// The SQLite URI of the file `path` with `options`: every byte of the
/// path but unreserved ASCII percent-encoded, so no character of a folder
/// name (`%`, `?`, `#`, spaces, bytes that are not UTF-8) is read as URI
/// syntax.
fn database_uri(path: &Path, options: &str) -> String {
    #[cfg(unix)]
    let bytes = {
        use std::os::unix::ffi::OsStrExt;
        path.as_os_str().as_bytes().to_vec()
    };
    #[cfg(not(unix))]
    let bytes = path.to_string_lossy().into_owned().into_bytes();
    // An absolute path after an empty authority (`file:///…`), so that
    // one starting with `//` is not read as a host name.
    let mut uri = String::from(if path.is_absolute() {
        "file://"
    } else {
        "file:"
    });
    for byte in bytes {
        if byte.is_ascii_alphanumeric() || b"/._-~".contains(&byte) {
            uri.push(byte as char);
        } else {
            uri.push_str(&format!("%{byte:02X}"));
        }
    }
    uri.push('?');
    uri.push_str(options);
    uri
}

/// Whether a registry is checked for damage when opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Integrity {
    /// Before anything is written (runs): a damaged database is refused.
    CheckBeforeWriting,
    /// For reading and auditing (`registry verify` must open a damaged one).
    Unchecked,
}

/// Whether SQLite says the database file is not a sound database.
fn is_damage(error: &rusqlite::Error) -> bool {
    matches!(
        error.sqlite_error_code(),
        Some(rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase)
    )
}

/// The refusal to write into a damaged registry database.
fn damaged(dir: &Path, problem: &str) -> anyhow::Error {
    let path = dir.join(DATABASE_FILE);
    input_error(format!(
        "{}: the registry database is damaged ({}), so nothing is written to it; \
         `scanloc registry verify --registry {}` shows what is wrong; restore {DATABASE_FILE} \
         from a backup, or save what still reads with `sqlite3 {} .recover`",
        path.display(),
        problem.lines().next().unwrap_or(problem),
        dir.display(),
        path.display()
    ))
}

/// Refuses to start a new database in a registry whose database is gone or
/// empty while its blob store holds artefacts: that database was lost (a
/// truncation, a bad copy), and a new one would silently forget every run.
fn refuse_lost_database(dir: &Path) -> anyhow::Result<()> {
    let path = dir.join(DATABASE_FILE);
    let state = match std::fs::metadata(&path) {
        Ok(metadata) if metadata.len() > 0 => return Ok(()),
        Ok(_) => "is empty (0 bytes)",
        Err(_) => "is missing",
    };
    let blobs = dir.join("blobs");
    let holds_blobs = std::fs::read_dir(&blobs)
        .into_iter()
        .flatten()
        .flatten()
        .any(|prefix| {
            std::fs::read_dir(prefix.path()).is_ok_and(|mut files| files.next().is_some())
        });
    if !holds_blobs {
        return Ok(());
    }
    Err(input_error(format!(
        "{}: {DATABASE_FILE} {state} but {} holds stored artefacts: the record of the runs was \
         lost, and scanloc will not start a new one over it; restore {DATABASE_FILE} from a \
         backup, or move the folder aside to start a new registry",
        dir.display(),
        blobs.display()
    )))
}

fn is_busy(error: &rusqlite::Error) -> bool {
    matches!(
        error,
        rusqlite::Error::SqliteFailure(e, _)
            if e.code == rusqlite::ErrorCode::DatabaseBusy || e.code == rusqlite::ErrorCode::DatabaseLocked
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blobs_round_trip_and_damage_is_detected() {
        let dir = tempfile::tempdir().unwrap();
        let registry = Registry::open(dir.path()).unwrap();
        let sha = registry.blobs().put(b"hello").unwrap();
        assert_eq!(registry.blobs().check(&sha).unwrap(), BlobState::Intact);
        assert_eq!(registry.blobs().get(&sha).unwrap().unwrap(), b"hello");
        let path = registry.blobs().path(&sha);
        let mut permissions = std::fs::metadata(&path).unwrap().permissions();
        assert!(permissions.readonly());
        #[allow(clippy::permissions_set_readonly_false)]
        permissions.set_readonly(false);
        std::fs::set_permissions(&path, permissions).unwrap();
        std::fs::write(&path, b"hellp").unwrap();
        assert!(matches!(
            registry.blobs().check(&sha).unwrap(),
            BlobState::Damaged { .. }
        ));
        assert!(registry.blobs().get(&sha).unwrap().is_err());
        // Putting the right bytes again repairs it.
        registry.blobs().put(b"hello").unwrap();
        assert_eq!(registry.blobs().check(&sha).unwrap(), BlobState::Intact);
        // A second open finds the schema in place.
        drop(registry);
        Registry::open_existing(dir.path()).unwrap();
    }

    fn dataset_artefact(key: &str, sha: &str) -> NewArtefact {
        NewArtefact {
            key: key.to_string(),
            kind: ArtefactKind::Dataset,
            name: "a".into(),
            spec: "{}".into(),
            code_version: "test".into(),
            run_id: None,
            compute_seconds: 0.0,
            blobs: vec![BlobRef {
                role: BlobRole::Frames,
                sha256: sha.to_string(),
            }],
            details: ArtefactDetails::Dataset {
                frames: 1,
                height: 1,
                width: 1,
                seed: u64::MAX,
                diffusion: None,
                brightness: 7.0.into(),
                params_json: "{}".into(),
            },
        }
    }

    #[test]
    fn recording_twice_is_idempotent_and_disagreement_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::open(dir.path()).unwrap();
        let one = registry.blobs().put(b"one").unwrap();
        let two = registry.blobs().put(b"two").unwrap();
        registry
            .record_artefact(&dataset_artefact("k", &one), false)
            .unwrap();
        registry
            .record_artefact(&dataset_artefact("k", &one), false)
            .unwrap();
        let error = registry
            .record_artefact(&dataset_artefact("k", &two), false)
            .unwrap_err();
        assert!(error.to_string().contains("not deterministic"), "{error}");
        assert_eq!(
            registry.artefact("k").unwrap().unwrap().blobs[0].sha256,
            one
        );
        // Replacing (after damage) is allowed when asked for.
        registry
            .record_artefact(&dataset_artefact("k", &two), true)
            .unwrap();
        assert_eq!(
            registry.artefact("k").unwrap().unwrap().blobs[0].sha256,
            two
        );
        // u64 seeds survive SQLite's signed integers as text.
        let seed: String = registry
            .connection()
            .query_row("SELECT seed FROM datasets WHERE key = 'k'", [], |r| {
                r.get(0)
            })
            .unwrap();
        assert_eq!(seed, u64::MAX.to_string());
    }

    #[test]
    fn the_brightness_column_holds_a_number_or_the_distributions_form() {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::open(dir.path()).unwrap();
        let sha = registry.blobs().put(b"frames").unwrap();
        let mut drawn = dataset_artefact("drawn", &sha);
        if let ArtefactDetails::Dataset { brightness, .. } = &mut drawn.details {
            *brightness = "uniform:5,10".parse().unwrap();
        }
        for artefact in [dataset_artefact("fixed", &sha), drawn] {
            registry.record_artefact(&artefact, false).unwrap();
        }
        let table = registry.list_datasets().unwrap();
        let column = table
            .columns
            .iter()
            .position(|c| c == "brightness")
            .unwrap();
        let key = table.columns.iter().position(|c| c == "key").unwrap();
        let mut cells: Vec<(String, serde_json::Value)> = table
            .rows
            .iter()
            .map(|row| (row[key].as_str().unwrap().to_string(), row[column].clone()))
            .collect();
        cells.sort_by(|a, b| a.0.cmp(&b.0));
        assert_eq!(
            cells,
            [
                ("drawn".to_string(), serde_json::json!("uniform:5,10")),
                ("fixed".to_string(), serde_json::json!(7.0)),
            ]
        );
    }

    #[test]
    fn a_version_1_registry_opens_and_its_cv_runs_get_their_plans() {
        let dir = tempfile::tempdir().unwrap();
        let conn = Connection::open(dir.path().join(DATABASE_FILE)).unwrap();
        conn.execute_batch(SCHEMA_V1).unwrap();
        conn.execute_batch("PRAGMA user_version = 1").unwrap();
        let insert_run = |id: &str, kind: &str| {
            conn.execute(
                "INSERT INTO runs (id, kind, manifest_name, manifest_path, manifest_text,
                     manifest_sha256, resolved, seeds, crate_version, git_commit, git_dirty, rustc,
                     host, pid, threads, forced, started_at, ended_at, status)
                 VALUES (?1, ?2, 'm', 'm.yaml', 'name: m', '00', '{}', '{}', '0.1.0', 'c', 'false',
                     'rustc', 'h', 1, 2, 0, '2026-01-01T00:00:00.000Z',
                     '2026-01-01T00:00:01.000Z', 'done')",
                params![id, kind],
            )
            .unwrap();
        };
        let insert_auc = |run: &str, detector: &str, dataset: &str| {
            conn.execute(
                "INSERT INTO run_auc (run_id, detector, dataset, diffusion, eps_px, auc, evaluation_key)
                 VALUES (?1, ?2, ?3, NULL, 1.0, 0.5, 'e')",
                params![run, detector, dataset],
            )
            .unwrap();
        };
        insert_run("sweep", "cv");
        for fold in 1..=3 {
            insert_auc("sweep", &format!("cnn-cv{fold}of3"), "x-held-out");
        }
        insert_run("one-fold", "cv");
        insert_auc("one-fold", "cnn-cv2of3", "test");
        insert_run("interrupted", "cv");
        insert_run("plain", "run");
        insert_auc("plain", "trackpy-cv1of2", "test");
        drop(conn);

        let registry = Registry::open(dir.path()).unwrap();
        let plan = |id: &str| registry.run_record(id).unwrap().cross_validation;
        let cv = |fold| {
            Some(CrossValidationPlan {
                detector: "cnn".into(),
                folds: 3,
                fold,
            })
        };
        assert_eq!(plan("sweep"), cv(None));
        assert_eq!(plan("one-fold"), cv(Some(2)));
        assert_eq!(plan("interrupted"), None);
        assert_eq!(plan("plain"), None, "only cv runs have a plan");
        assert_eq!(registry.run_record("plain").unwrap().kind, RunKind::Run);
        let version: i64 = registry
            .connection()
            .query_row("PRAGMA user_version", [], |row| row.get(0))
            .unwrap();
        assert_eq!(version, SCHEMA_VERSION);
    }

    #[test]
    fn a_version_2_registry_opens_and_its_auc_rows_read_without_a_best_guess() {
        let dir = tempfile::tempdir().unwrap();
        let conn = Connection::open(dir.path().join(DATABASE_FILE)).unwrap();
        conn.execute_batch(SCHEMA_V1).unwrap();
        conn.execute_batch(SCHEMA_V2).unwrap();
        conn.execute_batch("PRAGMA user_version = 2").unwrap();
        conn.execute(
            "INSERT INTO runs (id, kind, manifest_name, manifest_path, manifest_text,
                 manifest_sha256, resolved, seeds, crate_version, git_commit, git_dirty, rustc,
                 host, pid, threads, forced, started_at, ended_at, status)
             VALUES ('old', 'run', 'm', 'm.yaml', 'name: m', '00', '{}', '{}', '0.1.0', 'c',
                 'false', 'rustc', 'h', 1, 2, 0, '2026-01-01T00:00:00.000Z',
                 '2026-01-01T00:00:01.000Z', 'done')",
            [],
        )
        .unwrap();
        conn.execute(
            "INSERT INTO run_auc (run_id, detector, dataset, diffusion, eps_px, auc, evaluation_key)
             VALUES ('old', 'trackpy', 'test', 0.75, 1.0, 0.5, 'e')",
            [],
        )
        .unwrap();
        conn.execute_batch(
            "INSERT INTO artefacts (key, kind, name, spec, code_version, created_at, compute_seconds)
                 VALUES ('e', 'evaluation', 'trackpy@test', '{}', 't', '2026-01-01T00:00:00.000Z', 0);
             INSERT INTO evaluations (key, detector, dataset, dataset_key, predictions_key,
                 rmse_top_px, fraction_without_prediction)
                 VALUES ('e', 'trackpy', 'test', 'd', 'p', NULL, 0);
             INSERT INTO auc (evaluation_key, eps_px, auc, true_positives, false_positives)
                 VALUES ('e', 1.0, 0.5, 3, 1);",
        )
        .unwrap();
        drop(conn);

        let mut registry = Registry::open(dir.path()).unwrap();
        let version: i64 = registry
            .connection()
            .query_row("PRAGMA user_version", [], |row| row.get(0))
            .unwrap();
        assert_eq!(version, 3);
        assert_eq!(
            registry.run_record("old").unwrap().auc,
            [AucRow {
                detector: "trackpy".into(),
                dataset: "test".into(),
                diffusion: Some(0.75),
                eps_px: 1.0,
                auc: 0.5,
                auc_best_per_frame: None,
                evaluation_key: "e".into(),
            }]
        );
        let stored: (f64, Option<f64>) = registry
            .connection()
            .query_row(
                "SELECT auc, auc_best_per_frame FROM auc WHERE evaluation_key = 'e'",
                [],
                |row| Ok((row.get(0)?, row.get(1)?)),
            )
            .unwrap();
        assert_eq!(stored, (0.5, None));

        // A run recorded after the migration keeps its best-guess AUC.
        registry
            .begin_run(&RunStart {
                id: "new".into(),
                kind: RunKind::Run,
                parent_run: None,
                manifest_name: "m".into(),
                manifest_path: "m.yaml".into(),
                manifest_text: "name: m\n".into(),
                manifest_sha256: "00".into(),
                resolved_json: "{}".into(),
                seeds_json: "{}".into(),
                forced: false,
                cross_validation: None,
            })
            .unwrap();
        let row = AucRow {
            detector: "likelihood".into(),
            dataset: "test".into(),
            diffusion: None,
            eps_px: 1.0,
            auc: 0.625,
            auc_best_per_frame: Some(0.5),
            evaluation_key: "e".into(),
        };
        registry
            .finish_run(
                "new",
                RunStatus::Done,
                None,
                StepCounts::default(),
                std::slice::from_ref(&row),
            )
            .unwrap();
        assert_eq!(registry.run_record("new").unwrap().auc, [row]);
    }

    #[test]
    fn a_newer_schema_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        drop(Registry::open(dir.path()).unwrap());
        let conn = Connection::open(dir.path().join(DATABASE_FILE)).unwrap();
        conn.execute_batch("PRAGMA user_version = 99").unwrap();
        drop(conn);
        let error = Registry::open(dir.path()).err().unwrap();
        assert_eq!(crate::error::exit_code(&error), 2);
        assert!(error.to_string().contains("newer"), "{error}");
    }
}
