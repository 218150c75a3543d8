//! `registry diff`: what differs between two run records, and the JSON
//! flattening that comparison (and `reproduce`'s number by number
//! comparison) rests on.

use std::collections::{BTreeMap, BTreeSet};

use serde::Serialize;
use serde_json::{Value, json};

use super::RunRecord;

/// One difference between two runs.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Difference {
    /// `code`, `manifest`, `parameters`, `seeds`, `steps`, `auc`, `machine`.
    pub section: String,
    pub field: String,
    pub a: Value,
    pub b: Value,
}

/// Every leaf of `value` by its path: `a.b[2].c` (a bare leaf's path is
/// empty).
pub(crate) fn flatten(value: &Value) -> BTreeMap<String, Value> {
    fn walk(prefix: &str, value: &Value, out: &mut BTreeMap<String, Value>) {
        match value {
            Value::Object(map) => {
                for (k, v) in map {
                    let path = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    walk(&path, v, out);
                }
            }
            Value::Array(items) => {
                for (i, v) in items.iter().enumerate() {
                    walk(&format!("{prefix}[{i}]"), v, out);
                }
            }
            other => {
                out.insert(prefix.to_string(), other.clone());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk("", value, &mut out);
    out
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

/// What differs between two run records: code version, machine, manifest,
/// resolved parameters, seeds, the artefact key of each step, and each AUC
/// cell.
pub(crate) fn diff_runs(a: &RunRecord, b: &RunRecord) -> Vec<Difference> {
    let fields = |pairs: &[(&str, Value)]| -> BTreeMap<String, Value> {
        pairs
            .iter()
            .map(|(name, value)| (name.to_string(), value.clone()))
            .collect()
    };
    let code = |r: &RunRecord| {
        fields(&[
            ("crate_version", json!(r.code.crate_version)),
            ("git_commit", json!(r.code.git_commit)),
            ("git_dirty", json!(r.code.git_dirty)),
            ("rustc", json!(r.code.rustc)),
        ])
    };
    let machine = |r: &RunRecord| fields(&[("host", json!(r.host)), ("threads", json!(r.threads))]);
    let manifest = |r: &RunRecord| {
        fields(&[
            ("manifest_name", json!(r.manifest_name)),
            ("manifest_path", json!(r.manifest_path)),
            ("manifest_sha256", json!(r.manifest_sha256)),
        ])
    };
    let parameters = |r: &RunRecord| {
        let mut resolved = r.resolved.clone();
        if let Some(map) = resolved.as_object_mut() {
            // Already compared as the manifest's.
            map.remove("source");
            map.remove("manifest_sha256");
        }
        flatten(&resolved)
    };
    let seeds = |r: &RunRecord| -> BTreeMap<String, Value> {
        r.seeds
            .iter()
            .map(|(step, seed)| (step.clone(), json!(seed)))
            .collect()
    };
    let steps = |r: &RunRecord| -> BTreeMap<String, Value> {
        r.steps
            .iter()
            .map(|s| (s.step.to_string(), json!(s.artefact_key)))
            .collect()
    };
    // A cell of ranked lists also has its best guess per frame.
    let auc = |r: &RunRecord| -> BTreeMap<String, Value> {
        r.auc
            .iter()
            .flat_map(|row| {
                let cell = format!("{}@{} eps={}", row.detector, row.dataset, row.eps_px);
                let best = row
                    .auc_best_per_frame
                    .map(|best| (format!("{cell} best guess"), json!(best)));
                [(cell, json!(row.auc))].into_iter().chain(best)
            })
            .collect()
    };
    let mut differences = Vec::new();
    differences.extend(compare("code", &code(a), &code(b)));
    differences.extend(compare("machine", &machine(a), &machine(b)));
    differences.extend(compare("manifest", &manifest(a), &manifest(b)));
    differences.extend(compare("parameters", &parameters(a), &parameters(b)));
    differences.extend(compare("seeds", &seeds(a), &seeds(b)));
    differences.extend(compare("steps", &steps(a), &steps(b)));
    differences.extend(compare("auc", &auc(a), &auc(b)));
    differences
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flattens_to_leaf_paths() {
        let flat = flatten(&json!({"a": {"b": [1, {"c": null}]}, "d": "x"}));
        let expected: BTreeMap<String, Value> = [
            ("a.b[0]".to_string(), json!(1)),
            ("a.b[1].c".to_string(), Value::Null),
            ("d".to_string(), json!("x")),
        ]
        .into_iter()
        .collect();
        assert_eq!(flat, expected);
        assert_eq!(flatten(&json!(3)), [(String::new(), json!(3))].into());
    }
}
