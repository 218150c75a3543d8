//! Numerical stress: the simulator and the noise model from degenerate to
//! extreme parameters, and the frame readers on damaged files. Nothing may
//! panic; results are finite or refused with a clear input error. The
//! reader tests are fuzzing tests: `make fuzz` runs them with
//! `SCANLOC_FUZZ_CASES` cases each.

use crate::common;

use proptest::prelude::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use scanloc::error::exit_code;
use scanloc::io;
use scanloc::progress::hidden;
use scanloc::sim::{Distribution, RandomDistribution, SimParams, noise, simulate};
use scanloc::types::FrameStack;

fn log_uniform(low: f64, high: f64) -> impl Strategy<Value = f64> {
    (low.ln()..high.ln()).prop_map(f64::exp)
}

/// A photometry parameter: fixed (often 0), or drawn per frame from a
/// uniform between two values of the same range.
fn photometry(high: f64) -> impl Strategy<Value = Distribution> {
    prop_oneof![
        2 => Just(Distribution::Fixed(0.0)),
        4 => log_uniform(1e-3, high).prop_map(Distribution::Fixed),
        2 => (log_uniform(1e-3, high), log_uniform(1e-3, high)).prop_map(|(a, b)| {
            Distribution::Random(RandomDistribution::Uniform([a.min(b), a.max(b)]))
        }),
    ]
}

