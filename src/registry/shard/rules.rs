//! What a shard's rows must be before they are copied: the durable tables
//! and how each is keyed, and a rule for every column that becomes a path,
//! a label or a key. A shard is input like any other file, so a name in it
//! obeys the rule a manifest's names obey ([`is_plain_name`]): names end
//! up in file names (`report --out`), in tables and in messages.

use rusqlite::types::Value;

use crate::registry::hashing::sha256_hex;
use crate::registry::{ArtefactKind, BlobRole};
use crate::types::names::{MAX_NAME_LEN, is_plain_name};

/// How a table's rows are selected for a copy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum KeyedBy {
    /// By blob (`blobs.sha256`).
    Blob,
    /// By run id, in this column.
    Run(&'static str),
    /// By artefact key, in this column.
    Artefact(&'static str),
}

/// A table of the record that a copy carries over.
#[derive(Debug, Clone, Copy)]
pub(super) struct Durable {
    pub name: &'static str,
    pub keyed: KeyedBy,
    /// The columns that name one row in a message (its primary key).
    pub row_key: &'static [&'static str],
}

/// The durable tables, every referenced table before the tables that
/// refer to it, so that rows are inserted with their foreign keys checked
/// one by one. `step_claims` is not one: it says who computes what at the
/// moment, and a copied claim would make a run wait for a process that is
/// not there.
pub(super) const DURABLE: &[Durable] = &[
    durable("blobs", KeyedBy::Blob, &["sha256"]),
    durable("artefacts", KeyedBy::Artefact("key"), &["key"]),
    durable(
        "artefact_blobs",
        KeyedBy::Artefact("artefact_key"),
        &["artefact_key", "role"],
    ),
    durable("datasets", KeyedBy::Artefact("key"), &["key"]),
    durable("models", KeyedBy::Artefact("key"), &["key"]),
    durable("predictions", KeyedBy::Artefact("key"), &["key"]),
    durable("evaluations", KeyedBy::Artefact("key"), &["key"]),
    durable(
        "auc",
        KeyedBy::Artefact("evaluation_key"),
        &["evaluation_key", "eps_px"],
    ),
    durable("runs", KeyedBy::Run("id"), &["id"]),
    durable("run_steps", KeyedBy::Run("run_id"), &["run_id", "ordinal"]),
    durable(
        "run_auc",
        KeyedBy::Run("run_id"),
        &["run_id", "detector", "dataset", "eps_px"],
    ),
];

/// The oldest schema version a source may have: one whose durable tables
/// lack only columns of [`ADDED_COLUMNS`], which are read as NULL (as a
/// migration leaves them in rows recorded before it).
pub(super) const OLDEST_SOURCE_SCHEMA: i64 = 2;

/// Columns of durable tables added after [`OLDEST_SOURCE_SCHEMA`]: (the
/// schema version that added it, table, column).
pub(super) const ADDED_COLUMNS: &[(i64, &str, &str)] = &[
    (3, "auc", "auc_best_per_frame"),
    (3, "run_auc", "auc_best_per_frame"),
];

/// Whether `table.column` is one a source of schema `version` lacks.
pub(super) fn added_after(version: i64, table: &str, column: &str) -> bool {
    ADDED_COLUMNS
        .iter()
        .any(|&(added, t, c)| version < added && t == table && c == column)
}

/// Tables of the moment: present in a registry, never copied.
pub(super) const TRANSIENT: &[&str] = &["step_claims"];

const fn durable(name: &'static str, keyed: KeyedBy, row_key: &'static [&'static str]) -> Durable {
    Durable {
        name,
        keyed,
        row_key,
    }
}

/// Longest run id, and longest name a run derives from a manifest's names
/// (`DETECTOR@DATASET+firstN`, `TRAINING-cvKofN-held-out`): room for a few
/// of the manifest's longest names.
pub(super) const MAX_RECORDED_NAME_LEN: usize = 4 * MAX_NAME_LEN;

/// What a column's values must be.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Rule {
    /// A content key or blob hash: 64 lower-case hex digits.
    Key,
    /// A run id: a plain name.
    RunId,
    /// A dataset, detector or artefact name: plain names joined by `@`
    /// (`DETECTOR@DATASET`) or `+` (`DATASET+firstN`).
    Label,
    /// A blob's role in its artefact (`frames.npy`): a plain name.
    Role,
    /// A run step: `KIND/NAME`.
    Step,
    /// A blob's size in bytes: a whole number, at least 0.
    Size,
    /// Anything SQLite and the destination's constraints accept.
    Any,
}

