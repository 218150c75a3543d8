//! `scanloc simulate` as a user runs it: outputs, formats and bad input.

use std::path::Path;
use std::process::Command;

use scanloc::io::{self, csv_tables};

use crate::common::{scanloc, stderr};

fn files_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn writes_npy_and_truth_that_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let npy = dir.path().join("frames.npy");
    let truth = dir.path().join("truth.csv");
    let output = scanloc(&[
        "simulate",
        "--frames",
        "12",
        "--diffusion",
        "uniform:0.75,1.75",
        "--seed",
        "3",
        "--emitters",
        "2",
        "--out",
        npy.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let frames = io::read_frames(&npy).unwrap();
    assert_eq!((frames.n, frames.height, frames.width), (12, 24, 25));
    // uint16 suffices for the paper's counts: 128-byte header + 2 bytes/px.
    assert_eq!(
        std::fs::metadata(&npy).unwrap().len(),
        128 + 12 * 24 * 25 * 2
    );
    let header = std::fs::read_to_string(&truth).unwrap();
    assert!(header.starts_with("frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion\n"));
    let rows = csv_tables::read_truth(&truth).unwrap();
    assert_eq!(rows.len(), 24);
    assert!(rows.iter().all(|r| (0.75..=1.75).contains(&r.diffusion)));
}

#[test]
fn tiff_output_holds_the_same_frames_as_npy() {
    let dir = tempfile::tempdir().unwrap();
    let npy = dir.path().join("a.npy");
    let tif = dir.path().join("a.tif");
    for out in [&npy, &tif] {
        let output = scanloc(&[
            "simulate",
            "--frames",
            "5",
            "--seed",
            "9",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(output.status.success(), "{}", stderr(&output));
    }
    let a = io::read_frames(&npy).unwrap();
    let b = io::read_frames(&tif).unwrap();
    assert_eq!(a, b);
    assert_eq!(b.n, 5);
}

#[test]
fn counts_beyond_uint16_are_written_as_uint32_not_clipped() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["bright.npy", "bright.tif"] {
        let path = dir.path().join(name);
        let output = scanloc(&[
            "simulate",
            "--frames",
            "2",
            "--diffusion",
            "0",
            "--brightness",
            "1e6",
            "--out",
            path.to_str().unwrap(),
        ]);
        assert!(output.status.success(), "{}", stderr(&output));
        let frames = io::read_frames(&path).unwrap();
        // Peak ≈ 1e6 / (2π·0.21²) / √(2π·1.36²) ≈ 1.06e6 photons.
        assert!(frames.max_count() > 500_000, "max {}", frames.max_count());
    }
}

#[test]
fn identical_output_whatever_the_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let mut outputs = Vec::new();
    for threads in ["1", "2"] {
        let path = dir.path().join(format!("t{threads}.npy"));
        let output = Command::new(env!("CARGO_BIN_EXE_scanloc"))
            .env("RAYON_NUM_THREADS", threads)
            .args([
                "simulate",
                "--frames",
                "200",
                "--seed",
                "5",
                "--out",
                path.to_str().unwrap(),
            ])
            .output()
            .unwrap();
        assert!(output.status.success());
        outputs.push(std::fs::read(&path).unwrap());
    }
    assert_eq!(outputs[0], outputs[1]);
}

#[test]
fn bad_input_gives_one_line_naming_the_parameter_and_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.npy");
    let out = out.to_str().unwrap();
    let cases: &[(&[&str], &str)] = &[
        (&["--diffusion", "-1"], "diffusion"),
        (&["--diffusion", "nan"], "diffusion"),
        (&["--diffusion", "uniform:2,1"], "diffusion"),
        (&["--brightness", "-3"], "brightness"),
        (&["--brightness", "inf"], "brightness"),
        (&["--background", "NaN"], "background"),
        (&["--height", "0"], "height"),
        (&["--width", "0"], "width"),
        (&["--dwell-us", "0"], "dwell_us"),
        (&["--dwell-us", "-2"], "dwell_us"),
        (&["--sigma-xy-um", "0"], "sigma_xy_um"),
        (&["--substeps", "0"], "substeps"),
        (&["--margin-px", "13"], "margin_px"),
        (&["--margin-px", "-30"], "margin_px"),
        (&["--detector-noise", "pmt:0.5"], "excess_noise_factor"),
        (&["--detector-noise", "gaussian"], "detector-noise"),
        (&["--psf-cutoff-sigma", "0"], "psf_cutoff_sigma"),
        (&["--no-such-flag", "1"], "--no-such-flag"),
    ];
    for (extra, needle) in cases {
        let mut args = vec!["simulate", "--frames", "3", "--out", out];
        args.extend_from_slice(extra);
        let output = scanloc(&args);
        let message = stderr(&output);
        assert_eq!(output.status.code(), Some(2), "{extra:?}: {message}");
        assert!(message.contains(needle), "{extra:?}: {message}");
        assert!(!message.contains("panicked"), "{extra:?}: {message}");
    }
    // Nothing was written, not even a temporary file.
    assert!(
        files_in(dir.path()).is_empty(),
        "{:?}",
        files_in(dir.path())
    );
}

