//! Bounds on every number and length that comes from outside (issue 39):
//! table cells, SQL results, simulate's memory, CSV rows, the bootstrap's
//! frames, the likelihood's D, the headroom's share, sweep axes and
//! environment variables. Each case is refused with a one-line error and
//! exit code 2, or handled within a bound, never a panic, an abort or a
//! hang.

use crate::common;

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::*;
use scanloc::env_vars::{RAYON_NUM_THREADS, SCANLOC_FONT};

/// A manifest that runs in well under a second.
const TINY: &str = "\
name: tiny
seed: 5
datasets:
  a: {frames: 4}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [a]}
";

fn registry_with_a_run(dir: &Path) -> (std::path::PathBuf, String) {
    let manifest = write_manifest(dir, "tiny.yaml", TINY);
    let registry = dir.join("registry");
    let run = run_json(&manifest, &registry, &[]);
    (registry, run["run"].as_str().unwrap().to_string())
}

/// Asserts a refusal: exit code 2 and one line on stderr containing each
/// of `needles`.
fn assert_refused(output: &Output, needles: &[&str]) {
    let text = stderr(output);
    assert_eq!(output.status.code(), Some(2), "{text:.2000}");
    assert_eq!(text.trim_end().lines().count(), 1, "{text:.2000}");
    for needle in needles {
        assert!(text.contains(needle), "{needle:?} not in {text:.2000}");
    }
}

