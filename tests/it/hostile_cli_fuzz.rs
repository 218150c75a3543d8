//! Fuzzing the command line: random argument values for `simulate`,
//! `locate`, `score`, and the tracking commands `simulate-recording`,
//! `link`, `diffusion` and `score-tracks`, and random or damaged CSV, TIFF
//! and .npy bytes given to them. The tracking commands' cases also check
//! that an input is never modified and that a refusal writes nothing. Whatever comes in, the command exits 0, 1 or 2, never
//! panics, and a refusal is one `error:` line.
//!
//! The properties call the CLI in-process (`cli::main_with`, the function
//! `main` calls, with buffers for its output): thousands of cases a second
//! instead of one process per case. Every path given to it is inside the
//! case's own folder (the working directory is the whole test binary's).
//! The guards of `hostile_fuzz_guard` stand in for a process's limits:
//! an allocation no small case needs, or a case running too long, aborts
//! the test binary naming the case. A few cases still run the real binary
//! (`the_binary_keeps_the_contract`), for what only a process shows: its
//! exit status and a panic's abort. Valid values are kept small, so that
//! every accepted case is cheap; hostile values are out of range,
//! malformed or extreme. `make fuzz` runs these with `SCANLOC_FUZZ_CASES`
//! cases per property.

use crate::common;
use crate::hostile_fuzz_guard;
use scanloc::cli;

use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use proptest::prelude::*;

/// Address space a subprocess case may use: far above what any accepted
/// (small) case needs, far below what would disturb the machine.
const MEMORY_LIMIT_BYTES: u64 = 4 << 30;
/// Time a subprocess case may take; accepted cases take milliseconds.
const TIME_LIMIT: Duration = Duration::from_secs(10);

/// How one invocation ended.
#[derive(Debug)]
struct Ended {
    code: Option<i32>,
    stderr: String,
    /// What the command printed (empty from a subprocess).
    stdout: String,
    timed_out: bool,
    /// The panic's message, when the in-process call panicked.
    panic: Option<String>,
}

/// Runs the binary with `args` in `dir` under the memory and time limits.
fn run_limited(dir: &Path, args: &[String]) -> Ended {
    let binary = env!("CARGO_BIN_EXE_scanloc");
    // prlimit applies the address-space limit to the binary alone; without
    // it (not Linux) the case runs unlimited.
    let mut command = if Path::new("/usr/bin/prlimit").exists() {
        let mut command = Command::new("/usr/bin/prlimit");
        command
            .arg(format!("--as={MEMORY_LIMIT_BYTES}"))
            .arg("--")
            .arg(binary);
        command
    } else {
        Command::new(binary)
    };
    let mut child = command
        .args(args)
        .current_dir(dir)
        .env_remove("SCANLOC_REGISTRY")
        .env_remove("RUST_BACKTRACE")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start scanloc");
    let mut stderr = child.stderr.take().expect("piped");
    // Drain stderr while waiting, so a chatty case cannot block on a full pipe.
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        std::io::Read::read_to_string(&mut stderr, &mut text).ok();
        text
    });
    let started = Instant::now();
    let mut timed_out = false;
    let status = loop {
        if let Some(status) = child.try_wait().expect("wait for scanloc") {
            break status;
        }
        if started.elapsed() > TIME_LIMIT {
            timed_out = true;
            child.kill().ok();
            break child.wait().expect("wait for scanloc");
        }
        std::thread::sleep(Duration::from_millis(1));
    };
    Ended {
        code: status.code(),
        stderr: reader.join().unwrap_or_default(),
        stdout: String::new(),
        timed_out,
        panic: None,
    }
}

/// The flags whose values are paths.
const PATH_FLAGS: &[&str] = &[
    "--out", "--truth", "--input", "--locs", "--curve", "--tracks",
];

/// `args` with every path made absolute inside `dir`: the in-process
/// command shares the test binary's working directory. Values starting
/// with `--` stay as they are (clap reads them as flags), and so does the
/// empty path.
fn inside(dir: &Path, args: &[String]) -> Vec<String> {
    let mut placed = Vec::with_capacity(args.len());
    let mut path_follows = false;
    for arg in args {
        let is_path = path_follows && !arg.is_empty() && !arg.starts_with("--");
        placed.push(if is_path && Path::new(arg).is_relative() {
            dir.join(arg).to_string_lossy().into_owned()
        } else {
            arg.clone()
        });
        path_follows = PATH_FLAGS.contains(&arg.as_str());
    }
    placed
}

/// The number `ExitCode` stands for (it has no accessor).
fn exit_number(code: ExitCode) -> Option<i32> {
    (0..=255u8)
        .find(|&n| ExitCode::from(n) == code)
        .map(i32::from)
}

