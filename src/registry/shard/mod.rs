//! Shards: registry folders that carry some runs and artefacts from one
//! registry to another (`scanloc registry export` / `import`, and the
//! per-task registries of a sweep on a cluster, see `docs/cluster.md`).
//!
//! A shard is an ordinary registry folder (database plus blobs), so every
//! command that reads a registry reads a shard. Copying is always one way,
//! from a source folder opened read-only into an open destination
//! [`Registry`], and always the same three things: the blobs, the artefact
//! rows (every table keyed by an artefact key) and the run records (every
//! table keyed by a run id). Rows already present are kept as they are, so
//! a second copy changes nothing. An artefact key the destination stores
//! with other blobs is refused (the step that made it is not
//! deterministic, or two builds disagree): it, the runs that used it and
//! the artefacts only those runs used are not copied, and the refusal is
//! reported (an export refuses the whole copy).
//!
//! A shard is input like any other file, so an import is a validating
//! copy, in phases ([`copy`]): the shard's database is read from a private
//! copy ([`source`]); its durable tables ([`rules::DURABLE`]; never the
//! transient `step_claims`) must be real tables with this registry's
//! columns; every selected row must obey [`rules`] (plain names as a
//! manifest's, 64-hex keys and hashes, sizes, each artefact's key the
//! sha256 of its spec); every blob must be a regular file of its recorded
//! size whose bytes hash to its name, copied into a staging folder
//! ([`staging`]) as it is hashed. Then one transaction writes the rows
//! (foreign keys checked row by row), moves the staged blobs into the
//! store and commits: all or nothing, and a refusal names the shard, the
//! table and the row. A copy holds the registry's blob lock
//! ([`BlobLock`]) shared throughout, so `registry gc` never deletes blobs
//! it is writing.

mod rules;
mod source;
mod staging;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::Context;
use rusqlite::types::Value;
use rusqlite::{Connection, OptionalExtension};
use serde::Serialize;

use super::write_lock::{BlobLock, BlobLockUse};
use super::{BlobRef, BlobRole, BlobStore, DATABASE_FILE, Registry};
use crate::error::{CheckFailed, input_error};
use rules::KeyedBy;
use source::{Source, TableRows};
use staging::Staging;

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

/// Opens the database in registry folder `dir` read-only, in place (to
/// read a sweep task's record). A folder without one, a file that is not
/// a registry, a registry of a schema version this scanloc does not read
/// or one that fails SQLite's quick check is bad input naming it.
pub(crate) fn open_read_only(dir: &Path) -> anyhow::Result<Connection> {
    let path = dir.join(DATABASE_FILE);
    if !path.is_file() {
        return Err(input_error(format!(
            "{}: no registry here (no {DATABASE_FILE})",
            dir.display()
        )));
    }
    Ok(source::open_database(&path, &path)?.0)
}

/// The source's record in brief, read once to plan a copy.
#[derive(Debug, Default)]
struct Index {
    /// `runs.id`.
    runs: Vec<String>,
    /// Artefact key → name.
    artefacts: BTreeMap<String, String>,
    /// Artefact key → its blobs, by role.
    blobs_of: BTreeMap<String, Vec<BlobRef>>,
    /// (run id, artefact key) of every run step.
    steps: Vec<(String, String)>,
}

impl Index {
    fn read(src: &Source) -> anyhow::Result<Self> {
        let text = |value: &Value| match value {
            Value::Text(text) => Some(text.clone()),
            _ => None,
        };
        let mut index = Index {
            runs: src.texts("runs", "id")?,
            ..Index::default()
        };
        for row in src.rows("artefacts", &["key", "name"])? {
            if let (Some(key), Some(name)) = (text(&row[0]), text(&row[1])) {
                index.artefacts.insert(key, name);
            }
        }
        for row in src.rows("artefact_blobs", &["artefact_key", "role", "sha256"])? {
            // A role that is not a blob role is refused with its row
            // (rules.rs); the index only needs the ones that are.
            let role = text(&row[1]).and_then(|role| role.parse::<BlobRole>().ok());
            if let (Some(key), Some(role), Some(sha256)) = (text(&row[0]), role, text(&row[2])) {
                index
                    .blobs_of
                    .entry(key)
                    .or_default()
                    .push(BlobRef { role, sha256 });
            }
        }
        for refs in index.blobs_of.values_mut() {
            refs.sort_by_key(|r| r.role);
        }
        for row in src.rows("run_steps", &["run_id", "artefact_key"])? {
            if let (Some(run), Some(key)) = (text(&row[0]), text(&row[1])) {
                index.steps.push((run, key));
            }
        }
        Ok(index)
    }

