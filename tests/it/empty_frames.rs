//! A manifest that evaluates test sets of empty frames (0 QDs per frame):
//! `check` accepts it, `run` stores and prints the false localisations per
//! empty frame instead of an AUC, and the report shows them.

use std::collections::BTreeSet;

use scanloc::registry::Registry;
use scanloc::run::load_artefact;

use crate::common::{report_markdown, run_json, run_text, scanloc, stderr, write_manifest};

/// Smoke-sized: a CNN trained briefly on frames of 0–2 QDs, and test sets
/// of one QD, of empty frames, and of 0 or 1 QD per frame.
const MANIFEST: &str = "\
name: empty-frames
seed: 20261129
microscope:
  brightness: 7
  margin_px: 4
datasets:
  train:
    frames: 96
    emitters: {choice: [0, 1, 2]}
  test:
    frames: 24
    diffusion_um2_s: 0.75
  empty:
    frames: 40
    emitters: 0
    diffusion_um2_s: 1.0
  mixed:
    frames: 40
    emitters: {choice: [0, 1]}
    diffusion_um2_s: 1.75
metrics:
  eps_px: [1, 2]
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
  cnn:
    cnn:
      training_set: train
      architecture: {channels: 8, dilations: [1, 2, 1]}
      training: {epochs: 1, batch_size: 16}
evaluations:
  - detector: trackpy
    datasets: [test, empty, mixed]
  - detector: cnn
    datasets: [test, empty]
";