/// `scanloc` with `args` and the environment variable `name` set to
/// `value`, stopped (and the test failed) after `limit`.
fn scanloc_with_env(args: &[&str], name: &str, value: &str, limit: Duration) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(args)
        .current_dir(root())
        .env_remove(scanloc::env_vars::SCANLOC_REGISTRY)
        .env(name, value)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run scanloc");
    let start = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if start.elapsed() > limit {
            child.kill().unwrap();
            child.wait().unwrap();
            panic!("scanloc {args:?} with {name}={value} did not end within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// The longest line of `text`, in characters.
fn widest_line(text: &str) -> usize {
    text.lines().map(|l| l.chars().count()).max().unwrap_or(0)
}

#[test]
fn run_names_and_sql_cells_of_any_length_print_cut_and_whole_in_json() {
    let dir = tempfile::tempdir().unwrap();
    let (registry, run) = registry_with_a_run(dir.path());
    let database = registry.join("registry.sqlite");
    let dir_arg = registry.to_str().unwrap();
    // Around the formatter's 65,535 width limit, far beyond it, and in
    // characters of two bytes.
    for (length, fill) in [
        (65_535, "x"),
        (65_536, "x"),
        (70_000, "x"),
        (1_000_000, "x"),
        (70_000, "é"),
    ] {
        rusqlite::Connection::open(&database)
            .unwrap()
            .execute(
                "UPDATE runs SET manifest_name = replace(printf('%.*c', ?1, 'x'), 'x', ?2)",
                rusqlite::params![length, fill],
            )
            .unwrap();
        let output = scanloc(&["registry", "runs", "--registry", dir_arg]);
        assert!(output.status.success(), "{length}: {}", stderr(&output));
        let text = stdout(&output);
        assert!(text.contains(&format!("{}…", fill.repeat(199))), "{length}");
        assert!(widest_line(&text) < 11 * 202, "{length}");
        let output = scanloc(&["registry", "runs", "--registry", dir_arg, "--json"]);
        assert!(output.status.success(), "{length}: {}", stderr(&output));
        let rows: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
        let name = rows[0]["manifest_name"].as_str().unwrap();
        assert_eq!(name.chars().count(), length);
        let output = scanloc(&["registry", "show", &run, "--registry", dir_arg]);
        assert!(output.status.success(), "{length}: {}", stderr(&output));
    }
    for (length, column) in [(65_536, "v"), (70_000, "v"), (1_000_000, "v")] {
        let query = format!("SELECT printf('%.{length}c', 'x') AS {column}, 1 AS n");
        let output = scanloc(&["registry", "sql", "--registry", dir_arg, &query]);
        assert!(output.status.success(), "{length}: {}", stderr(&output));
        let text = stdout(&output);
        assert!(text.contains(&format!("{}…", "x".repeat(199))), "{length}");
        assert!(widest_line(&text) < 2 * 202, "{length}");
    }
    // A column name beyond the width limit too.
    let query = format!("SELECT 1 AS \"{}\"", "c".repeat(70_000));
    let output = scanloc(&["registry", "sql", "--registry", dir_arg, &query]);
    assert!(output.status.success(), "{}", stderr(&output));
}

#[test]
fn sql_results_past_their_byte_bounds_stop_with_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let (registry, _) = registry_with_a_run(dir.path());
    let dir_arg = registry.to_str().unwrap();
    let rows = |count: usize, bytes: usize| {
        format!(
            "WITH RECURSIVE r(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM r WHERE i < {count}) \
             SELECT i, printf('%.*c', {bytes}, 'x') AS v FROM r"
        )
    };
    let cases = [
        // The issue's case: 100 rows of 100 MB.
        (rows(100, 100_000_000), "per cell"),
        // One cell just past the bound, and one far past it.
        (rows(1, (1 << 20) + 1), "per cell"),
        (rows(2, 5 << 20), "per cell"),
        // Cells within the bound, too many of them.
        (rows(100, 1 << 20), "passes the limit"),
        (rows(10_000, 8_000), "passes the limit"),
    ];
    for (query, expected) in &cases {
        for json in [false, true] {
            let mut args = vec!["registry", "sql", "--registry", dir_arg, query.as_str()];
            if json {
                args.push("--json");
            }
            assert_refused(&scanloc(&args), &["sql: ", expected]);
        }
    }
    // Just within both bounds: printed.
    let output = scanloc(&["registry", "sql", "--registry", dir_arg, &rows(60, 1 << 20)]);
    assert!(output.status.success(), "{}", stderr(&output));
}

#[test]
fn simulate_recording_refuses_outputs_beyond_memory_before_writing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("big.npy");
    let truth = dir.path().join("big.csv");
    // Inside the pixel limit, beyond memory: the frames with a dense
    // volume's truth, and the truth alone over fewer frames.
    for frames in ["3000000", "200000"] {
        let args = [
            "simulate-recording",
            "--frames",
            frames,
            "--qd-density",
            "10",
            "--out",
            out.to_str().unwrap(),
            "--truth",
            truth.to_str().unwrap(),
        ];
        assert_refused(&scanloc(&args), &["--frames", "GiB of memory"]);
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert!(left.is_empty(), "--frames {frames} left {left:?}");
    }
}

#[test]
fn simulate_refuses_outputs_beyond_memory_before_writing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("big.tif");
    let truth = dir.path().join("big.csv");
    let cases: [&[&str]; 4] = [
        &[
            "--frames",
            "10000000",
            "--height",
            "1",
            "--width",
            "1",
            "--emitters",
            "10000",
        ],
        &["--frames", "2000000", "--emitters", "choice:0,10000"],
        &["--frames", "400000", "--emitters", "10000"],
        // Few emitters, many frames: the truth alone is beyond the limit.
        &[
            "--frames",
            "2000000",
            "--height",
            "10",
            "--width",
            "10",
            "--emitters",
            "100",
        ],
    ];
    for case in cases {
        let mut args = vec!["simulate"];
        args.extend_from_slice(case);
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(["--truth", truth.to_str().unwrap()]);
        assert_refused(&scanloc(&args), &["--frames", "GiB of memory"]);
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert!(left.is_empty(), "{case:?} left {left:?}");
    }
    // A small dataset is still written, with nothing else beside it.
    let output = scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--out",
        out.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["big.csv", "big.tif"]);
}

/// Writes `text` to `name` in `dir` and returns its path as text.
fn write(dir: &Path, name: &str, text: &[u8]) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.to_str().unwrap().to_string()
}

