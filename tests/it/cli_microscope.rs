//! One microscope on every command: `simulate`, `train` and `locate
//! --method likelihood` take the same microscope flags and
//! `--microscope FILE.yaml`; a non-paper microscope goes from simulation
//! through training and localisation on the command line alone; every
//! command writes through the streams handed to `cli::main_with`.

use std::path::Path;

use crate::common::{scanloc, stderr};
use scanloc::cli;

/// A microscope unlike the paper's in frame size, pixel size, timing and
/// PSF: as flags, and as the `microscope:` section of a manifest-style file.
const FLAGS: &[&str] = &[
    "--height",
    "32",
    "--width",
    "40",
    "--pixel-size-um",
    "0.1",
    "--dwell-us",
    "4",
    "--retrace-ms",
    "0.8",
    "--sigma-xy-um",
    "0.3",
    "--sigma-z-um",
    "1.5",
    "--brightness",
    "30",
    "--background",
    "4",
    "--margin-px",
    "4",
];
const FILE: &str = "name: other\nseed: 1\nmicroscope:\n  height: 32\n  width: 40\n  pixel_size_um: 0.1\n  dwell_us: 4\n  retrace_ms: 0.8\n  sigma_xy_um: 0.3\n  sigma_z_um: 1.5\n  brightness: 30\n  background: 4\n  margin_px: 4\ndatasets:\n  unused:\n    frames: 1\n";

/// Runs the CLI in-process; returns (exit code, stdout, stderr).
fn in_process(args: &[&str]) -> (u8, String, String) {
    let (mut out, mut err) = (Vec::new(), Vec::new());
    let argv = std::iter::once("scanloc").chain(args.iter().copied());
    let code = cli::main_with(argv, &mut out, &mut err, false);
    // ExitCode has no accessor: find the number it was made from.
    let code = (0..=255u8)
        .find(|&n| std::process::ExitCode::from(n) == code)
        .unwrap();
    (
        code,
        String::from_utf8(out).unwrap(),
        String::from_utf8(err).unwrap(),
    )
}

/// The long flags `--help` of `command` lists, in order.
fn long_flags(command: &[&str]) -> Vec<String> {
    let mut args = command.to_vec();
    args.push("--help");
    let (code, help, _) = in_process(&args);
    assert_eq!(code, 0);
    help.lines()
        .filter_map(|line| {
            let line = line.trim_start();
            let flag = line
                .strip_prefix("-h, ")
                .or(Some(line))
                .filter(|l| l.starts_with("--"))?;
            let end = flag.find([' ', ',', '\n']).unwrap_or(flag.len());
            Some(flag[..end].to_string())
        })
        .collect()
}

fn path(dir: &Path, name: &str) -> String {
    dir.join(name).to_string_lossy().into_owned()
}

/// `simulate ... --out FRAMES --truth TRUTH` with `microscope` flags,
/// asserted to succeed.
fn simulate(frames: &str, truth: &str, count: &str, seed: &str, microscope: &[&str]) {
    let mut args = vec![
        "simulate", "--frames", count, "--seed", seed, "--out", frames, "--truth", truth,
    ];
    args.extend_from_slice(microscope);
    let out = scanloc(&args);
    assert!(out.status.success(), "{}", stderr(&out));
}

/// The rows of a CSV file after its header, as numbers.
fn rows(path: &str) -> Vec<Vec<f64>> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|line| line.split(',').map(|v| v.parse().unwrap()).collect())
        .collect()
}

#[test]
fn train_and_the_likelihood_localiser_take_every_microscope_flag_simulate_does() {
    let own = ["--frames", "--seed", "--out", "--truth", "--help"];
    let microscope: Vec<String> = long_flags(&["simulate"])
        .into_iter()
        .filter(|flag| !own.contains(&flag.as_str()))
        .collect();
    // Every field of a manifest's `microscope` section, and the file.
    assert_eq!(microscope.len(), 17, "{microscope:?}");
    assert!(microscope.contains(&"--microscope".to_string()));
    for command in [
        &["train"][..],
        &["locate"],
        &["bench", "simulate"],
        &["bench", "locate"],
        &["bench", "train"],
        &["bench", "cnn-locate"],
    ] {
        let flags = long_flags(command);
        for flag in &microscope {
            assert!(flags.contains(flag), "{command:?} lacks {flag}: {flags:?}");
        }
    }
}

