//! The likelihood detector: its estimator against the Cramér–Rao floor on a
//! static QD, and as a manifest detector and a `locate` method.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scanloc::bench::tradeoff::cramer_rao_rmse_px;
use scanloc::detect::likelihood::{LikelihoodParams, locate_stack};
use scanloc::sim::{Distribution, SimParams, noise, static_emitter_image};
use scanloc::types::FrameStack;

use crate::common::*;

#[test]
fn on_a_static_qd_the_estimator_reaches_the_cramer_rao_floor() {
    // A static, in-focus QD (D = 0) at the 3 × 3 sub-pixel positions near
    // the frame centre the floor is averaged over, each seen in `repeats`
    // noisy frames (the simulator's forward model, Poisson counts). The
    // posterior mean is asymptotically efficient: its mean squared error
    // must match the floor's variance within the sampling error of M
    // frames. With errors near Gaussian, |error|² ≈ floor² · χ²₂ / 2, whose
    // mean over M frames has a relative standard error of 1/√M; allowed: 3.
    let params = SimParams {
        height: 14,
        width: 14,
        brightness: 15.0.into(),
        margin_px: 4.0,
        diffusion_um2_s: Distribution::Fixed(0.0),
        ..SimParams::default()
    };
    let positions = 3;
    let repeats = 16;
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut truths = Vec::new();
    let mut data = Vec::new();
    for iy in 0..positions {
        for ix in 0..positions {
            // The positions `cramer_rao_rmse_px` averages over.
            let x = params.width as f64 / 2.0 - 0.5 + ix as f64 / positions as f64;
            let y = params.height as f64 / 2.0 - 0.5 + iy as f64 / positions as f64;
            let expected = static_emitter_image(&params, x, y, 0.0).unwrap().expected;
            for _ in 0..repeats {
                truths.push((x, y));
                data.extend(
                    expected
                        .iter()
                        .map(|&mean| noise::poisson(&mut rng, mean) as u32),
                );
            }
        }
    }
    let frames = FrameStack::from_vec(truths.len(), params.height, params.width, data).unwrap();
    let settings = LikelihoodParams {
        particles: 8000,
        ..LikelihoodParams::default()
    };
    let predictions =
        locate_stack(&frames, &params, &settings, 5, &scanloc::progress::hidden()).unwrap();
    let m = predictions.len() as f64;
    let mse = predictions
        .iter()
        .zip(&truths)
        .map(|(p, (x, y))| (p.x - x).powi(2) + (p.y - y).powi(2))
        .sum::<f64>()
        / m;
    let floor = cramer_rao_rmse_px(&params, positions).unwrap();
    let ratio = mse / (floor * floor);
    assert!(
        (ratio - 1.0).abs() < 3.0 / m.sqrt(),
        "RMSE {:.4} px against the floor {floor:.4} px (MSE ratio {ratio:.3}, {m} frames)",
        mse.sqrt()
    );
}

/// A manifest scoring the likelihood detector (known D and a prior over D)
/// on the first 2 frames of a small dataset.
const SMALL_MANIFEST: &str = "name: bound-small
seed: 5
microscope: {height: 12, width: 12, margin_px: 3, brightness: 20}
datasets:
  test: {frames: 4, diffusion_um2_s: 1.0}
detectors:
  known: {likelihood: {particles: 200}}
  marginal: {likelihood: {particles: 200, diffusion_um2_s: {uniform: [0.5, 1.5]}}}
evaluations:
  - {detector: known, datasets: [test], frames: 2}
  - {detector: marginal, datasets: [test], frames: 2}
";