/// Counts the in-process cases of each command and writes a line every
/// 10,000 (straight to standard error, past the harness's capture), so a
/// long `make fuzz` shows how far it is.
fn count_case(command: &str) {
    static COUNTS: std::sync::Mutex<Vec<(String, u64)>> = std::sync::Mutex::new(Vec::new());
    let mut counts = COUNTS.lock().unwrap_or_else(|e| e.into_inner());
    let count = match counts.iter_mut().find(|(name, _)| name == command) {
        Some((_, count)) => count,
        None => {
            counts.push((command.to_string(), 0));
            &mut counts.last_mut().expect("just pushed").1
        }
    };
    *count += 1;
    if (*count).is_multiple_of(10_000) {
        let line = format!("fuzz progress: {count} {command} cases\n");
        // SAFETY: writing a valid buffer to a file descriptor.
        unsafe {
            libc::write(2, line.as_ptr().cast(), line.len());
        }
    }
}

/// Runs the CLI in-process with `args` (paths taken inside `dir`), under
/// the fuzz guards, its output captured.
fn run_in_process(dir: &Path, args: &[String]) -> Ended {
    count_case(args.first().map_or("", String::as_str));
    let args = inside(dir, args);
    let _case = hostile_fuzz_guard::Case::enter(format!(
        "scanloc {args:?} (input files in {})",
        dir.display()
    ));
    let mut stdout = Vec::new();
    let mut stderr = Vec::new();
    let argv = std::iter::once("scanloc".to_string()).chain(args.iter().cloned());
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        cli::main_with(argv, &mut stdout, &mut stderr, false)
    }));
    let stderr = String::from_utf8_lossy(&stderr).into_owned();
    let stdout = String::from_utf8_lossy(&stdout).into_owned();
    match outcome {
        Ok(code) => Ended {
            code: exit_number(code),
            stderr,
            stdout,
            timed_out: false,
            panic: None,
        },
        Err(payload) => Ended {
            code: None,
            stderr,
            stdout,
            timed_out: false,
            panic: Some(
                payload
                    .downcast_ref::<String>()
                    .cloned()
                    .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_else(|| "a panic without a message".into()),
            ),
        },
    }
}

/// The contract: exit 0, 1 or 2; no panic; a failure says so in exactly one
/// `error:` line.
fn check_contract(args: &[String], ended: &Ended) -> Result<(), TestCaseError> {
    let context = format!("scanloc {args:?}\nstderr: {}", ended.stderr);
    prop_assert!(!ended.timed_out, "took over {:?}: {}", TIME_LIMIT, context);
    prop_assert!(
        ended.panic.is_none(),
        "panicked: {:?}: {}",
        ended.panic,
        context
    );
    prop_assert!(
        matches!(ended.code, Some(0..=2)),
        "exit {:?}: {}",
        ended.code,
        context
    );
    prop_assert!(!ended.stderr.contains("panicked"), "{}", context);
    if ended.code != Some(0) {
        let errors = ended
            .stderr
            .lines()
            .filter(|l| l.starts_with("error"))
            .count();
        prop_assert_eq!(errors, 1, "{}", context);
    }
    Ok(())
}

/// Valid inputs made once by the binary itself: a small stack as .npy and
/// .tif, its ground truth and TrackPy-style localisations.
struct Inputs {
    _dir: tempfile::TempDir,
    npy: Vec<u8>,
    tif: Vec<u8>,
    truth: Vec<u8>,
    locs: Vec<u8>,
    /// A recording's truth (`simulate-recording --truth`), and the same
    /// positions as a tracks table (particle = QD).
    recording_truth: Vec<u8>,
    tracks: Vec<u8>,
}

fn inputs() -> &'static Inputs {
    static INPUTS: OnceLock<Inputs> = OnceLock::new();
    INPUTS.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let run = |args: &[&str]| {
            let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
            let ended = run_limited(dir.path(), &args);
            assert_eq!(ended.code, Some(0), "{args:?}: {}", ended.stderr);
        };
        let common = [
            "--frames",
            "3",
            "--emitters",
            "2",
            "--height",
            "16",
            "--width",
            "18",
        ];
        let mut args = vec!["simulate", "--out", "s.npy", "--truth", "truth.csv"];
        args.extend(common);
        run(&args);
        let mut args = vec!["simulate", "--out", "s.tif"];
        args.extend(common);
        run(&args);
        run(&[
            "locate",
            "--input",
            "s.npy",
            "--out",
            "locs.csv",
            "--minmass",
            "0",
        ]);
        run(&[
            "simulate-recording",
            "--frames",
            "12",
            "--qd-density",
            "0.3",
            "--seed",
            "5",
            "--out",
            "r.npy",
            "--truth",
            "rtruth.csv",
        ]);
        let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
        let recording_truth = read("rtruth.csv");
        let mut tracks = String::from("frame,x,y,particle\n");
        for row in
            scanloc::io::tracks::read_recording_truth(&dir.path().join("rtruth.csv")).unwrap()
        {
            tracks.push_str(&format!("{},{},{},{}\n", row.frame, row.x, row.y, row.qd));
        }
        Inputs {
            recording_truth,
            tracks: tracks.into_bytes(),
            npy: read("s.npy"),
            tif: read("s.tif"),
            truth: read("truth.csv"),
            locs: read("locs.csv"),
            _dir: dir,
        }
    })
}

