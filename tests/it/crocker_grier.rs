//! The Crocker–Grier locator against real TrackPy 0.7 on committed
//! fixtures (tests/fixtures/trackpy/, made by make_fixtures.py): the same
//! features, every number within float rounding of TrackPy's.

use std::path::{Path, PathBuf};

use scanloc::detect::crocker_grier::{
    self, CrockerGrierParams, Feature, locate_frame, locate_stack,
};
use scanloc::io;
use scanloc::progress::hidden;
use scanloc::types::Recording;

const CASES: [&str; 12] = [
    "paper_dim",
    "paper_bright",
    "paper_d5",
    "paper_no_preprocess",
    "noise_only",
    "edge_qds",
    "two_close",
    "large_d9",
    "large_d11",
    "large_options",
    "large_topn",
    "bright_counts",
];

/// Real-valued (float64) frames: normalised, background-subtracted,
/// without preprocessing, every option, and whole numbers in a float array
/// (TrackPy's float path all the same); made by make_float_fixtures.py.
const FLOAT_CASES: [&str; 5] = [
    "float_normalised",
    "float_background_subtracted",
    "float_no_preprocess",
    "float_options",
    "float_whole_counts",
];

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/trackpy")
        .join(name)
}

#[derive(serde::Deserialize)]
struct Expected {
    frame: usize,
    x: f64,
    y: f64,
    mass: f64,
    size: f64,
    ecc: f64,
    signal: f64,
    raw_mass: f64,
    ep: f64,
}

fn expected(name: &str) -> Vec<Expected> {
    let mut reader = csv::Reader::from_path(fixture(&format!("{name}.csv"))).unwrap();
    reader.deserialize().map(|r| r.unwrap()).collect()
}