#[test]
fn csv_rows_longer_than_the_bound_are_refused_naming_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let long = vec![b'7'; 3 << 20];
    let good_truth = write(dir.path(), "t.csv", b"frame,x,y\n0,5,5\n1,6,6\n");
    let good_locs = write(dir.path(), "l.csv", b"frame,x,y,score\n0,5,5,1\n1,6,6,1\n");
    let one_line = write(dir.path(), "one-line.csv", &long);
    let mut second = b"frame,x,y\n0,5,5\n".to_vec();
    second.extend_from_slice(&long);
    let second_line = write(dir.path(), "second-line.csv", &second);
    let mut quoted = b"frame,x,y,score,note\n0,5,5,1,\"".to_vec();
    quoted.extend(b"ab\n".repeat(1 << 19));
    quoted.extend_from_slice(b"\"\n");
    let quoted = write(dir.path(), "quoted.csv", &quoted);
    for (truth, locs, file, line) in [
        (&one_line, &good_locs, "one-line.csv", "line 1"),
        (&second_line, &good_locs, "second-line.csv", "line 3"),
        (&good_truth, &one_line, "one-line.csv", "line 1"),
        (&good_truth, &quoted, "quoted.csv", "line"),
    ] {
        let output = scanloc(&["score", "--truth", truth, "--locs", locs]);
        assert_refused(&output, &[file, line, "longer than"]);
    }
    // The tracking commands' tables are bounded alike (the tracks reader
    // held a whole 300 MB cell in memory and quoted it back in its error).
    let good_tracks = write(
        dir.path(),
        "tracks.csv",
        b"frame,x,y,particle\n0,5,5,0\n1,6,6,0\n2,6,7,0\n",
    );
    let mut tracks_row = b"frame,x,y,particle\n0,5,5,".to_vec();
    tracks_row.extend_from_slice(&long);
    let tracks_row = write(dir.path(), "tracks-row.csv", &tracks_row);
    let out = dir.path().join("out.csv");
    let out = out.to_str().unwrap();
    for (args, file, line) in [
        (
            vec!["diffusion", "--tracks", &tracks_row],
            "tracks-row.csv",
            "line 2",
        ),
        (
            vec![
                "link",
                "--locs",
                &one_line,
                "--search-range",
                "3",
                "--out",
                out,
            ],
            "one-line.csv",
            "line 1",
        ),
        (
            vec![
                "score-tracks",
                "--tracks",
                &good_tracks,
                "--truth",
                &one_line,
            ],
            "one-line.csv",
            "line 1",
        ),
    ] {
        assert_refused(&scanloc(&args), &[file, line, "longer than"]);
    }
}

#[test]
fn score_bounds_its_radii_as_a_manifest_does() {
    let dir = tempfile::tempdir().unwrap();
    let truth = write(dir.path(), "t.csv", b"frame,x,y\n0,5,5\n");
    let locs = write(dir.path(), "l.csv", b"frame,x,y,score\n0,5,5,1\n");
    let many: Vec<String> = (1..=33).map(|r| r.to_string()).collect();
    let many = many.join(",");
    for (eps, needle) in [
        (
            "1e300",
            "--eps: must be a positive number of pixels (at most 1e6), got 1e300",
        ),
        (&many[..], "--eps: at most 32 radii, got 33"),
    ] {
        let output = scanloc(&["score", "--truth", &truth, "--locs", &locs, "--eps", eps]);
        assert_refused(&output, &[needle]);
    }
}