/// Values a user (or a script gone wrong) might give any flag: out of
/// range, malformed or extreme.
const HOSTILE_VALUES: &[&str] = &[
    "0",
    "-1",
    "-0",
    "1e300",
    "-1e300",
    "1e-300",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "4294967295",
    "4294967296",
    "4000000001",
    "10000001",
    "1e12",
    "1000000000000",
    "9223372036854775807",
    "18446744073709551615",
    "18446744073709551616",
    "16385",
    "1025",
    "10001",
    "1001",
    "1002",
    "",
    " ",
    "abc",
    "1.5",
    "0x10",
    "1_000",
    "+3",
    "３",
    "1e",
    "--frames",
    "uniform:",
    "uniform:2,1",
    "uniform:nan,1",
    "uniform:0,1e300",
    "pmt:1",
    "pmt:1e300",
    "pmt:nan",
    "none",
];

/// A valid value (the strategy itself; a name for reading the tables below).
fn number(valid: impl Strategy<Value = String> + 'static) -> BoxedStrategy<String> {
    valid.boxed()
}

fn small_int(range: std::ops::Range<u64>) -> impl Strategy<Value = String> {
    range.prop_map(|v| v.to_string())
}

fn small_real(range: std::ops::Range<f64>) -> impl Strategy<Value = String> {
    range.prop_map(|v| format!("{v}"))
}

/// Each flag absent or given a valid value, then up to three flags given
/// a hostile value instead: one bad value at a time is what reaches the
/// code behind the first check that fails.
fn flags(options: Vec<(&'static str, BoxedStrategy<String>)>) -> BoxedStrategy<Vec<String>> {
    let names: Vec<&'static str> = options.iter().map(|(flag, _)| *flag).collect();
    let valid: Vec<BoxedStrategy<Option<String>>> = options
        .into_iter()
        .map(|(_, values)| proptest::option::of(values).boxed())
        .collect();
    let hostile = proptest::collection::vec(
        (
            any::<prop::sample::Index>(),
            prop::sample::select(HOSTILE_VALUES),
        ),
        0..4,
    );
    (valid, hostile)
        .prop_map(move |(mut values, hostile)| {
            for (index, value) in hostile {
                let at = index.index(values.len());
                values[at] = Some(value.to_string());
            }
            names
                .iter()
                .zip(values)
                .filter_map(|(flag, value)| value.map(|v| [flag.to_string(), v]))
                .flatten()
                .collect()
        })
        .boxed()
}

fn distribution() -> BoxedStrategy<String> {
    prop_oneof![
        3 => small_real(0.0..3.0),
        1 => (small_real(0.0..2.0), small_real(0.0..3.0))
            .prop_map(|(a, b)| format!("uniform:{a},{b}")),
    ]
    .boxed()
}

/// A brightness or background flag: a number, or drawn per frame from a
/// uniform below `max` (bounds in either order: reversed ones are refused).
fn photometry(max: f64) -> BoxedStrategy<String> {
    prop_oneof![
        3 => small_real(0.0..max),
        1 => (small_real(0.0..max), small_real(0.0..max))
            .prop_map(|(a, b)| format!("uniform:{a},{b}")),
    ]
    .boxed()
}

fn output_name(extensions: &'static [&'static str]) -> BoxedStrategy<String> {
    prop_oneof![
        4 => prop::sample::select(extensions).prop_map(|e| format!("out.{e}")),
        1 => prop::sample::select(vec![
            "", ".", "..", "/", "missing/out.npy", "out", "out.NPY", "out.tiff.", "in.npy",
        ])
        .prop_map(str::to_string),
    ]
    .boxed()
}