fn params(name: &str) -> CrockerGrierParams {
    let text = std::fs::read_to_string(fixture(&format!("{name}.json"))).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// How far a feature may be from TrackPy's: every quantity, positions in
/// px, ecc absolute, the rest relative. Measured over the fixtures (1081
/// features), positions, mass, raw_mass, size, signal and ep are
/// bit-identical and ecc differs by at most 2.2e-16 (one rounding); the
/// margin up to 1e-12 leaves room for another platform's libm, not for a
/// change to the algorithm.
const TRACKPY_TOLERANCE: f64 = 1e-12;

/// The largest deviations from TrackPy's features seen over the fixtures
/// (positions in px, ecc absolute, the rest relative to TrackPy's value).
#[derive(Debug, Default)]
struct Deviations {
    position_px: f64,
    mass: f64,
    raw_mass: f64,
    size: f64,
    ecc: f64,
    signal: f64,
    ep: f64,
}

/// `|a − b| / |b|`, 0 when both are NaN (TrackPy's `ep` is NaN where the
/// noise estimate is undefined) or equal (an infinite `ep`) and ∞ when
/// only one is NaN.
fn relative_deviation(a: f64, b: f64) -> f64 {
    if a == b {
        return 0.0;
    }
    match (a.is_nan(), b.is_nan()) {
        (true, true) => 0.0,
        (false, false) => (a - b).abs() / b.abs().max(1e-300),
        _ => f64::INFINITY,
    }
}

/// The features of every frame of fixture `name`, as read from its file
/// (counts or real values).
fn located(name: &str) -> Vec<Vec<Feature>> {
    let params = params(name);
    match io::npy::read_recording(&fixture(&format!("{name}.npy"))).unwrap() {
        Recording::Counts(frames) => (0..frames.n)
            .map(|i| locate_frame(frames.frame(i), frames.height, frames.width, &params).unwrap())
            .collect(),
        Recording::Real(frames) => (0..frames.n)
            .map(|i| locate_frame(frames.frame(i), frames.height, frames.width, &params).unwrap())
            .collect(),
    }
}

/// Compares the fixtures' features with TrackPy's; returns how many were
/// compared and the largest deviations.
fn compare_with_trackpy(cases: &[&str]) -> (usize, Deviations) {
    let mut compared = 0;
    let mut worst = Deviations::default();
    for &name in cases {
        let want = expected(name);
        for (index, got) in located(name).into_iter().enumerate() {
            let want: Vec<&Expected> = want.iter().filter(|e| e.frame == index).collect();
            assert_eq!(got.len(), want.len(), "{name} frame {index}: feature count");
            for w in want {
                // Match by position: TrackPy's topn output order is by mass.
                let g = got
                    .iter()
                    .min_by(|a, b| {
                        let da = (a.x - w.x).powi(2) + (a.y - w.y).powi(2);
                        let db = (b.x - w.x).powi(2) + (b.y - w.y).powi(2);
                        da.total_cmp(&db)
                    })
                    .unwrap();
                let this = Deviations {
                    position_px: (g.x - w.x).abs().max((g.y - w.y).abs()),
                    mass: relative_deviation(g.mass, w.mass),
                    raw_mass: relative_deviation(g.raw_mass, w.raw_mass),
                    size: relative_deviation(g.size, w.size),
                    ecc: (g.ecc - w.ecc).abs(),
                    signal: relative_deviation(g.signal, w.signal),
                    ep: relative_deviation(g.ep, w.ep),
                };
                assert!(
                    [
                        this.position_px,
                        this.mass,
                        this.raw_mass,
                        this.size,
                        this.ecc,
                        this.signal,
                        this.ep,
                    ]
                    .iter()
                    .all(|&deviation| deviation <= TRACKPY_TOLERANCE),
                    "{name} frame {index}: {this:?}\n got {g:?}\n want x {} y {} mass {} size {} ecc {} signal {} raw_mass {} ep {}",
                    w.x,
                    w.y,
                    w.mass,
                    w.size,
                    w.ecc,
                    w.signal,
                    w.raw_mass,
                    w.ep
                );
                worst.position_px = worst.position_px.max(this.position_px);
                worst.mass = worst.mass.max(this.mass);
                worst.raw_mass = worst.raw_mass.max(this.raw_mass);
                worst.size = worst.size.max(this.size);
                worst.ecc = worst.ecc.max(this.ecc);
                worst.signal = worst.signal.max(this.signal);
                worst.ep = worst.ep.max(this.ep);
                compared += 1;
            }
        }
    }
    (compared, worst)
}

#[test]
fn features_match_trackpy_on_every_fixture() {
    let (compared, worst) = compare_with_trackpy(&CASES);
    eprintln!("compared {compared} features; largest deviations {worst:?}");
    assert!(compared > 1000);
}

/// TrackPy's float-image path: real values (fractional, negative) are
/// located as TrackPy locates a float64 array.
#[test]
fn features_match_trackpy_on_real_valued_frames() {
    let (compared, worst) = compare_with_trackpy(&FLOAT_CASES);
    eprintln!("compared {compared} features; largest deviations {worst:?}");
    assert!(compared > 350);
}

/// The file's element type decides the path: the same whole numbers as
/// counts and as floats give different features (as in TrackPy), and the
/// stack entry point gives the per-frame ones.
#[test]
fn real_frames_take_the_float_path_through_the_stack_entry_point() {
    let name = "float_whole_counts";
    let recording = io::npy::read_recording(&fixture(&format!("{name}.npy"))).unwrap();
    let Recording::Real(real) = &recording else {
        panic!("a float64 .npy is read as real values")
    };
    let params = params(name);
    let from_stack = crocker_grier::locate_recording(&recording, &params, &hidden()).unwrap();
    let per_frame = located(name);
    assert_eq!(
        from_stack.len(),
        per_frame.iter().map(Vec::len).sum::<usize>()
    );
    for (frame, feature) in &from_stack {
        assert!(per_frame[*frame].contains(feature), "{feature:?}");
    }
    let counts = Recording::Real(real.clone()).into_counts().unwrap();
    let as_counts = locate_stack(&counts, &params, &hidden()).unwrap();
    assert_ne!(as_counts, from_stack, "counts take TrackPy's integer path");
}

#[test]
fn stack_results_are_ordered_by_frame_then_mass_whatever_the_threads() {
    let frames = io::read_frames(&fixture("large_d9.npy")).unwrap();
    let params = params("large_d9");
    let run = |threads| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| locate_stack(&frames, &params, &hidden()).unwrap())
    };
    let one = run(1);
    assert_eq!(one, run(2));
    for pair in one.windows(2) {
        let ((fa, a), (fb, b)) = (pair[0], pair[1]);
        assert!(fa < fb || (fa == fb && a.mass >= b.mass));
    }
}

