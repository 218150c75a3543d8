//! Hostile frames, files and command lines (issue 14, defects 1–9, 14, 15
//! and the frame/score items of its list): every case ends with exit 0, or
//! exit 2 and one line naming the file or flag, never a panic, never an
//! unbounded allocation, never a clobbered file.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;

use crate::common::{self, scanloc, stderr};
use scanloc::detect::cnn::{self, CnnArchitecture, TrainedCnn, TrainingSettings};
use scanloc::progress::hidden;
use scanloc::sim::{self, SimParams};
use scanloc::types::FrameStack;

/// Asserts exit code 2 with one line on stderr that contains `needle`, and
/// no panic.
fn assert_refused(output: &Output, needle: &str) {
    let text = stderr(output);
    assert!(!text.contains("panicked"), "panic: {text}");
    assert_eq!(output.status.code(), Some(2), "exit code; stderr: {text}");
    assert_eq!(text.trim().lines().count(), 1, "one line: {text}");
    assert!(text.contains(needle), "{needle:?} not in {text:?}");
}

fn assert_ok(output: &Output) {
    assert!(
        output.status.success(),
        "status {:?}: {}",
        output.status,
        stderr(output)
    );
}

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Writes a `uint16` .npy array of `shape` (all values `fill`).
fn write_filled_npy(path: &Path, shape: &[u64], fill: u16) {
    let count: u64 = shape.iter().product();
    common::write_npy(path, shape, &vec![fill; count as usize]);
}

/// Simulates 3 frames into `frames` with their truth in `truth`.
fn simulate_small(frames: &Path, truth: &Path) {
    assert_ok(&scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--out",
        text(frames),
        "--truth",
        text(truth),
    ]));
}

/// Hidden `.scanloc-partial-*` files left in `dir`.
fn partial_files(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| name.starts_with(".scanloc-partial-"))
        .collect()
}

/// A tiny CNN model folder, trained once for the whole file.
pub(crate) fn model_dir() -> &'static Path {
    static MODEL: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, path) = MODEL.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("model");
        tiny_model(3).save(&path).unwrap();
        (dir, path)
    });
    path
}

fn tiny_model(seed: u64) -> TrainedCnn {
    let params = SimParams {
        brightness: 40.0.into(),
        margin_px: 4.0,
        ..SimParams::default()
    };
    let data = sim::simulate(&params, seed, 0..24, &hidden()).unwrap();
    cnn::train(
        &CnnArchitecture {
            channels: 4,
            dilations: vec![1, 2, 1],
            ..CnnArchitecture::default()
        },
        &TrainingSettings {
            epochs: 1,
            batch_size: 8,
            validation_fraction: 0.25,
            // Every local maximum is a prediction, so an untrained net
            // still predicts (for comparing batchings).
            score_floor: 0.0,
            ..TrainingSettings::default()
        },
        &data,
        None,
        seed,
        &scanloc::metrics::paper_aucs,
        &hidden(),
    )
    .unwrap()
}

// ---- 1. frames without pixels -------------------------------------------

#[test]
fn zero_width_or_height_frames_are_refused_by_every_detector() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("l.csv");
    for shape in [[2, 5, 0], [2, 0, 5], [0, 5, 5]] {
        let input = dir
            .path()
            .join(format!("f{}x{}x{}.npy", shape[0], shape[1], shape[2]));
        write_filled_npy(&input, &shape, 0);
        let output = scanloc(&["locate", "--input", text(&input), "--out", text(&out)]);
        assert_refused(&output, text(&input));
        let output = scanloc(&[
            "locate",
            "--method",
            "cnn",
            "--model",
            text(model_dir()),
            "--input",
            text(&input),
            "--out",
            text(&out),
        ]);
        assert_refused(&output, text(&input));
        assert!(!out.exists());
    }
    for flag in ["--height", "--width"] {
        let output = scanloc(&[
            "simulate",
            flag,
            "0",
            "--out",
            text(&dir.path().join("s.npy")),
        ]);
        assert_refused(&output, flag.trim_start_matches("--"));
    }
    // The library refuses them too, rather than panicking or saying nothing.
    let empty = FrameStack {
        n: 2,
        height: 5,
        width: 0,
        data: Vec::new(),
    };
    let params = scanloc::detect::crocker_grier::CrockerGrierParams::default();
    assert!(scanloc::detect::crocker_grier::locate_stack(&empty, &params, &hidden()).is_err());
    let model = TrainedCnn::load(model_dir()).unwrap();
    assert!(model.locate(&empty, &hidden()).is_err());
}

