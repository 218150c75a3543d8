//! Reading the registry back: listings, one run or artefact in full, the
//! differences between two runs, verification of every blob, garbage
//! collection, and read-only SQL.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rayon::prelude::*;
use rusqlite::{Connection, TransactionBehavior, params};
use serde::Serialize;
use serde_json::{Value, json};

pub use super::sql_guard::read_only_sql;
use super::{BlobState, Registry, host_name, process_alive};
use crate::error::input_error;

/// Rows of a query: column names and JSON values.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Table {
    pub columns: Vec<String>,
    pub rows: Vec<Vec<Value>>,
}

impl Table {
    /// The rows as a JSON array of objects keyed by column.
    pub fn to_json(&self) -> Value {
        Value::Array(
            self.rows
                .iter()
                .map(|row| {
                    Value::Object(
                        self.columns
                            .iter()
                            .cloned()
                            .zip(row.iter().cloned())
                            .collect(),
                    )
                })
                .collect(),
        )
    }

    /// The rows as aligned text columns with a header.
    pub fn render(&self) -> String {
        let cells: Vec<Vec<String>> = self
            .rows
            .iter()
            .map(|row| row.iter().map(cell_text).collect())
            .collect();
        let mut widths: Vec<usize> = self.columns.iter().map(|c| c.chars().count()).collect();
        for row in &cells {
            for (width, cell) in widths.iter_mut().zip(row) {
                *width = (*width).max(cell.chars().count());
            }
        }
        let line = |values: &[String]| -> String {
            values
                .iter()
                .zip(&widths)
                .map(|(v, w)| format!("{v:<w$}"))
                .collect::<Vec<_>>()
                .join("  ")
                .trim_end()
                .to_string()
        };
        let mut out = line(&self.columns);
        out.push('\n');
        for row in &cells {
            out.push_str(&line(row));
            out.push('\n');
        }
        out
    }
}

fn cell_text(value: &Value) -> String {
    match value {
        Value::Null => "-".to_string(),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Runs `sql` with `args` and collects every row.
pub fn query(conn: &Connection, sql: &str, args: &[&dyn rusqlite::ToSql]) -> anyhow::Result<Table> {
    let mut statement = conn.prepare(sql)?;
    let columns: Vec<String> = statement
        .column_names()
        .iter()
        .map(|c| c.to_string())
        .collect();
    let count = columns.len();
    let mut rows = Vec::new();
    let mut cursor = statement.query(args)?;
    while let Some(row) = cursor.next()? {
        let mut values = Vec::with_capacity(count);
        for index in 0..count {
            values.push(super::sql_guard::json_value(row.get_ref(index)?));
        }
        rows.push(values);
    }
    Ok(Table { columns, rows })
}

/// Parses the UTC times this registry writes (`2026-11-22T23:05:00.123Z`).
pub fn parse_utc(text: &str) -> Option<SystemTime> {
    let number = |range: std::ops::Range<usize>| -> Option<i64> { text.get(range)?.parse().ok() };
    let (year, month, day) = (number(0..4)?, number(5..7)?, number(8..10)?);
    let (hour, minute, second) = (number(11..13)?, number(14..16)?, number(17..19)?);
    let millis = number(20..23).unwrap_or(0);
    // Days from civil (H. Hinnant's algorithm).
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468;
    let seconds = days * 86_400 + hour * 3600 + minute * 60 + second;
    let seconds = u64::try_from(seconds).ok()?;
    Some(UNIX_EPOCH + Duration::from_secs(seconds) + Duration::from_millis(millis as u64))
}

/// One blob that failed verification.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BadBlob {
    pub sha256: String,
    pub path: String,
    /// `missing` or `damaged`.
    pub problem: String,
    /// The hash the bytes have now (damaged blobs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub actual_sha256: Option<String>,
    /// The artefacts that use it: `kind name (key)`.
    pub used_by: Vec<String>,
}

/// What `verify` found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VerifyReport {
    pub blobs_checked: usize,
    pub bytes_checked: u64,
    pub bad: Vec<BadBlob>,
    /// Blob files no artefact records (left by an interrupted write; `gc`
    /// removes them).
    pub unrecorded_files: Vec<String>,
    /// Temporary files left by interrupted writes.
    pub leftover_temporaries: Vec<String>,
    /// SQLite's own `PRAGMA integrity_check` result.
    pub database_integrity: String,
}