    fn blobs(&self, key: &str) -> Vec<BlobRef> {
        self.blobs_of.get(key).cloned().unwrap_or_default()
    }

    /// The runs whose steps use artefact `key`.
    fn users(&self, key: &str) -> BTreeSet<&str> {
        self.steps
            .iter()
            .filter(|(_, k)| k == key)
            .map(|(run, _)| run.as_str())
            .collect()
    }
}

/// What a copy takes, decided before anything is written.
#[derive(Debug, Default)]
struct Plan {
    runs: BTreeSet<String>,
    keys: BTreeSet<String>,
    blobs: BTreeSet<String>,
}

/// The runs and artefact keys `selection` names in the source.
fn select(
    src: &Source,
    index: &Index,
    selection: &Selection,
) -> anyhow::Result<(Vec<String>, Vec<String>)> {
    Ok(match selection {
        Selection::Everything => (
            index.runs.clone(),
            index.artefacts.keys().cloned().collect(),
        ),
        Selection::Runs(ids) => {
            let mut keys = BTreeSet::new();
            for id in ids {
                if !index.runs.contains(id) {
                    return Err(input_error(format!(
                        "{}: no run {id} in this registry",
                        src.dir().display()
                    )));
                }
                keys.extend(
                    index
                        .steps
                        .iter()
                        .filter(|(run, key)| run == id && index.artefacts.contains_key(key))
                        .map(|(_, key)| key.clone()),
                );
            }
            (ids.clone(), keys.into_iter().collect())
        }
        Selection::Artefacts(wanted) => (
            Vec::new(),
            wanted
                .iter()
                .filter(|key| index.artefacts.contains_key(*key))
                .cloned()
                .collect(),
        ),
    })
}

/// Plans the copy of `selection`: an artefact the destination stores with
/// other blobs is refused (reported in `report`), and with it the runs
/// that used it and the artefacts only those runs used (which would
/// otherwise be left behind as orphans).
fn plan(
    destination: &Registry,
    src: &Source,
    index: &Index,
    selection: &Selection,
    report: &mut CopyReport,
) -> anyhow::Result<Plan> {
    let (mut run_ids, keys) = select(src, index, selection)?;
    report.artefacts = keys.len();
    let mut copied = BTreeSet::new();
    let mut new = BTreeSet::new();
    for key in keys {
        let theirs = index.blobs(&key);
        match destination.artefact(&key)? {
            Some(stored) if stored.blobs != theirs => {
                report.conflicts.push(Conflict {
                    name: index.artefacts[&key].clone(),
                    key,
                    ours: stored.blobs,
                    theirs,
                    runs_not_copied: Vec::new(),
                });
                continue;
            }
            Some(_) => {}
            None => {
                new.insert(key.clone());
            }
        }
        copied.insert(key);
    }
    let mut refused_runs = BTreeSet::new();
    for conflict in &mut report.conflicts {
        let users = index.users(&conflict.key);
        conflict.runs_not_copied = run_ids
            .iter()
            .filter(|run| users.contains(run.as_str()))
            .cloned()
            .collect();
        run_ids.retain(|run| !users.contains(run.as_str()));
        refused_runs.extend(conflict.runs_not_copied.iter().cloned());
    }
    copied.retain(|key| {
        let users = index.users(key);
        users.is_empty() || users.iter().any(|run| !refused_runs.contains(*run))
    });
    report.new_artefacts = copied.intersection(&new).count();
    report.runs = run_ids.len();
    Ok(Plan {
        blobs: copied
            .iter()
            .flat_map(|key| index.blobs(key).into_iter().map(|b| b.sha256))
            .collect(),
        runs: run_ids.into_iter().collect(),
        keys: copied,
    })
}

