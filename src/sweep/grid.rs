//! The manifest's `sweep:` block: named axes over manifest paths, run as
//! their grid product (the first axis varies slowest).
//!
//! ```yaml
//! sweep:
//!   channels:
//!     path: detectors.cnn.cnn.architecture.channels
//!     values: [8, 16]
//!   epochs:
//!     path: detectors.cnn.cnn.training.epochs
//!     values: [2, 4]
//! ```
//!
//! A path names keys from the top of the manifest, separated by dots; a key
//! that itself contains dots (`datasets.test-1.00.frames`) is matched as the
//! longest existing key. Each point is the manifest without its `sweep:`
//! block and with each axis's path set to the point's value, resolved and
//! validated like any manifest, so a value the manifest refuses is reported
//! with the axis and value that made it.

use std::sync::Arc;

use serde_json::json;
use serde_yaml::{Mapping, Value};

use super::SweepSpec;
use super::front_end::{Finished, FrontEnd};
use crate::error::input_error;
use crate::limits::display_cell;
use crate::manifest::{self, Manifest};
use crate::registry::{Registry, RunKind};
use crate::run::{Plan, RunOptions, TrackingRow};
use crate::track::diffusion::Method;

/// One axis of the grid.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Axis {
    pub name: String,
    /// Keys from the top of the manifest.
    pub path: Vec<String>,
    pub values: Vec<Value>,
}

/// One point of the grid: its label (`channels=8 epochs=2`) and manifest.
#[derive(Debug, Clone)]
pub(crate) struct GridPoint {
    pub label: String,
    pub manifest: Manifest,
}

/// Largest number of grid points one sweep may have.
pub(crate) const MAX_POINTS: usize = 10_000;

/// The axes of `text`'s `sweep:` block (none without one). `source` names
/// the manifest in errors.
pub(crate) fn axes(text: &str, source: &str) -> anyhow::Result<Vec<Axis>> {
    let document: Value = serde_yaml::from_str(text)
        .map_err(|e| input_error(format!("{source}: {}", one_line(&e.to_string()))))?;
    let Some(block) = document.get("sweep") else {
        return Ok(Vec::new());
    };
    let block = block.as_mapping().ok_or_else(|| {
        input_error(format!(
            "{source}: sweep: must map axis names to {{path, values}}"
        ))
    })?;
    let mut axes = Vec::new();
    for (name, axis) in block {
        let name = name
            .as_str()
            .ok_or_else(|| input_error(format!("{source}: sweep: axis names must be text")))?;
        let field = |f: &str| format!("{source}: sweep.{name}.{f}");
        let axis = axis.as_mapping().ok_or_else(|| {
            input_error(format!("{source}: sweep.{name}: must be {{path, values}}"))
        })?;
        for key in axis.keys() {
            if !matches!(key.as_str(), Some("path" | "values")) {
                return Err(input_error(format!(
                    "{source}: sweep.{name}: unknown field {}, expected path or values",
                    serde_yaml::to_string(key).unwrap_or_default().trim()
                )));
            }
        }
        let path = axis
            .get("path")
            .and_then(Value::as_str)
            .filter(|p| !p.is_empty() && !p.split('.').any(str::is_empty))
            .ok_or_else(|| {
                input_error(format!(
                    "{}: must be a dotted manifest path such as detectors.cnn.cnn.training.epochs",
                    field("path")
                ))
            })?;
        if path == "sweep" || path.starts_with("sweep.") {
            return Err(input_error(format!(
                "{}: cannot sweep the sweep block",
                field("path")
            )));
        }
        let values = axis
            .get("values")
            .and_then(Value::as_sequence)
            .filter(|v| !v.is_empty())
            .ok_or_else(|| input_error(format!("{}: must be a non-empty list", field("values"))))?;
        axes.push(Axis {
            name: name.to_string(),
            path: path.split('.').map(str::to_string).collect(),
            values: values.clone(),
        });
    }
    if axes.is_empty() {
        return Err(input_error(format!("{source}: sweep: declares no axis")));
    }
    refuse_overlapping_axes(&document, &axes, source)?;
    let points = axes
        .iter()
        .try_fold(1usize, |n, a| n.checked_mul(a.values.len()))
        .filter(|&n| n <= MAX_POINTS);
    if points.is_none() {
        return Err(input_error(format!(
            "{source}: sweep: more than {MAX_POINTS} grid points"
        )));
    }
    Ok(axes)
}