#[test]
fn sets_of_empty_frames_are_scored_by_their_false_localisations() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "empty.yaml", MANIFEST);
    let registry_dir = dir.path().join("registry");
    let check = scanloc(&["check", manifest.to_str().unwrap()]);
    assert!(check.status.success(), "{}", stderr(&check));

    let run = run_json(&manifest, &registry_dir, &[]);
    // No AUC for the set without ground truth; the others have theirs.
    let auc_sets: BTreeSet<(String, String)> = run["auc"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["detector"].to_string(), r["dataset"].to_string()))
        .collect();
    let pair = |d: &str, s: &str| (format!("\"{d}\""), format!("\"{s}\""));
    assert_eq!(
        auc_sets,
        BTreeSet::from([
            pair("trackpy", "test"),
            pair("trackpy", "mixed"),
            pair("cnn", "test")
        ]),
        "{run}"
    );
    let rows = run["empty_frames"].as_array().unwrap();
    let empty_sets: BTreeSet<(String, String)> = rows
        .iter()
        .map(|r| (r["detector"].to_string(), r["dataset"].to_string()))
        .collect();
    // The one-QD set has no empty frame, so no row.
    assert_eq!(
        empty_sets,
        BTreeSet::from([
            pair("trackpy", "empty"),
            pair("trackpy", "mixed"),
            pair("cnn", "empty")
        ]),
        "{run}"
    );

    // Each row is the stored evaluation's, and recounts from the stored
    // predictions and truth.
    let registry = Registry::open(&registry_dir).unwrap();
    let mut trackpy_on_empty = None;
    for row in rows {
        let detector = row["detector"].as_str().unwrap();
        let dataset = row["dataset"].as_str().unwrap();
        let step = run["steps"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["step"] == format!("evaluation/{detector}@{dataset}"))
            .unwrap_or_else(|| panic!("no evaluation step for {detector}@{dataset}: {run}"));
        let key = step["artefact_key"].as_str().unwrap();
        let stored = registry.evaluation(key).unwrap().unwrap();
        let score = load_artefact(&registry, key).unwrap();
        let score = score.evaluation().unwrap();
        let figures = score.empty_frames.unwrap();
        let predictions = load_artefact(&registry, &stored.predictions_key).unwrap();
        let predictions = predictions.predictions().unwrap();
        let set = load_artefact(&registry, &stored.dataset_key).unwrap();
        let set = set.dataset().unwrap();
        let with_truth: BTreeSet<usize> = set.truth.iter().map(|t| t.frame).collect();
        let threshold = match detector {
            "cnn" => 0.5,
            _ => f64::NEG_INFINITY,
        };
        let counted = predictions
            .iter()
            .filter(|p| !with_truth.contains(&p.frame) && p.score >= threshold)
            .count();
        assert_eq!(
            figures.frames,
            40 - with_truth.len(),
            "{detector}@{dataset}"
        );
        assert_eq!(figures.localisations, counted, "{detector}@{dataset}");
        assert_eq!(row["frames"], figures.frames);
        assert_eq!(row["localisations"], figures.localisations);
        let per_frame = figures.false_localisations_per_frame.unwrap();
        assert_eq!(per_frame, counted as f64 / figures.frames as f64);
        assert_eq!(row["false_localisations_per_frame"], per_frame);
        match detector {
            "cnn" => assert_eq!(row["threshold"], 0.5),
            _ => assert!(row["threshold"].is_null(), "{row}"),
        }
        if dataset == "empty" {
            assert!(score.per_eps.is_empty(), "{detector}: an AUC without truth");
            assert_eq!((score.ground_truths, score.frames), (0, 40));
        } else {
            // 40 frames of 0 or 1 QD: some of each.
            assert!(figures.frames > 0 && figures.frames < 40, "{figures:?}");
            assert_eq!(score.per_eps.len(), 2);
        }
        if (detector, dataset) == ("trackpy", "empty") {
            // minmass 0 finds noise in every frame: the figure is not 0 by
            // default.
            assert!(counted > 0);
            trackpy_on_empty = Some(per_frame);
        }
    }
    let trackpy_on_empty = trackpy_on_empty.unwrap();

    // The printed table (now all cached): the AUC grid without the empty
    // set, then the false localisations.
    let (text, _) = run_text(&manifest, &registry_dir);
    let lines: Vec<&str> = text.lines().collect();
    // Columns are labelled by D: test 0.75, empty 1, mixed 1.75.
    assert!(
        lines[0].starts_with("AUC")
            && lines[0].contains("D = 0.75 µm²/s")
            && lines[0].contains("D = 1.75 µm²/s"),
        "{text}"
    );
    assert!(!lines[0].contains("D = 1.00"), "{text}");
    let section = lines
        .iter()
        .position(|l| l.starts_with("false localisations per empty frame"))
        .unwrap_or_else(|| panic!("no empty-frame table: {text}"));
    let cells: Vec<Vec<&str>> = lines[section + 2..]
        .iter()
        .map(|l| l.split_whitespace().collect())
        .collect();
    let trackpy_row = format!("{trackpy_on_empty:.3}");
    assert!(
        cells.contains(&vec![
            "trackpy",
            "empty",
            "none",
            "40",
            &counted_of(rows, "trackpy"),
            &trackpy_row
        ]),
        "{text}"
    );
    assert!(
        cells
            .iter()
            .any(|c| c[..4] == ["cnn", "empty", "0.5", "40"]),
        "{text}"
    );

    // The report: no AUC column for the empty set, its false localisations
    // in the table at the score threshold.
    let report_dir = dir.path().join("report");
    let markdown = report_markdown(&registry_dir, run["run"].as_str().unwrap(), &report_dir);
    // Error histograms of the sets with QDs only.
    assert!(report_dir.join("errors_test.png").exists());
    assert!(!report_dir.join("errors_empty.png").exists(), "{markdown}");
    assert!(!markdown.contains("errors_empty"), "{markdown}");
    let auc_header = markdown
        .lines()
        .find(|l| l.starts_with("| detector | D = 0.75<br>ε = 1 |"))
        .unwrap_or_else(|| panic!("no AUC table: {markdown}"));
    assert!(auc_header.contains("D = 1.75<br>ε = 2"), "{markdown}");
    assert!(!auc_header.contains("D = 1.00<br>"), "{markdown}");
    assert!(
        markdown.contains(&format!(
            "| trackpy | empty | none | — | — | — | — | — | 40 | {trackpy_row} |"
        )),
        "{markdown}"
    );
    assert!(
        markdown
            .lines()
            .any(|l| l.starts_with("| cnn | empty | 0.5 | — |") && l.contains("| 40 |")),
        "{markdown}"
    );
}

/// The localisations of `detector` on the set `empty`, as `run --json`
/// printed them.
fn counted_of(rows: &[serde_json::Value], detector: &str) -> String {
    rows.iter()
        .find(|r| r["detector"] == detector && r["dataset"] == "empty")
        .map(|r| r["localisations"].to_string())
        .unwrap()
}
