//! SQL over the registry: listings of runs and artefacts, resolving ids,
//! one artefact in full, and read-only SQL from the command line.

use rusqlite::{Connection, OptionalExtension};
use serde_json::{Value, json};

use super::Registry;
use super::table::Table;
use crate::error::input_error;

/// What an id given on the command line names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Found {
    Run(String),
    Artefact(String),
}

/// The typed row of a stored evaluation and the D of its dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct EvaluationRow {
    pub detector: String,
    pub dataset: String,
    pub dataset_key: String,
    pub predictions_key: String,
    /// The dataset's D in µm²/s, if it is fixed.
    pub diffusion: Option<f64>,
}

/// Runs `sql` with `args` and collects every row.
pub(crate) fn query(
    conn: &Connection,
    sql: &str,
    args: &[&dyn rusqlite::ToSql],
) -> anyhow::Result<Table> {
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

pub(crate) use super::sql_guard::read_only_sql;

/// The longest run id, content key or model reference (`RUN:DETECTOR`)
/// looked up, in characters: far beyond any real one (a key has 64), and
/// short enough that no lookup or message grows with what was typed.
pub(crate) const MAX_ID_CHARS: usize = 256;

/// Refuses (exit code 2, one short line) an id longer than
/// [`MAX_ID_CHARS`], before it reaches a query or a message.
pub(crate) fn check_id_length(id: &str) -> anyhow::Result<()> {
    let length = id.chars().count();
    if length > MAX_ID_CHARS {
        let start: String = id.chars().take(16).collect();
        return Err(input_error(format!(
            "{start:?}…: an id of {length} characters; run ids and keys have at most {MAX_ID_CHARS}"
        )));
    }
    Ok(())
}

/// The `LIKE … ESCAPE '\'` pattern of the strings starting with `prefix`,
/// taken literally (its `%`, `_` and `\` escaped).
pub(crate) fn like_prefix(prefix: &str) -> String {
    let mut pattern = String::with_capacity(prefix.len() + 1);
    for c in prefix.chars() {
        if matches!(c, '%' | '_' | '\\') {
            pattern.push('\\');
        }
        pattern.push(c);
    }
    pattern.push('%');
    pattern
}

impl Registry {
    /// Every run, newest first, with its status in effect, as a table
    /// (the commit shortened to 12 characters).
    pub fn list_runs(&self) -> anyhow::Result<Table> {
        let columns = [
            "id",
            "kind",
            "manifest_name",
            "status",
            "started_at",
            "ended_at",
            "cached_steps",
            "computed_steps",
            "rebuilt_steps",
            "git_commit",
            "git_dirty",
        ];
        let rows = self
            .runs()?
            .into_iter()
            .map(|run| {
                vec![
                    json!(run.id),
                    json!(run.kind),
                    json!(run.manifest_name),
                    json!(run.status),
                    json!(run.started_at),
                    json!(run.ended_at),
                    json!(run.counts.cached),
                    json!(run.counts.computed),
                    json!(run.counts.rebuilt),
                    json!(run.git_commit.chars().take(12).collect::<String>()),
                    json!(run.git_dirty),
                ]
            })
            .collect();
        Ok(Table {
            columns: columns.iter().map(|c| c.to_string()).collect(),
            rows,
        })
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
            "SELECT e.key, e.detector, e.dataset, u.eps_px, u.auc, u.auc_best_per_frame, e.rmse_top_px,
                    e.fraction_without_prediction, a.created_at
             FROM evaluations e JOIN auc u ON u.evaluation_key = e.key
             JOIN artefacts a ON a.key = e.key ORDER BY a.created_at, e.detector, e.dataset, u.eps_px",
            &[],
        )
    }

    /// The evaluation stored under `key` with its dataset's D, if any.
    pub fn evaluation(&self, key: &str) -> anyhow::Result<Option<EvaluationRow>> {
        Ok(self
            .connection()
            .query_row(
                "SELECT e.detector, e.dataset, e.dataset_key, e.predictions_key, d.diffusion
                 FROM evaluations e JOIN datasets d ON d.key = e.dataset_key WHERE e.key = ?1",
                [key],
                |row| {
                    Ok(EvaluationRow {
                        detector: row.get("detector")?,
                        dataset: row.get("dataset")?,
                        dataset_key: row.get("dataset_key")?,
                        predictions_key: row.get("predictions_key")?,
                        diffusion: row.get("diffusion")?,
                    })
                },
            )
            .optional()?)
    }

    /// Resolves a run id or artefact key, or a unique prefix of one (at
    /// least 4 characters).
    pub fn resolve_id(&self, id: &str) -> anyhow::Result<Found> {
        check_id_length(id)?;
        if self.run_exists(id)? {
            return Ok(Found::Run(id.to_string()));
        }
        if id.len() < 4 {
            return Err(input_error(format!(
                "{id:?}: give a full run id or artefact key, or a prefix of at least 4 characters"
            )));
        }
        let pattern = like_prefix(id);
        let matching = |sql: &str| -> anyhow::Result<Vec<String>> {
            let mut statement = self.connection().prepare(sql)?;
            let ids = statement
                .query_map([&pattern], |row| row.get::<_, String>(0))?
                .collect::<Result<_, _>>()?;
            Ok(ids)
        };
        let found: Vec<Found> =
            matching("SELECT id FROM runs WHERE id LIKE ?1 ESCAPE '\\' LIMIT 3")?
                .into_iter()
                .map(Found::Run)
                .chain(
                    matching("SELECT key FROM artefacts WHERE key LIKE ?1 ESCAPE '\\' LIMIT 3")?
                        .into_iter()
                        .map(Found::Artefact),
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

    /// An artefact in full, as JSON: its record, blobs, typed row, and the
    /// runs that used it.
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
        let kind = self
            .artefact(key)?
            .map(|a| a.kind)
            .ok_or_else(|| input_error(format!("{key}: no such artefact")))?;
        record["details"] = query(
            self.connection(),
            &format!("SELECT * FROM {} WHERE key = ?1", kind.table()),
            &[&key],
        )?
        .to_json()
        .as_array()
        .and_then(|a| a.first().cloned())
        .unwrap_or(Value::Null);
        if kind == super::ArtefactKind::Evaluation {
            record["auc"] = query(
                self.connection(),
                "SELECT eps_px, auc, auc_best_per_frame, true_positives, false_positives FROM auc
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
}