fn simulate_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        ("--frames", number(small_int(1..5))),
        ("--seed", number(any::<u64>().prop_map(|v| v.to_string()))),
        ("--diffusion", distribution()),
        ("--brightness", photometry(50.0)),
        ("--background", photometry(20.0)),
        ("--height", number(small_int(1..33))),
        ("--width", number(small_int(1..33))),
        ("--pixel-size-um", number(small_real(0.01..1.0))),
        ("--dwell-us", number(small_real(0.1..10.0))),
        ("--retrace-ms", number(small_real(0.0..5.0))),
        ("--sigma-xy-um", number(small_real(0.05..1.0))),
        ("--sigma-z-um", number(small_real(0.1..3.0))),
        ("--z-start", distribution()),
        ("--margin-px", number(small_real(0.0..6.0))),
        ("--substeps", number(small_int(1..4))),
        ("--emitters", number(small_int(0..5))),
        (
            "--detector-noise",
            prop_oneof![
                Just("poisson".to_string()),
                number(small_real(1.01..3.0)).prop_map(|f| format!("pmt:{f}")),
                Just("gaussian".to_string()),
            ]
            .boxed(),
        ),
        (
            "--psf-cutoff-sigma",
            prop_oneof![Just("none".to_string()), number(small_real(0.5..8.0))].boxed(),
        ),
        ("--truth", output_name(&["csv"])),
    ])
    .prop_flat_map(|args| {
        output_name(&["npy", "tif", "tiff"]).prop_map(move |out| {
            let mut all = vec!["simulate".to_string(), "--out".to_string(), out];
            all.extend(args.iter().cloned());
            all
        })
    })
    .boxed()
}

fn locate_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        ("--diameter", number(small_int(1..16))),
        ("--minmass", number(small_real(0.0..500.0))),
        ("--maxsize", number(small_real(0.0..10.0))),
        ("--separation", number(small_real(0.0..10.0))),
        ("--noise-size", number(small_real(0.0..3.0))),
        ("--smoothing-size", number(small_int(1..16))),
        ("--threshold", number(small_real(0.0..50.0))),
        ("--percentile", number(small_real(0.0..100.0))),
        ("--topn", number(small_int(1..10))),
        ("--max-iterations", number(small_int(1..20))),
    ])
    .prop_flat_map(|args| {
        (
            prop_oneof![
                Just(Vec::new()),
                Just(vec!["--preprocess".to_string()]),
                Just(vec!["--no-preprocess".to_string()]),
            ],
            output_name(&["csv"]),
        )
            .prop_map(move |(preprocess, out)| {
                let mut all = vec!["locate".to_string(), "--out".to_string(), out];
                all.extend(args.clone());
                all.extend(preprocess);
                all
            })
    })
    .boxed()
}

/// Damages `bytes`: overwrites some, then maybe truncates and appends.
fn damaged(
    bytes: &[u8],
    edits: &[(prop::sample::Index, u8)],
    cut: Option<prop::sample::Index>,
    tail: &[u8],
) -> Vec<u8> {
    let mut bytes = bytes.to_vec();
    if !bytes.is_empty() {
        for (index, value) in edits {
            let at = index.index(bytes.len());
            bytes[at] = *value;
        }
    }
    if let Some(cut) = cut {
        bytes.truncate(cut.index(bytes.len() + 1));
    }
    bytes.extend_from_slice(tail);
    bytes
}

/// A .npy file with any header shape and element type, and `data` after
/// it: degenerate shapes (a zero side, a huge side, the wrong rank) that
/// damaged bytes rarely produce.
fn npy_with_shape(descr: &str, shape: &[u64], data: &[u8]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
    bytes.extend_from_slice(header.as_bytes());
    bytes.extend_from_slice(data);
    bytes
}

fn npy_of_any_shape() -> BoxedStrategy<Vec<u8>> {
    let side = prop_oneof![
        3 => 0u64..5,
        1 => prop::sample::select(vec![16u64, 1 << 20, 1 << 31, 1 << 40, u64::MAX / 4, u64::MAX]),
    ];
    (
        prop::sample::select(vec![
            "<u4", "<u2", "|u1", "<i2", "<i4", "<i8", "<f4", "<f8", ">u4", "<c8", "|b1",
        ]),
        proptest::collection::vec(side, 0..5),
        proptest::collection::vec(any::<u8>(), 0..256),
    )
        .prop_map(|(descr, shape, data)| npy_with_shape(descr, &shape, &data))
        .boxed()
}

/// Frame-file bytes: valid, damaged, or random, as .npy or .tif.
fn frame_file() -> BoxedStrategy<(&'static str, Vec<u8>)> {
    let edits = proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8);
    (
        prop_oneof![Just("npy"), Just("tif")],
        0u8..5,
        edits,
        proptest::option::of(any::<prop::sample::Index>()),
        proptest::collection::vec(any::<u8>(), 0..16),
        proptest::collection::vec(any::<u8>(), 0..600),
        npy_of_any_shape(),
    )
        .prop_map(|(extension, kind, edits, cut, tail, random, shaped)| {
            let valid = match extension {
                "npy" => &inputs().npy,
                _ => &inputs().tif,
            };
            match kind {
                0 => (extension, valid.clone()),
                1 | 2 => (extension, damaged(valid, &edits, cut, &tail)),
                3 => ("npy", shaped),
                _ => (extension, random),
            }
        })
        .boxed()
}