impl VerifyReport {
    pub fn ok(&self) -> bool {
        self.bad.is_empty() && self.database_integrity == "ok"
    }
}

/// What `gc` removed (or would remove, with `dry_run`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GcReport {
    pub dry_run: bool,
    /// Artefacts no run step references.
    pub artefacts: Vec<String>,
    /// Blob files no remaining artefact references.
    pub blobs: Vec<String>,
    pub bytes: u64,
    pub temporaries: Vec<String>,
}

/// What an id given on the command line names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Found {
    Run(String),
    Artefact(String),
}

impl Registry {
    /// Every run, newest first, with its effective status (`unfinished` for
    /// a `running` run whose process is gone).
    pub fn list_runs(&self) -> anyhow::Result<Table> {
        let mut table = query(
            self.connection(),
            "SELECT id, kind, manifest_name, status, started_at, ended_at,
                    cached_steps, computed_steps, rebuilt_steps, git_commit, git_dirty, host, pid
             FROM runs ORDER BY started_at DESC, id DESC",
            &[],
        )?;
        let host = host_name();
        for row in &mut table.rows {
            if row[3] == json!("running")
                && row[11] == json!(host)
                && row[12]
                    .as_i64()
                    .is_some_and(|pid| !process_alive(pid as u32))
            {
                row[3] = json!("unfinished");
            }
            if let Value::String(commit) = &row[9] {
                row[9] = json!(commit.chars().take(12).collect::<String>());
            }
        }
        for row in &mut table.rows {
            row.truncate(11);
        }
        table.columns.truncate(11);
        Ok(table)
    }

    pub fn list_datasets(&self) -> anyhow::Result<Table> {
        query(
            self.connection(),
            "SELECT d.key, d.name, d.frames, d.height, d.width, d.diffusion, d.brightness, d.seed,
                    a.created_at, a.compute_seconds
             FROM datasets d JOIN artefacts a ON a.key = d.key ORDER BY a.created_at, d.name",
            &[],
        )
    }

    pub fn list_models(&self) -> anyhow::Result<Table> {
        query(
            self.connection(),
            "SELECT m.key, m.detector, m.detector_kind, m.training_dataset_key, m.seed,
                    a.created_at, a.compute_seconds
             FROM models m JOIN artefacts a ON a.key = m.key ORDER BY a.created_at, m.detector",
            &[],
        )
    }

    pub fn list_evaluations(&self) -> anyhow::Result<Table> {
        query(
            self.connection(),
            "SELECT e.key, e.detector, e.dataset, u.eps_px, u.auc, e.rmse_top_px,
                    e.fraction_without_prediction, a.created_at
             FROM evaluations e JOIN auc u ON u.evaluation_key = e.key
             JOIN artefacts a ON a.key = e.key ORDER BY a.created_at, e.detector, e.dataset, u.eps_px",
            &[],
        )
    }

