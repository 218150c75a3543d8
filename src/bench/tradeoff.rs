//! Run time against error: sweeps of a stage's settings, each point timed
//! and scored in the same process run, with the Pareto front marked.
//!
//! Seeds: every data set and training run of the sweeps draws from
//! [`derive_seed`]`(`[`SEED`]`, kind, name)`, as the artefacts of a manifest
//! do (see [`seed`]).

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::detect::crocker_grier::{self, CrockerGrierParams};
use crate::metrics;
use crate::progress::hidden;
use crate::report::figures::{TradeoffChart, tradeoff_chart};
use crate::sim::{self, Distribution, SimParams};
use crate::types::derive_seed;
use crate::types::{Dataset, Prediction};

/// The master seed of the sweeps.
pub const SEED: u64 = 0;

/// The seed of the sweeps' data set or detector `name` (`kind` is
/// `"dataset"` or `"detector"`): `derive_seed(SEED, kind, name)`.
pub fn seed(kind: &str, name: &str) -> u64 {
    derive_seed(SEED, kind, name)
}

/// One setting of a sweep: its speed and its error.
#[derive(Debug, Clone, Serialize)]
pub struct TradeoffPoint {
    pub setting: String,
    pub frames_per_second: f64,
    /// The error measure of the sweep (see each sweep's documentation).
    pub error: f64,
    /// Further numbers of the point (e.g. AUC per ε).
    pub extra: Vec<(String, f64)>,
    pub pareto: bool,
    /// Whether this is the sweep's reference setting (scanloc's default),
    /// against which [`add_speed_ratios`] expresses every point's speed.
    pub reference: bool,
}

/// Adds the timing ratios against the sweep's reference point (the one
/// with [`TradeoffPoint::reference`], timed in the same process run, so the
/// machine's load and speed cancel): `speed_vs_reference` (frames/s over
/// the reference's; above 1 is faster) and, when the points have a
/// `training_seconds` extra, `training_time_vs_reference` (below 1 is
/// faster). Without a reference point nothing is added.
pub(crate) fn add_speed_ratios(points: &mut [TradeoffPoint]) {
    let Some(reference) = points.iter().find(|p| p.reference).cloned() else {
        return;
    };
    let reference_training = extra(&reference, "training_seconds");
    for point in points.iter_mut() {
        let training_ratio = extra(point, "training_seconds") / reference_training;
        point.extra.insert(
            0,
            (
                "speed_vs_reference".into(),
                point.frames_per_second / reference.frames_per_second,
            ),
        );
        if !reference_training.is_nan() {
            point
                .extra
                .insert(1, ("training_time_vs_reference".into(), training_ratio));
        }
    }
}

/// For each point, whether no other point is at least as good in both
/// coordinates and better in one (lower is better in both). A point with a
/// non-finite coordinate (e.g. a locator that found nothing: RMSE ∞) is
/// never on the front.
pub fn pareto_flags(points: &[(f64, f64)]) -> Vec<bool> {
    points
        .iter()
        .map(|&(cost, error)| {
            cost.is_finite()
                && error.is_finite()
                && !points.iter().any(|&(other_cost, other_error)| {
                    other_cost <= cost
                        && other_error <= error
                        && (other_cost < cost || other_error < error)
                })
        })
        .collect()
}

/// Marks the points no other point beats in both speed and error.
pub(crate) fn mark_pareto_front(points: &mut [TradeoffPoint]) {
    let flags = pareto_flags(
        &points
            .iter()
            .map(|p| (-p.frames_per_second, p.error))
            .collect::<Vec<_>>(),
    );
    for (point, flag) in points.iter_mut().zip(flags) {
        point.pareto = flag;
    }
}

/// Timing repetitions of the cheap stages (simulator, Crocker–Grier): the
/// fastest is kept, which discards the first run's warm-up (thread pool,
/// caches) and most of the noise of a shared machine.
const TIMING_REPEATS: usize = 3;

