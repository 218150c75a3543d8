//! Tracking pipelines in manifests (docs/tracking.md, "The tracking
//! experiment"): recordings as datasets, locate → link → score steps,
//! the run's tracking tables, caching, reproduction, and bad sections.

use crate::common::{
    TRACKING_MEASURES, report_markdown, report_section, run_json, run_text, scanloc, stderr,
    stdout, write_manifest,
};

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
    let (text, _) = run_text(&manifest, &registry);
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
    for measure in TRACKING_MEASURES {
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
        // Beyond any recording: their squares overflowed a link's cost,
        // which then linked nothing (exit 0).
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {diffusion_um2_s: 1e300}}\n",
            "linkers.lap.lap.diffusion_um2_s: must be at most 1e6",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  tp: {trackpy: {search_range: 1e300}}\n",
            "linkers.tp.trackpy.search_range: must be at most 1e9",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5, gate_sigmas: 1e300}}\n",
            "linkers.lap.lap.gate_sigmas: must be at most 1e3",
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
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {ensemble_margin_px: 12}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring.ensemble_margin_px: 12 px inside each edge leaves nothing of the 24 × 25 px field",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {gate_px: 0}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring.gate_px",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {gate_px: 1e300}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring.gate_px: must be at most 1e6",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [other]}\n",
            "tracking.evaluations[0].recordings[0]",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {bias_correction: {simulated: {recordings: 0}}}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring.bias_correction: recordings must be 1 to 16, got 0",
        ),
        (
            "recordings:\n  rec: {frames: 5}\nlinkers:\n  lap: {lap: {search_range: 5}}\ntracking:\n  scoring: {bias_correction: guessed}\n  evaluations:\n    - {detector: cg, linker: lap, recordings: [rec]}\n",
            "tracking.scoring",
        ),
        (
            "recordings:\n  rec: {frames: 5, qd_count: -3}\n",
            "recordings.rec.qd_count",
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

/// `scanloc ARGS`, asserting success: its output.
fn ok(args: &[&str]) -> String {
    let output = scanloc(args);
    assert!(output.status.success(), "{args:?}: {}", stderr(&output));
    stdout(&output)
}

/// The width and height of PNG file `path` (panics if it is not a PNG).
fn png_size(path: &std::path::Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(&bytes[1..4], b"PNG", "{} is not a PNG", path.display());
    let width = u32::from_be_bytes(bytes[16..20].try_into().unwrap());
    let height = u32::from_be_bytes(bytes[20..24].try_into().unwrap());
    (width, height)
}

/// The text of SVG file `path` (panics if it is not an SVG).
fn svg_text(path: &std::path::Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(
        text.contains("<svg") && text.trim_end().ends_with("</svg>"),
        "{} is not an SVG",
        path.display()
    );
    text
}

/// The tracking tables of a text output: from the first table's title to
/// the end of the last table.
fn tracking_tables(text: &str) -> String {
    let start = text
        .find("tracking measures (gate")
        .unwrap_or_else(|| panic!("no tracking tables: {text}"));
    text[start..]
        .lines()
        .take_while(|l| !l.starts_with("run "))
        .collect::<Vec<_>>()
        .join("\n")
}

/// Runs manifest `text` in a new folder's `registry` twice: `--json`, then
/// as text (served from the registry). Returns the folder, the JSON and
/// the text's tracking tables.
fn run_twice(text: &str) -> (tempfile::TempDir, serde_json::Value, String) {
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "manifest.yaml", text);
    let registry = dir.path().join("registry");
    let run = run_json(&manifest, &registry, &[]);
    let (text, _) = run_text(&manifest, &registry);
    (dir, run, tracking_tables(&text))
}

