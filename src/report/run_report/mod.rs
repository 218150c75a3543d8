//! `scanloc report RUN`: a Markdown report of a recorded run, with its AUC
//! table beside the reference (the paper's Table 1), each reference cell
//! judged against the test set's luck (a bootstrap over frames), where the AUC is lost
//! (the ranking headroom of the top predictions), each detector's gap to
//! the attainable bound with its bootstrap uncertainty, the scene figures at the
//! score threshold, the calibration of probability scores, precision–recall
//! curves, reliability diagrams, example frames, localisation panels and
//! error histograms; and, for runs with tracking pipelines, their tables,
//! tracks over a frame and D estimated against the true D (`tracking`).
//!
//! The tables are [`tables`]'s, the figures [`figures`]'s; this module
//! reads the run's evaluations and writes `report.md` from them.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::recorded::RecordedManifest;
use crate::metrics::Score;
use crate::registry::{Registry, RunRecord};
use crate::run::{load_artefact, recorded_tracking};
use crate::types::{Dataset, DetectorKind, Prediction};

mod figures;
mod tables;
mod tracking;

use figures::{
    error_histograms, example_frames, localisation_panels, precision_recall_curves,
    reliability_diagrams,
};
use tables::{
    write_auc_table, write_bound_comparison_table, write_calibration_table,
    write_cross_validation_table, write_headroom_table, write_quality_table,
    write_reference_bound_table, write_reference_note, write_reference_spread_table,
    write_scene_table, write_uncertainty_table,
};

/// One scored (detector, dataset) pair of the run.
struct Evaluation {
    detector: String,
    /// The kind of its manifest detector (unknown if the manifest no
    /// longer names it).
    detector_kind: Option<DetectorKind>,
    /// Whether its guesses are ranked lists (the AUC table then gives its
    /// best guess alone a row of its own, as `scanloc run` prints it).
    ranks_candidates: bool,
    dataset: String,
    diffusion: Option<f64>,
    dataset_key: String,
    predictions_key: String,
    score: Score,
}

/// Writes `report.md` and its figures (PNG and SVG) for run `run_id` into
/// the folder `destination`; returns the path of the Markdown file. The
/// folder is written whole or not at all (see
/// [`PendingFolder`](crate::io::PendingFolder)): `destination` must be a
/// new path or a folder holding only such files ([`is_report_file`]), and
/// is replaced whole. Figures named after a dataset get a file name made
/// by [`safe_file_name`](crate::io::safe_file_name): recorded names are
/// data, never paths.
pub(crate) fn write_report(
    registry: &Registry,
    run_id: &str,
    destination: &Path,
) -> anyhow::Result<PathBuf> {
    let folder = crate::io::PendingFolder::create(destination, is_report_file)?;
    let record = registry.run_record(run_id)?;
    let resolved = RecordedManifest::of(&record)?;
    let out = folder.path();
    let reference = resolved.reference.as_ref();
    let tracking = recorded_tracking(registry, &record)?;
    let tracking_keys: Vec<&str> = tracking
        .iter()
        .map(|t| t.row.evaluation_key.as_str())
        .collect();
    let evaluations = load_evaluations(registry, &record, &resolved, &tracking_keys)?;
    let mut markdown = String::new();
    writeln!(
        markdown,
        "# scanloc report: {}, run {run_id}\n",
        resolved.name
    )?;
    writeln!(
        markdown,
        "Status **{}**, started {}, ended {}; scanloc {} (commit {}, dirty {}), {} on {} with {} threads.\n",
        record.status,
        record.started_at,
        record.ended_at.as_deref().unwrap_or("—"),
        record.code.crate_version,
        record.code.git_commit,
        record.code.git_dirty,
        record.code.rustc,
        record.host,
        record.threads,
    )?;
    writeln!(
        markdown,
        "Steps: {} cached, {} computed. Re-run bit for bit with `scanloc reproduce {run_id}`.\n",
        record.counts.cached, record.counts.computed
    )?;

    // A run that scores only tracks has no AUC and no localisation table.
    let per_frame = !evaluations.is_empty() || tracking.is_empty();
    if per_frame {
        write_auc_table(&mut markdown, &evaluations, reference)?;
        if let Some(reference) = reference {
            write_reference_note(
                &mut markdown,
                &evaluations,
                reference,
                &resolved.microscope.brightness,
            )?;
        }
    }
    write_cross_validation_table(&mut markdown, &record, &resolved)?;
    if per_frame {
        write_quality_table(&mut markdown, &evaluations)?;
    }
    write_headroom_table(&mut markdown, &evaluations)?;
    let mut artefacts = Artefacts::new(registry);
    if let Some(reference) = reference {
        write_reference_spread_table(&mut artefacts, &mut markdown, &evaluations, reference)?;
    }
    write_bound_comparison_table(&mut artefacts, &mut markdown, &evaluations)?;
    if let Some(reference) = reference {
        write_reference_bound_table(&mut artefacts, &mut markdown, &evaluations, reference)?;
    }
    write_scene_table(&mut markdown, &evaluations)?;
    write_calibration_table(&mut markdown, &evaluations)?;
    write_uncertainty_table(&mut markdown, &evaluations)?;

    writeln!(markdown, "\n## Figures\n")?;
    example_frames(out, &resolved.microscope, resolved.seed)?;
    writeln!(
        markdown,
        "**Example frames** at D = 0, 0.75, 1 and 1.75 µm²/s (the paper's Fig. 1): the QD's path in green, its start (green circle), end (cyan circle) and trajectory centroid (green cross).\n\n![example frames](example_frames.png)\n"
    )?;
    let localisation = localisation_panels(registry, out, &resolved, &evaluations)?;
    if localisation {
        writeln!(
            markdown,
            "**Localisations** (the paper's localisation figure): trajectory and centroid in green, each detector's top prediction (CNN blue, Crocker–Grier purple).\n\n![localisations](localisations.png)\n"
        )?;
    }
    for file in precision_recall_curves(out, &evaluations)? {
        writeln!(markdown, "![precision–recall]({file}.png)\n")?;
    }
    for file in reliability_diagrams(out, &evaluations)? {
        writeln!(markdown, "![reliability]({file}.png)\n")?;
    }
    for file in error_histograms(registry, out, &evaluations)? {
        writeln!(markdown, "![errors]({file}.png)\n")?;
    }
    tracking::write_tracking_section(registry, out, &mut markdown, &tracking)?;
    crate::io::write_bytes_atomically(&folder.file(REPORT_FILE), markdown.as_bytes())?;
    folder.commit()?;
    Ok(destination.join(REPORT_FILE))
}