/// The planned rows of every durable table, each checked against the
/// rules, in the destination's columns.
fn read_rows(src: &Source, destination: &Registry, plan: &Plan) -> anyhow::Result<Vec<TableRows>> {
    rules::DURABLE
        .iter()
        .map(|table| {
            let columns = source::columns(destination.connection(), table.name)?
                .into_iter()
                .map(|(name, _)| name)
                .collect();
            let set = match table.keyed {
                KeyedBy::Blob => &plan.blobs,
                KeyedBy::Run(_) => &plan.runs,
                KeyedBy::Artefact(_) => &plan.keys,
            };
            src.selected_rows(table, columns, |value| set.contains(value))
        })
        .collect()
}

/// Copies every planned blob the destination does not hold intact into
/// the staging folder, hashed on the way, its size checked against the
/// size recorded for it.
fn stage_blobs(
    destination: &Registry,
    src: &Source,
    rows: &[TableRows],
    plan: &Plan,
    staging: &mut Staging,
    report: &mut CopyReport,
) -> anyhow::Result<()> {
    let blob_rows = rows
        .iter()
        .find(|t| t.table.name == "blobs")
        .expect("blobs is a durable table");
    let column = |name: &str| blob_rows.columns.iter().position(|c| c == name);
    let (sha_at, bytes_at) = (column("sha256"), column("bytes"));
    let recorded: BTreeMap<&str, i64> = blob_rows
        .rows
        .iter()
        .filter_map(|row| match (&row[sha_at?], &row[bytes_at?]) {
            (Value::Text(sha), Value::Integer(bytes)) => Some((sha.as_str(), *bytes)),
            _ => None,
        })
        .collect();
    let store = BlobStore::read_only(src.dir());
    for sha256 in &plan.blobs {
        let label = format!("(sha256=\"{sha256}\")");
        let recorded = recorded.get(sha256.as_str()).copied();
        if destination.blobs().check(sha256)? == super::BlobState::Intact {
            let size = std::fs::metadata(destination.blobs().path(sha256))?.len();
            if let Some(bytes) = recorded
                && u64::try_from(bytes) != Ok(size)
            {
                let problem = format!("bytes: {bytes}, the blob is {size} bytes");
                return Err(src.refuse_row("blobs", &label, &problem));
            }
            continue;
        }
        let recorded = match recorded {
            Some(bytes) => bytes,
            None => destination
                .connection()
                .query_row(
                    "SELECT bytes FROM blobs WHERE sha256 = ?1",
                    [sha256],
                    |row| row.get(0),
                )
                .optional()?
                .ok_or_else(|| {
                    src.refuse_row("blobs", &label, "no such row (artefact_blobs refers to it)")
                })?,
        };
        let path = store.path(sha256);
        let size = staging
            .stage_blob(&path, sha256, recorded)
            .map_err(|p| src.refuse_row("blobs", &label, &format!("{} {p}", path.display())))?;
        report.blobs_written += 1;
        report.bytes_written += size;
    }
    Ok(())
}

