//! `scanloc calibrate` (docs/metric.md) and `scanloc cv` on small manifests.

use crate::common::{report_markdown, scanloc, smoke, stderr, stdout, write_manifest};

const REFERENCE: &str = "
reference:
  source: the paper's Table 1
  rows:
    - detector: trackpy
      label: TrackPy
      auc:
        test-0.75: [0.06, 0.42, 0.73]
        test-1.00: [0.04, 0.30, 0.61]
        test-1.75: [0.02, 0.19, 0.47]
";

#[test]
fn calibration_records_a_run_per_point_and_picks_the_smallest_sse() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(smoke()).unwrap() + REFERENCE;
    let manifest = write_manifest(dir.path(), "cal.yaml", &text);
    let registry = dir.path().join("registry");
    let out = scanloc(&[
        "calibrate",
        manifest.to_str().unwrap(),
        "--brightness",
        "3,7,20",
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let result: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let points = result["points"].as_array().unwrap();
    assert_eq!(points.len(), 3);
    let mut best = (f64::INFINITY, f64::NAN);
    for point in points {
        // The SSE is the sum over the nine reference cells it lists.
        let table = point["table"].as_array().unwrap();
        assert_eq!(table.len(), 9);
        let sse: f64 = table
            .iter()
            .map(|cell| (cell[2].as_f64().unwrap() - cell[3].as_f64().unwrap()).powi(2))
            .sum();
        assert!((sse - point["sse"].as_f64().unwrap()).abs() < 1e-12);
        if sse < best.0 {
            best = (sse, point["brightness"].as_f64().unwrap());
        }
    }
    assert_eq!(result["best_brightness"].as_f64().unwrap(), best.1);
    // N_qd 3 is far too dim and 20 far too bright for the paper's row.
    assert_eq!(best.1, 7.0, "{result}");
    let runs = scanloc(&[
        "registry",
        "runs",
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    let runs: serde_json::Value = serde_json::from_str(&stdout(&runs)).unwrap();
    let calibration_runs = runs
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["kind"] == "calibrate" && r["status"] == "done")
        .count();
    assert_eq!(calibration_runs, 3);

    let out = scanloc(&[
        "calibrate",
        manifest.to_str().unwrap(),
        "--detector",
        "nobody",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("nobody"));
    let out = scanloc(&[
        "calibrate",
        smoke().to_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("reference"));
}

#[test]
fn cross_validation_reports_mean_and_spread_and_resumes_from_cache() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let args = |extra: &[&'static str]| {
        let mut args = vec![
            "cv",
            "experiments/smoke.yaml",
            "--detector",
            "cnn",
            "--folds",
            "3",
            "--json",
        ];
        args.extend_from_slice(extra);
        args
    };
    let mut first = args(&[]);
    first.extend(["--registry", registry.to_str().unwrap()]);
    let out = scanloc(&first);
    assert!(out.status.success(), "{}", stderr(&out));
    let result: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let cells = result["cells"].as_array().unwrap();
    // Held-out fold and three test sets, three ε each.
    assert_eq!(cells.len(), 12);
    for cell in cells {
        let per_fold: Vec<f64> = cell["per_fold"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(per_fold.len(), 3);
        let mean = per_fold.iter().sum::<f64>() / 3.0;
        let std = (per_fold.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / 2.0).sqrt();
        assert!((cell["mean"].as_f64().unwrap() - mean).abs() < 1e-12);
        assert!((cell["std"].as_f64().unwrap() - std).abs() < 1e-12);
    }
    // Three different models: the folds do not all agree.
    assert!(cells.iter().any(|c| c["std"].as_f64().unwrap() > 0.0));
    assert!(result["computed_steps"].as_u64().unwrap() > 0);
    // The report of the cv run has the mean ± sd table.
    let report = report_markdown(
        &registry,
        result["run"].as_str().unwrap(),
        &dir.path().join("report"),
    );
    assert!(
        report.contains("3-fold cross-validation of cnn"),
        "{report}"
    );
    let first_test_cell = cells
        .iter()
        .find(|c| c["dataset"] == "test-0.75" && c["eps_px"] == 1.0)
        .unwrap();
    let expected_cell = format!(
        "| test-0.75 (D = 0.75) | 1 | {:.3} ± {:.3} |",
        first_test_cell["mean"].as_f64().unwrap(),
        first_test_cell["std"].as_f64().unwrap()
    );
    assert!(report.contains(&expected_cell), "{expected_cell}\n{report}");
    // Each fold's model is selected on its own held-out fold.
    let out = scanloc(&[
        "registry",
        "sql",
        "SELECT m.name, m.spec, d.key FROM artefacts m JOIN artefacts d \
         ON d.name = replace(replace(m.name, 'cnn-', 'train-'), 'of3', 'of3-held-out') \
         WHERE m.kind = 'model' ORDER BY m.name",
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let models: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let models = models.as_array().unwrap();
    assert_eq!(models.len(), 3, "{models:?}");
    for model in models {
        let spec: serde_json::Value =
            serde_json::from_str(model["spec"].as_str().unwrap()).unwrap();
        assert_eq!(spec["validation"], model["key"], "{}", model["name"]);
    }
    let out = scanloc(&first);
    let again: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(
        again["computed_steps"].as_u64().unwrap(),
        0,
        "a finished sweep is fully cached"
    );
    assert_eq!(again["cells"], result["cells"]);

    // One fold alone, recomputed: the same artefacts as in the sweep, so
    // --force finds them identical and its scores are that fold's column.
    let mut second_fold = args(&["--fold", "2", "--force"]);
    second_fold.extend(["--registry", registry.to_str().unwrap()]);
    let out = scanloc(&second_fold);
    assert!(out.status.success(), "{}", stderr(&out));
    let alone: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert!(alone["computed_steps"].as_u64().unwrap() > 0);
    let alone_cells = alone["cells"].as_array().unwrap();
    assert_eq!(alone_cells.len(), cells.len());
    for (alone_cell, cell) in alone_cells.iter().zip(cells) {
        assert_eq!(
            alone_cell["per_fold"],
            serde_json::json!([cell["per_fold"][1]])
        );
        assert!(alone_cell["std"].is_null(), "no spread from one fold");
    }
    let mut no_such_fold = args(&["--fold", "4"]);
    no_such_fold.extend(["--registry", registry.to_str().unwrap()]);
    let out = scanloc(&no_such_fold);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("fold"), "{}", stderr(&out));

    // The whole sweep re-executes from scratch, bit for bit.
    let out = scanloc(&[
        "reproduce",
        result["run"].as_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    assert!(stdout(&out).contains("IDENTICAL"), "{}", stdout(&out));
    assert!(
        stdout(&out).contains("model/cnn-cv3of3"),
        "the fold models are among the compared steps: {}",
        stdout(&out)
    );
    // A one-fold run re-executes that fold alone.
    let out = scanloc(&[
        "reproduce",
        alone["run"].as_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    assert!(
        stdout(&out).contains("model/cnn-cv2of3"),
        "{}",
        stdout(&out)
    );
    assert!(
        !stdout(&out).contains("model/cnn-cv1of3"),
        "{}",
        stdout(&out)
    );

    let out = scanloc(&[
        "cv",
        "experiments/smoke.yaml",
        "--detector",
        "cnn",
        "--folds",
        "1",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let out = scanloc(&[
        "cv",
        "experiments/smoke.yaml",
        "--detector",
        "trackpy",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("not a trained detector"));
}