/// Runs `work` `repeats` times; its last result and the shortest wall time
/// in seconds.
fn fastest_of<T>(
    repeats: usize,
    mut work: impl FnMut() -> anyhow::Result<T>,
) -> anyhow::Result<(T, f64)> {
    let mut fastest = f64::INFINITY;
    let mut result = None;
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        let output = work()?;
        fastest = fastest.min(start.elapsed().as_secs_f64());
        result = Some(output);
    }
    Ok((result.expect("at least one repetition ran"), fastest))
}

/// The value of extra `name` of `point` (NaN if it has none).
pub fn extra(point: &TradeoffPoint, name: &str) -> f64 {
    point
        .extra
        .iter()
        .find(|(key, _)| key == name)
        .map_or(f64::NAN, |(_, value)| *value)
}

/// The paper's microscope at N_qd `brightness`, margin 4 px, fixed D.
fn test_params(brightness: f64, diffusion: f64) -> SimParams {
    SimParams {
        diffusion_um2_s: Distribution::Fixed(diffusion),
        margin_px: 4.0,
        brightness: brightness.into(),
        ..SimParams::default()
    }
}

/// The test sets every locator sweep is scored on: D = 1 µm²/s (`frames`
/// frames, the error axis) and a static QD, D = 0 (`static_frames`, for
/// the distance to the Cramér–Rao floor).
pub(crate) struct TestSets {
    pub moving: Dataset,
    pub still: Dataset,
}

impl TestSets {
    pub(crate) fn simulate(
        frames: usize,
        static_frames: usize,
        brightness: f64,
    ) -> anyhow::Result<Self> {
        Ok(Self {
            moving: sim::simulate(
                &test_params(brightness, 1.0),
                seed("dataset", "test-moving"),
                0..frames,
                &hidden(),
            )?,
            still: sim::simulate(
                &test_params(brightness, 0.0),
                seed("dataset", "test-static"),
                0..static_frames,
                &hidden(),
            )?,
        })
    }
}

/// Scores `predictions` of `dataset`: (RMSE of the top prediction, extras
/// named with `prefix`: AUC per ε and the fraction of frames without one).
fn score_extras(
    predictions: &[Prediction],
    dataset: &Dataset,
) -> anyhow::Result<(f64, Vec<(String, f64)>)> {
    let score = metrics::score(
        predictions,
        &dataset.truth,
        dataset.frames.n,
        &metrics::PAPER_EPS_PX,
        false,
    )?;
    let extras = score
        .per_eps
        .iter()
        .map(|e| (format!("auc_eps{}", e.eps_px), e.auc))
        .chain([(
            "fraction_without_prediction".to_string(),
            score.fraction_without_prediction,
        )])
        .collect();
    Ok((score.rmse_top_px.unwrap_or(f64::INFINITY), extras))
}

/// Radius (px) within which a static-set top prediction counts as the QD
/// found, for [`static_extras`]' precision: the largest ε of the metric.
pub(crate) const FOUND_RADIUS_PX: f64 = 3.0;

/// The static-QD (D = 0) errors of `predictions`, as extras:
/// `rmse_static_px` (every frame's top prediction; ∞ if none has one),
/// `precision_static_px` (RMSE over the frames whose top prediction lies
/// within [`FOUND_RADIUS_PX`] of the QD: the localisation precision the
/// Cramér–Rao bound speaks of, free of the wrong-spot outliers that dominate
/// the RMSE) and `found_static` (the fraction of frames counted there).
fn static_extras(
    predictions: &[Prediction],
    still: &Dataset,
) -> anyhow::Result<Vec<(String, f64)>> {
    let errors = metrics::top_prediction_errors(predictions, &still.truth, still.frames.n)?;
    let root_mean_square = |values: &[f64]| {
        if values.is_empty() {
            f64::INFINITY
        } else {
            (values.iter().map(|e| e * e).sum::<f64>() / values.len() as f64).sqrt()
        }
    };
    let located: Vec<f64> = errors.iter().flatten().copied().collect();
    let found: Vec<f64> = located
        .iter()
        .copied()
        .filter(|&e| e <= FOUND_RADIUS_PX)
        .collect();
    Ok(vec![
        ("rmse_static_px".into(), root_mean_square(&located)),
        ("precision_static_px".into(), root_mean_square(&found)),
        (
            "found_static".into(),
            found.len() as f64 / still.frames.n.max(1) as f64,
        ),
    ])
}

