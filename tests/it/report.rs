//! `scanloc report` on a recorded run: the table, the figures, bad ids.

use std::path::Path;

use crate::common::scanloc;

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
    let calibration = markdown
        .split("## Calibration of the score")
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .expect("a calibration section");
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
    let uncertainty = markdown
        .split("## Calibration of the uncertainty")
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .expect("an uncertainty section");
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
