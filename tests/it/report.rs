//! `scanloc report` on a recorded run: the table, the figures, bad ids.

use std::path::Path;

use crate::common::{report_markdown, report_section, run_json, scanloc, write_manifest};

#[test]
fn report_of_a_smoke_run_has_the_table_and_every_figure() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let registry = registry.to_str().unwrap();
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/smoke.yaml");
    let out = scanloc(&[
        "run",
        manifest.to_str().unwrap(),
        "--registry",
        registry,
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let run_id = run["run"].as_str().unwrap();
    let report_dir = dir.path().join("report");
    let out = scanloc(&[
        "report",
        &run_id[..12],
        "--registry",
        registry,
        "--out",
        report_dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let markdown = std::fs::read_to_string(report_dir.join("report.md")).unwrap();
    assert!(markdown.contains(run_id));
    assert!(markdown.contains("| detector |"));
    assert_eq!(
        markdown
            .lines()
            // The AUC row starts with a number; quality rows with a dataset.
            .filter(|l| l.starts_with("| trackpy | 0."))
            .count(),
        1
    );
    // Where the AUC is lost, per (detector, dataset, ε); the scene figures
    // at each detector's threshold (the CNN's 0.5, none for trackpy); the
    // CNN's calibration (its score is a sigmoid), not trackpy's (a mass).
    assert!(markdown.contains("## Where the AUC is lost"), "{markdown}");
    // No likelihood detector in the run: no comparison with a bound.
    assert!(
        !markdown.contains("## Against the attainable bound"),
        "{markdown}"
    );
    assert_eq!(
        markdown
            .lines()
            .filter(|l| l.starts_with("| cnn | test-1.00 | 2 | 0."))
            .count(),
        1,
        "{markdown}"
    );
    assert!(markdown.contains("## At the score threshold"), "{markdown}");
    assert!(
        markdown.contains("| cnn | test-0.75 | 0.5 | 1 |")
            && markdown.contains("| trackpy | test-0.75 | none | 1 |"),
        "{markdown}"
    );
    let calibration = report_section(&markdown, "Calibration of the score");
    assert_eq!(
        calibration
            .lines()
            .filter(|l| l.starts_with("| cnn | test-"))
            .count(),
        3,
        "{calibration}"
    );
    assert!(!calibration.contains("| trackpy |"), "{calibration}");
    // The CNN's σ against its errors; trackpy reports no σ.
    let uncertainty = report_section(&markdown, "Calibration of the uncertainty");
    let rows: Vec<&str> = uncertainty
        .lines()
        .filter(|l| l.starts_with("| cnn | test-"))
        .collect();
    assert_eq!(rows.len(), 3, "{uncertainty}");
    for row in rows {
        // localisations, RMS error/σ x and y, within 1 σ: numbers.
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        for cell in &cells[3..7] {
            assert!(cell.parse::<f64>().is_ok_and(f64::is_finite), "{row}");
        }
    }
    assert!(!uncertainty.contains("| trackpy |"), "{uncertainty}");
    for figure in [
        "example_frames",
        "localisations",
        "reliability_test-0.75",
        "reliability_test-1.75",
    ] {
        for extension in ["png", "svg"] {
            let path = report_dir.join(format!("{figure}.{extension}"));
            assert!(path.is_file(), "{} missing", path.display());
            assert!(std::fs::metadata(&path).unwrap().len() > 1000);
        }
    }
    let pr_curves = std::fs::read_dir(&report_dir)
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with("pr_")
        })
        .count();
    // PNG and SVG per (dataset, ε) of the run.
    let mut cells: Vec<String> = run["auc"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| format!("{}/{}", r["dataset"], r["eps_px"]))
        .collect();
    cells.sort();
    cells.dedup();
    // Three test sets at three radii in the smoke manifest.
    assert_eq!(cells.len(), 9, "{cells:?}");
    assert_eq!(pr_curves, 2 * cells.len());

    // `latest` names the run just made.
    let latest_dir = dir.path().join("latest");
    let out = scanloc(&[
        "report",
        "latest",
        "--registry",
        registry,
        "--out",
        latest_dir.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        std::fs::read_to_string(latest_dir.join("report.md"))
            .unwrap()
            .contains(run_id)
    );

    let out = scanloc(&[
        "report",
        "no-such-run",
        "--registry",
        registry,
        "--out",
        report_dir.to_str().unwrap(),
    ]);
    assert_eq!(
        out.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The reference table: each AUC with its bootstrap standard error, the
/// difference from the reference, √2 times that error, and a verdict that
/// follows the rule (ahead or behind only beyond twice the difference's
/// standard error plus the reference's rounding).
#[test]
fn report_judges_each_reference_cell_against_the_test_sets_luck() {
    const MANIFEST: &str = "\
name: luck
seed: 11
microscope: {brightness: 7, margin_px: 4}
datasets:
  test-0.75: {frames: 120, diffusion_um2_s: 0.75}
metrics: {eps_px: [1, 2, 3]}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - detector: trackpy
    datasets: [test-0.75]
reference:
  source: made up for the test
  rows:
    - detector: trackpy
      label: TrackPy
      auc:
        test-0.75: [0.99, 0.01, 0.5]
";
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "luck.yaml", MANIFEST);
    let registry = dir.path().join("registry");
    let run = run_json(&manifest, &registry, &[]);
    let markdown = report_markdown(
        &registry,
        run["run"].as_str().unwrap(),
        &dir.path().join("report"),
    );
    let section = report_section(&markdown, "Against the reference, with the test set's luck");
    let rows: Vec<Vec<&str>> = section
        .lines()
        .filter(|l| l.starts_with("| trackpy | test-0.75 |"))
        .map(|l| l.split('|').map(str::trim).collect())
        .collect();
    assert_eq!(rows.len(), 3, "{section}");
    let mut verdicts = Vec::new();
    // Each reference with half a unit of its last decimal.
    for (row, (reference, rounding)) in rows.iter().zip([(0.99, 0.005), (0.01, 0.005), (0.5, 0.05)])
    {
        // | detector | dataset | ε | AUC | SE | interval | reference | difference | its SE | verdict |
        let se = number(row[5]);
        // 120 frames: a hit rate's standard error is at most √(0.25/120) ≈ 0.046;
        // an AUC's is of that order, and not zero on frames this noisy.
        assert!(se > 0.001 && se < 0.1, "{row:?}");
        verdicts.push(checked_verdict(row, reference, rounding));
    }
    // Crocker–Grier is far from perfect at 1 px and far from nothing at 2 px.
    assert_eq!(&verdicts[..2], &["behind", "ahead"], "{section}");
}

/// A report table's cell read as a number (a test failure naming the cell
/// if it is not one).
fn number(cell: &str) -> f64 {
    cell.parse::<f64>()
        .unwrap_or_else(|_| panic!("not a number: {cell}"))
}

/// Checks the judged columns of a report row laid out as both reference
/// tables lay theirs out — `| name | dataset | ε | AUC | SE | … |
/// reference | difference | its SE | verdict |` — against `reference`
/// (known to ± `rounding`): the difference is AUC − reference, its standard
/// error √2 × SE, and the verdict the rule's (ahead or behind only beyond
/// twice that plus the rounding). Returns the verdict.
fn checked_verdict<'r>(row: &[&'r str], reference: f64, rounding: f64) -> &'r str {
    let (auc, se) = (number(row[4]), number(row[5]));
    assert_eq!(number(row[7]), reference, "{row:?}");
    let difference = number(row[8]);
    assert!((difference - (auc - reference)).abs() < 0.0011, "{row:?}");
    let combined = number(row[9]);
    assert!((combined - 2f64.sqrt() * se).abs() < 0.0011, "{row:?}");
    let expected = if difference > 2.0 * combined + rounding {
        "ahead"
    } else if difference < -2.0 * combined - rounding {
        "behind"
    } else {
        "level"
    };
    assert_eq!(row[10], expected, "{row:?}");
    row[10]
}

