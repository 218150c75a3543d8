//! The simulator against the physics of docs/simulator.md: statistics with stated
//! tolerances, the analytic PSF, the cut-off bound and determinism.

use scanloc::progress::hidden;
use scanloc::sim::{self, DetectorNoise, Distribution, SimParams, simulate};

fn paper(diffusion: f64) -> SimParams {
    SimParams {
        diffusion_um2_s: Distribution::Fixed(diffusion),
        ..SimParams::default()
    }
}

fn mean_and_variance(values: impl Iterator<Item = f64>) -> (f64, f64, usize) {
    let values: Vec<f64> = values.collect();
    let n = values.len();
    let mean = values.iter().sum::<f64>() / n as f64;
    let variance = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    (mean, variance, n)
}

#[test]
fn end_minus_start_displacement_has_variance_2_d_t() {
    // Between the first and the last sample there are H·W·s − 1 dwell steps
    // of δt/s and H − 1 retraces, so each axis moves N(0, 2·D·t).
    let params = SimParams {
        margin_px: 0.0,
        ..paper(1.0)
    };
    let frames = 4000;
    let dataset = simulate(&params, 11, 0..frames, &hidden()).unwrap();
    let t = (params.height * params.width - 1) as f64 * params.dwell_us * 1e-6
        + (params.height - 1) as f64 * params.retrace_ms * 1e-3;
    let expected_px2 = 2.0 * 1.0 * t / (params.pixel_size_um * params.pixel_size_um);
    for axis in ["x", "y"] {
        let (mean, variance, n) = mean_and_variance(dataset.truth.iter().map(|r| match axis {
            "x" => r.x_end - r.x_start,
            _ => r.y_end - r.y_start,
        }));
        // The sample variance of n normals has relative standard error
        // √(2/(n−1)) ≈ 2.2 % at n = 4000; allow 5 standard errors.
        let tolerance = 5.0 * (2.0 / (n - 1) as f64).sqrt();
        assert!(
            (variance / expected_px2 - 1.0).abs() < tolerance,
            "{axis}: variance {variance} px², expected {expected_px2} px² (±{tolerance})"
        );
        // The mean displacement is 0 with standard error √(var/n).
        assert!(
            mean.abs() < 5.0 * (expected_px2 / n as f64).sqrt(),
            "{axis}: mean {mean}"
        );
    }
}

#[test]
fn background_only_pixels_are_poisson_with_mean_and_variance_n_bkg() {
    let params = SimParams {
        brightness: 0.0.into(),
        ..paper(1.0)
    };
    let dataset = simulate(&params, 5, 0..200, &hidden()).unwrap();
    let (mean, variance, n) = mean_and_variance(dataset.frames.data.iter().map(|&c| c as f64));
    let lambda = params.background.fixed().unwrap();
    // Standard errors: √(λ/n) for the mean; for the variance
    // √((μ4 − σ⁴)/n) with Poisson μ4 = λ(1 + 3λ). Allow 5 of each.
    let mean_se = (lambda / n as f64).sqrt();
    let variance_se = ((lambda * (1.0 + 3.0 * lambda) - lambda * lambda) / n as f64).sqrt();
    assert!((mean - lambda).abs() < 5.0 * mean_se, "mean {mean}");
    assert!(
        (variance - lambda).abs() < 5.0 * variance_se,
        "variance {variance}"
    );
}

/// The analytic expected photons at pixel (r, c) for a static QD at µm
/// position (x, y, z), sampled at `substeps` beam positions across the pixel.
fn analytic_pixel(params: &SimParams, row: usize, column: usize, qd: (f64, f64, f64)) -> f64 {
    let a = params.pixel_size_um;
    let s = params.substeps as usize;
    let (sxy, sz) = (params.sigma_xy_um, params.sigma_z_um);
    let pi = std::f64::consts::PI;
    let beam_y = (row as f64 + 0.5) * a;
    let mut sum = 0.0;
    for j in 0..s {
        let beam_x = (column as f64 + (j as f64 + 0.5) / s as f64) * a;
        sum += params.brightness.fixed().unwrap() / (2.0 * pi * sxy * sxy)
            * (-((qd.0 - beam_x).powi(2) + (qd.1 - beam_y).powi(2)) / (2.0 * sxy * sxy)).exp()
            / (2.0 * pi * sz * sz).sqrt()
            * (-(qd.2 * qd.2) / (2.0 * sz * sz)).exp();
    }
    sum / s as f64 + params.background.fixed().unwrap()
}

