//! Tracking pipelines in manifests (docs/tracking.md, "The tracking
//! experiment"): recordings as datasets, locate → link → score steps,
//! the run's tracking tables, caching, reproduction, and bad sections.

use crate::common::{run_json, scanloc, stderr, stdout, write_manifest};

/// A recording bright enough for crocker-grier to find its in-focus QDs,
/// linked by both linkers.
const MANIFEST: &str = "\
name: tracking-smoke
seed: 7
microscope: {brightness: 30}
recordings:
  rec-1.00: {frames: 300, diffusion_um2_s: 1.0}
  rec-blink: {frames: 300, diffusion_um2_s: 1.0, blink_on_ms: 100, blink_off_ms: 50}
linkers:
  lap: {lap: {search_range: 10, max_gap: 2}}
  memory: {trackpy: {search_range: 10, memory: 2}}
detectors:
  cg:
    crocker_grier: {diameter: 7, minmass: 40}
tracking:
  scoring: {gate_px: 2, max_depth_um: 1.36, split_gaps_over: 2}
  evaluations:
    - {detector: cg, linker: lap, recordings: [rec-1.00, rec-blink]}
    - {detector: cg, linker: memory, recordings: [rec-blink]}
";

#[test]
fn a_manifest_runs_its_tracking_pipelines_and_a_second_run_is_served_from_the_registry() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "tracking.yaml", MANIFEST);
    let registry = dir.path().join("registry");
    let first = run_json(&manifest, &registry, &[]);
    // Two recordings, one locate per recording, three links and scores.
    assert_eq!(first["computed_steps"], 2 + 2 + 3 + 3);
    let rows = first["tracking"].as_array().unwrap();
    let names: Vec<(String, String)> = rows
        .iter()
        .map(|r| {
            (
                r["pipeline"].as_str().unwrap().to_string(),
                r["recording"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    assert_eq!(
        names,
        [
            ("cg+lap", "rec-1.00"),
            ("cg+lap", "rec-blink"),
            ("cg+memory", "rec-blink")
        ]
        .map(|(p, r)| (p.to_string(), r.to_string()))
    );
    for row in rows {
        assert_eq!(row["diffusion"], 1.0);
        let tracking = &row["tracking"];
        // Crocker-grier at these counts misses most QDs near the edges of
        // the small field; its tracks still follow some of the truth.
        assert!(tracking["alpha"].as_f64().unwrap() > 0.0, "{row}");
        assert!(tracking["true_links"].as_u64().unwrap() > 0, "{row}");
        let methods: Vec<&str> = row["estimators"]
            .as_array()
            .unwrap()
            .iter()
            .map(|e| e["method"].as_str().unwrap())
            .collect();
        assert_eq!(methods, ["cve", "msd", "ml"]);
        let ml = &row["estimators"][2];
        let d = ml["ensemble"]["d"].as_f64().unwrap();
        assert!(d > 0.3 && d < 3.0, "ML ensemble D {d}: {row}");
    }

    // The second run computes nothing and gives the same figures.
    let second = run_json(&manifest, &registry, &[]);
    assert_eq!(second["computed_steps"], 0);
    assert_eq!(second["cached_steps"], 10);
    assert_eq!(second["tracking"], first["tracking"]);

    // The text output has both tables and no empty AUC table.
    let output = scanloc(&[
        "run",
        manifest.to_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    assert!(text.contains("tracking measures (gate 2 px"), "{text}");
    assert!(text.contains("cg+memory  rec-blink"), "{text}");
    assert!(text.contains("diffusion coefficient"), "{text}");
    assert!(!text.contains("no AUC"), "{text}");

    // The run re-executes bit for bit.
    let run = first["run"].as_str().unwrap();
    let output = scanloc(&["reproduce", run, "--registry", registry.to_str().unwrap()]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("IDENTICAL"), "{}", stdout(&output));
}

#[test]
fn a_pipeline_in_a_run_gives_what_the_commands_give_by_hand() {
    // The same recording (its seed from `check`), located, linked and
    // scored with the commands a user would type: the run's figures must
    // be theirs.
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "tracking.yaml", MANIFEST);
    let output = scanloc(&["check", manifest.to_str().unwrap(), "--json"]);
    assert!(output.status.success(), "{}", stderr(&output));
    let check: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    let seed = check["plan"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["step"] == "dataset/rec-1.00")
        .and_then(|s| s["seed"].as_str())
        .unwrap()
        .to_string();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let by_hand: [&[&str]; 3] = [
        &[
            "simulate-recording",
            "--frames",
            "300",
            "--seed",
            &seed,
            "--diffusion",
            "1",
            "--brightness",
            "30",
            "--out",
            &path("rec.npy"),
            "--truth",
            &path("truth.csv"),
        ],
        &[
            "locate",
            "--input",
            &path("rec.npy"),
            "--out",
            &path("cg.csv"),
            "--minmass",
            "40",
        ],
        &[
            "link",
            "--locs",
            &path("cg.csv"),
            "--out",
            &path("tracks.csv"),
            "--linker",
            "lap",
            "--search-range",
            "10",
            "--max-gap",
            "2",
        ],
    ];
    for args in by_hand {
        let output = scanloc(args);
        assert!(output.status.success(), "{args:?}: {}", stderr(&output));
    }
    let output = scanloc(&[
        "score-tracks",
        "--tracks",
        &path("tracks.csv"),
        "--truth",
        &path("truth.csv"),
        "--gate-px",
        "2",
        "--max-depth-um",
        "1.36",
        "--split-gaps-over",
        "2",
        "--json",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let scored: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();

    let run = run_json(&manifest, &dir.path().join("registry"), &[]);
    let row = &run["tracking"][0];
    assert_eq!(row["pipeline"], "cg+lap");
    for measure in [
        "alpha",
        "beta",
        "jaccard_detections",
        "jaccard_tracks",
        "link_precision",
        "link_recall",
    ] {
        assert_eq!(row["tracking"][measure], scored[measure], "{measure}");
    }
    let output = scanloc(&["diffusion", "--tracks", &path("tracks.csv")]);
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    let ensemble_ml = text
        .lines()
        .find(|l| l.starts_with("ensemble,") && l.split(',').nth(2) == Some("ml"))
        .unwrap_or_else(|| panic!("no ensemble ML row: {text}"));
    let d: f64 = ensemble_ml.split(',').nth(3).unwrap().parse().unwrap();
    let ours = row["estimators"][2]["ensemble"]["d"].as_f64().unwrap();
    assert!(
        (d - ours).abs() <= 1e-9 * d.abs(),
        "by hand {d}, run {ours}"
    );
}

#[test]
fn existing_keys_do_not_change_when_a_manifest_gains_tracking() {
    // The same dataset and detector with and without a tracking section:
    // the per-frame steps keep their keys.
    let dir = tempfile::tempdir().unwrap();
    let plain = "name: k\nseed: 3\ndatasets:\n  test: {frames: 5, diffusion_um2_s: 1.0}\n\
        detectors:\n  cg: {crocker_grier: {diameter: 7}}\nevaluations:\n  - {detector: cg, datasets: [test]}\n";
    let with_tracking = format!(
        "{plain}recordings:\n  rec: {{frames: 5}}\nlinkers:\n  lap: {{lap: {{search_range: 5}}}}\n\
         tracking:\n  evaluations:\n    - {{detector: cg, linker: lap, recordings: [rec]}}\n"
    );
    let keys = |text: &str, name: &str| -> Vec<(String, String)> {
        let manifest = write_manifest(dir.path(), name, text);
        let output = scanloc(&["check", manifest.to_str().unwrap(), "--json"]);
        assert!(output.status.success(), "{}", stderr(&output));
        let value: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
        value["plan"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| {
                (
                    s["step"].as_str().unwrap().to_string(),
                    s["key"].as_str().unwrap().to_string(),
                )
            })
            .collect()
    };
    let before = keys(plain, "plain.yaml");
    let after = keys(&with_tracking, "tracking.yaml");
    assert_eq!(after[..before.len()], before[..]);
    let added: Vec<&str> = after[before.len()..]
        .iter()
        .map(|(s, _)| s.as_str())
        .collect();
    assert_eq!(
        added,
        [
            "dataset/rec",
            "predictions/cg@rec",
            "predictions/cg+lap@rec",
            "evaluation/cg+lap@rec"
        ]
    );
}

#[test]
fn bad_tracking_sections_are_one_line_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let base = "name: b\nseed: 1\ndetectors:\n  cg: {crocker_grier: {diameter: 7}}\n";
    let cases = [
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  evaluations:\n    - {detector: cg, linker: nope, recordings: [rec]}\n",
            "tracking.evaluations[0].linker",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5, diffusion_um2_s: 1}}\n",
            "linkers.lap.lap.search_range",
        ),
        (
            "recordings:\n  rec: {diffusion_um2_s: 1}\n",
            "recordings.rec",
        ),
        (
            "recordings:\n  rec: {frames: 5, blink_on_ms: 10}\n",
            "recordings.rec.blink_off_ms",
        ),
        (
            "recordings:\n  rec: {frames: 5, qd_density: -1}\n",
            "recordings.rec.qd_density",
        ),
        (
            "recordings:\n  rec: {frames: 5, diffusion_um2_s: {uniform: [1, 2]}}\n",
            "recordings.rec.diffusion_um2_s",
        ),
        (
            "datasets:\n  rec: {frames: 5}\nrecordings:\n  rec: {frames: 5}\n",
            "recordings.rec",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {gate_px: 0}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring.gate_px",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [other]}\n",
            "tracking.evaluations[0].recordings[0]",
        ),
    ];
    for (index, (section, field)) in cases.iter().enumerate() {
        let manifest = write_manifest(
            dir.path(),
            &format!("bad{index}.yaml"),
            &format!("{base}{section}"),
        );
        let registry = dir.path().join(format!("registry{index}"));
        let output = scanloc(&[
            "run",
            manifest.to_str().unwrap(),
            "--registry",
            registry.to_str().unwrap(),
        ]);
        assert_eq!(
            output.status.code(),
            Some(2),
            "case {index}: {}",
            stderr(&output)
        );
        let message = stderr(&output);
        assert_eq!(message.trim().lines().count(), 1, "case {index}: {message}");
        assert!(
            message.contains(field),
            "case {index}: expected {field}: {message}"
        );
        assert!(!registry.exists(), "case {index}: the registry was touched");
    }
}
