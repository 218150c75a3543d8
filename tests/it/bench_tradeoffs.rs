//! `scanloc bench tradeoffs`: every stage writes its table and plots, the
//! Pareto front is marked, the CNN sweep trains models that learn, and bad
//! settings are refused.

use crate::common::{scanloc, stderr, stdout};

/// Rows of a CSV file as maps from header to field.
fn read_csv(path: &std::path::Path) -> Vec<std::collections::HashMap<String, String>> {
    let mut reader = csv::Reader::from_path(path).unwrap();
    let headers = reader.headers().unwrap().clone();
    reader
        .records()
        .map(|record| {
            let record = record.unwrap();
            headers
                .iter()
                .zip(record.iter())
                .map(|(h, v)| (h.to_string(), v.to_string()))
                .collect()
        })
        .collect()
}

fn number(row: &std::collections::HashMap<String, String>, field: &str) -> f64 {
    row[field].parse().unwrap()
}

/// For each row of `table`, whether it is on the Pareto front of `cost`
/// against `error` (lower is better in both), by the library's rule applied
/// to the numbers the table holds: the marks written must be these.
fn pareto_front(
    table: &[std::collections::HashMap<String, String>],
    cost: impl Fn(&std::collections::HashMap<String, String>) -> f64,
) -> Vec<bool> {
    let points: Vec<(f64, f64)> = table
        .iter()
        .map(|row| (cost(row), number(row, "error")))
        .collect();
    scanloc::bench::tradeoff::pareto_flags(&points)
}

#[test]
fn every_stage_writes_a_table_and_plots_with_its_pareto_front() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bench");
    let result = scanloc(&[
        "bench",
        "tradeoffs",
        "--out",
        out.to_str().unwrap(),
        "--frames",
        "150",
        "--static-frames",
        "60",
        // Bright QDs so that a small network learns within a few hundred
        // samples.
        "--brightness",
        "40",
        "--cnn-train-frames",
        "600",
        "--cnn-channels",
        "8,16",
        "--cnn-depths",
        "6",
        "--cnn-epochs",
        "3",
    ]);
    assert!(result.status.success(), "{}", stderr(&result));
    let text = stdout(&result);
    assert!(text.contains("Cramér–Rao floor"), "{text}");
    assert!(text.contains("closest to the floor, cnn"), "{text}");
    for name in ["simulator", "crocker_grier", "cnn", "cnn_training"] {
        for ext in ["png", "svg"] {
            let file = out.join(format!("{name}.{ext}"));
            assert!(
                std::fs::metadata(&file).unwrap().len() > 1000,
                "{}",
                file.display()
            );
        }
    }
    let simulator = read_csv(&out.join("simulator.csv"));
    assert_eq!(simulator.len(), 5 * 6, "substeps × cut-offs");
    let crocker_grier = read_csv(&out.join("crocker_grier.csv"));
    assert_eq!(crocker_grier.len(), 5 * 2, "diameters × preprocessing");
    let cnn = read_csv(&out.join("cnn.csv"));
    assert_eq!(
        cnn.len(),
        2,
        "one channel count × two depths × one epoch count"
    );
    for table in [&simulator, &crocker_grier, &cnn] {
        // The marked rows are exactly the undominated ones (faster is
        // better), not merely some row: any non-empty sweep has a front.
        let marked: Vec<bool> = table.iter().map(|row| row["pareto"] == "true").collect();
        let front = pareto_front(table, |row| -number(row, "frames_per_second"));
        assert_eq!(marked, front, "{table:?}");
        assert!(
            table
                .iter()
                .all(|row| number(row, "frames_per_second") > 0.0)
        );
    }
    // Timing ratios are against each stage's reference setting, timed in
    // the same run: the simulator's default and the paper's TrackPy.
    for (table, reference) in [
        (&simulator, "substeps 1, cut-off 6σ"),
        (&crocker_grier, "diameter 7, preprocess true"),
    ] {
        let reference_fps = number(
            table
                .iter()
                .find(|row| row["setting"] == reference)
                .unwrap(),
            "frames_per_second",
        );
        for row in table {
            let expected = number(row, "frames_per_second") / reference_fps;
            let ratio = number(row, "speed_vs_reference");
            assert!((ratio - expected).abs() <= 1e-9 * expected, "{row:?}");
        }
    }
    // The exact image is approached as substeps grow with no cut-off.
    let error = |setting: &str| {
        number(
            simulator
                .iter()
                .find(|row| row["setting"] == setting)
                .unwrap(),
            "error",
        )
    };
    assert!(error("substeps 16, cut-off none") < error("substeps 1, cut-off none"));
    assert!(error("substeps 16, cut-off 2σ") > error("substeps 16, cut-off none"));
    for row in &cnn {
        assert!(number(row, "training_seconds") > 0.0);
        // Chance: the top prediction lands within 3 px of a QD that may
        // start anywhere in a 16×17 px region on a few % of frames; a
        // network that learned finds most of them.
        assert!(number(row, "auc_eps3") > 0.3, "{row:?}");
        let precision = number(row, "precision_static_px");
        assert!(precision.is_finite() && precision < 3.0, "{row:?}");
    }
    // The training-time front is the undominated rows by training time.
    let marked: Vec<bool> = cnn
        .iter()
        .map(|row| row["pareto_training"] == "1")
        .collect();
    let front = pareto_front(&cnn, |row| number(row, "training_seconds"));
    assert_eq!(marked, front, "{cnn:?}");
}

#[test]
fn bad_sweep_settings_are_refused_with_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    for (flag, value) in [
        ("--cnn-depths", "9"),
        ("--cnn-epochs", "0"),
        ("--cnn-channels", "0"),
        ("--brightness", "-1"),
        ("--frames", "0"),
    ] {
        let setting = format!("{flag}={value}");
        let result = scanloc(&[
            "bench",
            "tradeoffs",
            "--out",
            dir.path().to_str().unwrap(),
            &setting,
        ]);
        assert_eq!(result.status.code(), Some(2), "{flag} {value}");
        assert!(
            stderr(&result).contains(flag.trim_start_matches("--cnn-").trim_start_matches("--")),
            "{}",
            stderr(&result)
        );
    }
    assert!(
        std::fs::read_dir(dir.path()).unwrap().next().is_none(),
        "nothing written"
    );
}
