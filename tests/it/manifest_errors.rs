//! Malformed manifests: each gives one clear error line naming the file,
//! the line and the field, exit code 2, and leaves the registry untouched.
//!
//! The corpus is `tests/fixtures/manifests/bad/*.yaml`; the first line of
//! each file is `# expect: FRAGMENT`, the part of the error expected after
//! `error: PATH` (starting with `:LINE:`).

use std::path::PathBuf;

use crate::common::*;

fn corpus() -> Vec<(PathBuf, String)> {
    let dir = root().join("tests/fixtures/manifests/bad");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "yaml"))
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|path| {
            let text = std::fs::read_to_string(&path).unwrap();
            let expected = text
                .lines()
                .next()
                .and_then(|l| l.strip_prefix("# expect: "))
                .unwrap_or_else(|| panic!("{}: first line must be `# expect: …`", path.display()))
                .to_string();
            (path, expected)
        })
        .collect()
}

#[test]
fn the_corpus_is_large_enough() {
    assert!(corpus().len() >= 20);
}

#[test]
fn every_malformed_manifest_is_refused_with_its_error_and_exit_code_2() {
    // A registry that already holds a run, to show nothing touches it.
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    run_json(&smoke(), &registry, &[]);
    let before = snapshot(&registry);
    let fresh = dir.path().join("never-created");
    let mut failures = Vec::new();
    for (path, expected) in corpus() {
        let relative = path
            .strip_prefix(root())
            .unwrap()
            .to_str()
            .unwrap()
            .to_string();
        for (command, registry) in [("run", &registry), ("run", &fresh), ("check", &registry)] {
            let mut args = vec![command, relative.as_str()];
            if command == "run" {
                args.extend(["--registry", registry.to_str().unwrap()]);
            }
            let output = scanloc(&args);
            let error = stderr(&output);
            let wanted = format!("error: {relative}{expected}");
            if output.status.code() != Some(2)
                || !error.starts_with(&wanted)
                || error.trim_end().lines().count() != 1
                || !stdout(&output).is_empty()
            {
                failures.push(format!(
                    "{command} {relative}: exit {:?}, stderr {error:?}, wanted a line starting {wanted:?}",
                    output.status.code()
                ));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert_eq!(snapshot(&registry), before, "the registry changed");
    assert!(!fresh.exists(), "a registry was created for bad input");
}

#[test]
fn the_shipped_manifests_are_valid() {
    for manifest in ["experiments/smoke.yaml", "experiments/paper.yaml"] {
        let output = scanloc(&["check", manifest, "--json"]);
        assert!(output.status.success(), "{manifest}: {}", stderr(&output));
        let value: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
        assert!(!value["plan"].as_array().unwrap().is_empty());
    }
}

#[test]
fn check_prints_the_resolved_manifest_with_defaults_and_seeds() {
    let output = scanloc(&["check", "experiments/smoke.yaml"]);
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    // Defaults the manifest does not write are filled in.
    assert!(text.contains("sigma_xy_um: 0.21"), "{text}");
    assert!(text.contains("retrace_ms: 1.1"), "{text}");
    let resolved: serde_yaml::Value = serde_yaml::from_str(&text).unwrap();
    let datasets = resolved["datasets"].as_sequence().unwrap();
    assert_eq!(datasets.len(), 4);
    let mut seeds = Vec::new();
    for dataset in datasets {
        seeds.push(dataset["seed"].as_u64().unwrap());
        assert_eq!(dataset["params"]["margin_px"].as_f64(), Some(4.0));
    }
    // Each dataset draws from a seed of its own, derived from the
    // manifest's.
    seeds.sort();
    seeds.dedup();
    assert_eq!(seeds.len(), 4, "{seeds:?}");
    assert!(!seeds.contains(&20240613), "{seeds:?}");
    assert!(resolved["plan"].as_sequence().unwrap().len() >= 4);
    let missing = scanloc(&["check", "experiments/does-not-exist.yaml"]);
    assert_eq!(missing.status.code(), Some(2));
    assert!(stderr(&missing).contains("experiments/does-not-exist.yaml: cannot read"));
}