/// Writes the planned rows into the destination in one transaction, all
/// or nothing, moves the staged blobs into its store and commits. Rows the
/// destination has are kept as they are; a row SQLite refuses (a
/// constraint, a foreign key to a row neither has) refuses the copy.
fn write_rows(
    destination: &Registry,
    src: &Source,
    rows: &[TableRows],
    plan: &Plan,
    staging: &mut Staging,
    report: &mut CopyReport,
) -> anyhow::Result<()> {
    let tx = destination.write_transaction()?;
    let mut new_runs = Vec::new();
    for run in &plan.runs {
        let known = tx
            .query_row("SELECT 1 FROM runs WHERE id = ?1", [run], |_| Ok(()))
            .optional()?;
        if known.is_none() {
            new_runs.push(run.clone());
        }
    }
    report.new_runs = new_runs.len();
    for table in rows {
        let list: Vec<String> = table.columns.iter().map(|c| format!("\"{c}\"")).collect();
        let slots: Vec<String> = (1..=list.len()).map(|i| format!("?{i}")).collect();
        let mut insert = tx.prepare(&format!(
            "INSERT INTO main.\"{}\" ({}) VALUES ({}) ON CONFLICT DO NOTHING",
            table.table.name,
            list.join(", "),
            slots.join(", ")
        ))?;
        for values in &table.rows {
            insert
                .execute(rusqlite::params_from_iter(values))
                .map_err(|e| {
                    let label = rules::row_label(table.table, &table.columns, values);
                    src.refuse_row(table.table.name, &label, &e.to_string())
                })?;
        }
    }
    // A run still `running` in the source ended with its task.
    let mut mark = tx.prepare(
        "UPDATE main.runs SET status = 'unfinished',
           error = 'its task ended without finishing the run (copied from ' || ?2 || ')'
         WHERE id = ?1 AND status = 'running'",
    )?;
    for run in &new_runs {
        if mark.execute([run, &src.dir().display().to_string()])? > 0 {
            report.unfinished_runs.push(run.clone());
        }
    }
    drop(mark);
    staging.install(destination.blobs())?;
    tx.commit()?;
    Ok(())
}

/// Copies `selection` from the registry folder `source` into `destination`
/// (see the module docs). Nothing is written unless everything selected
/// passes: a missing, damaged or crafted source (database, row or blob) is
/// bad input naming the source, table and row, and leaves the destination
/// as it was. Refused keys are in the report, not errors, except when
/// exporting runs, where any refusal refuses the export.
pub fn copy(
    destination: &mut Registry,
    source: &Path,
    selection: &Selection,
) -> anyhow::Result<CopyReport> {
    if destination.is_read_only() {
        return Err(input_error(format!(
            "{}: the registry is read-only: nothing can be copied into it",
            destination.dir().display()
        )));
    }
    // `registry gc` would delete the blobs staged here before their rows
    // are written: it waits for this lock, and this for it.
    let _copying = BlobLock::take(destination.dir(), BlobLockUse::Copy, super::BUSY_TIMEOUT)?;
    let mut staging = Staging::new(destination.blobs())?;
    let src = match selection {
        Selection::Everything => Source::open_shard(source, &staging)?,
        Selection::Runs(_) | Selection::Artefacts(_) => Source::open_registry(source)?,
    };
    src.check_schema(destination.connection())?;
    let mut report = CopyReport {
        source: source.display().to_string(),
        ..CopyReport::default()
    };
    let plan = plan(
        destination,
        &src,
        &Index::read(&src)?,
        selection,
        &mut report,
    )?;
    if matches!(selection, Selection::Runs(_)) && !report.conflicts.is_empty() {
        return Err(anyhow::Error::new(CheckFailed(report.summary())));
    }
    let rows = read_rows(&src, destination, &plan)?;
    stage_blobs(destination, &src, &rows, &plan, &mut staging, &mut report)?;
    write_rows(destination, &src, &rows, &plan, &mut staging, &mut report)
        .with_context(|| format!("copying the records of {}", source.display()))?;
    Ok(report)
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
/// they used into a shard folder `out` (created; an existing registry
/// there is added to). A refused export writes nothing: a folder it
/// created is removed again.
pub fn export(source: &Path, run_ids: &[String], out: &Path) -> anyhow::Result<CopyReport> {
    let created = std::fs::symlink_metadata(out).is_err();
    let result = Registry::open(out)
        .and_then(|mut shard| copy(&mut shard, source, &Selection::Runs(run_ids.to_vec())));
    if result.is_err() && created {
        let _ = std::fs::remove_dir_all(out);
    }
    result
}
