//! Shards: registry folders that carry some runs and artefacts from one
//! registry to another (`scanloc registry export` / `import`, and the
//! per-task registries of a sweep on a cluster, see `docs/cluster.md`).
//!
//! A shard is an ordinary registry folder (database plus blobs), so every
//! command that reads a registry reads a shard. Copying is always one way,
//! from a source folder opened read-only into an open destination
//! [`Registry`], and always the same three things: the blobs (read back and
//! re-hashed, so a damaged source blob is never copied), the artefact rows
//! (every table keyed by an artefact key) and the run records (every table
//! keyed by a run id). Rows already present are kept as they are, so a
//! second copy changes nothing. An artefact key the destination stores with
//! other blobs is refused (the step that made it is not deterministic, or
//! two builds disagree): it and the runs that used it are not copied, and
//! the refusal is reported.
//!
//! Table by table, the copy goes by the tables the source database has and
//! the key column each has (`runs.id`, `run_id`, `blobs.sha256`, `key`,
//! `artefact_key`, `evaluation_key`), so a new table keyed the same way needs
//! no change here; a table keyed otherwise is refused rather than dropped.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::Duration;

use anyhow::Context;
use rusqlite::{Connection, OpenFlags, OptionalExtension};
use serde::Serialize;

use super::{BlobRef, BlobStore, DATABASE_FILE, Registry, SCHEMA_VERSION};
use crate::error::{CheckFailed, input_error};

/// What to copy from a source registry.
#[derive(Debug, Clone)]
pub enum Selection {
    /// Every artefact and every run (importing a shard).
    Everything,
    /// These runs and every artefact their steps name (exporting runs).
    Runs(Vec<String>),
    /// Those of these artefacts the source stores (no runs): a sweep task
    /// seeding its shard with inputs the main registry already holds.
    Artefacts(Vec<String>),
}

/// An artefact key refused because the destination stores it with other
/// blobs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Conflict {
    pub key: String,
    pub name: String,
    /// (role, sha256) in the destination.
    pub ours: Vec<BlobRef>,
    /// (role, sha256) in the source.
    pub theirs: Vec<BlobRef>,
    /// Runs of the source not copied because they used this artefact.
    pub runs_not_copied: Vec<String>,
}

/// What one copy did.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct CopyReport {
    /// The source folder.
    pub source: String,
    /// Artefacts selected in the source.
    pub artefacts: usize,
    /// Of those, how many were not yet in the destination.
    pub new_artefacts: usize,
    /// Blob files written (or repaired) in the destination.
    pub blobs_written: usize,
    pub bytes_written: u64,
    /// Runs selected in the source.
    pub runs: usize,
    /// Of those, how many were not yet in the destination.
    pub new_runs: usize,
    /// Runs copied while still marked `running` in the source, recorded as
    /// `unfinished` (their process ended with the task that ran them).
    pub unfinished_runs: Vec<String>,
    pub conflicts: Vec<Conflict>,
}

impl CopyReport {
    /// One line for people.
    pub fn summary(&self) -> String {
        let mut line = format!(
            "{}: {} artefact(s) ({} new), {} run(s) ({} new), {} blob(s) written ({} bytes)",
            self.source,
            self.artefacts,
            self.new_artefacts,
            self.runs,
            self.new_runs,
            self.blobs_written,
            self.bytes_written
        );
        if !self.unfinished_runs.is_empty() {
            line.push_str(&format!(
                "; {} run(s) recorded as unfinished",
                self.unfinished_runs.len()
            ));
        }
        for conflict in &self.conflicts {
            line.push_str(&format!(
                "\n  REFUSED {} ({}): stored here with blobs {:?}, the source has {:?}; runs not copied: {}",
                conflict.name,
                conflict.key,
                conflict.ours,
                conflict.theirs,
                if conflict.runs_not_copied.is_empty() {
                    "none".to_string()
                } else {
                    conflict.runs_not_copied.join(", ")
                }
            ));
        }
        line
    }
}