/// Simulator: substeps 1…16 and PSF cut-off (none … 2σ). Speed: frames/s
/// simulating the paper's frames at D = 1 µm²/s (fastest of
/// [`TIMING_REPEATS`]). Error: the largest
/// per-pixel difference, in expected photons, between the setting's expected
/// image and the exact one (no cut-off, 64 substeps) of a static QD (D = 0,
/// so both see the same QD; the random walk does not depend on these
/// settings except through the path's sampling), over 200 frames. Speed
/// ratios are against the simulator's default (1 substep, 6σ cut-off).
pub(crate) fn simulator_sweep(frames: usize) -> anyhow::Result<Vec<TradeoffPoint>> {
    let base = SimParams {
        margin_px: 4.0,
        ..SimParams::default()
    };
    let exact = SimParams {
        diffusion_um2_s: Distribution::Fixed(0.0),
        substeps: 64,
        psf_cutoff_sigma: None,
        ..base.clone()
    };
    let static_seed = seed("dataset", "simulator-static");
    let timing_seed = seed("dataset", "simulator-timing");
    let exact_images: Vec<Vec<f64>> = (0..200)
        .map(|i| sim::expected_frame(&exact, static_seed, i).0)
        .collect();
    let default = SimParams::default();
    let mut points = Vec::new();
    for substeps in [1u32, 2, 4, 8, 16] {
        for cutoff in [None, Some(6.0), Some(5.0), Some(4.0), Some(3.0), Some(2.0)] {
            let params = SimParams {
                substeps,
                psf_cutoff_sigma: cutoff,
                ..base.clone()
            };
            let (_, seconds) = fastest_of(TIMING_REPEATS, || {
                Ok(std::hint::black_box(sim::simulate(
                    &params,
                    timing_seed,
                    0..frames,
                    &hidden(),
                )?))
            })?;
            let fps = frames as f64 / seconds;
            let still = SimParams {
                diffusion_um2_s: Distribution::Fixed(0.0),
                ..params.clone()
            };
            let error = exact_images
                .iter()
                .enumerate()
                .map(|(i, exact_image)| {
                    let (image, _) = sim::expected_frame(&still, static_seed, i);
                    image
                        .iter()
                        .zip(exact_image)
                        .map(|(a, b)| (a - b).abs())
                        .fold(0.0f64, f64::max)
                })
                .fold(0.0f64, f64::max);
            let cutoff_label = cutoff.map_or("none".to_string(), |c| format!("{c}σ"));
            points.push(TradeoffPoint {
                setting: format!("substeps {substeps}, cut-off {cutoff_label}"),
                frames_per_second: fps,
                error,
                extra: vec![],
                pareto: false,
                reference: substeps == default.substeps && cutoff == default.psf_cutoff_sigma,
            });
        }
    }
    mark_pareto_front(&mut points);
    add_speed_ratios(&mut points);
    Ok(points)
}

/// TrackPy's diameter in the paper experiment (`experiments/paper.yaml`):
/// the Crocker–Grier sweep's reference setting, with preprocessing.
const PAPER_DIAMETER: usize = 7;