// ---- 2. size-like parameters are bounded, the same everywhere -----------

#[test]
fn huge_sizes_are_refused_on_the_command_line_and_in_manifests_alike() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("f.npy");
    write_filled_npy(&input, &[1, 24, 25], 3);
    let out = dir.path().join("l.csv");
    let beyond = (scanloc::limits::MAX_FEATURE_PX + 2).to_string();
    for (flag, value) in [
        ("--diameter", "4000000001"),
        ("--diameter", beyond.as_str()),
        ("--smoothing-size", "4000000001"),
        ("--separation", "1e12"),
        ("--noise-size", "1e9"),
        ("--max-iterations", "1000000000000"),
    ] {
        let started = std::time::Instant::now();
        let output = scanloc(&[
            "locate",
            "--input",
            text(&input),
            "--out",
            text(&out),
            flag,
            value,
        ]);
        assert_refused(
            &output,
            flag.trim_start_matches("--").replace('-', "_").as_str(),
        );
        assert!(started.elapsed().as_secs() < 10, "{flag} {value} took long");
    }
    // The manifest refuses the same values, with the same message.
    for diameter in ["4000000001", beyond.as_str()] {
        let manifest = common::write_manifest(
            dir.path(),
            "m.yaml",
            &format!(
                "name: t\nseed: 1\ndatasets:\n  a: {{frames: 2}}\ndetectors:\n  cg:\n    crocker_grier: {{diameter: {diameter}}}\n"
            ),
        );
        let output = scanloc(&["check", text(&manifest)]);
        assert_refused(&output, "diameter: must be at most");
    }
    for (flag, value) in [
        (
            "--dilations",
            "1,".repeat(100).trim_end_matches(',').to_string(),
        ),
        ("--heatmap-sigma-px", "1e9".to_string()),
        ("--fresh-frames-per-epoch", "100000000000".to_string()),
        ("--batch-size", "100000000000".to_string()),
    ] {
        let output = scanloc(&[
            "train",
            "--frames",
            "10",
            "--out",
            text(&dir.path().join("m")),
            flag,
            &value,
        ]);
        assert_refused(
            &output,
            flag.trim_start_matches("--").replace('-', "_").as_str(),
        );
    }
}

// ---- 3. score with huge frame numbers ------------------------------------

#[test]
fn score_refuses_frame_numbers_beyond_the_limit_without_allocating() {
    let dir = tempfile::tempdir().unwrap();
    let locs = dir.path().join("l.csv");
    std::fs::write(&locs, "frame,x,y,score\n0,1,1,0.5\n").unwrap();
    for frame in [
        "1000000000000",
        "18446744073709551615",
        "18446744073709551616",
        &scanloc::limits::MAX_FRAMES.to_string(),
    ] {
        let truth = dir.path().join("t.csv");
        std::fs::write(&truth, format!("frame,x,y\n0,1,1\n{frame},2,2\n")).unwrap();
        let started = std::time::Instant::now();
        let output = scanloc(&["score", "--truth", text(&truth), "--locs", text(&locs)]);
        assert_refused(&output, "row 2");
        assert!(stderr(&output).contains(text(&truth)));
        assert!(started.elapsed().as_secs() < 10);
        // The same bound for localisations.
        std::fs::write(&truth, "frame,x,y\n0,1,1\n").unwrap();
        let far = dir.path().join("far.csv");
        std::fs::write(
            &far,
            format!("frame,x,y,score\n0,1,1,0.5\n{frame},1,1,0.5\n"),
        )
        .unwrap();
        let output = scanloc(&["score", "--truth", text(&truth), "--locs", text(&far)]);
        assert_refused(&output, "row 2");
    }
    // The metric's memory grows with rows, not frame numbers: a large but
    // allowed frame number scores at once.
    let truth = dir.path().join("t.csv");
    let last = scanloc::limits::MAX_FRAMES - 1;
    std::fs::write(&truth, format!("frame,x,y\n0,1,1\n{last},1,1\n")).unwrap();
    let output = scanloc(&[
        "score",
        "--truth",
        text(&truth),
        "--locs",
        text(&locs),
        "--json",
    ]);
    assert_ok(&output);
    let score: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(score["frames"], scanloc::limits::MAX_FRAMES);
    assert_eq!(score["per_eps"][0]["auc"], 0.5);
}