/// CSV bytes: valid, damaged, lines edited as text, or random.
fn csv_file(valid: fn() -> &'static [u8]) -> BoxedStrategy<Vec<u8>> {
    let edits = proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..6);
    let cells = prop::sample::select(vec![
        "",
        "-1",
        "1e12",
        "1000000000000",
        "18446744073709551615",
        "18446744073709551616",
        "0.0",
        "2.5",
        "nan",
        "inf",
        "-inf",
        "1e308",
        "x",
        "\"",
        "0,0",
        "\u{feff}frame",
    ]);
    (
        0u8..5,
        edits,
        proptest::option::of(any::<prop::sample::Index>()),
        proptest::collection::vec(any::<u8>(), 0..16),
        proptest::collection::vec(
            (
                any::<prop::sample::Index>(),
                any::<prop::sample::Index>(),
                cells,
            ),
            1..4,
        ),
        proptest::collection::vec(any::<u8>(), 0..300),
    )
        .prop_map(move |(kind, edits, cut, tail, replacements, random)| {
            let valid = valid();
            match kind {
                0 => valid.to_vec(),
                1 => damaged(valid, &edits, cut, &tail),
                2 | 3 => {
                    // Replace whole cells, keeping the CSV shape.
                    let text = String::from_utf8_lossy(valid).into_owned();
                    let mut rows: Vec<Vec<String>> = text
                        .lines()
                        .map(|l| l.split(',').map(str::to_string).collect())
                        .collect();
                    for (row, column, cell) in &replacements {
                        let count = rows.len();
                        let row = &mut rows[row.index(count)];
                        // Half the time the frame column, where a number
                        // sizes what is allocated per frame.
                        let at = if kind == 2 {
                            0
                        } else {
                            column.index(row.len())
                        };
                        row[at] = cell.to_string();
                    }
                    let lines: Vec<String> = rows.iter().map(|r| r.join(",")).collect();
                    (lines.join("\n") + "\n").into_bytes()
                }
                _ => random,
            }
        })
        .boxed()
}