#[test]
fn expected_image_of_a_static_qd_matches_the_psf_formula() {
    for substeps in [1, 3] {
        let params = SimParams {
            brightness: 50.0.into(),
            z_start: Distribution::Fixed(0.4),
            psf_cutoff_sigma: None,
            substeps,
            ..paper(0.0)
        };
        for index in 0..5 {
            let (expected, truth) = sim::expected_frame(&params, 9, index);
            let t = truth[0];
            // A static QD: start, end and centroid coincide (to the rounding
            // of a mean over 600 samples).
            assert!((t.x - t.x_start).abs() < 1e-9 && (t.y - t.y_start).abs() < 1e-9);
            assert!((t.x_end - t.x_start).abs() < 1e-12 && (t.z_mean - 0.4).abs() < 1e-12);
            let a = params.pixel_size_um;
            let qd = ((t.x_start + 0.5) * a, (t.y_start + 0.5) * a, 0.4);
            for row in 0..params.height {
                for column in 0..params.width {
                    let want = analytic_pixel(&params, row, column, qd);
                    let got = expected[row * params.width + column];
                    assert!(
                        (got - want).abs() <= 1e-12 * want,
                        "substeps {substeps}, pixel ({row},{column}): {got} vs {want}"
                    );
                }
            }
        }
    }
}

#[test]
fn total_expected_signal_matches_the_analytic_sum() {
    // A static in-focus QD far from the edges of a large frame: the pixel sum
    // of a Gaussian of σ = 3 px is its integral divided by the pixel area to
    // within exp(−2π²σ²) (Poisson summation), so the signal totals
    // N_qd / a² / √(2π σz²) to rounding error.
    let params = SimParams {
        height: 64,
        width: 64,
        margin_px: 28.0,
        brightness: 7.0.into(),
        ..paper(0.0)
    };
    let (expected, _) = sim::expected_frame(&params, 1, 0);
    let signal: f64 = expected
        .iter()
        .map(|e| e - params.background.fixed().unwrap())
        .sum();
    let a = params.pixel_size_um;
    let analytic = params.brightness.fixed().unwrap()
        / (a * a)
        / (2.0 * std::f64::consts::PI * params.sigma_z_um.powi(2)).sqrt();
    // With the default 6σ cut-off, each of the ≤ 4096 pixels may lose at most
    // the bound; the lost mass is far smaller in practice.
    let bound = 4096.0 * params.cutoff_error_bound();
    assert!(
        (signal - analytic).abs() <= bound + 1e-9 * analytic,
        "signal {signal} vs {analytic} (bound {bound})"
    );
}

#[test]
fn psf_cutoff_error_stays_within_the_stated_bound() {
    for (cutoff, diffusion, substeps) in [(2.0, 1.0, 1), (3.0, 1.75, 4), (4.0, 0.0, 1)] {
        let exact = SimParams {
            brightness: 500.0.into(),
            psf_cutoff_sigma: None,
            substeps,
            ..paper(diffusion)
        };
        let cut = SimParams {
            psf_cutoff_sigma: Some(cutoff),
            ..exact.clone()
        };
        let bound = cut.cutoff_error_bound();
        assert!(bound > 0.0);
        let mut largest: f64 = 0.0;
        for index in 0..20 {
            let (a, truth_a) = sim::expected_frame(&exact, 3, index);
            let (b, truth_b) = sim::expected_frame(&cut, 3, index);
            // The cut-off changes no random draw, so the paths coincide.
            assert_eq!(truth_a, truth_b);
            for (x, y) in a.iter().zip(&b) {
                assert!(y <= x, "the cut-off only ever removes signal");
                largest = largest.max(x - y);
            }
        }
        assert!(
            largest <= bound,
            "cutoff {cutoff}σ: error {largest} > bound {bound}"
        );
        // The bound is not vacuous: a harsh cut-off does lose signal.
        if cutoff <= 2.0 {
            assert!(
                largest > 0.01 * bound,
                "cutoff {cutoff}: error {largest} ≪ bound {bound}"
            );
        }
    }
}

#[test]
fn frames_are_identical_across_thread_counts_and_chunking() {
    let params = SimParams {
        diffusion_um2_s: "uniform:0.75,1.75".parse().unwrap(),
        margin_px: 4.0,
        ..SimParams::default()
    };
    let run = |threads: usize, range: std::ops::Range<usize>| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| simulate(&params, 42, range, &hidden()).unwrap())
    };
    let one = run(1, 0..300);
    let two = run(2, 0..300);
    assert_eq!(one, two);
    let mut pieces = run(2, 0..120);
    let rest = run(1, 120..300);
    pieces.frames.append(rest.frames).unwrap();
    pieces.truth.extend(rest.truth);
    // Truth rows carry their dataset-wide frame index.
    assert_eq!(pieces, one);
    let other_seed = simulate(&params, 43, 0..300, &hidden()).unwrap();
    assert_ne!(other_seed.frames, one.frames);
}