#[test]
fn registry_show_report_and_shards_carry_a_tracking_only_run() {
    let (dir, run, printed) = run_twice(MANIFEST);
    let registry = dir.path().join("registry");
    let registry_arg = registry.to_str().unwrap();
    let id = run["run"].as_str().unwrap();

    // `registry show` prints the tables the run printed, and no empty AUC
    // table; with --json the rows of `run --json`.
    let show = |registry: &str| {
        let text = ok(&["registry", "show", id, "--registry", registry]);
        assert!(!text.contains("no AUC"), "{text}");
        assert!(text.contains("evaluation/cg+memory@rec-blink"), "{text}");
        let json = ok(&["registry", "show", id, "--json", "--registry", registry]);
        let json: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert_eq!(json["id"], id);
        (tracking_tables(&text), json["tracking"].clone())
    };
    let (text, json) = show(registry_arg);
    assert_eq!(text, printed);
    assert_eq!(json, run["tracking"]);

    // A shard of the run, imported into an empty registry, shows the same
    // tables and reproduces bit for bit.
    let shard = dir.path().join("shard");
    ok(&[
        "registry",
        "export",
        id,
        "--out",
        shard.to_str().unwrap(),
        "--registry",
        registry_arg,
    ]);
    let other = dir.path().join("other");
    let other_arg = other.to_str().unwrap();
    ok(&[
        "registry",
        "import",
        shard.to_str().unwrap(),
        "--registry",
        other_arg,
    ]);
    assert_eq!(show(other_arg), (printed.clone(), run["tracking"].clone()));
    let text = ok(&["reproduce", id, "--registry", other_arg]);
    assert!(text.contains("IDENTICAL"), "{text}");

    // The report: no AUC section, a Tracking section with both tables and
    // both figures.
    let out = dir.path().join("report");
    let markdown = report_markdown(&registry, id, &out);
    assert!(!markdown.contains("## AUC"), "{markdown}");
    assert!(!markdown.contains("## Localisation quality"), "{markdown}");
    let section = report_section(&markdown, "Tracking");
    assert!(
        section.contains("**tracking measures (gate 2 px"),
        "{section}"
    );
    // The run's counts of tracks, in the run's row order.
    let tracks = &run["tracking"][2]["tracking"];
    assert!(
        section.contains(&format!(
            "| cg+memory | rec-blink | 1 | {}/{} |",
            tracks["estimated_tracks"], tracks["truth_tracks"]
        )),
        "{section}"
    );
    let ml_rows = section
        .lines()
        .filter(|l| l.starts_with("| cg+") && l.contains(" | ml | "))
        .count();
    assert_eq!(ml_rows, 3, "{section}");
    // One figure per recording, one panel per pipeline on it.
    assert_eq!(png_size(&out.join("tracks_rec-1.00.png")), (360, 400));
    assert_eq!(png_size(&out.join("tracks_rec-blink.png")), (720, 400));
    let svg = svg_text(&out.join("tracks_rec-blink.svg"));
    assert!(svg.contains("cg+lap: rec-blink, frame"), "{svg}");
    assert!(svg.contains("cg+memory: rec-blink, frame"), "{svg}");
    assert!(section.contains("![tracks over a frame](tracks_rec-blink.png)"));
    assert_eq!(png_size(&out.join("diffusion_estimates.png")), (640, 520));
    let svg = svg_text(&out.join("diffusion_estimates.svg"));
    assert!(svg.contains("D estimated against true D"), "{svg}");
    assert!(svg.contains("cg+lap, ML") && svg.contains("cg+memory, ML"));
    assert!(section.contains("![D estimated against true D](diffusion_estimates.png)"));
}

/// A per-frame evaluation beside one tracking pipeline on recordings of two
/// D values.
const MIXED: &str = "\
name: mixed
seed: 11
microscope: {brightness: 30}
datasets:
  test-1.00: {frames: 6, diffusion_um2_s: 1.0}
recordings:
  rec-0.50: {frames: 200, diffusion_um2_s: 0.5}
  rec-1.50: {frames: 200, diffusion_um2_s: 1.5}
linkers:
  lap: {lap: {search_range: 10, max_gap: 2}}
detectors:
  cg:
    crocker_grier: {diameter: 7, minmass: 40}
evaluations:
  - {detector: cg, datasets: [test-1.00]}
tracking:
  scoring: {gate_px: 2, max_depth_um: 1.36, split_gaps_over: 2}
  evaluations:
    - {detector: cg, linker: lap, recordings: [rec-0.50, rec-1.50]}
";