// ---- 4. simulate / train limits, and no partial file ----------------------

#[test]
fn simulate_and_train_apply_the_manifest_limits_and_leave_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("s.npy");
    let truth = dir.path().join("t.csv");
    let too_many = (scanloc::limits::MAX_FRAMES + 1).to_string();
    for args in [
        vec!["--frames", "1000000000000"],
        vec!["--frames", "18446744073709551615"],
        vec!["--frames", &too_many],
        vec!["--frames", "100", "--height", "16384", "--width", "16384"],
        vec!["--height", "16385"],
    ] {
        let mut full = vec!["simulate", "--out", text(&out), "--truth", text(&truth)];
        full.extend(&args);
        let output = scanloc(&full);
        assert_refused(&output, args[0].trim_start_matches("--"));
        assert!(!out.exists() && !truth.exists());
        assert!(partial_files(dir.path()).is_empty(), "{args:?}");
    }
    // The manifest refuses the same sizes with the same words.
    let manifest = common::write_manifest(
        dir.path(),
        "m.yaml",
        "name: t\nseed: 1\nmicroscope: {height: 16384, width: 16384}\ndatasets:\n  a: {frames: 100}\n",
    );
    let from_manifest = stderr(&scanloc(&["check", text(&manifest)]));
    let from_cli = stderr(&scanloc(&[
        "simulate",
        "--height",
        "16384",
        "--width",
        "16384",
        "--frames",
        "100",
        "--out",
        text(&out),
    ]));
    let tail = |s: &str| s.split("frames").last().unwrap().trim().to_string();
    assert_eq!(tail(&from_manifest), tail(&from_cli));

    for frames in ["10000000000", too_many.as_str()] {
        let model = dir.path().join("model");
        let output = scanloc(&["train", "--frames", frames, "--out", text(&model)]);
        assert_refused(&output, "--frames");
        assert!(!model.exists());
        assert!(partial_files(dir.path()).is_empty());
    }
    // The benchmarks' frame counts too (paper-sized frames: 2³¹ pixels
    // are fewer than the frame limit's worth of them).
    for args in [
        vec!["bench", "simulate", "--frames", "1000000000000"],
        vec!["bench", "locate", "--frames", "5000000"],
        vec!["bench", "locate", "--reference-frames", "1000000000000"],
        vec![
            "bench",
            "tradeoffs",
            "--out",
            "unused",
            "--static-frames",
            "1000000000000",
        ],
        vec!["bench", "train", "--samples", "1000000000000"],
        vec![
            "bench",
            "cnn-locate",
            "--model",
            "m",
            "--frames",
            "1000000000000",
        ],
    ] {
        let output = scanloc(&args);
        assert_refused(&output, args[args.len() - 2]);
    }
    let output = scanloc(&[
        "train",
        "--frames",
        "10",
        "--test-frames",
        "100000000000",
        "--out",
        text(&dir.path().join("model")),
    ]);
    assert_refused(&output, "--test-frames");
}

// ---- 5. CNN memory: batches by pixels, predictions unchanged -------------

#[test]
fn cnn_batches_by_pixels_and_batching_never_changes_a_prediction() {
    use scanloc::detect::cnn::inference::{
        INFERENCE_BATCH, INFERENCE_PIXEL_BUDGET, inference_batch,
    };
    // Small frames keep the old batch; large ones go fewer at a time.
    assert_eq!(inference_batch(24 * 25), INFERENCE_BATCH);
    assert_eq!(inference_batch(512 * 512), 1);
    assert_eq!(inference_batch(4096 * 4096), 1);
    assert!(inference_batch(128 * 128) * 128 * 128 <= INFERENCE_PIXEL_BUDGET);

    let model = tiny_model(5);
    let params = SimParams {
        height: 40,
        width: 50,
        brightness: 40.0.into(),
        emitters: 3.into(),
        margin_px: 4.0,
        ..SimParams::default()
    };
    let frames = sim::simulate(&params, 9, 0..7, &hidden()).unwrap().frames;
    let reference = model.locate_in_batches(&frames, 256, &hidden()).unwrap();
    assert!(!reference.is_empty());
    for batch in [1, 2, 3, 7] {
        let predictions = model.locate_in_batches(&frames, batch, &hidden()).unwrap();
        assert_eq!(predictions.len(), reference.len(), "batch {batch}");
        for (a, b) in predictions.iter().zip(&reference) {
            assert_eq!(a.frame, b.frame);
            assert_eq!(a.x.to_bits(), b.x.to_bits(), "batch {batch}");
            assert_eq!(a.y.to_bits(), b.y.to_bits(), "batch {batch}");
            assert_eq!(a.score.to_bits(), b.score.to_bits(), "batch {batch}");
        }
    }
    assert_eq!(model.locate(&frames, &hidden()).unwrap(), reference);
}