#[test]
fn a_bad_cell_is_quoted_short_and_a_column_named_twice_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let long = "9".repeat(500_000);
    let out = dir.path().join("out.csv");
    let out = out.to_str().unwrap();
    let tracks = write(
        dir.path(),
        "long-cell.csv",
        format!("frame,x,y,particle\n0,1,1,{long}x\n").as_bytes(),
    );
    let locs = write(
        dir.path(),
        "long-x.csv",
        format!("frame,x,y\n0,{long}x,1\n").as_bytes(),
    );
    for (args, file, column) in [
        (
            vec!["diffusion", "--tracks", &tracks],
            "long-cell.csv",
            "particle",
        ),
        (
            vec!["link", "--locs", &locs, "--search-range", "3", "--out", out],
            "long-x.csv",
            "x",
        ),
    ] {
        let output = scanloc(&args);
        assert_refused(&output, &[file, column, "\"999", "…"]);
        assert!(stderr(&output).len() < 300, "{:.300}", stderr(&output));
    }
    // Which of two columns of one name a reader took was a guess: the
    // first, silently.
    let twice_tracks = write(
        dir.path(),
        "twice-tracks.csv",
        b"frame,x,y,particle,particle\n0,1,1,3,4\n1,1,1,3,4\n2,1,2,3,4\n",
    );
    let twice_locs = write(dir.path(), "twice-locs.csv", b"frame,x,y,x\n0,1,1,5\n");
    let twice_truth = write(dir.path(), "twice-truth.csv", b"frame,x,y, y\n0,1,1,2\n");
    let good_locs = write(dir.path(), "l.csv", b"frame,x,y,score\n0,5,5,1\n");
    for (args, file, column) in [
        (
            vec!["diffusion", "--tracks", &twice_tracks],
            "twice-tracks.csv",
            "\"particle\" appears twice in the header (columns 4 and 5)",
        ),
        (
            vec![
                "link",
                "--locs",
                &twice_locs,
                "--search-range",
                "3",
                "--out",
                out,
            ],
            "twice-locs.csv",
            "\"x\" appears twice in the header (columns 2 and 4)",
        ),
        (
            vec!["score", "--truth", &twice_truth, "--locs", &good_locs],
            "twice-truth.csv",
            "\"y\" appears twice",
        ),
    ] {
        assert_refused(&scanloc(&args), &[file, column]);
    }
    assert!(!Path::new(out).exists());
    // An unnamed column, as pandas writes its index, is no name at all.
    let indexed = write(dir.path(), "indexed.csv", b",frame,x,y\n0,0,1,1\n1,1,2,1\n");
    let output = scanloc(&[
        "link",
        "--locs",
        &indexed,
        "--search-range",
        "3",
        "--out",
        out,
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
}

/// Truth and predictions on frames `frames` (one QD and one prediction
/// per frame, every third missed by 1.5 px).
fn scored_set(dir: &Path, frames: impl Iterator<Item = usize>) -> (String, String) {
    let (mut truth, mut locs) = (
        String::from("frame,x,y\n"),
        String::from("frame,x,y,score\n"),
    );
    for (i, frame) in frames.enumerate() {
        truth.push_str(&format!("{frame},10,10\n"));
        let dx = if i % 3 == 0 { 1.5 } else { 0.2 };
        locs.push_str(&format!(
            "{frame},{},10,{}\n",
            10.0 + dx,
            1.0 / (i + 2) as f64
        ));
    }
    (
        write(dir, "truth.csv", truth.as_bytes()),
        write(dir, "locs.csv", locs.as_bytes()),
    )
}

fn bootstrap_spread(truth: &str, locs: &str, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "score",
        "--truth",
        truth,
        "--locs",
        locs,
        "--bootstrap",
        "--resamples",
        "300",
        "--json",
    ];
    args.extend_from_slice(extra);
    let output = scanloc(&args);
    assert!(output.status.success(), "{}", stderr(&output));
    let value: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    value["spread"].clone()
}

#[test]
fn the_bootstrap_resamples_frames_with_data_only() {
    let dir = tempfile::tempdir().unwrap();
    let (truth, locs) = scored_set(dir.path(), 0..40);
    let compact = bootstrap_spread(&truth, &locs, &[]);
    assert_eq!(compact[0]["resamples"], 300);
    // The same data among millions of empty frames (up to the largest
    // frame number a file may hold): the same draws, the same figures.
    for frames in ["41", "1000000", "10000000"] {
        let spread = bootstrap_spread(&truth, &locs, &["--frames", frames]);
        assert_eq!(spread, compact, "--frames {frames}");
    }
    // The same data on far-apart frame numbers, up to 9,999,999.
    let dir = tempfile::tempdir().unwrap();
    let far = (0..39).map(|i| i * 250_000).chain([9_999_999]);
    let (truth, locs) = scored_set(dir.path(), far);
    assert_eq!(bootstrap_spread(&truth, &locs, &[]), compact);
}

