//! Manifests a hostile or unlucky user writes: a byte-order mark from a
//! Windows editor, and values `check` must refuse exactly as `run` would
//! (the refusals themselves are in the bad-manifest corpus,
//! tests/fixtures/manifests/bad/, which runs both commands on each).

use crate::common::*;

/// `text` with a UTF-8 byte-order mark in front.
fn with_bom(text: &str) -> String {
    format!("\u{feff}{text}")
}

/// The smoke manifest without its leading comment (a mark right before a
/// comment happened to be read; before a key it was not).
fn smoke_text() -> String {
    let text = std::fs::read_to_string(smoke()).unwrap();
    let body: Vec<&str> = text.lines().skip_while(|l| l.starts_with('#')).collect();
    assert!(body[0].starts_with("name:"), "{}", body[0]);
    body.join("\n") + "\n"
}

#[test]
fn a_manifest_with_a_byte_order_mark_reads_as_without_one() {
    let text = smoke_text();
    let plain = scanloc::manifest::parse(&text, "smoke.yaml").unwrap();
    for variant in [
        with_bom(&text),
        with_bom(&format!("---\n{text}")),
        with_bom(&text.replace('\n', "\r\n")),
    ] {
        let marked = scanloc::manifest::parse(&variant, "smoke.yaml");
        let marked = marked.unwrap_or_else(|e| panic!("{variant:?}: {e:#}"));
        // The same experiment, keys and seeds included.
        assert_eq!(marked.datasets, plain.datasets);
        assert_eq!(marked.detectors, plain.detectors);
        assert_eq!(marked.evaluations, plain.evaluations);
    }

    let dir = tempfile::tempdir().unwrap();
    let path = write_manifest(dir.path(), "bom.yaml", &with_bom(&text));
    let output = scanloc(&["check", path.to_str().unwrap(), "--json"]);
    assert!(output.status.success(), "{}", stderr(&output));
    let checked: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    let reference = scanloc(&["check", smoke().to_str().unwrap(), "--json"]);
    let reference: serde_json::Value = serde_json::from_str(&stdout(&reference)).unwrap();
    assert_eq!(checked["plan"], reference["plan"]);
}

#[test]
fn a_byte_order_mark_does_not_hide_errors_or_shift_their_lines() {
    let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 0\n";
    let error = scanloc::manifest::parse(&with_bom(text), "x.yaml")
        .unwrap_err()
        .to_string();
    assert_eq!(
        error,
        "x.yaml:5: datasets.a.frames: must be a positive integer"
    );
}

/// What the new refusals must not catch: the same values where the run
/// does not need what they take away.
#[test]
fn values_that_only_fail_in_context_pass_where_they_can_run() {
    let fine = [
        // No emitters in a dataset nobody scores (a background-only stack).
        "name: t\nseed: 1\ndatasets:\n  a: {frames: 4}\n  empty: {frames: 4, emitters: 0}\ndetectors:\n  tp: {crocker_grier: {diameter: 7}}\nevaluations:\n  - {detector: tp, datasets: [a]}\n",
        // Every frame validates, fresh frames train.
        "name: t\nseed: 1\ndatasets:\n  train: {frames: 20}\ndetectors:\n  cnn:\n    cnn:\n      training_set: train\n      training: {validation_fraction: 1.0, fresh_frames_per_epoch: 8}\n",
        // A fraction that rounds to every frame but one.
        "name: t\nseed: 1\ndatasets:\n  train: {frames: 3}\ndetectors:\n  cnn:\n    cnn:\n      training_set: train\n      training: {validation_fraction: 0.6}\ncross_validation: {detector: cnn, folds: 3}\n",
        // Bright, but countable.
        "name: t\nseed: 1\ndatasets:\n  a: {frames: 4, brightness: 1e6, emitters: 3}\n",
    ];
    for text in fine {
        if let Err(error) = scanloc::manifest::parse(text, "t.yaml") {
            panic!("{text}\nrefused: {error:#}");
        }
    }
}