/// Refuses two axes that set the same manifest value, or one a value
/// inside the other's (the later would silently override the earlier at
/// every point). Paths are compared as the keys they resolve to in
/// `document`, so two spellings of one key are caught too.
fn refuse_overlapping_axes(document: &Value, axes: &[Axis], source: &str) -> anyhow::Result<()> {
    let resolved: Vec<Vec<String>> = axes
        .iter()
        .map(|axis| resolved_keys(document, &axis.path))
        .collect();
    for (second, keys) in resolved.iter().enumerate() {
        for (first, earlier) in resolved[..second].iter().enumerate() {
            let shorter = earlier.len().min(keys.len());
            if earlier[..shorter] == keys[..shorter] {
                let (a, b) = (&axes[first], &axes[second]);
                let relation = if earlier.len() == keys.len() {
                    "the same manifest path"
                } else {
                    "nested manifest paths"
                };
                return Err(input_error(format!(
                    "{source}: sweep.{}.path and sweep.{}.path set {relation} ({} and {}); an axis would override the other at every point: give each axis its own path",
                    a.name,
                    b.name,
                    a.path.join("."),
                    b.path.join(".")
                )));
            }
        }
    }
    Ok(())
}

/// The keys `path` leads through in `document`, as [`set_path`] matches
/// them: the longest existing key at each mapping, one segment at a time
/// where nothing exists yet.
fn resolved_keys(document: &Value, path: &[String]) -> Vec<String> {
    let mut keys = Vec::new();
    let mut node = Some(document);
    let mut rest = path;
    while !rest.is_empty() {
        let mapping = node.and_then(Value::as_mapping);
        let taken = mapping
            .and_then(|m| {
                (1..=rest.len())
                    .rev()
                    .find(|&n| m.contains_key(rest[..n].join(".").as_str()))
            })
            .unwrap_or(1);
        let key = rest[..taken].join(".");
        node = mapping.and_then(|m| m.get(key.as_str()));
        keys.push(key);
        rest = &rest[taken..];
    }
    keys
}

/// Every point of the grid of `text` (whose axes are `axes`), resolved.
pub(crate) fn points(text: &str, source: &str, axes: &[Axis]) -> anyhow::Result<Vec<GridPoint>> {
    let mut document: Value = serde_yaml::from_str(text)
        .map_err(|e| input_error(format!("{source}: {}", one_line(&e.to_string()))))?;
    if let Some(mapping) = document.as_mapping_mut() {
        mapping.remove("sweep");
    }
    let total: usize = axes.iter().map(|a| a.values.len()).product();
    let mut points = Vec::with_capacity(total);
    for index in 0..total {
        // Mixed radix, the last axis fastest.
        let mut rest = index;
        let mut choice = vec![0; axes.len()];
        for (slot, axis) in axes.iter().enumerate().rev() {
            choice[slot] = rest % axis.values.len();
            rest /= axis.values.len();
        }
        let mut point = document.clone();
        let mut label = Vec::new();
        for (axis, &pick) in axes.iter().zip(&choice) {
            let value = &axis.values[pick];
            set_path(&mut point, &axis.path).map_err(|e| {
                input_error(format!(
                    "{source}: sweep.{}.path: {}: {e}",
                    axis.name,
                    axis.path.join(".")
                ))
            })?;
            *get_path_mut(&mut point, &axis.path) = value.clone();
            label.push(format!("{}={}", axis.name, scalar_text(value)));
        }
        let label = label.join(" ");
        let point_text = serde_yaml::to_string(&point)?;
        let point_source = format!("{source} [{label}]");
        let manifest = manifest::parse(&point_text, &point_source).map_err(|e| {
            input_error(format!(
                "{source}: sweep point {label}: {}",
                e.to_string()
                    .strip_prefix(&format!("{point_source}: "))
                    .unwrap_or(&e.to_string())
            ))
        })?;
        points.push(GridPoint { label, manifest });
    }
    Ok(points)
}

/// A value as a label shows it: scalars plain, others as flow YAML.
fn scalar_text(value: &Value) -> String {
    match value {
        Value::String(s) => s.clone(),
        Value::Number(n) => n.to_string(),
        Value::Bool(b) => b.to_string(),
        other => one_line(serde_yaml::to_string(other).unwrap_or_default().trim()),
    }
}

fn one_line(text: &str) -> String {
    text.replace('\n', " ")
}

