//! The registry: a SQLite database (`registry.sqlite`) mapping content keys
//! of artefacts to the hashes of their stored bytes, plus the record of
//! every run; blobs live beside it (see [`blobs`]). The schema is in
//! `schema.sql`, `schema_v2.sql` (a cross-validation run's plan) and
//! `schema_v3.sql` (the best-guess-per-frame AUC of ranked lists), and
//! documented in `docs/registry.md`. Opening a registry is in `open.rs`,
//! its schema's migrations in `migrate.rs`, recording artefacts in
//! `insert.rs`, runs in `runs.rs` and the claims of steps being computed
//! in `claims.rs`; reading back is in
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

pub(crate) mod blobs;
mod claims;
pub(crate) mod dates;
pub(crate) mod diff;
pub(crate) mod gc;
pub(crate) mod hashing;
mod insert;
mod migrate;
pub(crate) mod models;
mod open;
pub(crate) mod record;
mod runs;
pub mod shard;
pub(crate) mod sql;
pub(crate) mod sql_guard;
pub(crate) mod step_id;
pub(crate) mod table;
pub(crate) mod verify;
pub mod write_lock;

use std::path::{Path, PathBuf};

use rusqlite::{Connection, OptionalExtension};
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

pub use claims::StepClaim;
pub use open::open_database_read_only;
use open::{BUSY_TIMEOUT, is_busy};

/// The schema version this code writes; see `schema.sql` (version 1),
/// `schema_v2.sql` and `schema_v3.sql` (the migrations to versions 2 and 3).
pub(crate) const SCHEMA_VERSION: i64 = 3;

/// The database file name inside a registry folder.
pub(crate) const DATABASE_FILE: &str = "registry.sqlite";

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

    /// The table of this kind's typed facts (`schema.sql`), one row per
    /// artefact keyed by `key`: the one place its name is spelt for SQL
    /// built by the code.
    pub fn table(self) -> &'static str {
        match self {
            ArtefactKind::Dataset => "datasets",
            ArtefactKind::Model => "models",
            ArtefactKind::Predictions => "predictions",
            ArtefactKind::Evaluation => "evaluations",
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
pub(crate) fn process_alive(pid: u32) -> bool {
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
}

#[cfg(test)]
mod tests {
    use rusqlite::params;

    use super::migrate::{SCHEMA_V1, SCHEMA_V2};
    use super::*;

    #[test]
    fn every_kinds_table_is_in_the_schema_keyed_by_key() {
        let dir = tempfile::tempdir().unwrap();
        let registry = Registry::open(dir.path()).unwrap();
        for kind in [
            ArtefactKind::Dataset,
            ArtefactKind::Model,
            ArtefactKind::Predictions,
            ArtefactKind::Evaluation,
        ] {
            let sql = format!("SELECT key FROM {} LIMIT 0", kind.table());
            registry.connection().prepare(&sql).unwrap();
        }
    }

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