/// The Markdown file of a report folder.
pub(crate) const REPORT_FILE: &str = "report.md";

/// Whether `name` is a file a report folder holds: `report.md` and the
/// figures (`.png`, `.svg`).
pub(crate) fn is_report_file(name: &str) -> bool {
    name == REPORT_FILE || name.ends_with(".png") || name.ends_with(".svg")
}

fn load_evaluations(
    registry: &Registry,
    record: &RunRecord,
    resolved: &RecordedManifest,
    tracking_keys: &[&str],
) -> anyhow::Result<Vec<Evaluation>> {
    let mut keys: Vec<&str> = Vec::new();
    for row in &record.auc {
        if !keys.contains(&row.evaluation_key.as_str()) {
            keys.push(&row.evaluation_key);
        }
    }
    // Evaluations of sets without ground truth have no AUC row; those of
    // tracking pipelines are the Tracking section's.
    for step in &record.steps {
        if step.kind == crate::registry::ArtefactKind::Evaluation
            && !keys.contains(&step.artefact_key.as_str())
            && !tracking_keys.contains(&step.artefact_key.as_str())
        {
            keys.push(&step.artefact_key);
        }
    }
    let mut evaluations = Vec::new();
    for key in keys {
        let Some(row) = registry.evaluation(key)? else {
            continue;
        };
        let score = load_artefact(registry, key)?.evaluation()?.as_ref().clone();
        // Fold models of a cross-validation are not manifest detectors:
        // their kind is their detector's.
        let detector = resolved.detector(&row.detector).or_else(|| {
            let cv = record.cross_validation.as_ref()?;
            resolved.detector(&cv.detector)
        });
        let detector_kind = detector.map(|d| d.spec.kind());
        evaluations.push(Evaluation {
            detector_kind,
            ranks_candidates: detector.is_some_and(|d| d.spec.ranks_candidates()),
            detector: row.detector,
            dataset: row.dataset,
            diffusion: row.diffusion,
            dataset_key: row.dataset_key,
            predictions_key: row.predictions_key,
            score,
        });
    }
    Ok(evaluations)
}

/// The run's datasets and predictions, each read from the registry once
/// however many tables use it (a test set serves every detector scored on
/// it, a detector's predictions every bound they are compared with).
struct Artefacts<'r, 'k> {
    registry: &'r Registry,
    datasets: HashMap<&'k str, Arc<Dataset>>,
    predictions: HashMap<&'k str, Arc<Vec<Prediction>>>,
}

impl<'r, 'k> Artefacts<'r, 'k> {
    fn new(registry: &'r Registry) -> Self {
        Self {
            registry,
            datasets: HashMap::new(),
            predictions: HashMap::new(),
        }
    }

    fn dataset(&mut self, key: &'k str) -> anyhow::Result<Arc<Dataset>> {
        let registry = self.registry;
        cached(&mut self.datasets, key, || {
            Ok(load_artefact(registry, key)?.dataset()?.clone())
        })
    }

    fn predictions(&mut self, key: &'k str) -> anyhow::Result<Arc<Vec<Prediction>>> {
        let registry = self.registry;
        cached(&mut self.predictions, key, || {
            Ok(load_artefact(registry, key)?.predictions()?.clone())
        })
    }
}

/// The value of `key` in `cache`, loaded by `load` the first time.
fn cached<'k, T>(
    cache: &mut HashMap<&'k str, Arc<T>>,
    key: &'k str,
    load: impl FnOnce() -> anyhow::Result<Arc<T>>,
) -> anyhow::Result<Arc<T>> {
    if let Some(value) = cache.get(key) {
        return Ok(value.clone());
    }
    let value = load()?;
    cache.insert(key, value.clone());
    Ok(value)
}