/// Makes sure `path` leads to a slot in `document`, matching keys that
/// contain dots as the longest existing key and creating missing mappings;
/// afterwards `path` is rewritten as the keys actually used.
fn set_path(document: &mut Value, path: &[String]) -> Result<(), String> {
    let mut node = document;
    let mut rest = path;
    while !rest.is_empty() {
        let mapping: &mut Mapping = match node {
            Value::Mapping(m) => m,
            Value::Null => {
                *node = Value::Mapping(Mapping::new());
                node.as_mapping_mut().expect("just made")
            }
            _ => return Err("leads into a value that is not a mapping".to_string()),
        };
        let taken = (1..=rest.len())
            .rev()
            .find(|&n| mapping.contains_key(rest[..n].join(".").as_str()))
            .unwrap_or(1);
        let key = Value::String(rest[..taken].join("."));
        if !mapping.contains_key(&key) {
            mapping.insert(key.clone(), Value::Null);
        }
        node = mapping.get_mut(&key).expect("present");
        rest = &rest[taken..];
    }
    Ok(())
}

/// The slot `path` leads to (after [`set_path`] made it).
fn get_path_mut<'a>(document: &'a mut Value, path: &[String]) -> &'a mut Value {
    let mut node = document;
    let mut rest = path;
    while !rest.is_empty() {
        let mapping = node.as_mapping_mut().expect("set_path made mappings");
        let taken = (1..=rest.len())
            .rev()
            .find(|&n| mapping.contains_key(rest[..n].join(".").as_str()))
            .expect("set_path made the key");
        node = mapping
            .get_mut(rest[..taken].join(".").as_str())
            .expect("present");
        rest = &rest[taken..];
    }
    node
}

/// `scanloc sweep run` as a sweep: a point per cell of the manifest's
/// grid; the aggregation lists each finished point's AUC rows and its
/// tracking pipelines' figures (JSON: `tracking`, the rows of `scanloc run
/// --json`).
pub(crate) struct GridSweep;

impl FrontEnd for GridSweep {
    fn name(&self) -> &'static str {
        "grid"
    }

    fn points(&self, _base: &Arc<Manifest>, spec: &SweepSpec) -> anyhow::Result<Vec<super::Point>> {
        let axes = axes(&spec.manifest_text, &spec.manifest_path)?;
        if axes.is_empty() {
            return Err(input_error(format!(
                "{}: no sweep block: `scanloc sweep run` needs `sweep:` axes (see docs/cluster.md)",
                spec.manifest_path
            )));
        }
        points(&spec.manifest_text, &spec.manifest_path, &axes)?
            .into_iter()
            .enumerate()
            .map(|(index, point)| {
                Ok(super::Point {
                    index,
                    label: point.label,
                    plan: Plan::from_manifest(&point.manifest)?,
                    manifest: Arc::new(point.manifest),
                    run: RunOptions {
                        kind: RunKind::Sweep,
                        ..RunOptions::default()
                    },
                })
            })
            .collect()
    }

    fn aggregate(
        &self,
        registry: &mut Registry,
        sweep: &Finished<'_>,
    ) -> anyhow::Result<(String, serde_json::Value)> {
        let file = sweep.file;
        let mut text = format!("sweep {} of {}\n", file.id, file.spec.manifest_path);
        let mut rows = Vec::new();
        for point in sweep.done() {
            let auc = super::point_auc(registry, point)?;
            text.push_str(&format!("{}\n", point.label));
            for row in &auc {
                text.push_str(&format!(
                    "  {:<12} {:<16} ε={:<4} AUC {:.4}\n",
                    row.detector, row.dataset, row.eps_px, row.auc
                ));
            }
            let tracking = super::point_tracking(registry, point)?;
            for row in &tracking {
                text.push_str(&tracking_line(row));
            }
            rows.push(json!({
                "point": point.index,
                "label": point.label,
                "run": sweep.states[point.index].run,
                "auc": auc,
                "tracking": tracking,
            }));
        }
        Ok((
            text,
            json!({"sweep": file.id, "grid": rows, "points": sweep.states}),
        ))
    }
}