#[test]
fn unwritable_outputs_fail_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("frames.npy");
    let output = scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--out",
        good.to_str().unwrap(),
        "--truth",
        "/nonexistent-folder/truth.csv",
    ]);
    assert_eq!(output.status.code(), Some(2));
    let message = stderr(&output);
    assert!(
        message.contains("/nonexistent-folder/truth.csv"),
        "{message}"
    );
    assert_eq!(message.trim().lines().count(), 1, "{message}");
    assert!(
        files_in(dir.path()).is_empty(),
        "partial output left: {:?}",
        files_in(dir.path())
    );

    let output = scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--out",
        dir.path().join("x.png").to_str().unwrap(),
    ]);
    assert_eq!(output.status.code(), Some(2));
    assert!(stderr(&output).contains("x.png"));
}

#[test]
fn help_explains_every_parameter() {
    let output = scanloc(&["simulate", "--help"]);
    assert!(output.status.success());
    let help = String::from_utf8_lossy(&output.stdout);
    for flag in [
        "--diffusion",
        "--frames",
        "--seed",
        "--brightness",
        "--background",
        "--height",
        "--width",
        "--pixel-size-um",
        "--dwell-us",
        "--retrace-ms",
        "--sigma-xy-um",
        "--sigma-z-um",
        "--z-start",
        "--margin-px",
        "--substeps",
        "--emitters",
        "--detector-noise",
        "--psf-cutoff-sigma",
        "--out",
        "--truth",
    ] {
        assert!(help.contains(flag), "missing {flag} in help");
    }
}