// ---- 6, 7. one writer: no special destinations replaced, umask respected --

/// Every command with an output, writing to `destination` plus `.npy`
/// (frames) or `.csv` (tables).
fn writers(dir: &Path, destination: &str) -> Vec<Vec<String>> {
    let frames = dir.join("in.npy");
    let truth = dir.join("in.csv");
    let locs = dir.join("in-locs.csv");
    std::fs::write(&locs, "frame,x,y,score\n0,1,1,0.5\n").unwrap();
    if !frames.exists() {
        simulate_small(&frames, &truth);
    }
    let npy = text(&dir.join(format!("{destination}.npy"))).to_string();
    let csv = text(&dir.join(format!("{destination}.csv"))).to_string();
    let own = |args: &[&str]| args.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    vec![
        own(&["simulate", "--frames", "2", "--out", &npy]),
        own(&[
            "simulate",
            "--frames",
            "2",
            "--out",
            text(&dir.join("x.npy")),
            "--truth",
            &csv,
        ]),
        own(&["locate", "--input", text(&frames), "--out", &csv]),
        own(&[
            "locate",
            "--method",
            "cnn",
            "--model",
            text(model_dir()),
            "--input",
            text(&frames),
            "--out",
            &csv,
        ]),
        own(&[
            "score",
            "--truth",
            text(&truth),
            "--locs",
            text(&locs),
            "--curve",
            &csv,
        ]),
    ]
}

#[test]
fn outputs_never_replace_symlinks_fifos_devices_or_folders() {
    let dir = tempfile::tempdir().unwrap();
    let target = dir.path().join("precious.txt");
    std::fs::write(&target, "keep me").unwrap();
    let mut kinds = vec![
        ("symbolic link", "link"),
        ("FIFO", "fifo"),
        ("folder", "folder"),
    ];
    for extension in ["npy", "csv"] {
        let link = dir.path().join(format!("link.{extension}"));
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let fifo = dir.path().join(format!("fifo.{extension}"));
        assert!(
            Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .unwrap()
                .success()
        );
        std::fs::create_dir(dir.path().join(format!("folder.{extension}"))).unwrap();
        // Only root may make device nodes; elsewhere that case is skipped.
        let device = dir.path().join(format!("device.{extension}"));
        let have_device = Command::new("mknod")
            .args([text(&device), "c", "1", "3"])
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        if have_device && extension == "npy" {
            kinds.push(("device node", "device"));
        }
    }
    for (kind, base) in kinds {
        for args in writers(dir.path(), base) {
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            let output = scanloc(&args);
            assert_refused(&output, kind);
            for extension in ["npy", "csv"] {
                let destination = dir.path().join(format!("{base}.{extension}"));
                let metadata = std::fs::symlink_metadata(&destination).unwrap();
                assert!(!metadata.file_type().is_file(), "{args:?} replaced {kind}");
            }
        }
    }
    assert_eq!(std::fs::read_to_string(&target).unwrap(), "keep me");
    assert!(partial_files(dir.path()).is_empty());
}

#[test]
fn outputs_respect_the_umask() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    for (umask, mode) in [("022", 0o644), ("002", 0o664), ("077", 0o600)] {
        let base = format!("out-{umask}");
        for args in writers(dir.path(), &base) {
            let destination =
                Path::new(args.iter().find(|a| a.contains(&base)).unwrap()).to_path_buf();
            let _ = std::fs::remove_file(&destination);
            // The shell sets the umask, then becomes scanloc.
            let output = Command::new("sh")
                .arg("-c")
                .arg(format!("umask {umask}; exec \"$0\" \"$@\""))
                .arg(env!("CARGO_BIN_EXE_scanloc"))
                .args(&args)
                .output()
                .unwrap();
            assert_ok(&output);
            let actual = std::fs::metadata(&destination)
                .unwrap()
                .permissions()
                .mode()
                & 0o777;
            assert_eq!(actual, mode, "umask {umask}: {args:?}");
        }
    }
}