/// The rule for `table.column`, and whether NULL is allowed besides.
fn rule(table: &str, column: &str) -> (Rule, bool) {
    match (table, column) {
        ("predictions", "model_key") => (Rule::Key, true),
        ("blobs", "sha256")
        | ("artefacts", "key")
        | ("artefact_blobs", "artefact_key" | "sha256")
        | ("datasets" | "models" | "predictions" | "evaluations", "key")
        | ("models", "training_dataset_key")
        | ("predictions", "dataset_key")
        | ("evaluations", "dataset_key" | "predictions_key")
        | ("auc", "evaluation_key")
        | ("run_steps", "artefact_key")
        | ("run_auc", "evaluation_key") => (Rule::Key, false),
        ("runs", "parent_run") | ("artefacts", "created_by_run") => (Rule::RunId, true),
        ("runs", "id") | ("run_steps" | "run_auc", "run_id") => (Rule::RunId, false),
        ("runs", "cv_detector") => (Rule::Label, true),
        ("artefacts" | "datasets", "name")
        | ("models" | "predictions" | "evaluations" | "run_auc", "detector")
        | ("models", "detector_kind")
        | ("evaluations" | "run_auc", "dataset") => (Rule::Label, false),
        ("artefact_blobs", "role") => (Rule::Role, false),
        ("run_steps", "step") => (Rule::Step, false),
        ("blobs", "bytes") => (Rule::Size, false),
        _ => (Rule::Any, true),
    }
}

