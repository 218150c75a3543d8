//! `scanloc link`: the TrackPy linker against TrackPy 0.7's own
//! trajectories (fixtures made by tests/fixtures/trackpy/make_link_fixtures.py),
//! the LAP linker's gap closing, and bad input.

use std::path::{Path, PathBuf};

use scanloc::bench::link::read_reference_labels;
use scanloc::io::localisation_table::read_localisation_table;
use scanloc::track::lap::{self, LapParams};
use scanloc::track::trackpy::{self, TrackpyParams};
use scanloc::track::{Detection, detections, same_partition};

use crate::common::{root, scanloc, stderr};

fn fixture(name: &str) -> PathBuf {
    root().join("tests/fixtures/trackpy").join(name)
}

/// (name, search range, memory) of every committed case.
fn cases() -> Vec<(String, f64, usize)> {
    let mut reader = csv::Reader::from_path(fixture("link_cases.csv")).expect("link_cases.csv");
    reader
        .records()
        .map(|r| {
            let r = r.expect("a case row");
            (
                r[0].to_string(),
                r[1].parse().unwrap(),
                r[2].parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn the_trackpy_linker_gives_trackpys_trajectories_on_its_fixtures() {
    let cases = cases();
    assert!(cases.iter().any(|c| c.2 == 0) && cases.iter().any(|c| c.2 > 0));
    for (name, search_range, memory) in cases {
        let locs = fixture(&format!("link_{name}_locs.csv"));
        let table = read_localisation_table(&locs).unwrap();
        let detections = detections(&table);
        let params = TrackpyParams {
            search_range,
            memory,
        };
        let linked = trackpy::link(&detections, &params).unwrap();
        let reference = read_reference_labels(
            &fixture(&format!("link_{name}_tracks.csv")),
            detections.len(),
        )
        .unwrap();
        assert!(
            same_partition(&linked.particle, &reference),
            "{name}: trajectories differ from TrackPy's"
        );
        // The fixture exercises what it is for: subnetworks to resolve, and
        // with memory, links over missing frames.
        assert!(linked.stats.contested > 0, "{name}: no subnetwork");
        if memory > 0 {
            assert!(linked.stats.gap_links > 0, "{name}: no link over a gap");
        }
    }
}

#[test]
fn the_command_sorts_unsorted_input_and_appends_particle() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("tracks.csv");
    let (name, search_range, memory) = cases()
        .into_iter()
        .find(|c| c.0 == "shuffled_m3")
        .expect("the shuffled case");
    let locs = fixture(&format!("link_{name}_locs.csv"));
    let run = scanloc(&[
        "link",
        "--locs",
        &locs.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
        "--search-range",
        &search_range.to_string(),
        "--memory",
        &memory.to_string(),
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    let input = read_localisation_table(&locs).unwrap();
    let output = read_localisation_table(&out).unwrap();
    let header: Vec<&str> = output.header.iter().collect();
    assert_eq!(header, ["frame", "x", "y", "mass", "particle"]);
    assert!(output.frames.is_sorted(), "rows not sorted by frame");
    // Each output row is an input row (same text); map it back to compare
    // the trajectories with TrackPy's.
    let row_of = |record: &csv::StringRecord| {
        let key: Vec<&str> = record.iter().take(4).collect();
        input
            .records
            .iter()
            .position(|r| r.iter().collect::<Vec<_>>() == key)
            .expect("an input row")
    };
    let particle = output.whole_numbers("particle", "out").unwrap();
    let mut labels = vec![usize::MAX; input.records.len()];
    for (record, label) in output.records.iter().zip(particle) {
        labels[row_of(record)] = label;
    }
    let reference = read_reference_labels(
        &fixture(&format!("link_{name}_tracks.csv")),
        input.records.len(),
    )
    .unwrap();
    assert!(same_partition(&labels, &reference));
}

/// Particle A blinks off for frames 3 and 4; C appears at frame 4 near A's
/// last position and moves away; A is back at frame 5 where it was. B is
/// far away throughout. Labels: the true particle of each detection.
fn blinking_case() -> (Vec<Detection>, Vec<usize>) {
    let a = [
        (0, 10.0, 10.0),
        (1, 10.5, 10.0),
        (2, 10.2, 10.3),
        (5, 10.4, 10.1),
        (6, 10.8, 10.2),
        (7, 11.0, 10.0),
    ];
    let c = [
        (4, 12.6, 10.0),
        (5, 14.0, 10.2),
        (6, 15.2, 10.0),
        (7, 16.5, 10.1),
    ];
    let b: Vec<(usize, f64, f64)> = (0..8).map(|f| (f, 30.0 + 0.3 * f as f64, 30.0)).collect();
    let mut detections = Vec::new();
    let mut truth = Vec::new();
    for (label, walk) in [(0, &a[..]), (1, &b[..]), (2, &c[..])] {
        for &(frame, x, y) in walk {
            detections.push(Detection::new(frame, x, y));
            truth.push(label);
        }
    }
    (detections, truth)
}

#[test]
fn gap_closing_recovers_the_blink_that_memory_linking_misses() {
    let (detections, truth) = blinking_case();
    // TrackPy's memory links A's remembered position to C, the first
    // detection near it, and A's return starts a new trajectory.
    let memory = trackpy::link(
        &detections,
        &TrackpyParams {
            search_range: 4.0,
            memory: 3,
        },
    )
    .unwrap();
    assert!(!same_partition(&memory.particle, &truth));
    let c_start = 14; // A (6 detections), B (8), then C's first.
    let a_end = 2;
    assert_eq!(memory.particle[a_end], memory.particle[c_start]);
    // The LAP's gap closing weighs both reappearances at once.
    let gaps = lap::link(&detections, &LapParams::from_search_range(4.0, 3)).unwrap();
    assert!(
        same_partition(&gaps.particle, &truth),
        "{:?}",
        gaps.particle
    );
    assert_eq!(gaps.stats.gap_links, 1);
    // Without gap closing the blink stays two trajectories.
    let no_gaps = lap::link(&detections, &LapParams::from_search_range(4.0, 0)).unwrap();
    assert_ne!(no_gaps.particle[a_end], no_gaps.particle[3]);
}

#[test]
fn the_lap_linker_uses_the_localisation_uncertainty() {
    // One source, two destinations 1.5 px along x and 2 px along y: without
    // σ the nearer wins; with the source and the farther one uncertain along
    // y, the farther one's displacement is the likelier (cost 2.41 against
    // 2.92, see track::lap's formula).
    let sigma = |x: f64, y: f64| Some(scanloc::types::LocalisationSigma { x, y });
    let mut detections = vec![
        Detection::new(0, 0.0, 0.0),
        Detection::new(1, 1.5, 0.0),
        Detection::new(1, 0.0, 2.0),
    ];
    let params = LapParams::from_search_range(3.0, 0);
    let plain = lap::link(&detections, &params).unwrap();
    assert_eq!(plain.particle[0], plain.particle[1]);
    detections[0].sigma = sigma(0.1, 1.0);
    detections[1].sigma = sigma(0.1, 0.1);
    detections[2].sigma = sigma(0.1, 1.5);
    let weighted = lap::link(&detections, &params).unwrap();
    assert_eq!(weighted.particle[0], weighted.particle[2]);
}

#[test]
fn the_lap_command_writes_each_links_gate_and_diffusion_uses_it() {
    // Two particles' rows; each link's gate is g·√v per axis with v = q
    // (no σ): 3 × (R/3) = R for a one-frame link, R·√2 over one missing
    // frame; a trajectory's first row has none.
    let dir = tempfile::tempdir().unwrap();
    let (locs, out) = (dir.path().join("locs.csv"), dir.path().join("tracks.csv"));
    std::fs::write(&locs, "frame,x,y\n0,1,1\n0,20,20\n1,2,1\n1,20,21\n3,3,2\n").unwrap();
    let run = scanloc(&[
        "link",
        "--linker",
        "lap",
        "--locs",
        &locs.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
        "--search-range",
        "6",
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    let text = std::fs::read_to_string(&out).unwrap();
    let r2 = (6.0f64 * 2f64.sqrt()).to_string();
    let expected = format!(
        "frame,x,y,gate_x,gate_y,particle\n0,1,1,,,0\n0,20,20,,,1\n1,2,1,6,6,0\n1,20,21,6,6,1\n3,3,2,{r2},{r2},0\n"
    );
    assert_eq!(text, expected);
    // The tracks table reads back with its gates; a gate ≤ 0 is refused.
    let tracks = scanloc::io::tracks::read_tracks(&out).unwrap();
    assert_eq!(tracks[0].points[0].gate, None);
    assert_eq!(tracks[0].points[1].gate, Some((6.0, 6.0)));
    let bad = dir.path().join("bad.csv");
    std::fs::write(
        &bad,
        "frame,x,y,gate_x,gate_y,particle\n0,1,1,,,0\n1,2,1,0,6,0\n",
    )
    .unwrap();
    let err = scanloc::io::tracks::read_tracks(&bad)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("bad.csv") && err.contains("row 2") && err.contains("gate_x"),
        "{err}"
    );
    // `scanloc diffusion` takes a share of the gate up to 1/√2, or 1.
    for (share, code) in [("0.5", 0), ("1", 0), ("0.8", 2), ("0", 2)] {
        let (got, _, err) = crate::common::cli_in_process(&[
            "diffusion",
            "--tracks",
            out.to_str().unwrap(),
            "--ensemble-gate",
            share,
        ]);
        assert_eq!(got, code, "--ensemble-gate {share}: {err}");
        if code == 2 {
            assert!(
                err.contains("--ensemble-gate") && err.trim().lines().count() == 1,
                "{err}"
            );
        }
    }
}

/// Runs `scanloc link` on a table with `text`, expecting a one-line refusal
/// (exit 2) that names the file and contains `expected`, and no output.
fn refused(text: &[u8], expected: &str) {
    refused_with(text, &[], expected);
}

/// [`refused`] with `extra` flags.
fn refused_with(text: &[u8], extra: &[&str], expected: &str) {
    let (message, locs) = link_refusal(text, extra);
    assert!(
        message.contains(&locs) && message.contains(expected),
        "{message}"
    );
}

/// Runs `scanloc link` on a table with `text` and `flags`, expecting a
/// one-line refusal (exit 2) containing `expected`, and no output.
fn refused_flags(text: &[u8], flags: &[&str], expected: &str) {
    let (message, _) = link_refusal(text, flags);
    assert!(message.contains(expected), "{flags:?}: {message}");
}

/// Runs `scanloc link` on a table with `text` and `flags` (with
/// `--search-range 3` unless they give the step), asserting a one-line
/// refusal with exit code 2 and no output: the message and the table's path.
fn link_refusal(text: &[u8], flags: &[&str]) -> (String, String) {
    let dir = tempfile::tempdir().unwrap();
    let locs = dir.path().join("locs.csv");
    let out = dir.path().join("tracks.csv");
    std::fs::write(&locs, text).unwrap();
    let (locs_arg, out_arg) = (locs.to_string_lossy(), out.to_string_lossy());
    let mut args = vec!["link", "--locs", &locs_arg, "--out", &out_arg];
    if !flags.contains(&"--search-range") && !flags.contains(&"--diffusion") {
        args.extend(["--search-range", "3"]);
    }
    args.extend_from_slice(flags);
    let run = scanloc(&args);
    let message = stderr(&run);
    assert_eq!(run.status.code(), Some(2), "{flags:?}: {message}");
    assert_eq!(message.lines().count(), 1, "{message}");
    assert!(!Path::new(&out).exists());
    (message, locs_arg.into_owned())
}

#[test]
fn bad_input_is_one_line_and_exit_2() {
    refused(b"frame,x\n0,1\n", "missing column(s) y");
    refused(
        b"frame,x,y\n0,1,NaN\n",
        "row 1: y: expected a finite number",
    );
    refused(
        b"frame,x,y\n-1,1,1\n",
        "row 1: frame: expected a whole number",
    );
    refused(
        b"frame,x,y\n0.5,1,1\n",
        "row 1: frame: expected a whole number",
    );
    refused(b"frame,x,y\n0,1,1\n1,2\n", "row 2");
    // --min-score needs a score column of numbers.
    refused_with(
        b"frame,x,y\n0,1,1\n",
        &["--min-score", "0.3"],
        "no score column",
    );
    refused_with(
        b"frame,x,y,score\n0,1,1,0.5\n1,1,1,NaN\n",
        &["--min-score", "0.3"],
        "row 2: score: expected a number",
    );
    // Settings beyond any recording: squared in a link's cost, they
    // overflowed it, and lap linked nothing (exit 0).
    let one = b"frame,x,y\n0,1,1\n1,2,2\n";
    for (flags, expected) in [
        (
            &["--search-range", "1e300"][..],
            "--search-range: must be at most 1e9",
        ),
        (
            &["--linker", "lap", "--gate", "1e300"],
            "--gate: must be at most 1e3",
        ),
        (
            &[
                "--linker",
                "lap",
                "--diffusion",
                "1e300",
                "--frame-time-ms",
                "27.6",
                "--pixel-size-um",
                "0.07",
            ],
            "--diffusion: must be at most 1e6",
        ),
        (
            &[
                "--linker",
                "lap",
                "--diffusion",
                "1",
                "--frame-time-ms",
                "1e300",
                "--pixel-size-um",
                "0.07",
            ],
            "step variance",
        ),
    ] {
        refused_flags(one, flags, expected);
    }
    // Not a table at all: the bytes of a .npy file.
    refused(
        b"\x93NUMPY\x01\x00v\x00{'descr': '<u2'}\n\xff\xfe\x00",
        "locs.csv",
    );
}

#[test]
fn a_search_range_that_joins_thousands_into_one_problem_is_refused_not_allocated() {
    // Two frames of 5,001 localisations along a line 1 px apart, the
    // second shifted by 0.2 px: with a search range of 3 every
    // localisation reaches its neighbours', so all 10,002 form one
    // connected assignment problem (a dense matrix of 0.8 GB beyond the
    // limit), for both linkers. With a range of 0.6 each problem is a pair.
    let mut text = String::from("frame,x,y\n");
    for frame in 0..2 {
        for i in 0..5_001 {
            text.push_str(&format!("{frame},{},1\n", i as f64 + 0.2 * frame as f64));
        }
    }
    for linker in ["trackpy", "lap"] {
        refused_with(
            text.as_bytes(),
            &["--linker", linker],
            "one connected assignment problem",
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let (locs, out) = (dir.path().join("locs.csv"), dir.path().join("tracks.csv"));
    std::fs::write(&locs, &text).unwrap();
    let run = scanloc(&[
        "link",
        "--locs",
        &locs.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
        "--search-range",
        "0.6",
        "--linker",
        "lap",
    ]);
    assert_eq!(run.status.code(), Some(0), "{}", stderr(&run));
}