// ---- 8. a closed stdout ends the command quietly --------------------------

#[test]
fn a_closed_stdout_ends_every_printing_command_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("t.csv");
    assert_ok(&scanloc(&[
        "simulate",
        "--frames",
        "3",
        "--out",
        text(&dir.path().join("f.npy")),
        "--truth",
        text(&truth),
    ]));
    let locs = dir.path().join("l.csv");
    std::fs::write(&locs, "frame,x,y,score\n0,1,1,0.5\n").unwrap();
    let smoke = common::smoke();
    let cases: Vec<Vec<&str>> = vec![
        vec!["check", text(&smoke)],
        vec!["score", "--truth", text(&truth), "--locs", text(&locs)],
        vec![
            "score",
            "--truth",
            text(&truth),
            "--locs",
            text(&locs),
            "--json",
        ],
        vec!["simulate", "--help"],
    ];
    for args in cases {
        // The pipe's reading end is closed before scanloc starts, so its
        // first write meets a closed pipe, every time.
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let output = Command::new(env!("CARGO_BIN_EXE_scanloc"))
            .args(&args)
            .current_dir(common::root())
            .env_remove("SCANLOC_REGISTRY")
            .stdout(writer)
            .stderr(Stdio::piped())
            .output()
            .unwrap();
        let text = stderr(&output);
        assert!(text.is_empty(), "{args:?} wrote to stderr: {text}");
        assert!(
            output.status.success() || output.status.signal() == Some(13),
            "{args:?}: {:?}",
            output.status
        );
    }
}

// ---- 9. multi-sample TIFF pages are refused, not read in part -------------

/// A one-page little-endian TIFF of `width × height` pixels with two
/// 16-bit samples per pixel stored as separate planes (PlanarConfiguration
/// 2): plane 0 all `first`, plane 1 all `second`.
fn planar_two_channel_tiff(width: u16, height: u16, first: u16, second: u16) -> Vec<u8> {
    let plane_len = width as usize * height as usize * 2;
    let entries: u16 = 10;
    let ifd_offset = 8u32;
    let ifd_len = 2 + entries as u32 * 12 + 4;
    let offsets_at = ifd_offset + ifd_len;
    let counts_at = offsets_at + 8;
    let data_at = counts_at + 8;
    let mut bytes = b"II*\0".to_vec();
    bytes.extend(ifd_offset.to_le_bytes());
    bytes.extend(entries.to_le_bytes());
    let mut entry = |tag: u16, kind: u16, count: u32, value: u32| {
        bytes.extend(tag.to_le_bytes());
        bytes.extend(kind.to_le_bytes());
        bytes.extend(count.to_le_bytes());
        bytes.extend(value.to_le_bytes());
    };
    const SHORT: u16 = 3;
    const LONG: u16 = 4;
    entry(256, SHORT, 1, width as u32); // ImageWidth
    entry(257, SHORT, 1, height as u32); // ImageLength
    entry(258, SHORT, 2, 16 | (16 << 16)); // BitsPerSample 16, 16
    entry(259, SHORT, 1, 1); // no compression
    entry(262, SHORT, 1, 1); // BlackIsZero
    entry(273, LONG, 2, offsets_at); // StripOffsets
    entry(277, SHORT, 1, 2); // SamplesPerPixel
    entry(278, SHORT, 1, height as u32); // RowsPerStrip
    entry(279, LONG, 2, counts_at); // StripByteCounts
    entry(284, SHORT, 1, 2); // PlanarConfiguration: separate planes
    bytes.extend(0u32.to_le_bytes());
    bytes.extend(data_at.to_le_bytes());
    bytes.extend((data_at + plane_len as u32).to_le_bytes());
    bytes.extend((plane_len as u32).to_le_bytes());
    bytes.extend((plane_len as u32).to_le_bytes());
    for value in [first, second] {
        for _ in 0..plane_len / 2 {
            bytes.extend(value.to_le_bytes());
        }
    }
    bytes
}

#[test]
fn tiff_pages_with_two_samples_are_refused_whatever_the_layout() {
    let dir = tempfile::tempdir().unwrap();
    let planar = dir.path().join("planar.tif");
    std::fs::write(&planar, planar_two_channel_tiff(25, 24, 3, 900)).unwrap();
    let output = scanloc(&[
        "locate",
        "--input",
        text(&planar),
        "--out",
        text(&dir.path().join("l.csv")),
    ]);
    assert_refused(&output, "2 samples per pixel");
    let error = scanloc::io::read_frames(&planar).unwrap_err().to_string();
    assert!(error.contains("2 samples per pixel"), "{error}");
}