fn eps_list() -> BoxedStrategy<String> {
    prop_oneof![
        3 => proptest::collection::vec(small_real(0.1..5.0), 1..4).prop_map(|v| v.join(",")),
        1 => proptest::collection::vec(prop::sample::select(HOSTILE_VALUES), 0..4)
            .prop_map(|v| v.join(",")),
        1 => prop::sample::select(vec!["", ",", "1,,2", "1,1", "1e7", "1e300", "0"]).prop_map(str::to_string),
    ]
    .boxed()
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

/// Whether `simulate` arguments ask for work the limits allow that is
/// still too much for a cheap case: frames × pixels × substeps × emitters
/// above 2²⁰ (valid values stay below 50,000; the defaults, 100 frames of
/// 24 × 25, make 60,000). A legitimate request, not a hostile one; sizes
/// beyond the limits stay fuzzed (they must be refused at once).
fn legitimately_large(args: &[String]) -> bool {
    let value = |flag: &str, default: u64| -> Option<u64> {
        match args.iter().position(|a| a == flag) {
            Some(at) => args.get(at + 1)?.parse().ok(),
            None => Some(default),
        }
    };
    let (Some(frames), Some(height), Some(width), Some(substeps), Some(emitters)) = (
        value("--frames", 100),
        value("--height", 24),
        value("--width", 25),
        value("--substeps", 1),
        value("--emitters", 1),
    ) else {
        return false;
    };
    let side_limit = scanloc::limits::MAX_FRAME_SIDE as u64;
    let pixels = frames.saturating_mul(height).saturating_mul(width);
    let within_limits = frames <= scanloc::limits::MAX_FRAMES as u64
        && (1..=side_limit).contains(&height)
        && (1..=side_limit).contains(&width)
        && pixels <= scanloc::limits::MAX_DATASET_PIXELS as u64
        && (1..=1024).contains(&substeps)
        && emitters <= 10_000;
    let work = pixels
        .saturating_mul(substeps)
        .saturating_mul(emitters.max(1));
    within_limits && work > 1 << 20
}

fn simulate_case(
    dir: &Path,
    args: &[String],
    run: fn(&Path, &[String]) -> Ended,
) -> Result<(), TestCaseError> {
    write(dir, "in.npy", &inputs().npy);
    let ended = run(dir, args);
    check_contract(args, &ended)
}

fn locate_case(
    dir: &Path,
    args: &[String],
    extension: &str,
    bytes: &[u8],
    run: fn(&Path, &[String]) -> Ended,
) -> Result<(), TestCaseError> {
    let input = format!("in.{extension}");
    write(dir, &input, bytes);
    let mut args = args.to_vec();
    args.extend(["--input".to_string(), input]);
    let ended = run(dir, &args);
    check_contract(&args, &ended)
}

#[allow(clippy::too_many_arguments)]
fn score_case(
    dir: &Path,
    truth: &[u8],
    locs: &[u8],
    eps: Option<String>,
    json: bool,
    curve: Option<String>,
    run: fn(&Path, &[String]) -> Ended,
) -> Result<(), TestCaseError> {
    write(dir, "truth.csv", truth);
    write(dir, "locs.csv", locs);
    let mut args: Vec<String> = ["score", "--truth", "truth.csv", "--locs", "locs.csv"]
        .iter()
        .map(|a| a.to_string())
        .collect();
    if let Some(eps) = eps {
        args.push(format!("--eps={eps}"));
    }
    if json {
        args.push("--json".into());
    }
    if let Some(curve) = curve {
        args.extend(["--curve".to_string(), curve]);
    }
    let ended = run(dir, &args);
    check_contract(&args, &ended)
}

fn simulate_recording_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        ("--frames", number(small_int(1..5))),
        ("--seed", number(any::<u64>().prop_map(|v| v.to_string()))),
        ("--diffusion", number(small_real(0.0..3.0))),
        ("--brightness", number(small_real(0.0..50.0))),
        ("--background", number(small_real(0.0..20.0))),
        ("--height", number(small_int(1..33))),
        ("--width", number(small_int(1..33))),
        ("--pixel-size-um", number(small_real(0.01..1.0))),
        ("--dwell-us", number(small_real(0.1..10.0))),
        ("--retrace-ms", number(small_real(0.0..5.0))),
        ("--dead-time-ms", number(small_real(0.0..5.0))),
        ("--sigma-xy-um", number(small_real(0.05..1.0))),
        ("--sigma-z-um", number(small_real(0.1..3.0))),
        ("--substeps", number(small_int(1..4))),
        ("--qd-density", number(small_real(0.0..0.3))),
        ("--qd-count", number(small_int(0..6))),
        ("--margin-um", number(small_real(0.0..3.0))),
        ("--half-depth-um", number(small_real(0.01..5.0))),
        ("--blink-on-ms", number(small_real(0.001..100.0))),
        ("--blink-off-ms", number(small_real(0.001..100.0))),
        (
            "--detector-noise",
            prop_oneof![
                Just("poisson".to_string()),
                number(small_real(1.01..3.0)).prop_map(|f| format!("pmt:{f}")),
                Just("gaussian".to_string()),
            ]
            .boxed(),
        ),
        ("--truth", output_name(&["csv"])),
    ])
    .prop_flat_map(|args| {
        output_name(&["npy", "tif", "tiff"]).prop_map(move |out| {
            let mut all = vec!["simulate-recording".to_string(), "--out".to_string(), out];
            all.extend(args.iter().cloned());
            all
        })
    })
    .boxed()
}

/// Whether `simulate-recording` arguments ask for more work than a cheap
/// case (frames × pixels × substeps × QDs above 2²¹; the QDs of a density
/// taken at its largest valid value over the volume); as
/// [`legitimately_large`], legitimate, not hostile.
fn recording_legitimately_large(args: &[String]) -> bool {
    let value = |flag: &str, default: f64| -> Option<f64> {
        match args.iter().position(|a| a == flag) {
            Some(at) => args.get(at + 1)?.parse().ok(),
            None => Some(default),
        }
    };
    let (Some(frames), Some(height), Some(width), Some(substeps)) = (
        value("--frames", 200.0),
        value("--height", 24.0),
        value("--width", 25.0),
        value("--substeps", 1.0),
    ) else {
        return false;
    };
    let (Some(a), Some(margin), Some(depth), Some(density)) = (
        value("--pixel-size-um", 0.07),
        value("--margin-um", 1.5),
        value("--half-depth-um", 4.0),
        value("--qd-density", 0.05),
    ) else {
        return false;
    };
    let qds = match args.iter().position(|a| a == "--qd-count") {
        Some(_) => value("--qd-count", 0.0).unwrap_or(0.0),
        None => density * (width * a + 2.0 * margin) * (height * a + 2.0 * margin) * 2.0 * depth,
    };
    let work = frames * height * width * substeps * qds.max(1.0);
    // Beyond the limits it must be refused at once: fuzzed.
    let within = frames <= scanloc::limits::MAX_FRAMES as f64
        && height <= scanloc::limits::MAX_FRAME_SIDE as f64
        && width <= scanloc::limits::MAX_FRAME_SIDE as f64
        && frames * height * width <= scanloc::limits::MAX_DATASET_PIXELS as f64
        && substeps <= 1024.0
        && qds <= scanloc::sim::recording::MAX_RECORDING_QDS as f64 / 2.0;
    within && work.is_finite() && work > (1u64 << 21) as f64
}