#[test]
fn a_manifest_scores_the_likelihood_detector_on_the_first_frames() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("bound.yaml");
    std::fs::write(&manifest, SMALL_MANIFEST).unwrap();
    let registry = dir.path().join("registry");
    let run = run_json(&manifest, &registry, &[]);
    let steps: Vec<&str> = run["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["step"].as_str().unwrap())
        .collect();
    assert!(steps.contains(&"dataset/test+first2"), "{steps:?}");
    assert!(steps.contains(&"evaluation/known@test+first2"), "{steps:?}");
    let auc = run["auc"].as_array().unwrap();
    assert_eq!(auc.len(), 6, "{auc:?}");
    for cell in auc {
        assert_eq!(cell["dataset"], "test+first2");
        assert!(
            (0.0..=1.0).contains(&cell["auc"].as_f64().unwrap()),
            "{cell}"
        );
    }
    // One prediction per scored frame, from the detector's recorded seed.
    let output = scanloc(&[
        "registry",
        "sql",
        "--registry",
        registry.to_str().unwrap(),
        "--json",
        "SELECT count FROM predictions",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let counts: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(counts, serde_json::json!([{"count": 2}, {"count": 2}]));
    // The plan records the filter's seed; a second run makes nothing anew.
    let again = run_json(&manifest, &registry, &[]);
    assert_eq!(again["computed_steps"], 0);
    assert_eq!(again["auc"], run["auc"]);
}

/// Ranked lists beside detectors without them: `list` gives two guesses
/// per frame; `single` one; TrackPy's algorithm (diameter 3) several per
/// frame without ranks, whose best-per-frame AUC differs from its AUC
/// (checked below), so only ranks, not differing numbers, make the row.
const RANKED_MANIFEST: &str = "name: best-guess
seed: 5
microscope: {height: 12, width: 12, margin_px: 3, brightness: 5}
datasets:
  test: {frames: 10, diffusion_um2_s: 1.75}
detectors:
  list: {likelihood: {particles: 200, max_candidates: 2}}
  single: {likelihood: {particles: 200}}
  trackpy:
    crocker_grier: {diameter: 3, minmass: 0}
evaluations:
  - {detector: list, datasets: [test]}
  - {detector: single, datasets: [test]}
  - {detector: trackpy, datasets: [test]}
";

/// The AUC grid of a run's text: from its `AUC` heading to the last row.
fn auc_grid(text: &str) -> Vec<&str> {
    text.lines()
        .skip_while(|l| !l.starts_with("AUC"))
        .take_while(|l| !l.is_empty() && !l.starts_with("run "))
        .collect()
}

#[test]
fn the_run_table_gives_ranked_lists_a_best_guess_row_and_registry_show_reprints_it() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(dir.path(), "ranked.yaml", RANKED_MANIFEST);
    let registry = dir.path().join("registry");
    let (text, run) = run_text(&manifest, &registry);
    let grid = auc_grid(&text);
    let labels: Vec<&str> = grid[2..]
        .iter()
        .map(|l| l.split("  ").next().unwrap())
        .collect();
    assert_eq!(
        labels,
        ["list", "list, best guess", "single", "trackpy"],
        "{text}"
    );

    // The row holds the evaluation's best-guess AUCs, stored in both the
    // evaluation's and the run's rows; NULL in the run's rows without lists.
    let sql = |query: &str| -> serde_json::Value {
        let output = scanloc(&[
            "registry",
            "sql",
            "--registry",
            registry.to_str().unwrap(),
            "--json",
            query,
        ]);
        assert!(output.status.success(), "{}", stderr(&output));
        serde_json::from_str(&stdout(&output)).unwrap()
    };
    let stored = sql(
        "SELECT e.detector, u.eps_px, u.auc, u.auc_best_per_frame AS best, r.auc_best_per_frame AS shown
         FROM auc u JOIN evaluations e ON e.key = u.evaluation_key
         JOIN run_auc r ON r.evaluation_key = u.evaluation_key AND r.eps_px = u.eps_px
         ORDER BY r.rowid",
    );
    let rows = stored.as_array().unwrap();
    assert_eq!(rows.len(), 9, "{stored}");
    let best_row: Vec<String> = grid[3]
        .split_whitespace()
        .skip(3)
        .map(str::to_string)
        .collect();
    let mut best_cells = Vec::new();
    for row in rows {
        let best = row["best"]
            .as_f64()
            .expect("every evaluation has its best guess");
        match row["detector"].as_str().unwrap() {
            "list" => {
                assert_eq!(row["shown"].as_f64(), Some(best), "{row}");
                best_cells.push(format!("{best:.3}"));
            }
            _ => assert!(row["shown"].is_null(), "{row}"),
        }
    }
    assert_eq!(best_row, best_cells, "{text}");
    let differs = |detector: &str| {
        rows.iter()
            .any(|r| r["detector"] == detector && r["auc"] != r["best"])
    };
    assert!(differs("list"), "a second guess changes the AUC: {stored}");
    assert!(
        differs("trackpy"),
        "unranked extras change it too: {stored}"
    );

    // `registry show` reprints the same grid from the record.
    let output = scanloc(&[
        "registry",
        "show",
        &run,
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let shown = stdout(&output);
    assert_eq!(auc_grid(&shown), grid, "{shown}");

    // The report gives the list's calibration per rank: ranks 1 and 2,
    // one guess of rank 1 per frame, a mean score and an observed share
    // in [0, 1]; the single-guess detector has no such rows.
    let report = crate::common::report_markdown(&registry, &run, &dir.path().join("report"));
    let section = crate::common::report_section(&report, "Calibration of the score");
    let rank_rows: Vec<Vec<&str>> = section
        .lines()
        .filter(|l| l.starts_with("| list |"))
        .map(|l| l.split('|').map(str::trim).collect())
        .collect();
    assert_eq!(
        rank_rows.len(),
        3,
        "the pooled row and one per rank: {section}"
    );
    let ranks: Vec<&str> = rank_rows[1..].iter().map(|r| r[3]).collect();
    assert_eq!(ranks, ["1", "2"], "{section}");
    for row in &rank_rows[1..] {
        for cell in [row[5], row[6]] {
            let value: f64 = cell.parse().unwrap_or_else(|_| panic!("{section}"));
            assert!((0.0..=1.0).contains(&value), "{section}");
        }
    }
    assert!(!section.contains("| single | test | 1 |"), "{section}");

    // A second run reads every evaluation from its stored score.json:
    // the same table.
    let (again, _) = run_text(&manifest, &registry);
    assert_eq!(auc_grid(&again), grid, "{again}");

    // A run without ranked lists prints no extra row, with its evaluations
    // cached or not.
    let plain = write_manifest(
        dir.path(),
        "plain.yaml",
        &RANKED_MANIFEST
            .replace(
                "  list: {likelihood: {particles: 200, max_candidates: 2}}\n",
                "",
            )
            .replace("  - {detector: list, datasets: [test]}\n", ""),
    );
    for registry in [registry.clone(), dir.path().join("fresh")] {
        let (text, _) = run_text(&plain, &registry);
        let grid = auc_grid(&text);
        assert_eq!(grid.len(), 4, "{text}");
        assert!(!text.contains("best guess"), "{text}");
    }
}

#[test]
fn evaluations_that_cannot_run_are_refused_by_check() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("bad.yaml");
    for (text, message) in [
        (
            SMALL_MANIFEST.replace(
                "frames: 2}\n  - {detector: marginal",
                "frames: 5}\n  - {detector: marginal",
            ),
            "evaluations[0].frames: 5 frames asked of `test`, which has 4",
        ),
        (
            SMALL_MANIFEST.replace(
                "frames: 2}\n  - {detector: marginal",
                "frames: 0}\n  - {detector: marginal",
            ),
            "evaluations[0].frames: must be a positive integer",
        ),
        (
            SMALL_MANIFEST.replace(
                "diffusion_um2_s: 1.0}",
                "diffusion_um2_s: 1.0, detector_noise: {pmt: {excess_noise_factor: 2}}}",
            ),
            "`known` cannot model `test`",
        ),
        (
            SMALL_MANIFEST.replace("particles: 200}}\n  marginal", "particles: 1}}\n  marginal"),
            "detectors.known.likelihood.particles: must be between 2",
        ),
    ] {
        std::fs::write(&manifest, &text).unwrap();
        let output = scanloc(&["check", manifest.to_str().unwrap()]);
        assert_eq!(output.status.code(), Some(2), "{text}");
        assert!(stderr(&output).contains(message), "{}", stderr(&output));
    }
}

#[test]
fn locate_with_the_likelihood_method_writes_one_row_per_frame() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    let (frames, truth, locs) = (path("f.npy"), path("t.csv"), path("l.csv"));
    let out = scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--height",
        "12",
        "--width",
        "12",
        "--brightness",
        "20",
        "--margin-px",
        "3",
        "--out",
        &frames,
        "--truth",
        &truth,
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let locate = |extra: &[&str]| {
        let mut args = vec![
            "locate",
            "--method",
            "likelihood",
            "--input",
            &frames,
            "--out",
            &locs,
            "--brightness",
            "20",
            "--margin-px",
            "3",
        ];
        args.extend_from_slice(extra);
        scanloc(&args)
    };
    let out = locate(&["--particles", "300", "--diffusion", "uniform:0.5,1.5"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&locs).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines[0], "frame,x,y,score");
    assert_eq!(lines.len(), 4, "{text}");
    for (frame, line) in lines[1..].iter().enumerate() {
        assert!(line.starts_with(&format!("{frame},")), "{line}");
    }
    // A ranked list: up to 3 rows per frame, ranks 1, 2, ... in the last
    // column, read back as ranked predictions.
    let out = locate(&["--particles", "300", "--max-candidates", "3"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&locs).unwrap();
    assert!(text.starts_with("frame,x,y,score,candidate\n"), "{text}");
    let listed = scanloc::io::csv_tables::read_predictions(std::path::Path::new(&locs)).unwrap();
    for frame in 0..3 {
        let ranks: Vec<u32> = listed
            .iter()
            .filter(|p| p.frame == frame)
            .map(|p| p.candidate.unwrap())
            .collect();
        assert!(!ranks.is_empty() && ranks.len() <= 3, "{text}");
        assert_eq!(
            ranks,
            (1..=ranks.len() as u32).collect::<Vec<_>>(),
            "{text}"
        );
    }
    for (bad, message) in [
        (vec!["--particles", "1"], "particles"),
        (
            vec!["--particles", "10", "--max-candidates", "0"],
            "max_candidates",
        ),
        (
            vec![
                "--particles",
                "10",
                "--max-candidates",
                "2",
                "--candidate-radius-px",
                "0",
            ],
            "candidate_radius_px",
        ),
        (
            vec!["--particles", "10", "--diffusion", "-1"],
            "diffusion_um2_s",
        ),
        (
            vec!["--particles", "10", "--score-radius-px", "0"],
            "score_radius_px",
        ),
    ] {
        let out = locate(&bad);
        assert_eq!(out.status.code(), Some(2), "{bad:?}");
        assert!(stderr(&out).contains(message), "{}", stderr(&out));
    }
}

#[test]
fn the_report_states_each_detectors_gap_to_the_bound_with_its_uncertainty() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("bound.yaml");
    // Crocker–Grier beside the two bounds on the same first frames.
    let text = SMALL_MANIFEST
        .replace("frames: 4,", "frames: 12,")
        .replace("frames: 2}", "frames: 10}")
        .replace(
            "evaluations:\n",
            "  cg: {crocker_grier: {diameter: 5, minmass: 0}}\nevaluations:\n  - {detector: cg, datasets: [test], frames: 10}\n",
        );
    std::fs::write(&manifest, &text).unwrap();
    let registry = dir.path().join("registry");
    let run = run_json(&manifest, &registry, &[]);
    let auc = |detector: &str, eps: f64| {
        run["auc"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["detector"] == detector && c["eps_px"] == eps)
            .unwrap_or_else(|| panic!("{detector} at {eps} in {}", run["auc"]))["auc"]
            .as_f64()
            .unwrap()
    };
    let report = report_markdown(
        &registry,
        run["run"].as_str().unwrap(),
        &dir.path().join("report"),
    );
    assert!(
        report.contains("## Against the attainable bound"),
        "{report}"
    );
    // One row per (detector, bound, ε); none compares a bound with itself.
    let rows: Vec<Vec<&str>> = report
        .lines()
        .skip_while(|l| !l.starts_with("## Against the attainable bound"))
        .filter(|l| {
            l.starts_with("| cg |") || l.starts_with("| known |") || l.starts_with("| marginal |")
        })
        .map(|l| l.split('|').map(str::trim).collect())
        .take_while(|cells: &Vec<&str>| cells.len() == 11)
        .collect();
    assert_eq!(rows.len(), 6, "{report}");
    for cells in &rows {
        assert_eq!(cells[1], "cg");
        assert!(["known", "marginal"].contains(&cells[2]), "{cells:?}");
        assert_eq!(cells[3], "test+first10");
        let eps: f64 = cells[4].parse().unwrap();
        let number = |i: usize| cells[i].parse::<f64>().unwrap();
        // The AUCs are the run's, the difference theirs (to the printed
        // rounding), the interval holds a standard error's worth of room.
        assert!((number(5) - auc("cg", eps)).abs() < 0.0006, "{cells:?}");
        assert!((number(6) - auc(cells[2], eps)).abs() < 0.0006, "{cells:?}");
        assert!(
            (number(7) - (number(5) - number(6))).abs() < 0.0015,
            "{cells:?}"
        );
        assert!(number(8) >= 0.0, "{cells:?}");
        let interval: Vec<f64> = cells[9]
            .trim_matches(['[', ']'])
            .split(", ")
            .map(|v| v.parse().unwrap())
            .collect();
        assert!(interval[0] <= interval[1], "{cells:?}");
    }
}
