//! `registry show RUN`: a run record as a person reads it, top-down:
//! status, manifest, code version, seeds, each step with its outcome and
//! time, and the AUC table and tracking tables as the same grids `scanloc
//! run` prints.

use std::fmt::Write as _;

use super::recorded::RecordedManifest;
use crate::limits::display_cell;
use crate::registry::dates::seconds_between;
use crate::registry::{Registry, RunRecord};
use crate::run::{TrackingRow, recorded_tracking, table};

/// `record` as text, for people (programs read the record as JSON); its
/// tracking tables are rebuilt from the evaluations in `registry`.
pub(crate) fn run_summary(registry: &Registry, record: &RunRecord) -> String {
    let tracking =
        recorded_tracking(registry, record).map(|found| found.into_iter().map(|t| t.row).collect());
    let mut out = String::new();
    write_summary(&mut out, record, tracking).expect("writing to a String cannot fail");
    out
}

/// `record` as JSON, for programs: the record with a `tracking` key, the
/// rows of its tracking tables as `scanloc run --json` gives them.
pub(crate) fn run_summary_json(
    registry: &Registry,
    record: &RunRecord,
) -> anyhow::Result<serde_json::Value> {
    let tracking: Vec<TrackingRow> = recorded_tracking(registry, record)?
        .into_iter()
        .map(|t| t.row)
        .collect();
    let mut value = serde_json::to_value(record)?;
    value["tracking"] = serde_json::to_value(tracking)?;
    Ok(value)
}

/// One labelled field of the summary.
fn field(out: &mut String, label: &str, value: &str) -> std::fmt::Result {
    writeln!(out, "  {label:<10} {value}")
}

/// The run's own fields, its manifest and the code that ran it.
fn write_run_fields(out: &mut String, record: &RunRecord) -> std::fmt::Result {
    writeln!(out, "run {}: {}", record.id, record.status)?;
    field(out, "kind", record.kind.as_str())?;
    if let Some(parent) = &record.parent_run {
        field(out, "of run", parent)?;
    }
    if let Some(cv) = &record.cross_validation {
        let folds = match cv.fold {
            Some(fold) => format!("fold {fold} of {}", cv.folds),
            None => format!("{} folds", cv.folds),
        };
        field(out, "cv", &format!("{}, {folds}", cv.detector))?;
    }
    field(out, "started", &record.started_at)?;
    match &record.ended_at {
        Some(ended) => {
            let took = seconds_between(&record.started_at, ended)
                .map_or(String::new(), |s| format!(" ({s:.2} s)"));
            field(out, "ended", &format!("{ended}{took}"))?;
        }
        None => field(out, "ended", "-")?,
    }
    if record.forced {
        field(
            out,
            "forced",
            "yes (--force: every step recomputed and compared)",
        )?;
    }
    if let Some(error) = &record.error {
        field(out, "error", error)?;
    }

    writeln!(out, "manifest")?;
    field(out, "name", &record.manifest_name)?;
    field(out, "sha256", &record.manifest_sha256)?;
    field(out, "path", &record.manifest_path)?;

    writeln!(out, "code")?;
    let code = &record.code;
    field(
        out,
        "scanloc",
        &format!(
            "{}, commit {} (dirty: {})",
            code.crate_version, code.git_commit, code.git_dirty
        ),
    )?;
    field(out, "rustc", &code.rustc)?;
    field(
        out,
        "machine",
        &format!(
            "{}, pid {}, {} threads",
            record.host, record.pid, record.threads
        ),
    )?;
    Ok(())
}

fn write_summary(
    out: &mut String,
    record: &RunRecord,
    tracking: anyhow::Result<Vec<TrackingRow>>,
) -> std::fmt::Result {
    write_run_fields(out, record)?;
    writeln!(out, "seeds")?;
    // Step names are cut to a bounded width: a recorded name of any length
    // can make no format width overflow.
    let width = record
        .seeds
        .keys()
        .map(|s| display_cell(s).len())
        .max()
        .unwrap_or(0);
    for (step, seed) in &record.seeds {
        let step = display_cell(step);
        writeln!(out, "  {step:<width$}  {seed}")?;
    }

    let counts = &record.counts;
    writeln!(
        out,
        "steps: {} cached, {} computed, {} rebuilt",
        counts.cached, counts.computed, counts.rebuilt
    )?;
    let width = record
        .steps
        .iter()
        .map(|s| display_cell(&s.step.to_string()).chars().count())
        .max()
        .unwrap_or(0);
    for step in &record.steps {
        let detail = step
            .detail
            .as_ref()
            .map_or(String::new(), |d| format!("  ({d})"));
        writeln!(
            out,
            "  {:<9} {:<width$}  {:>8.2} s{detail}",
            step.outcome,
            display_cell(&step.step.to_string()),
            step.seconds
        )?;
    }

    // The grid opens with its own `AUC` heading.
    let reference = match RecordedManifest::of(record) {
        Ok(manifest) => manifest.reference,
        Err(e) => {
            writeln!(out, "(reference rows not shown: {e:#})")?;
            None
        }
    };
    let tracking = tracking.unwrap_or_else(|e| {
        out.push_str(&format!("(tracking tables not shown: {e:#})\n"));
        Vec::new()
    });
    // A run that scores only tracks has no AUC to show.
    if !record.auc.is_empty() || tracking.is_empty() {
        out.push_str(&table::render(&record.auc, reference.as_ref()));
    }
    out.push_str(&table::render_tracking(&tracking));
    Ok(())
}