prop_compose! {
    fn extreme_params()(
        diffusion in prop_oneof![Just(0.0), log_uniform(1e-6, 100.0)],
        brightness in photometry(1e6),
        background in photometry(1e4),
        height in prop_oneof![Just(1usize), 1usize..64, Just(512usize)],
        width in prop_oneof![Just(1usize), 1usize..64],
        sigma_xy in log_uniform(1e-4, 100.0),
        sigma_z in log_uniform(1e-3, 1e3),
        z_start in prop_oneof![Just(0.0), -1e3..1e3f64],
        substeps in 1u32..5,
        emitters in 0u32..4,
        cutoff in prop_oneof![Just(None), (0.5..8.0f64).prop_map(Some)],
    ) -> SimParams {
        SimParams {
            height,
            width,
            sigma_xy_um: sigma_xy,
            sigma_z_um: sigma_z,
            background,
            brightness,
            diffusion_um2_s: Distribution::Fixed(diffusion),
            z_start: Distribution::Fixed(z_start),
            substeps,
            emitters: emitters.into(),
            psf_cutoff_sigma: cutoff,
            ..SimParams::default()
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[test]
    fn simulator_gives_finite_results_or_a_clear_error(params in extreme_params(), seed in any::<u64>()) {
        // 512-row frames are costly: keep their stacks short.
        let frames = if params.height * params.width > 10_000 { 1 } else { 3 };
        match simulate(&params, seed, 0..frames, &hidden()) {
            Ok(dataset) => {
                prop_assert_eq!(dataset.frames.data.len(), frames * params.height * params.width);
                prop_assert_eq!(dataset.truth.len(), frames * params.emitters.max() as usize);
                for t in &dataset.truth {
                    for value in [t.x, t.y, t.x_start, t.y_start, t.x_end, t.y_end, t.z_mean, t.diffusion] {
                        prop_assert!(value.is_finite(), "non-finite truth {:?}", t);
                    }
                }
                let (expected, _) = scanloc::sim::expected_frame(&params, seed, 0);
                prop_assert!(expected.iter().all(|e| e.is_finite() && *e >= 0.0));
            }
            Err(error) => {
                // Only overflowing or non-finite expected counts may be refused.
                prop_assert_eq!(exit_code(&error), 2, "{}", error);
                let message = error.to_string();
                prop_assert!(message.contains("uint32") || message.contains("not finite"), "{}", message);
            }
        }
    }
}

#[test]
fn poisson_sampling_has_the_right_mean_and_variance_from_0_to_1e9() {
    let mut rng = ChaCha8Rng::seed_from_u64(99);
    let n = 20_000;
    for lambda in [0.0, 1e-3, 0.5, 8.4, 29.99, 30.0, 100.0, 1e4, 1e6, 1e9] {
        let draws: Vec<f64> = (0..n)
            .map(|_| noise::poisson(&mut rng, lambda) as f64)
            .collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let variance = draws.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        if lambda == 0.0 {
            assert!(draws.iter().all(|&d| d == 0.0));
            continue;
        }
        // Mean: 5 standard errors √(λ/n). Variance: its standard error is
        // √((μ4 − λ²)/n) with μ4 = λ(1 + 3λ); allow 5.
        let mean_tolerance = 5.0 * (lambda / n as f64).sqrt();
        let variance_tolerance =
            5.0 * ((lambda * (1.0 + 3.0 * lambda) - lambda * lambda) / n as f64).sqrt();
        assert!(
            (mean - lambda).abs() < mean_tolerance,
            "λ {lambda}: mean {mean}"
        );
        assert!(
            (variance - lambda).abs() < variance_tolerance,
            "λ {lambda}: variance {variance}"
        );
    }
}

#[test]
fn background_table_matches_poisson_for_every_table_mean() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let n = 50_000;
    for lambda in [0.01, 1.0, 8.4, 20.0] {
        let table = noise::PoissonTable::new(lambda);
        let draws: Vec<f64> = (0..n).map(|_| table.sample(&mut rng) as f64).collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let zeros = draws.iter().filter(|&&d| d == 0.0).count() as f64 / n as f64;
        let p0 = (-lambda).exp();
        assert!(
            (mean - lambda).abs() < 5.0 * (lambda / n as f64).sqrt(),
            "λ {lambda}: mean {mean}"
        );
        assert!(
            (zeros - p0).abs() < 5.0 * (p0 * (1.0 - p0) / n as f64).sqrt() + 1e-12,
            "λ {lambda}: P(0) {zeros} vs {p0}"
        );
    }
}

fn valid_file(dir: &std::path::Path, name: &str) -> Vec<u8> {
    let frames = FrameStack::from_vec(2, 3, 4, (0..24).map(|v| v * 1000).collect()).unwrap();
    let path = dir.join(name);
    io::write_frames(&path, &frames).unwrap();
    std::fs::read(&path).unwrap()
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::fuzz_cases(256), ..ProptestConfig::default() })]

    /// A fuzzing test of the readers: valid files with random bytes
    /// overwritten, truncated or extended must read or be refused with an
    /// input error, never panic or exhaust memory.
    #[test]
    fn damaged_frame_files_are_refused_cleanly(
        extension in prop_oneof![Just("npy"), Just("tif")],
        edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        truncate in proptest::option::of(any::<prop::sample::Index>()),
        append in proptest::collection::vec(any::<u8>(), 0..16),
    ) {
        let dir = common::fuzz_case_dir();
        let mut bytes = valid_file(dir.path(), &format!("valid.{extension}"));
        for (index, value) in &edits {
            let at = index.index(bytes.len());
            bytes[at] = *value;
        }
        if let Some(index) = truncate {
            bytes.truncate(index.index(bytes.len()));
        }
        bytes.extend(append);
        let path = dir.path().join(format!("damaged.{extension}"));
        std::fs::write(&path, &bytes).unwrap();
        match io::read_frames(&path) {
            Ok(frames) => prop_assert_eq!(frames.data.len(), frames.n * frames.height * frames.width),
            Err(error) => {
                prop_assert_eq!(exit_code(&error), 2, "{:#}", error);
                prop_assert!(error.to_string().contains("damaged."), "{}", error);
            }
        }
        // The reader of counts or real values (float pages) alike.
        match io::read_recording_of_channel(&path, None) {
            Ok(recording) => {
                let (n, height, width) = recording.shape();
                let len = match &recording {
                    scanloc::types::Recording::Counts(frames) => frames.data.len(),
                    scanloc::types::Recording::Real(frames) => frames.data.len(),
                };
                prop_assert_eq!(len, n * height * width);
            }
            Err(error) => {
                prop_assert_eq!(exit_code(&error), 2, "{:#}", error);
                prop_assert!(error.to_string().contains("damaged."), "{}", error);
            }
        }
    }

    #[test]
    fn random_bytes_are_refused_cleanly(
        extension in prop_oneof![Just("npy"), Just("tif")],
        bytes in proptest::collection::vec(any::<u8>(), 0..512),
    ) {
        let dir = common::fuzz_case_dir();
        let path = dir.path().join(format!("random.{extension}"));
        std::fs::write(&path, &bytes).unwrap();
        if let Err(error) = io::read_frames(&path) {
            prop_assert_eq!(exit_code(&error), 2, "{:#}", error);
        }
        if let Err(error) = io::read_recording_of_channel(&path, None) {
            prop_assert_eq!(exit_code(&error), 2, "{:#}", error);
        }
    }
}