#[test]
fn invalid_parameters_are_refused_naming_the_field() {
    let frame = vec![5u32; 24 * 25];
    for (params, field) in [
        (
            CrockerGrierParams {
                diameter: 6,
                ..Default::default()
            },
            "diameter",
        ),
        (
            CrockerGrierParams {
                diameter: 0,
                ..Default::default()
            },
            "diameter",
        ),
        (
            CrockerGrierParams {
                noise_size: f64::NAN,
                ..Default::default()
            },
            "noise_size",
        ),
        (
            CrockerGrierParams {
                smoothing_size: Some(4),
                ..Default::default()
            },
            "smoothing_size",
        ),
        (
            CrockerGrierParams {
                percentile: 101.0,
                ..Default::default()
            },
            "percentile",
        ),
        (
            CrockerGrierParams {
                minmass: Some(-1.0),
                ..Default::default()
            },
            "minmass",
        ),
        (
            CrockerGrierParams {
                max_iterations: 0,
                ..Default::default()
            },
            "max_iterations",
        ),
    ] {
        let error = locate_frame(&frame, 24, 25, &params).unwrap_err();
        assert_eq!(scanloc::error::exit_code(&error), 2);
        assert!(error.to_string().contains(field), "{error}");
    }
}

#[test]
fn degenerate_frames_give_no_feature_and_no_panic() {
    let params = CrockerGrierParams::default();
    for (height, width, value) in [
        (24, 25, 0u32),
        (24, 25, 7),
        (24, 25, u16::MAX as u32),
        (24, 25, u32::MAX),
        (1, 1, 3),
        (3, 3, 9),
    ] {
        let frame = vec![value; height * width];
        let features = locate_frame(&frame, height, width, &params).unwrap();
        assert!(
            features.is_empty(),
            "{height}×{width} of {value}: {features:?}"
        );
    }
    // A single bright pixel is a feature at that pixel.
    let mut frame = vec![0u32; 24 * 25];
    frame[12 * 25 + 10] = 1000;
    let features = locate_frame(&frame, 24, 25, &params).unwrap();
    assert_eq!(features.len(), 1);
    assert!(
        (features[0].x - 10.0).abs() < 0.01 && (features[0].y - 12.0).abs() < 0.01,
        "{features:?}"
    );
    assert!(
        features
            .iter()
            .all(|f| f.mass.is_finite() && f.size.is_finite())
    );
}

/// The entry point the Python bindings call on chunks of a caller's
/// array (`locate_frames_in_range`): with the stack's rescaling range,
/// chunks give the stack's features, and a numpy dtype's own range gives
/// TrackPy's treatment of that dtype (uint16 = the counts' range here).
#[test]
fn chunks_and_narrow_dtypes_give_the_stacks_features() {
    let recording = io::npy::read_recording(&fixture("paper_bright.npy")).unwrap();
    let Recording::Counts(frames) = recording else {
        panic!("paper_bright holds counts");
    };
    assert!(frames.max_count() <= u32::from(u16::MAX) && frames.n >= 3);
    let params = params("paper_bright");
    let whole = locate_stack(&frames, &params, &hidden()).unwrap();
    let as_u16: Vec<u16> = frames.data.iter().map(|&c| c as u16).collect();
    let frame_len = frames.height * frames.width;
    let mut chunked = Vec::new();
    for start in (0..frames.n).step_by(2) {
        let end = (start + 2).min(frames.n);
        let part = crocker_grier::locate_frames_in_range(
            &as_u16[start * frame_len..end * frame_len],
            end - start,
            frames.height,
            frames.width,
            &params,
            u64::from(u16::MAX),
            &hidden(),
        )
        .unwrap();
        chunked.extend(part.into_iter().map(|(i, f)| (i + start, f)));
    }
    assert!(!whole.is_empty());
    assert_eq!(chunked, whole);
    // Fewer values than the frames asked for: refused, not a panic.
    let refused = crocker_grier::locate_frames_in_range(
        &as_u16[..frame_len],
        2,
        frames.height,
        frames.width,
        &params,
        u64::from(u16::MAX),
        &hidden(),
    );
    assert!(refused.is_err());
}