/// Opens the database in registry folder `dir` read-only. A folder without
/// one, a file that is not a registry, a registry of another schema version
/// or one that fails SQLite's integrity check is bad input naming `dir`.
pub fn open_read_only(dir: &Path) -> anyhow::Result<Connection> {
    let path = dir.join(DATABASE_FILE);
    if !path.is_file() {
        return Err(input_error(format!(
            "{}: no registry here (no {DATABASE_FILE})",
            dir.display()
        )));
    }
    let damaged = |e: &dyn std::fmt::Display| {
        input_error(format!("{}: damaged registry: {e}", path.display()))
    };
    let conn = Connection::open_with_flags(
        &path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|e| damaged(&e))?;
    conn.busy_timeout(Duration::from_secs(60))?;
    let version: i64 = conn
        .query_row("PRAGMA user_version", [], |row| row.get(0))
        .map_err(|e| damaged(&e))?;
    if version != SCHEMA_VERSION {
        return Err(input_error(format!(
            "{}: registry schema version {version}, this scanloc reads version {SCHEMA_VERSION}{}",
            path.display(),
            if version < SCHEMA_VERSION {
                " (any scanloc registry command on it, e.g. `scanloc registry runs --registry DIR`, upgrades it)"
            } else {
                ""
            }
        )));
    }
    let check: String = conn
        .query_row("PRAGMA quick_check", [], |row| row.get(0))
        .map_err(|e| damaged(&e))?;
    if check != "ok" {
        return Err(damaged(&check));
    }
    Ok(conn)
}