/// Crocker–Grier: diameter and preprocessing. Speed: frames/s on the
/// D = 1 µm²/s test set (fastest of [`TIMING_REPEATS`]); ratios against
/// the paper's setting (diameter 7, preprocessing on). Error: RMSE (px) of
/// each frame's top prediction
/// there; AUC per ε, the fraction of frames without a prediction and the
/// static-set errors of [`static_extras`] as extras.
pub(crate) fn crocker_grier_sweep(tests: &TestSets) -> anyhow::Result<Vec<TradeoffPoint>> {
    let frames = tests.moving.frames.n;
    let mut points = Vec::new();
    for diameter in [3usize, 5, 7, 9, 11] {
        for preprocess in [true, false] {
            let detector = CrockerGrierParams {
                diameter,
                minmass: Some(0.0),
                preprocess,
                ..Default::default()
            };
            let (features, seconds) = fastest_of(TIMING_REPEATS, || {
                crocker_grier::locate_stack(&tests.moving.frames, &detector, &hidden())
            })?;
            let fps = frames as f64 / seconds;
            let predictions = crocker_grier::to_predictions(&features);
            let (rmse, mut extras) = score_extras(&predictions, &tests.moving)?;
            let still = crocker_grier::to_predictions(&crocker_grier::locate_stack(
                &tests.still.frames,
                &detector,
                &hidden(),
            )?);
            extras.extend(static_extras(&still, &tests.still)?);
            points.push(TradeoffPoint {
                setting: format!("diameter {diameter}, preprocess {preprocess}"),
                frames_per_second: fps,
                error: rmse,
                extra: extras,
                pareto: false,
                reference: diameter == PAPER_DIAMETER && preprocess,
            });
        }
    }
    mark_pareto_front(&mut points);
    add_speed_ratios(&mut points);
    Ok(points)
}

/// What the CNN sweep trains and scores.
#[derive(Debug, Clone)]
pub(crate) struct CnnSweep {
    /// Frames of the fixed training set (D uniform in [0.75, 1.75]).
    pub train_frames: usize,
    /// Hidden conv channels to try.
    pub channels: Vec<usize>,
    /// Numbers of hidden conv layers to try (see [`dilations_for_depth`]).
    pub depths: Vec<usize>,
    /// Epoch counts to try (each its own training run, cosine schedule
    /// stretched over its epochs).
    pub epochs: Vec<usize>,
    /// N_qd of the training frames.
    pub brightness: f64,
}

/// The dilations of a network with `depth` hidden layers: rising then
/// falling, so that the receptive field grows with depth (6 is the
/// library's default).
pub(crate) fn dilations_for_depth(depth: usize) -> anyhow::Result<Vec<usize>> {
    Ok(match depth {
        2 => vec![1, 2],
        3 => vec![1, 2, 1],
        4 => vec![1, 2, 4, 1],
        5 => vec![1, 1, 2, 4, 1],
        6 => vec![1, 1, 2, 4, 2, 1],
        7 => vec![1, 1, 2, 4, 4, 2, 1],
        8 => vec![1, 1, 2, 4, 8, 4, 2, 1],
        other => crate::bail_input!("--cnn-depths: each must be in 2..=8, got {other}"),
    })
}