/// Whether `text` is a content key or blob hash (64 lower-case hex digits).
pub(super) fn is_key(text: &str) -> bool {
    text.len() == 64 && text.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

/// Whether `text` is a label: plain names joined by `@` or `+`.
fn is_label(text: &str) -> bool {
    text.len() <= MAX_RECORDED_NAME_LEN
        && text
            .split(['@', '+'])
            .all(|part| is_plain_name(part, MAX_RECORDED_NAME_LEN))
}

fn is_step(text: &str) -> bool {
    text.split_once('/')
        .is_some_and(|(kind, name)| ArtefactKind::parse(kind).is_ok() && is_label(name))
}

/// Why `value` breaks `rule` (`None`: it does not).
fn problem(rule: Rule, nullable: bool, value: &Value) -> Option<String> {
    let text = match value {
        Value::Null if nullable => return None,
        Value::Text(text) => Some(text.as_str()),
        _ => None,
    };
    let fits = match rule {
        Rule::Any => return None,
        Rule::Size => return size_problem(value),
        Rule::Key => text.is_some_and(is_key),
        Rule::RunId => text.is_some_and(|t| is_plain_name(t, MAX_RECORDED_NAME_LEN)),
        Rule::Role => text.is_some_and(|t| t.parse::<BlobRole>().is_ok()),
        Rule::Label => text.is_some_and(is_label),
        Rule::Step => text.is_some_and(is_step),
    };
    (!fits).then(|| {
        let wanted = match rule {
            Rule::Key => "64 lower-case hex digits",
            Rule::Label => "plain names (letters, digits, '.', '_', '-') joined by '@' or '+'",
            Rule::Step => "KIND/NAME with KIND an artefact kind",
            Rule::Role => {
                "a blob role (frames.npy, model.bin, predictions.csv, score.json, truth.csv)"
            }
            _ => "a plain name (letters, digits, '.', '_', '-', starting with a letter or digit)",
        };
        format!("{} is not {wanted}", shown(value))
    })
}

fn size_problem(value: &Value) -> Option<String> {
    match value {
        Value::Integer(bytes) if *bytes >= 0 => None,
        other => Some(format!(
            "{} is not a size in bytes (a whole number, at least 0)",
            shown(other)
        )),
    }
}

/// A value as a message shows it: quoted, and cut short when long.
pub(super) fn shown(value: &Value) -> String {
    const LONGEST: usize = 80;
    match value {
        Value::Null => "NULL".to_string(),
        Value::Integer(n) => n.to_string(),
        Value::Real(x) => x.to_string(),
        Value::Text(text) if text.chars().count() > LONGEST => {
            let start: String = text.chars().take(LONGEST).collect();
            format!("{start:?}… ({} bytes)", text.len())
        }
        Value::Text(text) => format!("{text:?}"),
        Value::Blob(bytes) => format!("a {}-byte BLOB", bytes.len()),
    }
}

/// The row's key columns as a message names the row: `(run_id="…", ordinal=3)`.
pub(super) fn row_label(table: &Durable, columns: &[String], values: &[Value]) -> String {
    let parts: Vec<String> = table
        .row_key
        .iter()
        .filter_map(|key| {
            let at = columns.iter().position(|c| c == key)?;
            Some(format!("{key}={}", shown(&values[at])))
        })
        .collect();
    format!("({})", parts.join(", "))
}

/// Why the row `values` (of `columns`) of `table` may not be copied, if
/// it may not: a name that is not plain, a key that is not a key, a size
/// that is not one, an artefact whose spec does not hash to its key.
pub(super) fn row_problem(table: &Durable, columns: &[String], values: &[Value]) -> Option<String> {
    for (column, value) in columns.iter().zip(values) {
        let (rule, nullable) = rule(table.name, column);
        if let Some(problem) = problem(rule, nullable, value) {
            return Some(format!("{column}: {problem}"));
        }
    }
    if table.name == "artefacts" {
        let get = |name: &str| {
            columns
                .iter()
                .position(|c| c == name)
                .and_then(|at| match &values[at] {
                    Value::Text(text) => Some(text.as_str()),
                    _ => None,
                })
        };
        return spec_problem(get("key")?, get("kind"), get("spec"));
    }
    None
}

/// Re-derives an artefact's key from its recorded spec (the key is the
/// sha256 of the spec's canonical JSON, the check `registry verify` makes)
/// and checks the spec is of the artefact's kind.
fn spec_problem(key: &str, kind: Option<&str>, spec: Option<&str>) -> Option<String> {
    let Some(spec) = spec else {
        return Some("spec: not text".to_string());
    };
    let derived = sha256_hex(spec.as_bytes());
    if derived != key {
        return Some(format!(
            "spec: hashes to {derived}, not to the key (the spec was edited or damaged)"
        ));
    }
    let spec_kind = serde_json::from_str::<serde_json::Value>(spec)
        .ok()
        .and_then(|tree| tree.get("kind")?.as_str().map(str::to_string));
    if spec_kind.as_deref() != kind {
        return Some(format!(
            "kind: {:?}, but the spec describes {}",
            kind.unwrap_or("NULL"),
            spec_kind.map_or("no kind".to_string(), |k| format!("{k:?}"))
        ));
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(s: &str) -> Value {
        Value::Text(s.to_string())
    }

    #[test]
    fn names_that_are_paths_are_refused() {
        for label in ["test-1.00", "trackpy@test-1.00", "a+first10", "cnn-cv1of5"] {
            assert!(is_label(label), "{label}");
        }
        for label in [
            "", "../x", "/etc", "a/b", "a@", "@b", ".hidden", "a b", "é", "a\\b",
        ] {
            assert!(!is_label(label), "{label}");
        }
        assert!(is_step("evaluation/trackpy@test-1.00"));
        assert!(!is_step("evaluation/../x") && !is_step("thing/x") && !is_step("dataset"));
        assert!(problem(Rule::RunId, false, &text("20261122T230500Z-0a1b2c3d")).is_none());
        assert!(problem(Rule::RunId, false, &Value::Null).is_some());
        assert!(problem(Rule::RunId, true, &Value::Null).is_none());
        assert!(problem(Rule::Key, false, &text(&"A".repeat(64))).is_some());
        assert!(problem(Rule::Key, false, &text(&"../".repeat(21))).is_some());
        assert!(problem(Rule::Key, false, &Value::Blob(vec![b'a'; 64])).is_some());
        assert!(problem(Rule::Size, false, &Value::Integer(-5)).is_some());
        assert!(problem(Rule::Size, false, &Value::Real(5.0)).is_some());
        assert!(problem(Rule::Size, false, &Value::Integer(5)).is_none());
    }

    #[test]
    fn a_key_is_re_derived_from_its_spec() {
        let spec = r#"{"code":"x","kind":"dataset"}"#;
        let key = sha256_hex(spec.as_bytes());
        assert_eq!(spec_problem(&key, Some("dataset"), Some(spec)), None);
        assert!(spec_problem(&key, Some("model"), Some(spec)).is_some());
        let edited = spec.replace('x', "y");
        assert!(spec_problem(&key, Some("dataset"), Some(&edited)).is_some());
    }
}