/// How a table's rows are selected.
#[derive(Debug, Clone, Copy, PartialEq)]
enum KeyedBy {
    Blob,
    Run(&'static str),
    Artefact(&'static str),
}

/// The tables of the database behind `conn` (schema `schema`) with their
/// columns and how each is keyed; a table keyed otherwise is an error.
fn tables(conn: &Connection, schema: &str) -> anyhow::Result<Vec<(String, Vec<String>, KeyedBy)>> {
    let names: Vec<String> = conn
        .prepare(&format!(
            "SELECT name FROM {schema}.sqlite_master WHERE type = 'table' AND name NOT LIKE 'sqlite_%' ORDER BY name"
        ))?
        .query_map([], |row| row.get(0))?
        .collect::<Result<_, _>>()?;
    let mut out = Vec::new();
    for name in names {
        let columns: Vec<String> = conn
            .prepare(&format!("PRAGMA {schema}.table_info(\"{name}\")"))?
            .query_map([], |row| row.get(1))?
            .collect::<Result<_, _>>()?;
        let has = |c: &str| columns.iter().any(|x| x == c);
        let keyed = if name == "blobs" {
            KeyedBy::Blob
        } else if name == "runs" {
            KeyedBy::Run("id")
        } else if has("run_id") {
            KeyedBy::Run("run_id")
        } else if has("key") {
            KeyedBy::Artefact("key")
        } else if has("artefact_key") {
            KeyedBy::Artefact("artefact_key")
        } else if has("evaluation_key") {
            KeyedBy::Artefact("evaluation_key")
        } else {
            anyhow::bail!("registry table {name} is keyed neither by run nor by artefact");
        };
        out.push((name, columns, keyed));
    }
    Ok(out)
}

fn blob_refs(conn: &Connection, schema: &str, key: &str) -> anyhow::Result<Vec<BlobRef>> {
    conn.prepare_cached(&format!(
        "SELECT role, sha256 FROM {schema}.artefact_blobs WHERE artefact_key = ?1 ORDER BY role"
    ))?
    .query_map([key], |row| {
        Ok(BlobRef {
            role: row.get(0)?,
            sha256: row.get(1)?,
        })
    })?
    .collect::<Result<_, _>>()
    .map_err(Into::into)
}

/// Copies `selection` from the registry folder `source` into `destination`
/// (see the module docs). Errors before anything is written if the source
/// is missing, damaged (database or a selected blob) or of another schema;
/// refused keys are in the report, not errors.
pub fn copy(
    destination: &mut Registry,
    source: &Path,
    selection: &Selection,
) -> anyhow::Result<CopyReport> {
    let src = open_read_only(source)?;
    let mut report = CopyReport {
        source: source.display().to_string(),
        ..CopyReport::default()
    };

    // What the selection means in the source.
    let (mut run_ids, keys): (Vec<String>, Vec<String>) = match selection {
        Selection::Everything => (
            src.prepare("SELECT id FROM runs ORDER BY started_at, id")?
                .query_map([], |row| row.get(0))?
                .collect::<Result<_, _>>()?,
            src.prepare("SELECT key FROM artefacts ORDER BY key")?
                .query_map([], |row| row.get(0))?
                .collect::<Result<_, _>>()?,
        ),
        Selection::Runs(ids) => {
            let mut keys = BTreeSet::new();
            for id in ids {
                let found: Option<String> = src
                    .query_row("SELECT id FROM runs WHERE id = ?1", [id], |row| row.get(0))
                    .optional()?;
                if found.is_none() {
                    return Err(input_error(format!(
                        "{}: no run {id} in this registry",
                        source.display()
                    )));
                }
                let mut statement = src.prepare(
                    "SELECT DISTINCT artefact_key FROM run_steps WHERE run_id = ?1
                       AND artefact_key IN (SELECT key FROM artefacts)",
                )?;
                for key in statement.query_map([id], |row| row.get::<_, String>(0))? {
                    keys.insert(key?);
                }
            }
            (ids.clone(), keys.into_iter().collect())
        }
        Selection::Artefacts(wanted) => {
            let mut keys = Vec::new();
            for key in wanted {
                let found: Option<String> = src
                    .query_row("SELECT key FROM artefacts WHERE key = ?1", [key], |row| {
                        row.get(0)
                    })
                    .optional()?;
                keys.extend(found);
            }
            (Vec::new(), keys)
        }
    };

    // Compare with the destination; check and copy the blobs first, so a
    // damaged source is refused before any row is written.
    let mut copied_keys = Vec::new();
    let mut blobs: BTreeSet<String> = BTreeSet::new();
    for key in &keys {
        let theirs = blob_refs(&src, "main", key)?;
        match destination.artefact(key)? {
            Some(stored) if stored.blobs != theirs => {
                let name: String =
                    src.query_row("SELECT name FROM artefacts WHERE key = ?1", [key], |row| {
                        row.get(0)
                    })?;
                report.conflicts.push(Conflict {
                    key: key.clone(),
                    name,
                    ours: stored.blobs,
                    theirs,
                    runs_not_copied: Vec::new(),
                });
                continue;
            }
            Some(_) => {}
            None => report.new_artefacts += 1,
        }
        blobs.extend(theirs.into_iter().map(|b| b.sha256));
        copied_keys.push(key.clone());
    }
    report.artefacts = keys.len();
    let source_store = BlobStore::read_only(source);
    let mut bytes_by_blob: BTreeMap<String, Vec<u8>> = BTreeMap::new();
    for sha256 in &blobs {
        if destination.blobs().check(sha256)? == super::BlobState::Intact {
            continue;
        }
        match source_store.get(sha256)? {
            Ok(bytes) => {
                bytes_by_blob.insert(sha256.clone(), bytes);
            }
            Err(state) => {
                return Err(input_error(format!(
                    "{}: damaged shard: blob {sha256} ({}) is {state:?}",
                    source.display(),
                    source_store.path(sha256).display()
                )));
            }
        }
    }
    for (sha256, bytes) in bytes_by_blob {
        let written = destination.blobs().put(&bytes)?;
        anyhow::ensure!(written == sha256, "blob {sha256} re-hashed to {written}");
        report.blobs_written += 1;
        report.bytes_written += bytes.len() as u64;
    }

    // Runs that used a refused artefact are not copied.
    for conflict in &mut report.conflicts {
        let users: Vec<String> = src
            .prepare("SELECT DISTINCT run_id FROM run_steps WHERE artefact_key = ?1")?
            .query_map([&conflict.key], |row| row.get(0))?
            .collect::<Result<_, _>>()?;
        conflict.runs_not_copied = users
            .into_iter()
            .filter(|run| run_ids.contains(run))
            .collect();
        run_ids.retain(|run| !conflict.runs_not_copied.contains(run));
    }
    report.runs = run_ids.len();
    drop(src);

    copy_rows(
        destination,
        source,
        &copied_keys,
        &blobs,
        &run_ids,
        &mut report,
    )
    .with_context(|| format!("copying the records of {}", source.display()))?;
    Ok(report)
}

/// The row half of [`copy`]: one transaction on the destination with the
/// source attached read-only.
fn copy_rows(
    destination: &mut Registry,
    source: &Path,
    keys: &[String],
    blobs: &BTreeSet<String>,
    run_ids: &[String],
    report: &mut CopyReport,
) -> anyhow::Result<()> {
    let conn = destination.connection();
    let uri = format!(
        "file:{}?mode=ro",
        source
            .join(DATABASE_FILE)
            .display()
            .to_string()
            .replace('?', "%3f")
            .replace('#', "%23")
    );
    conn.execute("ATTACH DATABASE ?1 AS shard", [&uri])?;
    let result = (|| -> anyhow::Result<()> {
        conn.execute_batch(
            "CREATE TEMP TABLE IF NOT EXISTS copy_keys (value TEXT PRIMARY KEY);
             CREATE TEMP TABLE IF NOT EXISTS copy_runs (value TEXT PRIMARY KEY);
             CREATE TEMP TABLE IF NOT EXISTS copy_blobs (value TEXT PRIMARY KEY);
             DELETE FROM copy_keys; DELETE FROM copy_runs; DELETE FROM copy_blobs;",
        )?;
        conn.execute_batch("BEGIN IMMEDIATE; PRAGMA defer_foreign_keys = ON;")?;
        let body = (|| -> anyhow::Result<()> {
            for (table, values) in [
                ("copy_keys", keys.iter().collect::<Vec<_>>()),
                ("copy_runs", run_ids.iter().collect()),
                ("copy_blobs", blobs.iter().collect()),
            ] {
                let mut insert =
                    conn.prepare(&format!("INSERT OR IGNORE INTO temp.{table} VALUES (?1)"))?;
                for value in values {
                    insert.execute([value])?;
                }
            }
            let new_runs: Vec<String> = conn
                .prepare(
                    "SELECT value FROM temp.copy_runs WHERE value NOT IN (SELECT id FROM main.runs)",
                )?
                .query_map([], |row| row.get(0))?
                .collect::<Result<_, _>>()?;
            report.new_runs = new_runs.len();
            let ours = tables(conn, "main")?;
            for (table, columns, keyed) in tables(conn, "shard")? {
                let Some((_, our_columns, _)) = ours.iter().find(|(name, ..)| *name == table)
                else {
                    anyhow::bail!("the source has a table {table} this registry does not");
                };
                let columns: Vec<String> = columns
                    .into_iter()
                    .filter(|c| our_columns.contains(c))
                    .map(|c| format!("\"{c}\""))
                    .collect();
                let (column, set) = match keyed {
                    KeyedBy::Blob => ("sha256", "copy_blobs"),
                    KeyedBy::Run(column) => (column, "copy_runs"),
                    KeyedBy::Artefact(column) => (column, "copy_keys"),
                };
                let list = columns.join(", ");
                conn.execute(
                    &format!(
                        "INSERT OR IGNORE INTO main.\"{table}\" ({list})
                         SELECT {list} FROM shard.\"{table}\" WHERE \"{column}\" IN (SELECT value FROM temp.{set})"
                    ),
                    [],
                )?;
            }
            // A run still `running` in the source ended with its task.
            let mut mark = conn.prepare(
                "UPDATE main.runs SET status = 'unfinished',
                   error = 'its task ended without finishing the run (copied from ' || ?2 || ')'
                 WHERE id = ?1 AND status = 'running'",
            )?;
            for run in &new_runs {
                if mark.execute([run, &source.display().to_string()])? > 0 {
                    report.unfinished_runs.push(run.clone());
                }
            }
            Ok(())
        })();
        match body {
            Ok(()) => conn.execute_batch("COMMIT")?,
            Err(e) => {
                let _ = conn.execute_batch("ROLLBACK");
                return Err(e);
            }
        }
        Ok(())
    })();
    conn.execute_batch("DETACH DATABASE shard")?;
    result
}

/// Imports every shard in `shards` into `registry`, one after another: a
/// missing or damaged shard is reported and the others imported. Returns
/// one result per shard.
pub fn import_all(
    registry: &mut Registry,
    shards: &[&Path],
) -> Vec<(String, anyhow::Result<CopyReport>)> {
    shards
        .iter()
        .map(|shard| {
            (
                shard.display().to_string(),
                copy(registry, shard, &Selection::Everything),
            )
        })
        .collect()
}

/// Writes runs `run_ids` of the registry in `source` and every artefact
/// they used into a new shard folder `out` (created; an existing registry
/// there is added to).
pub fn export(source: &Path, run_ids: &[String], out: &Path) -> anyhow::Result<CopyReport> {
    let mut shard = Registry::open(out)?;
    let report = copy(&mut shard, source, &Selection::Runs(run_ids.to_vec()))?;
    if !report.conflicts.is_empty() {
        return Err(anyhow::Error::new(CheckFailed(report.summary())));
    }
    Ok(report)
}
