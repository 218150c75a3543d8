//! A model trained by `scanloc run` reused outside the run: `locate
//! --model RUN:DETECTOR` (or a key) and `registry model` (issue 17).

use std::path::Path;

use crate::common::{run_json, scanloc, stderr, stdout};

/// A tiny experiment: 12×12 frames, a 4-channel CNN trained for one epoch.
const MANIFEST: &str = "name: tiny-models
seed: 5
microscope: {height: 12, width: 12, brightness: 30, margin_px: 2}
datasets:
  train: {frames: 48, emitters: {choice: [0, 1, 2]}}
  test: {frames: 8}
detectors:
  trackpy:
    crocker_grier: {diameter: 5, minmass: 0}
  cnn:
    cnn:
      training_set: train
      architecture: {channels: 4, dilations: [1, 2]}
      # Every local maximum a prediction: the test compares predictions,
      # and an untrained network's scores are low.
      training: {epochs: 1, batch_size: 16, score_floor: 0.0}
evaluations:
  - {detector: trackpy, datasets: [test]}
  - {detector: cnn, datasets: [test]}
";

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// The arguments of `scanloc locate --method cnn --model MODEL` over
/// `frames` into `out`.
fn locate_args(model: &str, registry: &Path, frames: &Path, out: &Path) -> Vec<String> {
    [
        "locate",
        "--method",
        "cnn",
        "--model",
        model,
        "--registry",
        text(registry),
        "--input",
        text(frames),
        "--out",
        text(out),
    ]
    .map(str::to_string)
    .to_vec()
}

/// The arguments of `scanloc registry model MODEL --out OUT`.
fn export_args(model: &str, registry: &Path, out: &Path) -> Vec<String> {
    [
        "registry",
        "--registry",
        text(registry),
        "model",
        model,
        "--out",
        text(out),
    ]
    .map(str::to_string)
    .to_vec()
}

/// Runs `scanloc locate --method cnn --model MODEL` over `frames` into
/// `out`: its stdout, after asserting success.
fn locate(model: &str, registry: &Path, frames: &Path, out: &Path) -> String {
    let args = locate_args(model, registry, frames, out);
    let output = scanloc(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(output.status.success(), "{model}: {}", stderr(&output));
    stdout(&output)
}

/// The `model.bin sha256 …` a locate summary names.
fn model_hash(summary: &str) -> &str {
    summary
        .split("model.bin sha256 ")
        .nth(1)
        .and_then(|rest| rest.split(';').next())
        .unwrap_or_else(|| panic!("no model hash in {summary:?}"))
}

/// Asserts `args` fail with exit code 2 and one line naming `expected`.
fn refused(args: &[&str], expected: &str) {
    let output = scanloc(args);
    let message = stderr(&output);
    assert_eq!(output.status.code(), Some(2), "{args:?}: {message}");
    assert_eq!(message.trim().lines().count(), 1, "{args:?}: {message}");
    assert!(message.contains(expected), "{args:?}: {message}");
}

#[test]
fn a_registry_model_locates_as_its_exported_folder_does() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name);
    std::fs::write(path("tiny.yaml"), MANIFEST).unwrap();
    let registry = path("registry");
    let first = run_json(&path("tiny.yaml"), &registry, &[]);
    let second = run_json(&path("tiny.yaml"), &registry, &[]);
    let run = first["run"].as_str().unwrap();
    let other = second["run"].as_str().unwrap();
    assert_ne!(run, other);

    let frames = path("frames.npy");
    let simulated = scanloc(&[
        "simulate",
        "--frames",
        "6",
        "--height",
        "12",
        "--width",
        "12",
        "--brightness",
        "30",
        "--emitters",
        "choice:0,1,2",
        "--seed",
        "9",
        "--out",
        text(&frames),
    ]);
    assert!(simulated.status.success(), "{}", stderr(&simulated));

    // By run and detector.
    let by_run = locate(
        &format!("{run}:cnn"),
        &registry,
        &frames,
        &path("by-run.csv"),
    );
    assert!(
        by_run.contains(&format!("detector cnn of run {run}")),
        "{by_run}"
    );
    let key = by_run
        .split("with model ")
        .nth(1)
        .and_then(|rest| rest.split(' ').next())
        .unwrap()
        .to_string();
    assert_eq!(key.len(), 64, "{by_run}");
    // By a unique prefix of the run, and by a prefix of the key.
    let by_prefix = locate(
        &format!("{}:cnn", &run[..run.len() - 1]),
        &registry,
        &frames,
        &path("by-prefix.csv"),
    );
    let by_key = locate(&key[..12], &registry, &frames, &path("by-key.csv"));
    assert!(by_key.contains(&key), "{by_key}");

    // Written out as a folder, it is the same model.
    let folder = path("exported");
    let args = export_args(&format!("{run}:cnn"), &registry, &folder);
    let output = scanloc(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains(&key));
    for file in ["model.bpk", "config.json", "training.json"] {
        assert!(folder.join(file).is_file(), "{file}");
    }
    let by_folder = locate(text(&folder), &registry, &frames, &path("by-folder.csv"));
    assert!(by_folder.contains("folder "), "{by_folder}");

    let predictions = std::fs::read(path("by-run.csv")).unwrap();
    let header = "frame,x,y,sigma_x,sigma_y,score\n";
    assert!(predictions.starts_with(header.as_bytes()));
    assert!(predictions.len() > header.len(), "some predictions");
    for other in ["by-prefix.csv", "by-key.csv", "by-folder.csv"] {
        assert_eq!(std::fs::read(path(other)).unwrap(), predictions, "{other}");
    }
    for summary in [&by_prefix, &by_key, &by_folder] {
        assert_eq!(model_hash(summary), model_hash(&by_run));
    }
    // … which is the hash of the model's blob in the registry.
    let query = format!("SELECT sha256 FROM artefact_blobs WHERE artefact_key = '{key}'");
    let output = scanloc(&["registry", "--registry", text(&registry), "sql", &query]);
    assert!(
        stdout(&output).contains(model_hash(&by_run)),
        "{}",
        stdout(&output)
    );

    // Bad references: one line each, exit code 2.
    let out = path("refused.csv");
    let common_prefix: String = run
        .chars()
        .zip(other.chars())
        .take_while(|(a, b)| a == b)
        .map(|(a, _)| a)
        .collect();
    assert!(common_prefix.len() >= 4, "{run} {other}");
    for (model, expected) in [
        (
            "99999999T000000Z-00000000:cnn".to_string(),
            "no run with this id or prefix",
        ),
        (format!("{common_prefix}:cnn"), "ambiguous"),
        (
            format!("{run}:nosuch"),
            "has no detector `nosuch` (its trained models: cnn)",
        ),
        (format!("{run}:trackpy"), "not a CNN"),
        ("ffffffffffff".to_string(), "no model with this key"),
    ] {
        let args = locate_args(&model, &registry, &frames, &out);
        refused(
            &args.iter().map(String::as_str).collect::<Vec<_>>(),
            expected,
        );
    }
    assert!(!out.exists(), "no output after a refusal");

    // The export refuses to replace what is not a regular file.
    let blocked = path("blocked");
    std::fs::create_dir_all(blocked.join("model.bpk")).unwrap();
    let args = export_args(&format!("{run}:cnn"), &registry, &blocked);
    refused(
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        "model.bpk",
    );
}