#[test]
fn locate_help_groups_the_flags_by_method() {
    let (code, help, _) = in_process(&["locate", "--help"]);
    assert_eq!(code, 0);
    let at = |text: &str| {
        help.find(text)
            .unwrap_or_else(|| panic!("no {text:?} in\n{help}"))
    };
    let crocker_grier = at("With --method crocker-grier:");
    let cnn = at("With --method cnn:");
    let likelihood = at("With --method likelihood");
    assert!(crocker_grier < cnn && cnn < likelihood, "{help}");
    for flag in ["--diameter <", "--minmass <", "--no-preprocess"] {
        assert!((crocker_grier..cnn).contains(&at(flag)), "{flag}: {help}");
    }
    assert!((cnn..likelihood).contains(&at("--model <")), "{help}");
    for flag in [
        "--particles <",
        "--dwell-us <",
        "--microscope <",
        "--height <",
    ] {
        assert!(at(flag) > likelihood, "{flag}: {help}");
    }
    // The common flags come first.
    assert!(at("--input <") < crocker_grier, "{help}");
}

#[test]
fn a_commands_output_reaches_the_stdout_handed_to_main_with() {
    let smoke = crate::common::smoke();
    let (code, out, err) = in_process(&["check", smoke.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("\nplan:\n- step: "), "{out}");
    assert!(err.ends_with(": ok\n"), "{err}");
    let (code, out, _) = in_process(&["check", smoke.to_str().unwrap(), "--json"]);
    assert_eq!(code, 0);
    let json: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert!(json["plan"].as_array().is_some_and(|plan| !plan.is_empty()));
}

#[test]
fn a_microscope_file_gives_what_its_flags_give_and_flags_override_it() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("microscope.yaml");
    std::fs::write(&file, FILE).unwrap();
    let file = file.to_string_lossy().into_owned();
    let [flags_frames, flags_truth, file_frames, file_truth] =
        ["a.npy", "a.csv", "b.npy", "b.csv"].map(|name| path(dir.path(), name));
    simulate(&flags_frames, &flags_truth, "4", "3", FLAGS);
    simulate(
        &file_frames,
        &file_truth,
        "4",
        "3",
        &["--microscope", &file],
    );
    for (a, b) in [(&flags_frames, &file_frames), (&flags_truth, &file_truth)] {
        assert_eq!(std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    }
    // A flag beats the file's field: the file with --width 36 is the flags
    // with --width 36.
    let mut narrower = FLAGS.to_vec();
    narrower[3] = "36";
    simulate(&flags_frames, &flags_truth, "4", "3", &narrower);
    simulate(
        &file_frames,
        &file_truth,
        "4",
        "3",
        &["--microscope", &file, "--width", "36"],
    );
    assert_eq!(
        std::fs::read(&flags_frames).unwrap(),
        std::fs::read(&file_frames).unwrap()
    );
    // A bad field is refused naming the file, its line and the field.
    std::fs::write(
        dir.path().join("bad.yaml"),
        "microscope:\n  dwell_us: fast\n",
    )
    .unwrap();
    let out = scanloc(&[
        "simulate",
        "--microscope",
        &path(dir.path(), "bad.yaml"),
        "--out",
        &flags_frames,
    ]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out).contains("bad.yaml:2: microscope.dwell_us"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn the_likelihood_localiser_models_a_non_paper_microscope_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let [frames, truth, by_flags, by_file] =
        ["f.npy", "t.csv", "flags.csv", "file.csv"].map(|name| path(dir.path(), name));
    let file = path(dir.path(), "microscope.yaml");
    std::fs::write(&file, FILE).unwrap();
    simulate(&frames, &truth, "6", "5", FLAGS);
    let locate = |out: &str, microscope: &[&str]| {
        let mut args = vec![
            "locate",
            "--method",
            "likelihood",
            "--particles",
            "2000",
            "--input",
            &frames,
            "--out",
            out,
        ];
        args.extend_from_slice(microscope);
        scanloc(&args)
    };
    let out = locate(&by_flags, FLAGS);
    assert!(out.status.success(), "{}", stderr(&out));
    let out = locate(&by_file, &["--microscope", &file]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(
        std::fs::read(&by_flags).unwrap(),
        std::fs::read(&by_file).unwrap()
    );
    // Each estimate is inside the 32 × 40 field and near the QD's true
    // centroid: a bright QD (N_qd 30 over 4 background photons) is
    // localised to well under a pixel; 1.5 px allows for the motion blur.
    let (estimates, truths) = (rows(&by_flags), rows(&truth));
    assert_eq!(estimates.len(), 6);
    for (estimate, truth) in estimates.iter().zip(&truths) {
        assert_eq!(estimate[0], truth[0]);
        let (x, y) = (estimate[1], estimate[2]);
        assert!(
            (0.0..=39.0).contains(&x) && (0.0..=31.0).contains(&y),
            "{x}, {y}"
        );
        let error = (x - truth[1]).hypot(y - truth[2]);
        assert!(error < 1.5, "frame {}: error {error} px", truth[0]);
    }
    // A frame size that is not the input's is refused.
    let out = locate(&by_flags, &["--height", "24"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        stderr(&out)
            .contains("height: the microscope's frames have 24 pixels, those of --input 32"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn train_learns_on_a_non_paper_microscope_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let file = path(dir.path(), "microscope.yaml");
    std::fs::write(&file, FILE).unwrap();
    let train = |name: &str, microscope: &[&str]| {
        let out_dir = path(dir.path(), name);
        let mut args = vec![
            "train",
            "--frames",
            "400",
            "--epochs",
            "4",
            "--channels",
            "8",
            "--batch-size",
            "16",
            "--seed",
            "2",
            "--out",
            &out_dir,
        ];
        args.extend_from_slice(microscope);
        let out = scanloc(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        (
            std::fs::read(Path::new(&out_dir).join("model.bpk")).unwrap(),
            stderr(&out),
        )
    };
    let (by_flags, log) = train("flags", FLAGS);
    // It learned: the training loss fell by a fifth from the first epoch to
    // the last, and the last epoch's network finds the QD within 3 px of
    // the validation frames with an AUC above 0.9 (a network that had
    // learned nothing scores no frame: 0). Measured: 31.4 → 22.9, AUC 1.0.
    let epochs: Vec<(f64, f64)> = log
        .lines()
        .filter(|line| line.starts_with("epoch "))
        .map(|line| {
            let loss = line
                .split("loss ")
                .nth(1)
                .unwrap()
                .split(' ')
                .next()
                .unwrap();
            let auc = line.rsplit('/').next().unwrap();
            (loss.parse().unwrap(), auc.parse().unwrap())
        })
        .collect();
    assert_eq!(epochs.len(), 4, "{log}");
    let (first, last) = (epochs[0], epochs[3]);
    assert!(last.0 < 0.8 * first.0, "losses {epochs:?}");
    assert!(last.1 > 0.9, "validation AUC at 3 px {epochs:?}");
    // The file gives the same weights as its flags; the frame size alone
    // changes them, so the microscope reached the training frames.
    let (by_file, _) = train("file", &["--microscope", &file]);
    assert!(
        by_flags == by_file,
        "the file's model differs from the flags'"
    );
    let (paper_sized, _) = train("paper", &["--microscope", &file, "--height", "24"]);
    assert!(
        by_flags != paper_sized,
        "--height did not reach the training"
    );
}