#[test]
fn a_run_with_auc_and_tracking_reports_and_shows_both_and_a_sweep_lists_the_tracking() {
    let (dir, run, printed) = run_twice(MIXED);
    let registry = dir.path().join("registry");
    let registry_arg = registry.to_str().unwrap();
    let id = run["run"].as_str().unwrap();
    assert_eq!(run["auc"][0]["detector"], "cg");
    let diffusions: Vec<f64> = run["tracking"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["diffusion"].as_f64().unwrap())
        .collect();
    assert_eq!(diffusions, [0.5, 1.5]);

    let text = ok(&["registry", "show", id, "--registry", registry_arg]);
    assert!(text.contains("test-1.00"), "the AUC grid: {text}");
    assert!(!text.contains("no AUC"), "{text}");
    assert_eq!(tracking_tables(&text), printed);

    // The report keeps its AUC and quality tables for the per-frame
    // evaluation alone, and adds the Tracking section.
    let out = dir.path().join("report");
    let markdown = report_markdown(&registry, id, &out);
    assert!(markdown.contains("## AUC"), "{markdown}");
    let quality = report_section(&markdown, "Localisation quality");
    assert!(quality.contains("| cg | test-1.00 |"), "{quality}");
    assert!(!quality.contains("cg+lap"), "{quality}");
    let section = report_section(&markdown, "Tracking");
    for row in [
        "| cg+lap | rec-0.50 | 0.5 | ml |",
        "| cg+lap | rec-1.50 | 1.5 | ml |",
    ] {
        assert!(section.contains(row), "{row}: {section}");
    }
    for recording in ["rec-0.50", "rec-1.50"] {
        assert_eq!(
            png_size(&out.join(format!("tracks_{recording}.png"))),
            (360, 400)
        );
        let svg = svg_text(&out.join(format!("tracks_{recording}.svg")));
        assert!(
            svg.contains(&format!("cg+lap: {recording}, frame")),
            "{svg}"
        );
    }
    let svg = svg_text(&out.join("diffusion_estimates.svg"));
    assert!(
        svg.contains("true D (µm²/s)") && svg.contains("cg+lap, ML"),
        "{svg}"
    );

    // A grid over the linker's search range lists each point's tracking
    // rows; the point of the manifest's own value is the run's.
    let grid = format!(
        "{MIXED}sweep:\n  range:\n    path: linkers.lap.lap.search_range\n    values: [5, 10]\n"
    );
    let manifest = write_manifest(dir.path(), "grid.yaml", &grid);
    let json = ok(&[
        "sweep",
        "run",
        manifest.to_str().unwrap(),
        "--json",
        "--registry",
        registry_arg,
    ]);
    let sweep: serde_json::Value = serde_json::from_str(&json).unwrap();
    let points = sweep["grid"].as_array().unwrap();
    assert_eq!(points.len(), 2);
    assert_eq!(points[0]["tracking"].as_array().unwrap().len(), 2);
    assert_eq!(points[1]["tracking"], run["tracking"]);
    assert_eq!(points[1]["auc"], run["auc"]);
    let text = ok(&[
        "sweep",
        "run",
        manifest.to_str().unwrap(),
        "--registry",
        registry_arg,
    ]);
    assert!(
        text.lines()
            .filter(|l| l.contains("cg+lap") && l.contains("ML D"))
            .count()
            == 4,
        "{text}"
    );
}

/// Crocker-grier misses the frames where a QD moved fast (its spot
/// smeared), so its tracks read D low; the pipeline reads the same on the
/// simulated recordings, which divides it out.
const BIASED: &str = "\
name: bias-smoke
seed: 11
microscope: {brightness: 30}
recordings:
  dense: {frames: 3000, diffusion_um2_s: 1.0, qd_density: 0.25}
linkers:
  memory: {trackpy: {search_range: 12, memory: 2}}
  lap: {lap: {search_range: 12, max_gap: 2}}
detectors:
  cg:
    crocker_grier: {diameter: 7, minmass: 40}
tracking:
  scoring: {gate_px: 2, max_depth_um: 1.36, split_gaps_over: 2, bias_correction: {simulated: {recordings: 2}}}
  evaluations:
    - {detector: cg, linker: memory, recordings: [dense]}
    # A pipeline's own setting replaces the scoring's.
    - {detector: cg, linker: lap, recordings: [dense], bias_correction: none}
";