/// The reference against the bound: a likelihood detector scored on a
/// whole test set the reference has figures for gets one row per reference
/// figure, its AUC the run's, the difference and verdict by the rule; a
/// bound scored on the first frames only (another dataset) gets none.
#[test]
fn report_sets_each_reference_figure_beside_the_attainable_bound() {
    const MANIFEST: &str = "\
name: bound-reference
seed: 5
microscope: {height: 16, width: 16, margin_px: 3, brightness: 5}
datasets:
  test: {frames: 40, diffusion_um2_s: 1.75}
metrics: {eps_px: [1, 2, 3]}
detectors:
  cg: {crocker_grier: {diameter: 5, minmass: 0}}
  exact: {likelihood: {particles: 300}}
evaluations:
  - {detector: cg, datasets: [test]}
  - {detector: exact, datasets: [test]}
  - {detector: exact, datasets: [test], frames: 10}
reference:
  source: made up for the test
  rows:
    - detector: cg
      label: Published
      auc:
        test: [0.999, 0.01, 0.5]
";
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "bound-reference.yaml", MANIFEST);
    let registry = dir.path().join("registry");
    let run = run_json(&manifest, &registry, &[]);
    let bound_auc = |eps: f64| {
        run["auc"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["detector"] == "exact" && c["dataset"] == "test" && c["eps_px"] == eps)
            .unwrap_or_else(|| panic!("exact at {eps} in {}", run["auc"]))["auc"]
            .as_f64()
            .unwrap()
    };
    let markdown = report_markdown(
        &registry,
        run["run"].as_str().unwrap(),
        &dir.path().join("report"),
    );
    let section = report_section(&markdown, "The reference against the attainable bound");
    let rows: Vec<Vec<&str>> = section
        .lines()
        .take_while(|l| !l.starts_with("## "))
        .filter(|l| l.starts_with("| exact |"))
        .map(|l| l.split('|').map(str::trim).collect())
        .collect();
    assert_eq!(rows.len(), 3, "{section}");
    let mut verdicts = Vec::new();
    for (row, (eps, reference, rounding)) in
        rows.iter()
            .zip([(1.0, 0.999, 0.0005), (2.0, 0.01, 0.005), (3.0, 0.5, 0.05)])
    {
        // | bound | dataset | ε | AUC | SE | reference | its AUC | difference | its SE | verdict |
        assert_eq!(row[2], "test", "{row:?}");
        assert_eq!(number(row[3]), eps, "{row:?}");
        let (auc, se) = (number(row[4]), number(row[5]));
        assert!((auc - bound_auc(eps)).abs() < 0.0006, "{row:?}");
        assert!((0.0..0.2).contains(&se), "{row:?}");
        assert_eq!(row[6], "Published");
        verdicts.push(checked_verdict(row, reference, rounding));
    }
    // No method localises 40 dim, fast QDs within 1 px at 0.999; at 2 px
    // any localiser worth the name beats 0.01.
    assert_eq!(&verdicts[..2], &["behind", "ahead"], "{section}");
}

/// The tables a reader of the smoke run sees: `scanloc run`'s printed AUC
/// table and the report's AUC and headroom tables, snapshotted (the run
/// is bit-identical on any CPU, so are its figures); no line of the
/// printed table is wider than a terminal's 120 characters.
#[test]
fn the_smoke_runs_printed_and_reported_tables_are_as_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let (text, run) = crate::common::run_text(&crate::common::smoke(), &registry);
    // The last line names the run and its timing: not part of the table.
    let table: Vec<&str> = text.lines().filter(|l| !l.starts_with("run ")).collect();
    assert!(table.iter().all(|l| l.chars().count() <= 120), "{text}");
    insta::assert_snapshot!("smoke_run_table", table.join("\n"));
    let markdown = report_markdown(&registry, &run, &dir.path().join("report"));
    insta::assert_snapshot!(
        "smoke_report_auc",
        report_section(&markdown, "AUC (precision–recall), ours vs the reference")
    );
    insta::assert_snapshot!(
        "smoke_report_headroom",
        report_section(&markdown, "Where the AUC is lost")
    );
}