    /// Resolves a run id or artefact key, or a unique prefix of one (at
    /// least 4 characters).
    pub fn resolve_id(&self, id: &str) -> anyhow::Result<Found> {
        let exact_run: bool = self.connection().query_row(
            "SELECT EXISTS(SELECT 1 FROM runs WHERE id = ?1)",
            [id],
            |r| r.get(0),
        )?;
        if exact_run {
            return Ok(Found::Run(id.to_string()));
        }
        if id.len() < 4 {
            return Err(input_error(format!(
                "{id:?}: give a full run id or artefact key, or a prefix of at least 4 characters"
            )));
        }
        let pattern = format!("{}%", id.replace(['%', '_'], ""));
        let runs = query(
            self.connection(),
            "SELECT id FROM runs WHERE id LIKE ?1 LIMIT 3",
            &[&pattern],
        )?;
        let artefacts = query(
            self.connection(),
            "SELECT key FROM artefacts WHERE key LIKE ?1 LIMIT 3",
            &[&pattern],
        )?;
        let found: Vec<Found> = runs
            .rows
            .iter()
            .map(|r| Found::Run(cell_text(&r[0])))
            .chain(
                artefacts
                    .rows
                    .iter()
                    .map(|r| Found::Artefact(cell_text(&r[0]))),
            )
            .collect();
        match found.len() {
            0 => Err(input_error(format!(
                "{id}: no run or artefact with this id in {}",
                self.dir().display()
            ))),
            1 => Ok(found.into_iter().next().expect("one")),
            _ => Err(input_error(format!(
                "{id}: ambiguous, matches several runs or artefacts; give more characters"
            ))),
        }
    }

    /// A run in full: its record, steps and AUC table, as JSON.
    pub fn run_record(&self, id: &str) -> anyhow::Result<Value> {
        let run = query(
            self.connection(),
            "SELECT * FROM runs WHERE id = ?1",
            &[&id],
        )?;
        let Some(mut record) = run.to_json().as_array().and_then(|a| a.first().cloned()) else {
            return Err(input_error(format!("{id}: no such run")));
        };
        if record["status"] == json!("running")
            && record["host"] == json!(host_name())
            && record["pid"]
                .as_i64()
                .is_some_and(|pid| !process_alive(pid as u32))
        {
            record["status"] = json!("unfinished");
        }
        for field in ["resolved", "seeds"] {
            if let Some(text) = record[field].as_str()
                && let Ok(value) = serde_json::from_str::<Value>(text)
            {
                record[field] = value;
            }
        }
        let mut steps = query(
            self.connection(),
            "SELECT ordinal, step, kind, artefact_key, outcome, seconds, blobs, detail
             FROM run_steps WHERE run_id = ?1 ORDER BY ordinal",
            &[&id],
        )?
        .to_json();
        if let Some(steps) = steps.as_array_mut() {
            for step in steps {
                if let Some(text) = step["blobs"].as_str()
                    && let Ok(value) = serde_json::from_str::<Value>(text)
                {
                    step["blobs"] = value;
                }
            }
        }
        record["steps"] = steps;
        record["auc"] = query(
            self.connection(),
            "SELECT detector, dataset, diffusion, eps_px, auc, evaluation_key
             FROM run_auc WHERE run_id = ?1 ORDER BY rowid",
            &[&id],
        )?
        .to_json();
        Ok(record)
    }

    /// An artefact in full: its record, blobs, typed row, and the runs
    /// that used it.
    pub fn artefact_record(&self, key: &str) -> anyhow::Result<Value> {
        let table = query(
            self.connection(),
            "SELECT * FROM artefacts WHERE key = ?1",
            &[&key],
        )?;
        let Some(mut record) = table.to_json().as_array().and_then(|a| a.first().cloned()) else {
            return Err(input_error(format!("{key}: no such artefact")));
        };
        if let Some(text) = record["spec"].as_str()
            && let Ok(value) = serde_json::from_str::<Value>(text)
        {
            record["spec"] = value;
        }
        let kind = record["kind"].as_str().unwrap_or("").to_string();
        let typed_table = match kind.as_str() {
            "dataset" => "datasets",
            "model" => "models",
            "predictions" => "predictions",
            _ => "evaluations",
        };
        record["details"] = query(
            self.connection(),
            &format!("SELECT * FROM {typed_table} WHERE key = ?1"),
            &[&key],
        )?
        .to_json()
        .as_array()
        .and_then(|a| a.first().cloned())
        .unwrap_or(Value::Null);
        if kind == "evaluation" {
            record["auc"] = query(
                self.connection(),
                "SELECT eps_px, auc, true_positives, false_positives FROM auc
                 WHERE evaluation_key = ?1 ORDER BY eps_px",
                &[&key],
            )?
            .to_json();
        }
        let blobs = query(
            self.connection(),
            "SELECT ab.role, ab.sha256, b.bytes FROM artefact_blobs ab
             LEFT JOIN blobs b ON b.sha256 = ab.sha256 WHERE ab.artefact_key = ?1 ORDER BY ab.role",
            &[&key],
        )?;
        let mut blobs = blobs.to_json();
        if let Some(list) = blobs.as_array_mut() {
            for blob in list {
                if let Some(sha) = blob["sha256"].as_str() {
                    blob["path"] = json!(self.blobs().path(sha).display().to_string());
                }
            }
        }
        record["blobs"] = blobs;
        record["used_by_runs"] = query(
            self.connection(),
            "SELECT run_id, step, outcome FROM run_steps WHERE artefact_key = ?1 ORDER BY run_id",
            &[&key],
        )?
        .to_json();
        Ok(record)
    }