fn link_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        (
            "--linker",
            prop::sample::select(vec!["trackpy", "lap"])
                .prop_map(str::to_string)
                .boxed(),
        ),
        ("--search-range", number(small_real(0.1..20.0))),
        ("--memory", number(small_int(0..4))),
        ("--max-gap", number(small_int(0..4))),
        ("--diffusion", number(small_real(0.01..3.0))),
        ("--frame-time-ms", number(small_real(1.0..50.0))),
        ("--pixel-size-um", number(small_real(0.01..1.0))),
        ("--min-score", number(small_real(0.0..1.0))),
        ("--gate", number(small_real(0.5..6.0))),
    ])
    .prop_flat_map(|args| {
        prop_oneof![4 => output_name(&["csv"]), 1 => Just("locs.csv".to_string())].prop_map(
            move |out| {
                let mut all = vec!["link".to_string(), "--out".to_string(), out];
                all.extend(args.iter().cloned());
                all
            },
        )
    })
    .boxed()
}

fn diffusion_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        ("--height", number(small_int(1..40))),
        ("--width", number(small_int(1..40))),
        ("--pixel-size-um", number(small_real(0.01..1.0))),
        ("--dwell-us", number(small_real(0.1..10.0))),
        ("--retrace-ms", number(small_real(0.0..5.0))),
        ("--dead-time-ms", number(small_real(0.0..5.0))),
        ("--sigma-xy-um", number(small_real(0.05..1.0))),
        (
            "--exposure",
            prop::sample::select(vec![
                "auto",
                "whole-frame",
                "rows",
                "frame-index",
                "uniform-frame",
            ])
            .prop_map(str::to_string)
            .boxed(),
        ),
        ("--min-points", number(small_int(0..6))),
        ("--ensemble-gate", number(small_real(0.1..0.707))),
        ("--ensemble-margin-px", number(small_real(0.0..4.0))),
    ])
    .prop_flat_map(|args| {
        (any::<bool>(), any::<bool>()).prop_map(move |(given, no_profile)| {
            let mut all = vec![
                "diffusion".to_string(),
                "--tracks".to_string(),
                "tracks.csv".into(),
            ];
            all.extend(args.iter().cloned());
            if given {
                all.push("--given-sigma".into());
            }
            if no_profile {
                all.push("--no-detection-profile".into());
            }
            all
        })
    })
    .boxed()
}

fn score_tracks_args() -> BoxedStrategy<Vec<String>> {
    flags(vec![
        ("--gate-px", number(small_real(0.1..5.0))),
        (
            "--truth-position",
            prop::sample::select(vec!["centroid", "seen"])
                .prop_map(str::to_string)
                .boxed(),
        ),
        ("--max-depth-um", number(small_real(0.0..3.0))),
        ("--min-on-fraction", number(small_real(0.0..1.0))),
        ("--split-gaps-over", number(small_int(0..5))),
    ])
    .prop_flat_map(|args| {
        any::<bool>().prop_map(move |json| {
            let mut all: Vec<String> = [
                "score-tracks",
                "--tracks",
                "tracks.csv",
                "--truth",
                "truth.csv",
            ]
            .iter()
            .map(|a| a.to_string())
            .collect();
            all.extend(args.iter().cloned());
            if json {
                all.push("--json".into());
            }
            all
        })
    })
    .boxed()
}

/// Every file in `dir` with its bytes.
fn snapshot(dir: &Path) -> std::collections::BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|entry| {
            let entry = entry.unwrap();
            let name = entry.file_name().to_string_lossy().into_owned();
            (name, std::fs::read(entry.path()).unwrap_or_default())
        })
        .collect()
}