#[test]
fn a_bias_correction_by_simulation_divides_out_what_the_pipeline_reads_on_recordings_like_its_own()
{
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "bias.yaml", BIASED);
    let registry = dir.path().join("registry");
    let first = run_json(&manifest, &registry, &[]);
    let row = &first["tracking"][0];
    let ml = &row["estimators"][2];
    assert_eq!(ml["method"], "ml");
    let raw = ml["ensemble"]["d"].as_f64().unwrap();
    let raw_se = ml["ensemble"]["standard_error"].as_f64().unwrap();
    let corrected = &row["corrected_ensemble"];
    let d = corrected["estimate"]["d"].as_f64().unwrap();
    let se = corrected["estimate"]["standard_error"].as_f64().unwrap();
    let simulated = corrected["simulated"]["d"].as_f64().unwrap();
    let simulated_se = corrected["simulated"]["standard_error"].as_f64().unwrap();

    // The correction's formula: D̂²/D̂ₛ, relative errors in quadrature.
    assert!((d - raw * raw / simulated).abs() < 1e-12 * d, "{corrected}");
    let relative = (raw_se / raw).hypot(simulated_se / simulated);
    assert!((se - d * relative).abs() < 1e-12 * se, "{corrected}");
    assert_eq!(corrected["simulated_frames"], 2 * 3000);

    // As many QDs as the recording holds, matched by the localisations per
    // frame alone (the pilot starts from the volume's expected number).
    let spec = &scanloc::manifest::load(&manifest).unwrap().recordings[0];
    let one_frame = scanloc::sim::recording::RecordingParams {
        frames: 1,
        ..spec.params.clone()
    };
    let held = scanloc::sim::recording::simulate_recording(&one_frame, spec.seed, false)
        .unwrap()
        .qds as f64;
    let matched = corrected["simulated_qds"].as_f64().unwrap();
    // Tolerance: the localisations per frame of 3,000 and 750 frames,
    // each counted to a few per cent.
    assert!(
        (matched / held - 1.0).abs() < 0.15,
        "{matched} QDs against {held}"
    );
    let expected = (0.25 * (25.0 * 0.07 + 3.0) * (24.0 * 0.07 + 3.0) * 8.0_f64).round();
    assert_eq!(corrected["pilot_qds"].as_f64().unwrap(), expected);

    // The raw ensemble reads D low by more than twice its standard error,
    // the corrected one is within twice its own of the truth (on this
    // recording; over seeds 11–15 the raw reads −10 to −17 %, the
    // corrected −8 to +1 %).
    assert!(raw - 1.0 < -2.0 * raw_se, "raw D {raw} (SE {raw_se})");
    assert!((d - 1.0).abs() < 2.0 * se, "corrected D {d} (SE {se})");
    assert!((d - 1.0).abs() < (raw - 1.0).abs(), "{d} against {raw}");

    assert_eq!(first["tracking"][1]["pipeline"], "cg+lap");
    assert!(first["tracking"][1].get("corrected_ensemble").is_none());

    // Cached: the second run draws nothing and shows the same row.
    let second = run_json(&manifest, &registry, &[]);
    assert_eq!(second["computed_steps"], 0);
    assert_eq!(second["tracking"][0]["corrected_ensemble"], *corrected);
    let (text, _) = run_text(&manifest, &registry);
    assert!(text.contains("ml, bias-corrected"), "{text}");
    // The report's table and figure show it beside the uncorrected one.
    let out = dir.path().join("report");
    let markdown = report_markdown(&registry, "latest", &out);
    let section = report_section(&markdown, "Tracking");
    assert!(
        section.contains("| cg+memory | dense | 1 | ml, bias-corrected |"),
        "{section}"
    );
    let svg = svg_text(&out.join("diffusion_estimates.svg"));
    assert!(svg.contains("cg+memory, ML bias-corrected"), "{svg}");
    assert!(!svg.contains("cg+lap, ML bias-corrected"), "{svg}");
}

#[test]
fn a_bias_correction_is_keyed_by_the_seed_its_pipeline_name_derives() {
    // Renaming a linker keeps its tracks' key (the same linking) and, with
    // no correction, its evaluation's; a correction draws its recordings
    // from a seed the pipeline's name derives, so its key changes with it.
    let dir = tempfile::tempdir().unwrap();
    let keys = |name: &str, text: &str| -> Vec<(String, String)> {
        let manifest = write_manifest(dir.path(), name, text);
        let listed = ok(&["check", manifest.to_str().unwrap()]);
        let lines: Vec<&str> = listed.lines().collect();
        lines
            .windows(2)
            .filter_map(|pair| {
                let step = pair[0].strip_prefix("- step: ")?;
                let key = pair[1].trim().strip_prefix("key: ")?;
                Some((step.to_string(), key.to_string()))
            })
            .collect()
    };
    let renamed_text = BIASED
        .replace("  memory: {trackpy", "  mem: {trackpy")
        .replace("linker: memory", "linker: mem")
        .replace("  lap: {lap", "  gaps: {lap")
        .replace("linker: lap", "linker: gaps");
    let original = keys("original.yaml", BIASED);
    let renamed = keys("renamed.yaml", &renamed_text);
    let key = |list: &[(String, String)], step: &str| -> String {
        list.iter()
            .find(|(s, _)| s == step)
            .unwrap_or_else(|| panic!("no step {step}: {list:?}"))
            .1
            .clone()
    };
    assert_eq!(
        key(&original, "predictions/cg+memory@dense"),
        key(&renamed, "predictions/cg+mem@dense")
    );
    assert_eq!(
        key(&original, "evaluation/cg+lap@dense"),
        key(&renamed, "evaluation/cg+gaps@dense")
    );
    assert_ne!(
        key(&original, "evaluation/cg+memory@dense"),
        key(&renamed, "evaluation/cg+mem@dense")
    );
}