    /// Re-hashes every blob file, in parallel, and checks the database.
    pub fn verify(&self) -> anyhow::Result<VerifyReport> {
        let integrity: String =
            self.connection()
                .query_row("PRAGMA integrity_check", [], |row| row.get(0))?;
        let recorded = query(
            self.connection(),
            "SELECT b.sha256, b.bytes,
                    group_concat(a.kind || ' ' || a.name || ' (' || a.key || ')', '; ')
             FROM blobs b LEFT JOIN artefact_blobs ab ON ab.sha256 = b.sha256
             LEFT JOIN artefacts a ON a.key = ab.artefact_key
             GROUP BY b.sha256 ORDER BY b.sha256",
            &[],
        )?;
        let entries: Vec<(String, Vec<String>)> = recorded
            .rows
            .iter()
            .map(|row| {
                let users = match &row[2] {
                    Value::String(s) => s.split("; ").map(str::to_string).collect(),
                    _ => Vec::new(),
                };
                (cell_text(&row[0]), users)
            })
            .collect();
        let store = self.blobs();
        let results: Vec<anyhow::Result<(BlobState, u64)>> = entries
            .par_iter()
            .map(|(sha, _)| {
                let state = store.check(sha)?;
                let bytes = std::fs::metadata(store.path(sha))
                    .map(|m| m.len())
                    .unwrap_or(0);
                Ok((state, bytes))
            })
            .collect();
        let mut bad = Vec::new();
        let mut bytes_checked = 0;
        for ((sha, users), result) in entries.iter().zip(results) {
            let (state, bytes) = result?;
            bytes_checked += bytes;
            let (problem, actual) = match state {
                BlobState::Intact => continue,
                BlobState::Missing => ("missing", None),
                BlobState::Damaged { actual } => ("damaged", Some(actual)),
            };
            bad.push(BadBlob {
                sha256: sha.clone(),
                path: store.path(sha).display().to_string(),
                problem: problem.to_string(),
                actual_sha256: actual,
                used_by: users.clone(),
            });
        }
        let known: BTreeSet<&str> = entries.iter().map(|(sha, _)| sha.as_str()).collect();
        let unrecorded_files = store
            .list()?
            .into_iter()
            .filter(|(name, _, _)| !known.contains(name.as_str()))
            .map(|(_, path, _)| path.display().to_string())
            .collect();
        Ok(VerifyReport {
            blobs_checked: entries.len(),
            bytes_checked,
            bad,
            unrecorded_files,
            leftover_temporaries: store
                .leftovers()?
                .into_iter()
                .map(|p| p.display().to_string())
                .collect(),
            database_integrity: integrity,
        })
    }