/// The tracking commands' contract beyond [`check_contract`]: the inputs
/// (`inputs`, names in `dir`) are never modified, and a refusal writes
/// nothing (no file, nothing on stdout).
fn tracking_case(
    dir: &Path,
    args: &[String],
    inputs: &[(&str, &[u8])],
    run: fn(&Path, &[String]) -> Ended,
) -> Result<(), TestCaseError> {
    for (name, bytes) in inputs {
        write(dir, name, bytes);
    }
    let before = snapshot(dir);
    let ended = run(dir, args);
    check_contract(args, &ended)?;
    let after = snapshot(dir);
    for (name, bytes) in inputs {
        prop_assert!(
            after.get(*name).map(Vec::as_slice) == Some(*bytes),
            "{name} was modified: scanloc {args:?}\nstderr: {}",
            ended.stderr
        );
    }
    if ended.code != Some(0) {
        prop_assert_eq!(&after, &before, "a refusal wrote: scanloc {:?}", args);
        prop_assert!(
            ended.stdout.is_empty(),
            "a refusal printed: scanloc {args:?}: {}",
            ended.stdout
        );
    }
    Ok(())
}

proptest! {
    // Little shrinking: a failing case may take seconds.
    #![proptest_config(ProptestConfig {
        cases: common::fuzz_cases(200),
        max_shrink_iters: 256,
        max_shrink_time: 60_000,
        ..ProptestConfig::default()
    })]

    #[test]
    fn simulate_never_panics_on_any_arguments(
        args in simulate_args().prop_filter("a legitimately large dataset", |a| !legitimately_large(a)),
    ) {
        let dir = common::fuzz_case_dir();
        simulate_case(dir.path(), &args, run_in_process)?;
    }

    #[test]
    fn locate_never_panics_on_any_arguments_or_frame_bytes(
        args in locate_args(),
        (extension, bytes) in frame_file(),
    ) {
        let dir = common::fuzz_case_dir();
        locate_case(dir.path(), &args, extension, &bytes, run_in_process)?;
    }

    #[test]
    fn score_never_panics_on_any_arguments_or_csv_bytes(
        truth in csv_file(|| &inputs().truth),
        locs in csv_file(|| &inputs().locs),
        eps in proptest::option::of(eps_list()),
        json in any::<bool>(),
        curve in proptest::option::of(output_name(&["csv"])),
    ) {
        let dir = common::fuzz_case_dir();
        score_case(dir.path(), &truth, &locs, eps, json, curve, run_in_process)?;
    }

    #[test]
    fn simulate_recording_never_panics_on_any_arguments(
        args in simulate_recording_args()
            .prop_filter("a legitimately large recording", |a| !recording_legitimately_large(a)),
    ) {
        let dir = common::fuzz_case_dir();
        tracking_case(dir.path(), &args, &[], run_in_process)?;
    }

    #[test]
    fn link_never_panics_on_any_arguments_or_csv_bytes(
        args in link_args(),
        locs in csv_file(|| &inputs().locs),
    ) {
        let dir = common::fuzz_case_dir();
        let mut args = args;
        args.extend(["--locs".to_string(), "locs.csv".to_string()]);
        tracking_case(dir.path(), &args, &[("locs.csv", &locs)], run_in_process)?;
    }

    #[test]
    fn diffusion_never_panics_on_any_arguments_or_csv_bytes(
        args in diffusion_args(),
        tracks in csv_file(|| &inputs().tracks),
    ) {
        let dir = common::fuzz_case_dir();
        tracking_case(dir.path(), &args, &[("tracks.csv", &tracks)], run_in_process)?;
    }

    #[test]
    fn score_tracks_never_panics_on_any_arguments_or_csv_bytes(
        args in score_tracks_args(),
        tracks in csv_file(|| &inputs().tracks),
        truth in csv_file(|| &inputs().recording_truth),
    ) {
        let dir = common::fuzz_case_dir();
        tracking_case(
            dir.path(),
            &args,
            &[("tracks.csv", &tracks), ("truth.csv", &truth)],
            run_in_process,
        )?;
    }
}

proptest! {
    // The real binary, a few cases per command: its exit status, and a
    // panic's abort, are what only a process shows.
    #![proptest_config(ProptestConfig {
        cases: 8,
        max_shrink_iters: 16,
        max_shrink_time: 60_000,
        ..ProptestConfig::default()
    })]

    #[test]
    fn the_binary_keeps_the_contract(
        simulate in simulate_args().prop_filter("a legitimately large dataset", |a| !legitimately_large(a)),
        locate in locate_args(),
        (extension, bytes) in frame_file(),
        truth in csv_file(|| &inputs().truth),
        locs in csv_file(|| &inputs().locs),
        eps in proptest::option::of(eps_list()),
    ) {
        let dir = common::fuzz_case_dir();
        simulate_case(dir.path(), &simulate, run_limited)?;
        let dir = common::fuzz_case_dir();
        locate_case(dir.path(), &locate, extension, &bytes, run_limited)?;
        let dir = common::fuzz_case_dir();
        score_case(dir.path(), &truth, &locs, eps, false, None, run_limited)?;
    }
}