// ---- ImageJ hyperstacks and signed TIFF ------------------------------------

/// Writes an ImageJ hyperstack of `channels × frames` 16-bit pages, page
/// `p` (channel `p % channels`, frame `p / channels`) filled with `p`.
fn imagej_hyperstack(path: &Path, channels: usize, frames: usize) {
    use tiff::encoder::{TiffEncoder, colortype};
    use tiff::tags::Tag;
    let mut file = std::fs::File::create(path).unwrap();
    let mut encoder = TiffEncoder::new(&mut file).unwrap();
    let (width, height) = (6u32, 5u32);
    for page in 0..channels * frames {
        let data = vec![page as u16; (width * height) as usize];
        let mut image = encoder
            .new_image::<colortype::Gray16>(width, height)
            .unwrap();
        if page == 0 {
            let description = format!(
                "ImageJ=1.54f\nimages={}\nchannels={channels}\nframes={frames}\nhyperstack=true\nmode=composite\n",
                channels * frames
            );
            image
                .encoder()
                .write_tag(Tag::ImageDescription, description.as_str())
                .unwrap();
        }
        image.write_data(&data).unwrap();
    }
}

#[test]
fn imagej_hyperstacks_need_a_channel_choice_and_read_that_channel() {
    let dir = tempfile::tempdir().unwrap();
    let stack = dir.path().join("hyper.tif");
    imagej_hyperstack(&stack, 2, 3);
    let out = dir.path().join("l.csv");
    let locate = |extra: &[&str]| {
        let mut args = vec!["locate", "--input", text(&stack), "--out", text(&out)];
        args.extend_from_slice(extra);
        scanloc(&args)
    };
    assert_refused(&locate(&[]), "--channel");
    assert_refused(&locate(&["--channel", "2"]), "--channel 2");
    assert_ok(&locate(&["--channel", "1"]));
    for channel in 0..2 {
        let frames = scanloc::io::read_frames_of_channel(&stack, Some(channel)).unwrap();
        assert_eq!((frames.n, frames.height, frames.width), (3, 5, 6));
        for (index, frame) in frames.iter().enumerate() {
            let page = (index * 2 + channel) as u32;
            assert!(
                frame.iter().all(|&v| v == page),
                "channel {channel} frame {index}"
            );
        }
    }
    // One channel: no choice needed (0 is accepted), as for .npy.
    let single = dir.path().join("single.tif");
    imagej_hyperstack(&single, 1, 3);
    assert_eq!(scanloc::io::read_frames(&single).unwrap().n, 3);
    assert!(scanloc::io::read_frames_of_channel(&single, Some(1)).is_err());
}

#[test]
fn signed_integer_tiff_is_read_like_signed_npy() {
    use tiff::encoder::{TiffEncoder, colortype};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("i16.tif");
    {
        let mut file = std::fs::File::create(&path).unwrap();
        let mut encoder = TiffEncoder::new(&mut file).unwrap();
        let page: Vec<i16> = (0..30).collect();
        encoder
            .write_image::<colortype::GrayI16>(6, 5, &page)
            .unwrap();
    }
    let frames = scanloc::io::read_frames(&path).unwrap();
    assert_eq!(frames.data, (0..30).collect::<Vec<u32>>());
    let output = scanloc(&[
        "locate",
        "--input",
        text(&path),
        "--out",
        text(&dir.path().join("l.csv")),
    ]);
    assert_ok(&output);
}

// ---- 14. the same file as input and output --------------------------------