    /// Removes artefacts no run step references and blob files no remaining
    /// artefact references (`dry_run`: only says what it would remove).
    /// Anything newer than the start of the oldest run still in progress is
    /// kept, since that run may be about to record it.
    pub fn gc(&mut self, dry_run: bool) -> anyhow::Result<GcReport> {
        let live = query(
            self.connection(),
            "SELECT started_at, host, pid FROM runs WHERE status = 'running'",
            &[],
        )?;
        let host = host_name();
        let mut cutoff = SystemTime::now();
        let mut live_started: Option<String> = None;
        for row in &live.rows {
            let alive = row[1] != json!(host)
                || row[2].as_i64().is_some_and(|pid| process_alive(pid as u32));
            if alive && let Some(started) = row[0].as_str().and_then(parse_utc) {
                cutoff = cutoff.min(started - Duration::from_secs(60));
                live_started = Some(cell_text(&row[0]));
            }
        }
        let live_cutoff_text = live_started.map(|_| super::format_utc(cutoff));

        let orphans = query(
            self.connection(),
            "SELECT a.key, a.kind, a.name, a.created_at FROM artefacts a
             WHERE NOT EXISTS (SELECT 1 FROM run_steps s WHERE s.artefact_key = a.key)
             ORDER BY a.created_at",
            &[],
        )?;
        let artefacts: Vec<(String, String)> = orphans
            .rows
            .iter()
            .filter(|row| {
                live_cutoff_text
                    .as_deref()
                    .is_none_or(|c| cell_text(&row[3]).as_str() < c)
            })
            .map(|row| {
                (
                    cell_text(&row[0]),
                    format!(
                        "{} {} ({})",
                        cell_text(&row[1]),
                        cell_text(&row[2]),
                        cell_text(&row[0])
                    ),
                )
            })
            .collect();
        let doomed: BTreeSet<&str> = artefacts.iter().map(|(k, _)| k.as_str()).collect();

        let still_used: BTreeSet<String> = {
            let rows = query(
                self.connection(),
                "SELECT artefact_key, sha256 FROM artefact_blobs",
                &[],
            )?;
            rows.rows
                .iter()
                .filter(|r| !doomed.contains(cell_text(&r[0]).as_str()))
                .map(|r| cell_text(&r[1]))
                .collect()
        };
        let mut blobs = Vec::new();
        let mut bytes = 0;
        let mut blob_paths = Vec::new();
        for (sha, path, size) in self.blobs().list()? {
            if still_used.contains(&sha) {
                continue;
            }
            let modified = std::fs::metadata(&path)
                .and_then(|m| m.modified())
                .unwrap_or(UNIX_EPOCH);
            if modified >= cutoff {
                continue;
            }
            bytes += size;
            blobs.push(sha);
            blob_paths.push(path);
        }
        let mut temporaries = Vec::new();
        let day_ago = SystemTime::now() - Duration::from_secs(86_400);
        for path in self.blobs().leftovers()? {
            let modified = std::fs::metadata(&path)
                .and_then(|m| m.modified())
                .unwrap_or(UNIX_EPOCH);
            // A temporary is in use while its write lasts; only old ones
            // or ones from before every live run are certainly abandoned.
            if modified < cutoff.min(day_ago) || live_cutoff_text.is_none() {
                temporaries.push(path);
            }
        }
        if !dry_run {
            let tx = self
                .conn
                .transaction_with_behavior(TransactionBehavior::Immediate)?;
            for (key, _) in &artefacts {
                tx.execute("DELETE FROM auc WHERE evaluation_key = ?1", [key])?;
                for table in ["datasets", "models", "predictions", "evaluations"] {
                    tx.execute(&format!("DELETE FROM {table} WHERE key = ?1"), [key])?;
                }
                tx.execute("DELETE FROM artefact_blobs WHERE artefact_key = ?1", [key])?;
                tx.execute("DELETE FROM artefacts WHERE key = ?1", [key])?;
            }
            for sha in &blobs {
                tx.execute("DELETE FROM blobs WHERE sha256 = ?1", params![sha])?;
            }
            tx.commit()?;
            for path in blob_paths.iter().chain(&temporaries) {
                match std::fs::remove_file(path) {
                    Ok(()) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        Ok(GcReport {
            dry_run,
            artefacts: artefacts.into_iter().map(|(_, label)| label).collect(),
            blobs,
            bytes,
            temporaries: temporaries
                .into_iter()
                .map(|p| p.display().to_string())
                .collect(),
        })
    }
}

/// One difference between two runs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Difference {
    /// `code`, `manifest`, `parameters`, `seeds`, `steps`, `auc`, `machine`.
    pub section: String,
    pub field: String,
    pub a: Value,
    pub b: Value,
}

fn flatten(prefix: &str, value: &Value, out: &mut BTreeMap<String, Value>) {
    match value {
        Value::Object(map) => {
            for (k, v) in map {
                let path = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(&path, v, out);
            }
        }
        Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                flatten(&format!("{prefix}[{i}]"), v, out);
            }
        }
        other => {
            out.insert(prefix.to_string(), other.clone());
        }
    }
}

