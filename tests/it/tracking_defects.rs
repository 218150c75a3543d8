//! The defects of issue 64 in the tracking commands, one test each (the
//! class of each, not only the example the issue gave).

use std::path::{Path, PathBuf};

use crate::common::cli_in_process;

/// A small localisation table (two particles over four frames).
const LOCS: &str = "frame,x,y,score\n0,5,5,0.9\n0,15,15,0.2\n1,5.5,5.2,0.9\n1,15.3,15.1,0.9\n\
                    2,5.9,5.1,0.1\n2,15.1,15.4,0.9\n3,6.1,5.3,0.9\n3,15.2,15.9,0.9\n";

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// The ways an output can name an input: the same path, the same path
/// spelled through `.`, a hard link and a symbolic link to it.
fn aliases(dir: &Path, input: &Path, tag: &str) -> Vec<PathBuf> {
    let dotted = dir.join(".").join(input.file_name().unwrap());
    let hard = dir.join(format!("hard-{tag}"));
    std::fs::hard_link(input, &hard).unwrap();
    let mut all = vec![input.to_path_buf(), dotted, hard];
    #[cfg(unix)]
    {
        let soft = dir.join(format!("soft-{tag}"));
        std::os::unix::fs::symlink(input, &soft).unwrap();
        all.push(soft);
    }
    all
}

/// Every command that writes a file, each with an output naming one of its
/// inputs (same path, `./`, hard link, symlink), is refused with exit 2 and
/// leaves the input byte for byte as it was.
#[test]
fn every_writing_command_refuses_an_output_that_is_or_links_to_an_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let locs = d.join("locs.csv");
    std::fs::write(&locs, LOCS).unwrap();
    let truth = d.join("truth.csv");
    std::fs::write(&truth, "frame,x,y\n0,5,5\n1,15,15\n").unwrap();
    let compare = d.join("compare.csv");
    std::fs::write(&compare, LOCS).unwrap();
    let frames = d.join("frames.npy");
    let (code, _, err) = cli_in_process(&[
        "simulate",
        "--frames",
        "2",
        "--seed",
        "1",
        "--out",
        text(&frames),
    ]);
    assert_eq!(code, 0, "{err}");
    let sim_out = d.join("sim.npy");
    let rec_out = d.join("rec.npy");
    std::fs::write(&sim_out, b"frames").unwrap();
    std::fs::write(&rec_out, b"frames").unwrap();

    // (command line with OUT for the output, the input it names)
    type Case = (Vec<String>, PathBuf);
    let owned = |args: &[&str]| args.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let mut cases: Vec<Case> = Vec::new();
    for extra in [
        &["--search-range", "3"][..],
        &["--search-range", "3", "--min-score", "0.5"],
        &["--linker", "lap", "--search-range", "3"],
    ] {
        let mut args = owned(&["link", "--locs", text(&locs), "--out", "OUT"]);
        args.extend(owned(extra));
        cases.push((args, locs.clone()));
    }
    cases.push((
        owned(&["locate", "--input", text(&frames), "--out", "OUT"]),
        frames.clone(),
    ));
    for input in [&truth, &locs, &compare] {
        cases.push((
            owned(&[
                "score",
                "--truth",
                text(&truth),
                "--locs",
                text(&locs),
                "--compare",
                text(&compare),
                "--curve",
                "OUT",
            ]),
            input.clone(),
        ));
    }
    // The simulators' two outputs, each the other.
    cases.push((
        owned(&[
            "simulate",
            "--frames",
            "1",
            "--out",
            text(&sim_out),
            "--truth",
            "OUT",
        ]),
        sim_out.clone(),
    ));
    cases.push((
        owned(&[
            "simulate-recording",
            "--frames",
            "2",
            "--out",
            text(&rec_out),
            "--truth",
            "OUT",
        ]),
        rec_out.clone(),
    ));

    for (index, (args, input)) in cases.iter().enumerate() {
        let before = std::fs::read(input).unwrap();
        for alias in aliases(d, input, &index.to_string()) {
            let args: Vec<&str> = args
                .iter()
                .map(|a| if a == "OUT" { text(&alias) } else { a.as_str() })
                .collect();
            let (code, out, err) = cli_in_process(&args);
            assert_eq!(code, 2, "{args:?} not refused: {out}{err}");
            assert_eq!(err.trim().lines().count(), 1, "{args:?}: one line: {err}");
            assert_eq!(
                std::fs::read(input).unwrap(),
                before,
                "{args:?} modified its input"
            );
        }
    }
}

