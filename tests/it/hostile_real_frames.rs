//! Real-valued frames (issue 14): float .npy and float TIFF pages with
//! fractional or negative values (background-subtracted, normalised
//! recordings) are located by crocker-grier as TrackPy locates a float
//! array, refused by the CNN with what to do, and NaN or infinities are
//! refused naming the file and the first bad value.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::common::{scanloc, stderr, write_npy};

/// The TrackPy fixture of background-subtracted float64 frames.
fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/trackpy")
        .join(name)
}

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

fn assert_refused(output: &Output, needles: &[&str]) {
    let text = stderr(output);
    assert!(!text.contains("panicked"), "panic: {text}");
    assert_eq!(output.status.code(), Some(2), "exit code; stderr: {text}");
    assert_eq!(text.trim().lines().count(), 1, "one line: {text}");
    for needle in needles {
        assert!(text.contains(needle), "{needle:?} not in {text:?}");
    }
}

/// Writes `frames` frames of `height × width` float32 values as TIFF pages.
fn write_float_tiff(path: &Path, height: u32, width: u32, values: &[f32]) {
    let mut file = std::fs::File::create(path).unwrap();
    let mut encoder = tiff::encoder::TiffEncoder::new(&mut file).unwrap();
    for page in values.chunks((height * width) as usize) {
        encoder
            .write_image::<tiff::encoder::colortype::Gray32Float>(width, height, page)
            .unwrap();
    }
}

/// The rows of a localisation CSV (header dropped).
fn rows(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .skip(1)
        .map(str::to_string)
        .collect()
}

fn locate(input: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec!["locate", "--input", text(input), "--out", text(out)];
    args.extend_from_slice(extra);
    scanloc(&args)
}

/// Each row's first four columns (frame, x, y, mass in TrackPy's and
/// `locate`'s tables), parsed.
fn features(path: &Path) -> Vec<(usize, f64, f64, f64)> {
    rows(path)
        .iter()
        .map(|row| {
            let cells: Vec<&str> = row.split(',').collect();
            (
                cells[0].parse().unwrap(),
                cells[1].parse().unwrap(),
                cells[2].parse().unwrap(),
                cells[3].parse().unwrap(),
            )
        })
        .collect()
}

#[test]
fn crocker_grier_locates_background_subtracted_frames_as_trackpy() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("locs.csv");
    let output = locate(&fixture("float_background_subtracted.npy"), &out, &[]);
    assert!(output.status.success(), "{}", stderr(&output));
    // TrackPy's features (make_float_fixtures.py), to the last bit.
    let want = features(&fixture("float_background_subtracted.csv"));
    let got = features(&out);
    assert_eq!(got.len(), want.len());
    for feature in &want {
        assert!(
            got.contains(feature),
            "TrackPy's {feature:?} not in {got:?}"
        );
    }
}

#[test]
fn float_tiff_pages_and_float32_npy_give_the_same_features() {
    let dir = tempfile::tempdir().unwrap();
    let (n, height, width) = (4u32, 24u32, 25u32);
    // Spots on a background that was subtracted: negative and fractional.
    let values: Vec<f32> = (0..n * height * width)
        .map(|i| {
            let (frame, pixel) = (i / (height * width), i % (height * width));
            let (row, column) = ((pixel / width) as f32, (pixel % width) as f32);
            let (y, x) = (6.0 + 3.0 * frame as f32, 8.5 + 2.0 * frame as f32);
            let spot = 30.0 * (-((row - y).powi(2) + (column - x).powi(2)) / 8.0).exp();
            let noise = ((i * 7919) % 13) as f32 / 13.0 - 0.5;
            spot + 1.7 * noise - 0.25
        })
        .collect();
    assert!(values.iter().any(|&v| v < 0.0));
    let tif = dir.path().join("frames.tif");
    let npy = dir.path().join("frames.npy");
    write_float_tiff(&tif, height, width, &values);
    write_npy(&npy, &[n as u64, height as u64, width as u64], &values);
    let (from_tif, from_npy) = (dir.path().join("tif.csv"), dir.path().join("npy.csv"));
    for (input, out) in [(&tif, &from_tif), (&npy, &from_npy)] {
        let output = locate(input, out, &["--minmass", "1"]);
        assert!(output.status.success(), "{}", stderr(&output));
    }
    assert_eq!(rows(&from_tif), rows(&from_npy));
    assert!(!rows(&from_tif).is_empty(), "the spots are found");
}

#[test]
fn the_cnn_refuses_real_values_saying_which_detector_takes_them() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("float_normalised.npy");
    let output = locate(
        &input,
        &dir.path().join("cnn.csv"),
        &[
            "--method",
            "cnn",
            "--model",
            text(crate::hostile_files::model_dir()),
        ],
    );
    assert_refused(
        &output,
        &[
            "float_normalised.npy",
            "flat index",
            "not a photon count",
            "crocker-grier",
        ],
    );
    // Whole non-negative floats are counts to the CNN.
    let whole = dir.path().join("whole.npy");
    write_npy(&whole, &[2, 24, 25], &vec![3.0f64; 2 * 24 * 25]);
    let output = locate(
        &whole,
        &dir.path().join("whole.csv"),
        &[
            "--method",
            "cnn",
            "--model",
            text(crate::hostile_files::model_dir()),
        ],
    );
    assert!(output.status.success(), "{}", stderr(&output));
}

#[test]
fn nan_and_infinities_are_refused_naming_the_file_and_the_first_one() {
    let dir = tempfile::tempdir().unwrap();
    let mut values = vec![0.5f64; 2 * 16 * 16];
    values[300] = f64::NAN;
    values[400] = f64::INFINITY;
    let npy = dir.path().join("nan.npy");
    write_npy(&npy, &[2, 16, 16], &values);
    let output = locate(&npy, &dir.path().join("a.csv"), &[]);
    assert_refused(&output, &["nan.npy", "flat index 300", "NaN"]);

    let mut pages = vec![0.5f32; 2 * 16 * 16];
    pages[256 + 17] = f32::NEG_INFINITY;
    let tif = dir.path().join("inf.tif");
    write_float_tiff(&tif, 16, 16, &pages);
    let output = locate(&tif, &dir.path().join("b.csv"), &[]);
    assert_refused(&output, &["inf.tif", "page 1", "flat index 17", "-inf"]);
}

#[test]
fn negative_integers_are_refused_with_the_advice_to_save_floats() {
    let dir = tempfile::tempdir().unwrap();
    let mut values = vec![5i16; 16 * 16];
    values[42] = -3;
    let npy = dir.path().join("signed.npy");
    write_npy(&npy, &[16, 16], &values);
    let output = locate(&npy, &dir.path().join("a.csv"), &[]);
    assert_refused(
        &output,
        &["signed.npy", "flat index 42", "(-3)", "float32/float64"],
    );
}