/// A tracking row in a grid's text: the pipeline and recording, the
/// tracks' Jaccard index and the ML ensemble D against the true D.
fn tracking_line(row: &TrackingRow) -> String {
    let jaccard = row
        .tracking
        .jaccard_tracks
        .map_or("-".to_string(), |j| format!("{j:.3}"));
    let ml = row
        .estimators
        .iter()
        .find(|e| e.method == Method::Ml)
        .and_then(|e| e.ensemble)
        .map_or("-".to_string(), |e| {
            format!("{:.3} ({:.3})", e.d, e.standard_error)
        });
    format!(
        "  {:<12} {:<16} JSC tracks {jaccard}  ML D {ml} (true D {})\n",
        display_cell(&row.pipeline),
        display_cell(&row.recording),
        row.diffusion
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASE: &str = "name: g\nseed: 1\ndatasets:\n  test-1.00: {frames: 4}\ndetectors:\n  trackpy:\n    crocker_grier: {diameter: 7}\nevaluations:\n  - {detector: trackpy, datasets: [test-1.00]}\n";

    #[test]
    fn grid_is_the_product_with_the_first_axis_slowest() {
        let text = format!(
            "{BASE}sweep:\n  frames:\n    path: datasets.test-1.00.frames\n    values: [2, 3]\n  diameter:\n    path: detectors.trackpy.crocker_grier.diameter\n    values: [5, 7, 9]\n"
        );
        let axes = axes(&text, "g.yaml").unwrap();
        assert_eq!(axes[0].path, ["datasets", "test-1", "00", "frames"]);
        let points = points(&text, "g.yaml", &axes).unwrap();
        assert_eq!(points.len(), 6);
        assert_eq!(points[0].label, "frames=2 diameter=5");
        assert_eq!(points[1].label, "frames=2 diameter=7");
        assert_eq!(points[5].label, "frames=3 diameter=9");
        assert_eq!(points[5].manifest.datasets[0].frames, 3);
        assert!(!points[0].manifest.text.contains("sweep"));
    }

    #[test]
    fn bad_blocks_and_bad_values_name_the_axis() {
        let bad = |block: &str| {
            let text = format!("{BASE}sweep:\n{block}");
            let axes = axes(&text, "g.yaml")?;
            points(&text, "g.yaml", &axes).map(|_| ())
        };
        let error = bad("  f: {path: datasets.test-1.00.frames, values: []}\n").unwrap_err();
        assert!(error.to_string().contains("sweep.f.values"), "{error}");
        let error = bad("  f: {path: datasets.test-1.00.frames, value: [1]}\n").unwrap_err();
        assert!(error.to_string().contains("unknown field"), "{error}");
        let error = bad("  f: {path: datasets.test-1.00.frames, values: [0]}\n").unwrap_err();
        assert_eq!(crate::error::exit_code(&error), 2);
        assert!(error.to_string().contains("sweep point f=0"), "{error}");
        assert!(error.to_string().contains("frames"), "{error}");
        assert!(bad("  f: {path: name.x, values: [1]}\n").is_err());
        assert!(axes(BASE, "g.yaml").unwrap().is_empty());
    }

    #[test]
    fn axes_on_the_same_or_nested_paths_are_refused_naming_both() {
        let cases = [
            // The same path twice, through a key with dots or plain keys.
            "  a: {path: datasets.test-1.00.frames, values: [2, 3]}\n  b: {path: datasets.test-1.00.frames, values: [4]}\n",
            "  a: {path: detectors.trackpy.crocker_grier.diameter, values: [5]}\n  b: {path: detectors.trackpy.crocker_grier.diameter, values: [7, 9]}\n",
            // One inside the other, in either order.
            "  a: {path: detectors.trackpy.crocker_grier, values: [{diameter: 5}]}\n  b: {path: detectors.trackpy.crocker_grier.diameter, values: [7]}\n",
            "  b: {path: detectors.trackpy.crocker_grier.diameter, values: [7]}\n  a: {path: detectors.trackpy, values: [{crocker_grier: {diameter: 5}}]}\n",
            // A path that does not exist yet, twice.
            "  a: {path: detectors.trackpy.crocker_grier.minmass, values: [1]}\n  b: {path: detectors.trackpy.crocker_grier.minmass, values: [2]}\n",
        ];
        for block in cases {
            let text = format!("{BASE}sweep:\n{block}");
            let error = axes(&text, "g.yaml").unwrap_err();
            let message = error.to_string();
            assert_eq!(crate::error::exit_code(&error), 2, "{message}");
            assert!(
                message.contains("sweep.a.path") && message.contains("sweep.b.path"),
                "{message}"
            );
        }
        // Siblings are fine.
        let text = format!(
            "{BASE}sweep:\n  a: {{path: detectors.trackpy.crocker_grier.diameter, values: [5]}}\n  b: {{path: detectors.trackpy.crocker_grier.minmass, values: [1]}}\n"
        );
        assert_eq!(axes(&text, "g.yaml").unwrap().len(), 2);
    }
}
