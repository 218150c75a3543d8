//! The Crocker–Grier locator against real TrackPy 0.7 on committed
//! fixtures (tests/fixtures/trackpy/, made by make_fixtures.py): the same
//! features, positions within 0.01 px and mass within 0.1 %.

use std::path::{Path, PathBuf};

use scanloc::detect::crocker_grier::{CrockerGrierParams, Feature, locate_frame, locate_stack};
use scanloc::io;
use scanloc::progress::hidden;

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

fn close(a: f64, b: f64, relative: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() <= relative * b.abs().max(1e-9)
}

#[test]
fn features_match_trackpy_on_every_fixture() {
    let mut compared = 0;
    let mut worst_position: f64 = 0.0;
    let mut worst_mass: f64 = 0.0;
    for name in CASES {
        let frames = io::read_frames(&fixture(&format!("{name}.npy"))).unwrap();
        let params = params(name);
        let want = expected(name);
        for index in 0..frames.n {
            let got: Vec<Feature> =
                locate_frame(frames.frame(index), frames.height, frames.width, &params).unwrap();
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
                let position_error = (g.x - w.x).abs().max((g.y - w.y).abs());
                let mass_error = (g.mass - w.mass).abs() / w.mass.abs().max(1e-9);
                worst_position = worst_position.max(position_error);
                worst_mass = worst_mass.max(mass_error);
                assert!(
                    position_error <= 0.01,
                    "{name} frame {index}: ({}, {}) vs ({}, {})",
                    g.x,
                    g.y,
                    w.x,
                    w.y
                );
                assert!(
                    mass_error <= 1e-3,
                    "{name} frame {index}: mass {} vs {}",
                    g.mass,
                    w.mass
                );
                assert!(
                    close(g.raw_mass, w.raw_mass, 1e-9),
                    "{name} frame {index}: raw_mass {} vs {}",
                    g.raw_mass,
                    w.raw_mass
                );
                assert!(
                    close(g.size, w.size, 1e-3),
                    "{name} frame {index}: size {} vs {}",
                    g.size,
                    w.size
                );
                assert!(
                    (g.ecc - w.ecc).abs() <= 1e-3,
                    "{name} frame {index}: ecc {} vs {}",
                    g.ecc,
                    w.ecc
                );
                assert!(
                    close(g.signal, w.signal, 1e-3),
                    "{name} frame {index}: signal {} vs {}",
                    g.signal,
                    w.signal
                );
                assert!(
                    close(g.ep, w.ep, 1e-3),
                    "{name} frame {index}: ep {} vs {}",
                    g.ep,
                    w.ep
                );
                compared += 1;
            }
        }
    }
    eprintln!(
        "compared {compared} features; worst position error {worst_position:.2e} px, worst mass error {worst_mass:.2e}"
    );
    assert!(compared > 1000);
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