fn compare(
    section: &str,
    a: &BTreeMap<String, Value>,
    b: &BTreeMap<String, Value>,
) -> Vec<Difference> {
    let keys: BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| Difference {
            section: section.to_string(),
            field: k.clone(),
            a: a.get(k).cloned().unwrap_or(Value::Null),
            b: b.get(k).cloned().unwrap_or(Value::Null),
        })
        .collect()
}

/// What differs between two run records (as [`Registry::run_record`]
/// gives them): code version, machine, manifest, resolved parameters,
/// seeds, the artefact key of each step, and each AUC cell.
pub fn diff_runs(a: &Value, b: &Value) -> Vec<Difference> {
    let mut differences = Vec::new();
    let fields = |record: &Value, names: &[&str]| -> BTreeMap<String, Value> {
        names
            .iter()
            .map(|n| (n.to_string(), record[*n].clone()))
            .collect()
    };
    differences.extend(compare(
        "code",
        &fields(a, &["crate_version", "git_commit", "git_dirty", "rustc"]),
        &fields(b, &["crate_version", "git_commit", "git_dirty", "rustc"]),
    ));
    differences.extend(compare(
        "machine",
        &fields(a, &["host", "threads"]),
        &fields(b, &["host", "threads"]),
    ));
    differences.extend(compare(
        "manifest",
        &fields(a, &["manifest_name", "manifest_path", "manifest_sha256"]),
        &fields(b, &["manifest_name", "manifest_path", "manifest_sha256"]),
    ));
    let resolved = |record: &Value| {
        let mut out = BTreeMap::new();
        let mut value = record["resolved"].clone();
        if let Some(map) = value.as_object_mut() {
            // Already compared above, or derived below.
            map.remove("source");
            map.remove("manifest_sha256");
        }
        flatten("", &value, &mut out);
        out
    };
    differences.extend(compare("parameters", &resolved(a), &resolved(b)));
    let seeds = |record: &Value| {
        let mut out = BTreeMap::new();
        flatten("", &record["seeds"], &mut out);
        out
    };
    differences.extend(compare("seeds", &seeds(a), &seeds(b)));
    let steps = |record: &Value| -> BTreeMap<String, Value> {
        record["steps"]
            .as_array()
            .map(|steps| {
                steps
                    .iter()
                    .map(|s| (cell_text(&s["step"]), s["artefact_key"].clone()))
                    .collect()
            })
            .unwrap_or_default()
    };
    differences.extend(compare("steps", &steps(a), &steps(b)));
    let auc = |record: &Value| -> BTreeMap<String, Value> {
        record["auc"]
            .as_array()
            .map(|rows| {
                rows.iter()
                    .map(|r| {
                        (
                            format!(
                                "{}@{} eps={}",
                                cell_text(&r["detector"]),
                                cell_text(&r["dataset"]),
                                r["eps_px"]
                            ),
                            r["auc"].clone(),
                        )
                    })
                    .collect()
            })
            .unwrap_or_default()
    };
    differences.extend(compare("auc", &auc(a), &auc(b)));
    differences
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_what_format_utc_writes() {
        let t = UNIX_EPOCH + Duration::from_millis(1_763_852_700_456);
        assert_eq!(parse_utc(&super::super::format_utc(t)), Some(t));
    }
}