#[test]
fn the_likelihood_refuses_a_diffusion_beyond_any_liquid_and_writes_finite_positions() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("f.npy");
    let locs = dir.path().join("l.csv");
    let output = scanloc(&[
        "simulate",
        "--frames",
        "2",
        "--height",
        "12",
        "--width",
        "12",
        "--margin-px",
        "3",
        "--out",
        frames.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let locate = |extra: &[&str]| {
        let mut args = vec![
            "locate",
            "--method",
            "likelihood",
            "--particles",
            "64",
            "--margin-px",
            "3",
            "--input",
            frames.to_str().unwrap(),
            "--out",
            locs.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        scanloc(&args)
    };
    for (flag, value) in [
        ("--diffusion", "1e300"),
        ("--diffusion", "uniform:0,1e308"),
        ("--diffusion", "1000.001"),
        ("--diffusion", "uniform:0.75,5e3"),
        ("--diffusion", "inf"),
        ("--brightness", "uniform:0,1e308"),
        ("--brightness", "1e300"),
    ] {
        let output = locate(&[flag, value]);
        let field = &flag[2..];
        assert_refused(&output, &[field]);
        assert!(!locs.exists(), "{flag} {value}");
    }
    // The largest D accepted still gives finite positions.
    for diffusion in ["1000", "uniform:0,1000", "1"] {
        let output = locate(&["--diffusion", diffusion]);
        assert!(output.status.success(), "{diffusion}: {}", stderr(&output));
        let predictions = scanloc::io::csv_tables::read_predictions(&locs).unwrap();
        assert_eq!(predictions.len(), 2);
        for p in predictions {
            assert!(
                p.x.is_finite() && p.y.is_finite() && p.score.is_finite(),
                "{p:?}"
            );
        }
    }
}

#[test]
fn headroom_figures_stay_in_range_whatever_the_rounding() {
    use scanloc::metrics::score;
    use scanloc::types::{Prediction, TruthRow};
    // Every top prediction within ε (ε = 50 px): oracle = random, so no
    // share; with frames missed too (G > n), and with mass-like scores.
    for truths in (1..=64).chain([97, 1000, 4099]) {
        for missed in [0, truths / 3] {
            let truth: Vec<TruthRow> = (0..truths)
                .map(|f| TruthRow::stationary(f, 10.0, 10.0))
                .collect();
            let predictions: Vec<Prediction> = (missed..truths)
                .map(|f| {
                    Prediction::new(
                        f,
                        10.0 + (f % 7) as f64,
                        10.0,
                        1000.0 + (f * 37 % 101) as f64,
                    )
                })
                .collect();
            let result = score(&predictions, &truth, truths, &[1.0, 50.0], false).unwrap();
            for per_eps in &result.per_eps {
                let h = per_eps.headroom.unwrap();
                assert!((0.0..=1.0).contains(&h.oracle_auc), "{truths}: {h:?}");
                assert!(
                    (0.0..=h.oracle_auc).contains(&h.random_auc),
                    "{truths}: {h:?}"
                );
                if let Some(share) = h.share_used {
                    assert!(share.is_finite() && share.abs() < 1e6, "{truths}: {h:?}");
                }
                if per_eps.eps_px == 50.0 {
                    assert_eq!(h.share_used, None, "{truths}: {h:?}");
                    let expected = (truths - missed) as f64 / truths as f64;
                    assert_eq!(h.oracle_auc, expected, "{truths}");
                }
            }
        }
    }
}

#[test]
fn headroom_in_score_output_is_n_a_without_headroom() {
    let dir = tempfile::tempdir().unwrap();
    let (truth, locs) = scored_set(dir.path(), 0..300);
    let output = scanloc(&[
        "score", "--truth", &truth, "--locs", &locs, "--eps", "50", "--json",
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let value: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let headroom = &value["per_eps"][0]["headroom"];
    assert!(
        headroom["oracle_auc"].as_f64().unwrap() <= 1.0,
        "{headroom}"
    );
    assert!(headroom["share_used"].is_null(), "{headroom}");
    let output = scanloc(&["score", "--truth", &truth, "--locs", &locs, "--eps", "50"]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("n/a"), "{}", stdout(&output));
}

#[test]
fn sweep_axes_on_one_path_are_refused_by_check_and_run() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let blocks = [
        "  a: {path: datasets.a.frames, values: [2, 3]}\n  b: {path: datasets.a.frames, values: [4]}\n",
        "  a: {path: detectors.trackpy.crocker_grier.diameter, values: [5]}\n  b: {path: detectors.trackpy.crocker_grier.diameter, values: [7]}\n",
        "  a: {path: detectors.trackpy.crocker_grier, values: [{diameter: 5}]}\n  b: {path: detectors.trackpy.crocker_grier.diameter, values: [7]}\n",
    ];
    for (i, block) in blocks.iter().enumerate() {
        let manifest = write_manifest(
            dir.path(),
            &format!("s{i}.yaml"),
            &format!("{TINY}sweep:\n{block}"),
        );
        let manifest = manifest.to_str().unwrap();
        assert_refused(
            &scanloc(&["check", manifest]),
            &["sweep.a.path", "sweep.b.path"],
        );
        let output = scanloc(&["run", manifest, "--registry", registry.to_str().unwrap()]);
        assert_refused(&output, &["sweep.a.path", "sweep.b.path"]);
        assert!(!registry.exists(), "run touched the registry");
    }
    let fine = format!(
        "{TINY}sweep:\n  a: {{path: datasets.a.frames, values: [2, 3]}}\n  b: {{path: detectors.trackpy.crocker_grier.diameter, values: [5]}}\n"
    );
    let manifest = write_manifest(dir.path(), "fine.yaml", &fine);
    assert!(
        scanloc(&["check", manifest.to_str().unwrap()])
            .status
            .success()
    );
}

#[test]
fn absurd_thread_counts_are_refused_and_odd_fonts_are_not_read() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("f.npy");
    let output = scanloc(&[
        "simulate",
        "--frames",
        "2",
        "--out",
        frames.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let locs = dir.path().join("l.csv");
    let locate = [
        "locate",
        "--method",
        "crocker-grier",
        "--diameter",
        "7",
        "--input",
        frames.to_str().unwrap(),
        "--out",
        locs.to_str().unwrap(),
    ];
    let limit = Duration::from_secs(60);
    for threads in ["1000000000", "1025", "18446744073709551616"] {
        let output = scanloc_with_env(&locate, RAYON_NUM_THREADS, threads, limit);
        assert_refused(&output, &[RAYON_NUM_THREADS, "at most 1024"]);
    }
    for threads in ["3", "0", "not-a-number"] {
        let output = scanloc_with_env(&locate, RAYON_NUM_THREADS, threads, limit);
        assert!(output.status.success(), "{threads}: {}", stderr(&output));
    }

    let (registry, run) = registry_with_a_run(dir.path());
    let fifo = dir.path().join("font.fifo");
    let name = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
    // SAFETY: a valid NUL-terminated path; mkfifo only creates a file.
    assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
    for (i, font) in ["/dev/zero", fifo.to_str().unwrap(), "/"]
        .iter()
        .enumerate()
    {
        let out = dir.path().join(format!("report-{i}"));
        let args = [
            "report",
            &run,
            "--registry",
            registry.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        let output = scanloc_with_env(&args, SCANLOC_FONT, font, limit);
        assert!(output.status.success(), "{font}: {}", stderr(&output));
        assert!(
            stderr(&output).contains("not a regular file"),
            "{}",
            stderr(&output)
        );
        assert!(out.join("report.md").is_file());
    }
}