#[test]
fn an_output_naming_an_input_or_another_output_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("x.npy");
    let truth = dir.path().join("t.csv");
    simulate_small(&frames, &truth);
    let before = std::fs::read(&frames).unwrap();
    let same_folder = dir.path().join("sub");
    std::fs::create_dir(&same_folder).unwrap();
    let dotted = same_folder.join("../x.npy");
    let linked_folder = dir.path().join("linked");
    std::os::unix::fs::symlink(dir.path(), &linked_folder).unwrap();
    let through_link = linked_folder.join("x.npy");
    let hard = dir.path().join("hard.npy");
    std::fs::hard_link(&frames, &hard).unwrap();
    for alias in [&frames, &dotted, &through_link, &hard] {
        let output = scanloc(&["locate", "--input", text(&frames), "--out", text(alias)]);
        assert_refused(&output, "same file");
        let output = scanloc(&[
            "simulate",
            "--frames",
            "2",
            "--out",
            text(&frames),
            "--truth",
            text(alias),
        ]);
        assert_refused(&output, "same file");
        let output = scanloc(&[
            "score",
            "--truth",
            text(&truth),
            "--locs",
            text(&truth),
            "--curve",
            text(&truth),
        ]);
        assert_refused(&output, "same file");
    }
    assert_eq!(std::fs::read(&frames).unwrap(), before);
}

// ---- 15. train --out naming a file ----------------------------------------

#[test]
fn train_into_an_existing_file_is_bad_input_found_before_training() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("model");
    std::fs::write(&file, "not a folder").unwrap();
    let started = std::time::Instant::now();
    let output = scanloc(&["train", "--frames", "2000", "--out", text(&file)]);
    assert_refused(&output, "not a folder");
    assert!(started.elapsed().as_secs() < 10, "it trained first");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "not a folder");
}

// ---- score on TrackPy's own output ------------------------------------------

#[test]
fn score_reads_trackpy_output_with_a_score_column_and_pandas_cells() {
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("t.csv");
    // pandas writes whole floats for frame numbers and empty missing cells.
    std::fs::write(
        &truth,
        "frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion\n0.0,5,5,,,,,,\n1.0,7,7,,,,,0.5,\n",
    )
    .unwrap();
    // TrackPy's `locate` output as `DataFrame.to_csv` writes it: the index
    // first, no `score` column, `frame` as floats, an empty `ep`.
    let trackpy = dir.path().join("tp.csv");
    std::fs::write(
        &trackpy,
        ",y,x,mass,size,ecc,signal,raw_mass,ep,frame\n0,5.1,5.0,90.0,1.2,0.1,9,100,,0.0\n1,2.0,2.0,10.0,1.2,0.1,9,100,0.1,0.0\n2,7.0,7.2,80.0,1.2,0.1,9,100,0.1,1.0\n",
    )
    .unwrap();
    let output = scanloc(&["score", "--truth", text(&truth), "--locs", text(&trackpy)]);
    assert_refused(&output, "score");
    let output = scanloc(&[
        "score",
        "--truth",
        text(&truth),
        "--locs",
        text(&trackpy),
        "--score-column",
        "mass",
        "--json",
    ]);
    assert_ok(&output);
    let score: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    // Ranked by mass: the two true positives first, then the false one.
    assert_eq!(score["per_eps"][0]["true_positives"], 2);
    assert_eq!(score["per_eps"][0]["auc"], 1.0);
    assert_eq!(score["frames"], 2);

    // Frames that do not overlap (numbered from 1 in one file) are an
    // error, not an AUC of 0.
    let shifted = dir.path().join("shifted.csv");
    std::fs::write(&shifted, "frame,x,y\n2,5,5\n3,7,7\n").unwrap();
    let output = scanloc(&[
        "score",
        "--truth",
        text(&shifted),
        "--locs",
        text(&trackpy),
        "--score-column",
        "mass",
    ]);
    assert_refused(&output, "no localisation is on a frame of");
    // A non-whole frame number is refused, naming the row.
    std::fs::write(&shifted, "frame,x,y\n0.5,5,5\n").unwrap();
    let output = scanloc(&["score", "--truth", text(&shifted), "--locs", text(&trackpy)]);
    assert_refused(&output, "row 1");
}

// ---- training that diverges ------------------------------------------------

#[test]
fn a_diverging_training_says_so_with_epoch_and_batch() {
    let dir = tempfile::tempdir().unwrap();
    let output = scanloc(&[
        "train",
        "--frames",
        "32",
        "--epochs",
        "2",
        "--batch-size",
        "8",
        "--channels",
        "4",
        "--dilations",
        "1,2,1",
        "--learning-rate",
        "1e30",
        "--out",
        text(&dir.path().join("m")),
    ]);
    assert_refused(&output, "training diverged");
    let text = stderr(&output);
    assert!(
        text.contains("epoch 1") || text.contains("epoch 2"),
        "{text}"
    );
    assert!(text.contains("batch"), "{text}");
    assert!(!text.contains("damaged"), "{text}");
}