/// The text of `--help` of `command` describing `flag`: from the flag to
/// the next flag's line.
fn flag_help(command: &[&str], flag: &str) -> String {
    let mut args = command.to_vec();
    args.push("--help");
    let output = scanloc(&args);
    assert!(output.status.success(), "{}", stderr(&output));
    let help = String::from_utf8_lossy(&output.stdout).into_owned();
    let mut lines = help
        .lines()
        .skip_while(|line| !line.trim_start().starts_with(&format!("{flag} ")));
    let first = lines
        .next()
        .unwrap_or_else(|| panic!("{command:?}: no {flag} in\n{help}"));
    let rest = lines.take_while(|line| !line.trim_start().starts_with('-'));
    std::iter::once(first)
        .chain(rest)
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_shared_microscope_flags_keep_each_commands_defaults() {
    for (command, flag, default) in [
        (&["simulate"][..], "--diffusion", "[default: 1.0]"),
        (&["simulate"][..], "--brightness", "[default: 7]"),
        (&["simulate"][..], "--background", "[default: 8.4]"),
        (&["simulate"][..], "--z-start", "[default: 0]"),
        (&["simulate"][..], "--margin-px", "[default: 0]"),
        (&["locate"][..], "--diffusion", "[default: 1.0]"),
        (&["locate"][..], "--brightness", "[default: 7]"),
        (&["locate"][..], "--background", "[default: 8.4]"),
        (&["locate"][..], "--margin-px", "[default: 0]"),
        (
            &["train"][..],
            "--diffusion",
            "[default: uniform:0.75,1.75]",
        ),
        (&["train"][..], "--brightness", "[default: 7]"),
        (&["train"][..], "--background", "[default: 8.4]"),
        (&["train"][..], "--z-start", "[default: 0]"),
        (&["train"][..], "--margin-px", "[default: 4]"),
    ] {
        let help = flag_help(command, flag);
        assert!(help.contains(default), "{command:?} {flag}: {help}");
        if flag == "--brightness" || flag == "--background" {
            assert!(
                help.contains("uniform:LOW,HIGH"),
                "{command:?} {flag}: {help}"
            );
        }
    }
}

#[test]
fn brightness_and_background_can_be_drawn_per_frame_from_the_flags() {
    let dir = tempfile::tempdir().unwrap();
    let simulate = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "simulate",
            "--frames",
            "30",
            "--seed",
            "4",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        (scanloc(&args), out)
    };
    let (output, fixed) = simulate("fixed.npy", &[]);
    assert!(output.status.success(), "{}", stderr(&output));
    let (output, drawn) = simulate(
        "drawn.npy",
        &[
            "--brightness",
            "uniform:5,10",
            "--background",
            "uniform:1,20",
        ],
    );
    assert!(output.status.success(), "{}", stderr(&output));
    // Each frame's mean count follows its own background: with N_bkg
    // uniform on [1, 20] the frames' means spread over most of that range
    // (at a fixed 8.4 they stay within ≈ ±0.5 of 8.4 + the QD's share).
    let frame_means = |path: &Path| -> Vec<f64> {
        let frames = io::read_frames(path).unwrap();
        (0..frames.n)
            .map(|i| {
                frames.frame(i).iter().map(|&c| f64::from(c)).sum::<f64>()
                    / frames.frame_len() as f64
            })
            .collect()
    };
    let spread = |means: Vec<f64>| {
        means.iter().cloned().fold(f64::MIN, f64::max)
            - means.iter().cloned().fold(f64::MAX, f64::min)
    };
    assert!(spread(frame_means(&fixed)) < 2.0);
    assert!(spread(frame_means(&drawn)) > 8.0);
    for (flags, field) in [
        (["--brightness", "uniform:10,5"], "brightness"),
        (["--brightness", "uniform:-1,5"], "brightness"),
        (["--background", "uniform:1,inf"], "background"),
        (["--background", "-3"], "background"),
    ] {
        let (output, _) = simulate("bad.npy", &flags);
        assert_eq!(output.status.code(), Some(2), "{flags:?}");
        let message = stderr(&output);
        assert!(message.contains(field), "{flags:?}: {message}");
        assert_eq!(message.trim_end().lines().count(), 1, "{message}");
    }
    let (output, _) = simulate("bad.npy", &["--brightness", "uniform:5"]);
    assert_eq!(output.status.code(), Some(2));
    assert!(
        stderr(&output).contains("--brightness"),
        "{}",
        stderr(&output)
    );
    // train refuses the same before simulating anything.
    let output = scanloc(&[
        "train",
        "--frames",
        "10",
        "--background",
        "uniform:9,2",
        "--out",
        dir.path().join("m").to_str().unwrap(),
    ]);
    assert_eq!(output.status.code(), Some(2));
    assert!(
        stderr(&output).contains("background"),
        "{}",
        stderr(&output)
    );
    assert!(!dir.path().join("m").exists());
}