#[test]
fn several_emitters_give_one_truth_row_each() {
    let params = SimParams {
        emitters: 3.into(),
        height: 40,
        width: 40,
        ..paper(1.0)
    };
    let dataset = simulate(&params, 2, 0..10, &hidden()).unwrap();
    assert_eq!(dataset.truth.len(), 30);
    for (i, row) in dataset.truth.iter().enumerate() {
        assert_eq!(row.frame, i / 3);
    }
    // Three emitters add three times the signal of one on average.
    let one = simulate(
        &SimParams {
            emitters: 1.into(),
            ..params.clone()
        },
        2,
        0..10,
        &hidden(),
    )
    .unwrap();
    let total = |d: &scanloc::types::Dataset| d.frames.data.iter().map(|&c| c as f64).sum::<f64>();
    let background = params.background.fixed().unwrap() * (10 * 40 * 40) as f64;
    let ratio = (total(&dataset) - background) / (total(&one) - background);
    // Signal per QD ≈ 420 photons × 10 frames, shot noise of the whole
    // stack ≈ √(135k) ≈ 370: the ratio is 3 ± ~0.3.
    assert!((ratio - 3.0).abs() < 0.6, "ratio {ratio}");
}

#[test]
fn pmt_noise_keeps_the_mean_and_scales_the_variance_by_the_excess_factor() {
    let factor = 1.5;
    let params = SimParams {
        brightness: 0.0.into(),
        detector_noise: DetectorNoise::Pmt {
            excess_noise_factor: factor,
        },
        ..paper(1.0)
    };
    let dataset = simulate(&params, 8, 0..200, &hidden()).unwrap();
    let (mean, variance, n) = mean_and_variance(dataset.frames.data.iter().map(|&c| c as f64));
    let lambda = params.background.fixed().unwrap();
    // Rounding to whole counts adds ≈ 1/12 to the variance. Tolerances: 5
    // standard errors of the mean (√(F²λ/n)); 5 % on the variance (its
    // relative standard error is ≈ 1 % at n = 120k).
    assert!(
        (mean - lambda).abs() < 5.0 * (factor * lambda / n as f64).sqrt(),
        "mean {mean}"
    );
    let want = factor * lambda + 1.0 / 12.0;
    assert!(
        (variance / want - 1.0).abs() < 0.05,
        "variance {variance}, want {want}"
    );
}

#[test]
fn start_positions_respect_the_margin() {
    let params = SimParams {
        margin_px: 4.0,
        ..paper(1.0)
    };
    let dataset = simulate(&params, 3, 0..2000, &hidden()).unwrap();
    assert_eq!(dataset.truth.len(), 2000);
    for t in &dataset.truth {
        assert!((3.5..=20.5).contains(&t.x_start), "x_start {}", t.x_start);
        assert!((3.5..=19.5).contains(&t.y_start), "y_start {}", t.y_start);
    }
}

#[test]
fn per_frame_diffusion_follows_its_uniform_distribution() {
    let params = SimParams {
        diffusion_um2_s: "uniform:0.75,1.75".parse().unwrap(),
        ..SimParams::default()
    };
    let dataset = simulate(&params, 4, 0..3000, &hidden()).unwrap();
    let (mean, variance, n) = mean_and_variance(dataset.truth.iter().map(|t| t.diffusion));
    assert!(
        dataset
            .truth
            .iter()
            .all(|t| (0.75..=1.75).contains(&t.diffusion))
    );
    // Uniform[0.75, 1.75]: mean 1.25, variance 1/12; 5 standard errors.
    assert!(
        (mean - 1.25).abs() < 5.0 * (1.0 / 12.0 / n as f64).sqrt(),
        "mean {mean}"
    );
    assert!((variance - 1.0 / 12.0).abs() < 0.01, "variance {variance}");
}

#[test]
fn trajectories_replay_the_walk_behind_the_truth() {
    let params = SimParams {
        emitters: 2.into(),
        substeps: 2,
        ..paper(1.75)
    };
    let dataset = simulate(&params, 21, 0..3, &hidden()).unwrap();
    for frame in 0..3 {
        let paths = sim::trajectories(&params, 21, frame);
        assert_eq!(paths.len(), 2);
        for (emitter, path) in paths.iter().enumerate() {
            let truth = dataset.truth[frame * 2 + emitter];
            assert_eq!(path.len(), params.height * params.width * 2);
            let n = path.len() as f64;
            let mean_x = path.iter().map(|p| p.0).sum::<f64>() / n;
            let mean_y = path.iter().map(|p| p.1).sum::<f64>() / n;
            assert!((mean_x - truth.x).abs() < 1e-9 && (mean_y - truth.y).abs() < 1e-9);
            assert!((path[0].0 - truth.x_start).abs() < 1e-9);
            let last = path[path.len() - 1];
            assert!((last.0 - truth.x_end).abs() < 1e-12 && (last.1 - truth.y_end).abs() < 1e-12);
        }
    }
}