/// CNN: width, depth and epochs. Each setting is trained from the same
/// seed on the same frames (no validation split: the last epoch is kept)
/// and timed. Speed: inference frames/s on the D = 1 test set. Error: RMSE
/// of the top prediction there. Extras: `training_seconds`, AUC per ε, the
/// fraction without a prediction, the static-set errors of
/// [`static_extras`], and `pareto_training`
/// (1 if no setting trains at least as fast with at most the error).
/// `progress` counts settings.
pub(crate) fn cnn_sweep(
    sweep: &CnnSweep,
    tests: &TestSets,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<Vec<TradeoffPoint>> {
    use crate::detect::cnn::{self, CnnArchitecture, TrainingSettings};
    let training_params = SimParams {
        diffusion_um2_s: Distribution::Random(sim::RandomDistribution::Uniform([0.75, 1.75])),
        margin_px: 4.0,
        brightness: sweep.brightness.into(),
        ..SimParams::default()
    };
    let training = sim::simulate(
        &training_params,
        seed("dataset", "cnn-training"),
        0..sweep.train_frames,
        &hidden(),
    )?;
    let training_seed = seed("detector", "cnn");
    let settings_count = sweep.channels.len() * sweep.depths.len() * sweep.epochs.len();
    progress.set_length(settings_count as u64);
    let default = CnnArchitecture::default();
    let longest_epochs = sweep.epochs.iter().max();
    let mut points = Vec::with_capacity(settings_count);
    for &depth in &sweep.depths {
        let dilations = dilations_for_depth(depth)?;
        for &channels in &sweep.channels {
            for &epochs in &sweep.epochs {
                let architecture = CnnArchitecture {
                    channels,
                    dilations: dilations.clone(),
                    ..CnnArchitecture::default()
                };
                let settings = TrainingSettings {
                    epochs,
                    validation_fraction: 0.0,
                    ..TrainingSettings::default()
                };
                let start = Instant::now();
                // No validation frames: the score is never computed.
                let model = cnn::train(
                    &architecture,
                    &settings,
                    &training,
                    None,
                    training_seed,
                    &metrics::paper_aucs,
                    &hidden(),
                )?;
                let training_seconds = start.elapsed().as_secs_f64();
                let start = Instant::now();
                let predictions = model.locate(&tests.moving.frames, &hidden())?;
                let fps = tests.moving.frames.n as f64 / start.elapsed().as_secs_f64();
                let (rmse, mut extras) = score_extras(&predictions, &tests.moving)?;
                let still = model.locate(&tests.still.frames, &hidden())?;
                extras.extend(static_extras(&still, &tests.still)?);
                extras.insert(0, ("training_seconds".into(), training_seconds));
                let setting = format!("{channels} ch × {depth} layers, {epochs} epochs");
                progress.println(format!(
                    "{setting}: trained in {training_seconds:.1} s, {fps:.0} frames/s, RMSE {rmse:.3} px"
                ));
                progress.inc(1);
                points.push(TradeoffPoint {
                    setting,
                    frames_per_second: fps,
                    error: rmse,
                    extra: extras,
                    pareto: false,
                    // The library's default network at the longest training
                    // swept.
                    reference: channels == default.channels
                        && dilations == default.dilations
                        && Some(&epochs) == longest_epochs,
                });
            }
        }
    }
    mark_pareto_front(&mut points);
    let by_training = pareto_flags(
        &points
            .iter()
            .map(|p| (extra(p, "training_seconds"), p.error))
            .collect::<Vec<_>>(),
    );
    for (point, flag) in points.iter_mut().zip(by_training) {
        point
            .extra
            .push(("pareto_training".into(), f64::from(u8::from(flag))));
    }
    add_speed_ratios(&mut points);
    Ok(points)
}

/// The Cramér–Rao lower bound on the 2-D localisation RMSE (px) of a static
/// QD (D = 0, in focus) with this microscope: the inverse Fisher information
/// of the expected counts under Poisson noise (Mortensen et al., Nat.
/// Methods 7:377, 2010, for a Poisson detector), `I = Σ_pixels ∇μ ∇μᵀ / μ`,
/// with `μ` the simulator's own forward model
/// ([`sim::static_emitter_image`]: the scanned PSF plus background).
/// Averaged (as variance) over `positions × positions` sub-pixel QD
/// positions near the frame centre.
///
/// The bound is of one microscope: a brightness or background given as a
/// distribution is refused (the error names the field).
pub fn cramer_rao_rmse_px(
    params: &SimParams,
    positions: usize,
) -> Result<f64, crate::error::FieldError> {
    let mut total_variance = 0.0;
    let mut count = 0usize;
    for iy in 0..positions {
        for ix in 0..positions {
            // TrackPy pixel coordinates, a pixel centre plus a fraction.
            let x = params.width as f64 / 2.0 - 0.5 + ix as f64 / positions as f64;
            let y = params.height as f64 / 2.0 - 0.5 + iy as f64 / positions as f64;
            let image = sim::static_emitter_image(params, x, y, 0.0)?;
            let (mut ixx, mut ixy, mut iyy) = (0.0, 0.0, 0.0);
            for ((&expected, &dx), &dy) in image.expected.iter().zip(&image.d_dx).zip(&image.d_dy) {
                if expected > 0.0 {
                    ixx += dx * dx / expected;
                    ixy += dx * dy / expected;
                    iyy += dy * dy / expected;
                }
            }
            let determinant = ixx * iyy - ixy * ixy;
            if determinant > 0.0 {
                total_variance += (ixx + iyy) / determinant;
                count += 1;
            }
        }
    }
    Ok(if count == 0 {
        f64::INFINITY
    } else {
        (total_variance / count as f64).sqrt()
    })
}

/// Writes a sweep as `NAME.csv` (every point with its extras) and a
/// frames/s-against-error plot `NAME.png`/`NAME.svg` with the Pareto front
/// drawn as a line. With `floor` (the Cramér–Rao bound, which holds for a
/// static QD) the plot also shows each setting's `precision_static_px`, so
/// the distance to the floor can be read off.
pub(crate) fn write_sweep(
    dir: &Path,
    name: &str,
    error_label: &str,
    points: &[TradeoffPoint],
    floor: Option<f64>,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir)?;
    let mut header = vec![
        "setting".to_string(),
        "frames_per_second".into(),
        "error".into(),
        "pareto".into(),
    ];
    if let Some(first) = points.first() {
        header.extend(first.extra.iter().map(|(k, _)| k.clone()));
    }
    let rows = points.iter().map(|p| {
        let mut record = vec![
            p.setting.clone(),
            p.frames_per_second.to_string(),
            p.error.to_string(),
            p.pareto.to_string(),
        ];
        record.extend(p.extra.iter().map(|(_, v)| v.to_string()));
        record
    });
    crate::io::csv_tables::write_table(&dir.join(format!("{name}.csv")), &header, rows)?;
    let flags: Vec<bool> = points.iter().map(|p| p.pareto).collect();
    plot_sweep(
        &dir.join(name),
        &format!("{name}: speed against error"),
        ("frames per second", error_label),
        points,
        |p| p.frames_per_second,
        &flags,
        floor,
    )
}