/// A tracks table of `particles` straight walks of `frames` frames from
/// (`x0`, `y0`), `step` px a frame along x.
fn walks(particles: usize, frames: usize, x0: f64, y0: f64, step: f64) -> String {
    let mut text = String::from("frame,x,y,particle\n");
    for particle in 0..particles {
        for frame in 0..frames {
            // A small zig-zag so that no estimator sees a degenerate track.
            let wiggle = if (frame + particle) % 2 == 0 {
                0.3
            } else {
                -0.3
            };
            text.push_str(&format!(
                "{frame},{},{},{particle}\n",
                x0 + step * frame as f64 + wiggle,
                y0 + particle as f64 - wiggle
            ));
        }
    }
    text
}

/// `diffusion` refuses tracks that cannot come from the field it is told
/// (a 64 × 64 recording's tracks analysed as the default 24 × 25 field,
/// positions of 1e150 px) and time stamps off the frame clock: exit 2, one
/// line naming the file and the column, nothing on stdout.
#[test]
fn diffusion_refuses_tracks_from_another_field_or_clock() {
    let dir = tempfile::tempdir().unwrap();
    let tracks = dir.path().join("tracks.csv");
    // Inside the 64 × 64 field, far outside the 24 × 25 one.
    std::fs::write(&tracks, walks(4, 30, 10.0, 40.0, 0.5)).unwrap();
    let (code, out, err) = cli_in_process(&["diffusion", "--tracks", text(&tracks)]);
    assert_eq!(code, 2, "{out}{err}");
    assert!(out.is_empty(), "{out}");
    assert!(
        err.contains("tracks.csv") && err.contains("column y"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    let (code, out, err) = cli_in_process(&[
        "diffusion",
        "--tracks",
        text(&tracks),
        "--height",
        "64",
        "--width",
        "64",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(out.lines().any(|l| l.starts_with("ensemble,")), "{out}");

    let huge = dir.path().join("huge.csv");
    std::fs::write(&huge, walks(3, 10, 1e150, 5.0, 1e149)).unwrap();
    let (code, out, err) = cli_in_process(&["diffusion", "--tracks", text(&huge)]);
    assert_eq!(code, 2, "{out}{err}");
    assert!(err.contains("column x") && err.contains("1e150"), "{err}");
    assert!(err.len() < 300, "a short message: {err}");

    // Time stamps 10 s apart for consecutive frames of a 27.6 ms clock.
    let timed = dir.path().join("timed.csv");
    let mut table = String::from("frame,x,y,particle,time\n");
    for frame in 0..10 {
        table.push_str(&format!(
            "{frame},{},5,0,{}\n",
            5.0 + 0.1 * frame as f64,
            10.0 * frame as f64
        ));
    }
    std::fs::write(&timed, table).unwrap();
    let (code, out, err) = cli_in_process(&["diffusion", "--tracks", text(&timed)]);
    assert_eq!(code, 2, "{out}{err}");
    assert!(
        err.contains("column time") && err.contains("frame clock"),
        "{err}"
    );
}

/// `simulate-recording` checks only the bounds of the mode it runs: a set
/// QD count does not fail on the density bound of a volume it does not
/// draw from; the same in a manifest's recording.
#[test]
fn a_set_qd_count_is_not_refused_by_the_density_bound() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec.npy");
    let (code, _, err) = cli_in_process(&[
        "simulate-recording",
        "--frames",
        "2",
        "--qd-count",
        "5",
        "--margin-um",
        "100",
        "--out",
        text(&out),
    ]);
    assert_eq!(code, 0, "{err}");
    // The density bound still holds where the density is used.
    let (code, _, err) = cli_in_process(&[
        "simulate-recording",
        "--frames",
        "2",
        "--margin-um",
        "100",
        "--qd-density",
        "10",
        "--out",
        text(&out),
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("qd_density"), "{err}");
    let manifest = dir.path().join("m.yaml");
    std::fs::write(
        &manifest,
        "name: t\nseed: 1\nrecordings:\n  r: {frames: 2, qd_count: 5, lateral_margin_um: 100}\n",
    )
    .unwrap();
    let (code, _, err) = cli_in_process(&["check", text(&manifest)]);
    assert_eq!(code, 0, "{err}");
}

/// The peak memory of `scanloc ARGS` (maximum resident set), in bytes.
#[cfg(target_os = "linux")]
#[allow(clippy::zombie_processes)] // reaped by wait4, which also gives its peak
fn peak_bytes(args: &[&str]) -> u64 {
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(args)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut status = 0;
    // SAFETY: an all-zero rusage is a valid value for wait4 to fill.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: waits for our own child, which has not been waited for.
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as i32);
    assert_eq!(status, 0, "scanloc {args:?} failed");
    usage.ru_maxrss as u64 * 1024
}

/// `simulate-recording`'s memory estimate, which `check_memory` compares
/// with the machine's, is not below the peak it measures on a mid-sized
/// recording (98 MB of counts), nor far above it.
///
/// Run alone (`cargo test --release --test it -- --ignored
/// the_recordings_memory`): a child spawned from the test process reports
/// as its peak the larger of its own and the test process's resident memory
/// at the spawn (the spawn shares the parent's memory until `exec`), so
/// beside the other tests, whose memory comes and goes, the figure is the
/// harness's, not the command's. Alone, the one-frame baseline is 20 MB.
#[cfg(target_os = "linux")]
#[test]
#[ignore = "measures a child's peak memory: run alone (see its doc)"]
fn the_recordings_memory_estimate_covers_its_measured_peak() {
    use scanloc::sim::SimParams;
    use scanloc::sim::recording::RecordingParams;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec.npy");
    let truth = dir.path().join("truth.csv");
    let run = |frames: usize| {
        peak_bytes(&[
            "simulate-recording",
            "--frames",
            &frames.to_string(),
            "--height",
            "128",
            "--width",
            "128",
            "--qd-count",
            "30",
            "--margin-um",
            "0.5",
            "--out",
            text(&out),
            "--truth",
            text(&truth),
        ])
    };
    let params = |frames: usize| RecordingParams {
        microscope: SimParams {
            height: 128,
            width: 128,
            ..SimParams::default()
        },
        frames,
        density_per_um3: 0.05,
        qd_count: Some(30),
        lateral_margin_um: 0.5,
        half_depth_um: 4.0,
        blinking: None,
        dead_time_ms: 0.0,
    };
    let frames = 1500;
    // The process's own footprint (code, libraries; its one frame's data
    // are 0.1 MB) measured on one frame, taken off the peak: the median of
    // three runs, and both comparisons allow 32 MiB for the footprint's
    // variation, against 98 MB of counts.
    let mut baselines = [run(1), run(1), run(1)];
    baselines.sort_unstable();
    let baseline = baselines[1];
    let noise = 32 << 20;
    let used = run(frames).saturating_sub(baseline);
    let estimate = params(frames).dataset_bytes();
    eprintln!("estimate {estimate} B, measured {used} B (baselines {baselines:?} B)");
    assert!(
        estimate + noise >= used,
        "estimate {estimate} < measured peak {used} (beyond {noise} B)"
    );
    assert!(
        estimate < 2 * used + noise,
        "estimate {estimate} ≥ twice the peak {used} (beyond {noise} B)"
    );
}

/// The LAP linker's costs stay finite at every accepted value: σ beyond
/// what its costs can hold and step variances below it are refused (no
/// table with an infinite gate is written), and a tiny accepted search
/// range links still particles as TrackPy's rules do.
#[test]
fn the_lap_linker_refuses_what_its_costs_cannot_hold_and_links_tiny_ranges() {
    let dir = tempfile::tempdir().unwrap();
    let locs = dir.path().join("locs.csv");
    let out = dir.path().join("tracks.csv");
    std::fs::write(
        &locs,
        "frame,x,y,sigma_x,sigma_y\n0,1,1,1e77,1e77\n0,5,5,1e77,1e77\n1,1,1,1e77,1e77\n1,5,5,1e77,1e77\n",
    )
    .unwrap();
    let (code, _, err) = cli_in_process(&[
        "link",
        "--locs",
        text(&locs),
        "--out",
        text(&out),
        "--linker",
        "lap",
        "--search-range",
        "3",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("sigma_x") && err.contains("1e77"), "{err}");
    assert!(!out.exists());
    let (code, _, err) = cli_in_process(&[
        "link",
        "--locs",
        text(&locs),
        "--out",
        text(&out),
        "--linker",
        "lap",
        "--search-range",
        "1e-160",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("step variance") && err.contains("at least"),
        "{err}"
    );
    // Still particles, a search range of 1e-40 px: linked frame to frame.
    std::fs::write(
        &locs,
        "frame,x,y\n0,1,1\n0,5,5\n1,1,1\n1,5,5\n2,1,1\n2,5,5\n",
    )
    .unwrap();
    for linker in ["lap", "trackpy"] {
        let (code, _, err) = cli_in_process(&[
            "link",
            "--locs",
            text(&locs),
            "--out",
            text(&out),
            "--linker",
            linker,
            "--search-range",
            "1e-40",
        ]);
        assert_eq!(code, 0, "{err}");
        let table = std::fs::read_to_string(&out).unwrap();
        assert!(!table.contains("inf"), "{table}");
        let mut reader = csv::Reader::from_reader(table.as_bytes());
        let particle = reader
            .headers()
            .unwrap()
            .iter()
            .position(|h| h == "particle")
            .unwrap();
        let labels: std::collections::BTreeSet<String> = reader
            .records()
            .map(|r| r.unwrap()[particle].to_string())
            .collect();
        assert_eq!(labels.len(), 2, "{linker}: two trajectories: {table}");
    }
}

/// A manifest is read with a size limit: `check /dev/zero` ends, refused.
#[cfg(unix)]
#[test]
fn a_manifest_is_read_with_a_size_limit() {
    let (code, _, err) = cli_in_process(&["check", "/dev/zero"]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("/dev/zero") && err.contains("MiB"), "{err}");
}

/// A recording's field that a recording does not use is an error, as the
/// CLI's conflicts are.
#[test]
fn a_recording_field_it_does_not_use_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = dir.path().join("m.yaml");
    for (fields, named) in [
        ("emitters: 3", "emitters"),
        ("margin_px: 2", "margin_px"),
        ("qd_density: 0.1, qd_count: 4", "qd_density"),
    ] {
        std::fs::write(
            &manifest,
            format!("name: t\nseed: 1\nrecordings:\n  r: {{frames: 2, {fields}}}\n"),
        )
        .unwrap();
        let (code, _, err) = cli_in_process(&["check", text(&manifest)]);
        assert_eq!(code, 2, "{fields}: {err}");
        assert!(err.contains(&format!("recordings.r.{named}")), "{err}");
    }
}

/// Numbers in messages are short (shortest round-trip, scientific for
/// extremes); negative values are answered as out of range, not as clap's
/// "unexpected argument"; a truth `qd` of `3.0` is read as `frame` is;
/// `on_fraction` beyond 1 is refused.
#[test]
fn messages_show_readable_numbers_and_negative_values_are_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let locs = dir.path().join("locs.csv");
    let out = dir.path().join("tracks.csv");
    std::fs::write(&locs, LOCS).unwrap();
    let huge = format!("{}", 1e300);
    for args in [
        vec![
            "link",
            "--locs",
            text(&locs),
            "--out",
            text(&out),
            "--search-range",
            &huge,
        ],
        vec![
            "link",
            "--locs",
            text(&locs),
            "--out",
            text(&out),
            "--search-range",
            "-1",
        ],
        vec![
            "link",
            "--locs",
            text(&locs),
            "--out",
            text(&out),
            "--search-range",
            "3",
            "--memory",
            "-1",
        ],
        vec!["diffusion", "--tracks", text(&locs), "--min-points", "-2"],
        vec![
            "diffusion",
            "--tracks",
            text(&locs),
            "--ensemble-margin-px",
            "-1e-300",
        ],
        vec![
            "score-tracks",
            "--tracks",
            text(&locs),
            "--truth",
            text(&locs),
            "--gate-px",
            "-3",
        ],
        vec!["simulate-recording", "--frames", "-5", "--out", text(&out)],
        vec![
            "simulate-recording",
            "--frames",
            "2",
            "--qd-count",
            "-5",
            "--out",
            text(&out),
        ],
    ] {
        let (code, _, err) = cli_in_process(&args);
        assert_eq!(code, 2, "{args:?}: {err}");
        assert!(!err.contains("unexpected argument"), "{args:?}: {err}");
        assert!(err.len() < 400, "{args:?}: a short message: {err}");
        assert!(
            err.contains("out of range") || err.contains("must be"),
            "{args:?}: {err}"
        );
    }

    let header = scanloc::io::tracks::RECORDING_TRUTH_COLUMNS.join(",");
    let truth = dir.path().join("truth.csv");
    let tracks = dir.path().join("tracks.csv");
    std::fs::write(&tracks, "frame,x,y,particle\n0,5,5,0\n1,5.1,5,0\n").unwrap();
    std::fs::write(
        &truth,
        format!("{header}\n0.0,3.0,5,5,0,1,5,5,0,0,0,1\n1,3.0,5.1,5,0,1,5.1,5,0.03,0.03,0.03,1\n"),
    )
    .unwrap();
    let (code, _, err) = cli_in_process(&[
        "score-tracks",
        "--tracks",
        text(&tracks),
        "--truth",
        text(&truth),
    ]);
    assert_eq!(code, 0, "qd 3.0: {err}");
    std::fs::write(&truth, format!("{header}\n0,3,5,5,0,7,5,5,0,0,0,1\n")).unwrap();
    let (code, _, err) = cli_in_process(&[
        "score-tracks",
        "--tracks",
        text(&tracks),
        "--truth",
        text(&truth),
    ]);
    assert_eq!(code, 2, "on_fraction 7: {err}");
    assert!(err.contains("on_fraction"), "{err}");
}

/// Every QD in the field has a truth row in every frame, also in frames in
/// which it wraps around the periodic volume (a volume 0.1 µm deep wraps
/// every QD in depth in every frame).
#[test]
fn a_qd_that_wraps_keeps_its_truth_rows() {
    use scanloc::sim::SimParams;
    use scanloc::sim::recording::{RecordingParams, simulate_recording};
    let params = |half_depth_um: f64, margin: f64| RecordingParams {
        microscope: SimParams {
            diffusion_um2_s: 1.0.into(),
            ..SimParams::default()
        },
        frames: 40,
        density_per_um3: 0.05,
        qd_count: Some(6),
        lateral_margin_um: margin,
        half_depth_um,
        blinking: None,
        dead_time_ms: 0.0,
    };
    // Depth wraps: every frame holds a row per QD in the field.
    let thin = simulate_recording(&params(0.05, 0.0), 3, false).unwrap();
    assert!(!thin.truth.is_empty());
    for frame in 0..40 {
        assert!(
            thin.truth.iter().any(|r| r.frame == frame),
            "no truth row in frame {frame}"
        );
    }
    // Without a margin QDs wrap across the field's edges: every frame still
    // has its 6 QDs' rows, minus those whose path left the field.
    let edge = simulate_recording(&params(4.0, 0.0), 5, false).unwrap();
    let rows_per_frame = edge.truth.len() as f64 / 40.0;
    assert!(
        rows_per_frame > 4.0,
        "{rows_per_frame} rows a frame of 6 QDs"
    );
}

/// `simulate-recording` takes the detector noise flag of `simulate`: a
/// PMT's excess noise widens the counts' spread.
#[test]
fn simulate_recording_takes_the_detector_noise() {
    let dir = tempfile::tempdir().unwrap();
    let spread = |noise: &str| {
        let out = dir.path().join(format!("{}.npy", noise.replace(':', "-")));
        let (code, _, err) = cli_in_process(&[
            "simulate-recording",
            "--frames",
            "20",
            "--qd-count",
            "0",
            "--detector-noise",
            noise,
            "--out",
            text(&out),
        ]);
        assert_eq!(code, 0, "{err}");
        let frames = scanloc::io::read_frames(&out).unwrap();
        let values: Vec<f64> = frames.data.iter().map(|&c| c as f64).collect();
        let mean = values.iter().sum::<f64>() / values.len() as f64;
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64 / mean
    };
    // Poisson: variance/mean 1; a PMT with F² = 3: about 3 (12,000 pixels,
    // SE of the ratio ≈ 0.02–0.05).
    let (poisson, pmt) = (spread("poisson"), spread("pmt:3"));
    assert!((poisson - 1.0).abs() < 0.15, "{poisson}");
    assert!(pmt > 2.0, "{pmt}");
    let (code, _, err) = cli_in_process(&[
        "simulate-recording",
        "--frames",
        "1",
        "--detector-noise",
        "pmt:0.5",
        "--out",
        text(&dir.path().join("x.npy")),
    ]);
    assert_eq!(code, 2, "{err}");
}