/// Plots a CNN sweep's training time against its error as
/// `NAME_training.png`/`.svg`, with the front of `pareto_training`.
pub(crate) fn write_training_plot(
    dir: &Path,
    name: &str,
    error_label: &str,
    points: &[TradeoffPoint],
    floor: Option<f64>,
) -> anyhow::Result<()> {
    let flags: Vec<bool> = points
        .iter()
        .map(|p| extra(p, "pareto_training") == 1.0)
        .collect();
    plot_sweep(
        &dir.join(format!("{name}_training")),
        &format!("{name}: training time against error"),
        ("training time (s)", error_label),
        points,
        |p| extra(p, "training_seconds"),
        &flags,
        floor,
    )
}

fn plot_sweep(
    base: &Path,
    title: &str,
    (x_label, y_label): (&str, &str),
    points: &[TradeoffPoint],
    x: impl Fn(&TradeoffPoint) -> f64,
    front_flags: &[bool],
    floor: Option<f64>,
) -> anyhow::Result<()> {
    let mut front: Vec<(f64, f64)> = points
        .iter()
        .zip(front_flags)
        .filter(|(_, on_front)| **on_front)
        .map(|(p, _)| (x(p), p.error))
        .collect();
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    let static_points = match floor {
        Some(_) => points
            .iter()
            .map(|p| (x(p), extra(p, "precision_static_px")))
            .filter(|(_, e)| e.is_finite())
            .collect(),
        None => Vec::new(),
    };
    tradeoff_chart(
        base,
        &TradeoffChart {
            title: title.to_string(),
            x_label: x_label.to_string(),
            y_label: y_label.to_string(),
            points: points.iter().map(|p| (x(p), p.error)).collect(),
            front,
            static_points,
            floor: floor.map(|f| ("Cramér–Rao floor (D = 0)".to_string(), f)),
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pareto_front_keeps_only_undominated_points() {
        let point = |fps: f64, error: f64| TradeoffPoint {
            setting: String::new(),
            frames_per_second: fps,
            error,
            extra: vec![],
            pareto: false,
            reference: false,
        };
        let mut points = vec![
            point(10.0, 1.0),
            point(5.0, 0.5),
            point(4.0, 0.9),
            point(10.0, 2.0),
        ];
        mark_pareto_front(&mut points);
        let front: Vec<bool> = points.iter().map(|p| p.pareto).collect();
        assert_eq!(front, vec![true, true, false, false]);
    }

    #[test]
    fn speed_ratios_are_against_the_reference_point() {
        let point = |fps: f64, training: f64, reference: bool| TradeoffPoint {
            setting: String::new(),
            frames_per_second: fps,
            error: 1.0,
            extra: vec![("training_seconds".into(), training)],
            pareto: false,
            reference,
        };
        let mut points = vec![
            point(300.0, 5.0, false),
            point(100.0, 20.0, true),
            point(50.0, 40.0, false),
        ];
        add_speed_ratios(&mut points);
        let ratios: Vec<(f64, f64)> = points
            .iter()
            .map(|p| {
                (
                    extra(p, "speed_vs_reference"),
                    extra(p, "training_time_vs_reference"),
                )
            })
            .collect();
        assert_eq!(ratios, [(3.0, 0.25), (1.0, 1.0), (0.5, 2.0)]);
        // Without training times only the speed ratio is added.
        let mut untrained = vec![TradeoffPoint {
            extra: vec![],
            ..point(10.0, 0.0, true)
        }];
        add_speed_ratios(&mut untrained);
        assert_eq!(
            untrained[0].extra,
            [("speed_vs_reference".to_string(), 1.0)]
        );
    }

    #[test]
    fn settings_that_locate_nothing_are_never_on_the_front() {
        let flags = pareto_flags(&[(1.0, f64::INFINITY), (2.0, 3.0), (f64::NAN, 1.0)]);
        assert_eq!(flags, vec![false, true, false]);
    }

    #[test]
    fn cramer_rao_bound_shrinks_with_brightness_like_one_over_root_n() {
        // Without background the bound scales as 1/√N_qd exactly.
        let dim = SimParams {
            brightness: 100.0.into(),
            background: 0.0.into(),
            height: 32,
            width: 32,
            ..SimParams::default()
        };
        let bright = SimParams {
            brightness: 400.0.into(),
            ..dim.clone()
        };
        let ratio = cramer_rao_rmse_px(&dim, 3).unwrap() / cramer_rao_rmse_px(&bright, 3).unwrap();
        assert!((ratio - 2.0).abs() < 1e-6, "ratio {ratio}");
        // For a Gaussian spot without background, each axis has variance
        // σ²/N_signal (photons); σ = 3 px, N_signal = Σ μ.
        let sigma_px = dim.sigma_xy_um / dim.pixel_size_um;
        let photons = 100.0
            / (dim.pixel_size_um * dim.pixel_size_um)
            / (2.0 * std::f64::consts::PI * dim.sigma_z_um * dim.sigma_z_um).sqrt();
        let expected = (2.0 * sigma_px * sigma_px / photons).sqrt();
        let got = cramer_rao_rmse_px(&dim, 3).unwrap();
        // A distribution is not one microscope: refused, naming the field.
        let spread = SimParams {
            background: "uniform:0,1".parse().unwrap(),
            ..dim.clone()
        };
        let error = cramer_rao_rmse_px(&spread, 3).unwrap_err();
        assert_eq!(error.field(), "background");
        assert!((got / expected - 1.0).abs() < 1e-3, "{got} vs {expected}");
    }
}
