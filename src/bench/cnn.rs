//! Evaluation and throughput measurements of the CNN, for `scanloc train
//! --test-frames` and the `scanloc bench` sub-benchmarks.
//!
//! Seeds: every data set and training run draws from
//! [`derive_seed`]`(seed, kind, name)` of the seed it is given, as the
//! artefacts of a manifest do.

use std::time::Instant;

use indicatif::ProgressBar;
use serde::Serialize;

use crate::detect::cnn::{self, CnnArchitecture, TrainedCnn, TrainingSettings};
use crate::manifest::derive_seed;
use crate::metrics::{self, PAPER_EPS_PX};
use crate::sim::{self, Distribution, SimParams};
use crate::types::Dataset;

/// The paper's FCNN row of Table 1 (AUC at ε = 1, 2, 3 px for D = 0.75,
/// 1.0, 1.75 µm²/s).
pub const PAPER_FCNN: [(f64, [f64; 3]); 3] = [
    (0.75, [0.48, 0.91, 0.99]),
    (1.0, [0.41, 0.87, 0.98]),
    (1.75, [0.26, 0.72, 0.92]),
];

/// AUCs of a model on one test set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TestRow {
    pub diffusion: f64,
    pub frames: usize,
    /// Seed the test set was simulated with.
    pub seed: u64,
    /// AUC at ε = 1, 2, 3 px.
    pub auc: [f64; 3],
    pub rmse_top_px: Option<f64>,
    pub fraction_without_prediction: f64,
    /// Inference throughput on this set, frames per second.
    pub frames_per_second: f64,
}

/// Simulates one test set per `diffusions` value (the microscope of
/// `params`, fixed D; the set of D = d µm²/s with seed
/// [`test_set_seed`]`(seed, d)`) of `frames` frames and scores `model` on
/// each.
pub fn auc_table(
    model: &TrainedCnn,
    params: &SimParams,
    diffusions: &[f64],
    frames: usize,
    seed: u64,
) -> anyhow::Result<Vec<TestRow>> {
    let mut rows = Vec::with_capacity(diffusions.len());
    for &diffusion in diffusions {
        let test_params = SimParams {
            diffusion_um2_s: Distribution::Fixed(diffusion),
            ..params.clone()
        };
        let test_seed = test_set_seed(seed, diffusion);
        let dataset = sim::simulate(&test_params, test_seed, 0..frames, &ProgressBar::hidden())?;
        let started = Instant::now();
        let predictions = model.locate(&dataset.frames, &ProgressBar::hidden())?;
        let seconds = started.elapsed().as_secs_f64();
        let score = metrics::score(&predictions, &dataset.truth, frames, &PAPER_EPS_PX, false)?;
        let mut auc = [0.0; 3];
        for (slot, per_eps) in auc.iter_mut().zip(&score.per_eps) {
            *slot = per_eps.auc;
        }
        rows.push(TestRow {
            diffusion,
            frames,
            seed: test_seed,
            auc,
            rmse_top_px: score.rmse_top_px,
            fraction_without_prediction: score.fraction_without_prediction,
            frames_per_second: frames as f64 / seconds.max(1e-9),
        });
    }
    Ok(rows)
}

/// The seed of [`auc_table`]'s test set of D = `diffusion` µm²/s:
/// `derive_seed(seed, "dataset", "test-D{diffusion}")`.
pub fn test_set_seed(seed: u64, diffusion: f64) -> u64 {
    derive_seed(seed, "dataset", &format!("test-D{diffusion}"))
}

/// The table as text, with the paper's FCNN row beside each D it has.
pub fn format_auc_table(rows: &[TestRow]) -> String {
    let mut out = String::from(
        "D (µm²/s)  frames   AUC ε=1   ε=2   ε=3   | paper FCNN ε=1  ε=2  ε=3 | RMSE top  none\n",
    );
    for row in rows {
        let paper = PAPER_FCNN
            .iter()
            .find(|(d, _)| (d - row.diffusion).abs() < 1e-9)
            .map(|(_, a)| format!("{:.2} {:.2} {:.2}", a[0], a[1], a[2]))
            .unwrap_or_else(|| "   -    -    -".to_string());
        out.push_str(&format!(
            "{:>9.2}  {:>6}  {:>8.3} {:>5.3} {:>5.3}   |           {paper} | {:>8} {:>5.3}\n",
            row.diffusion,
            row.frames,
            row.auc[0],
            row.auc[1],
            row.auc[2],
            row.rmse_top_px
                .map(|r| format!("{r:.3}"))
                .unwrap_or_else(|| "-".into()),
            row.fraction_without_prediction
        ));
    }
    out
}

/// Throughput of training and inference.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Throughput {
    pub architecture: CnnArchitecture,
    pub batch_size: usize,
    pub threads: usize,
    /// Training samples (frames) per second over `train_samples` samples,
    /// including target building and the optimiser step (no validation).
    pub train_samples_per_second: f64,
    pub train_samples: usize,
    /// Inference frames per second in batches of 256, peak finding included.
    pub locate_frames_per_second: f64,
    pub locate_frames: usize,
}

/// Measures training and inference throughput of `arch` on paper-sized
/// frames (brightness 7, margin 4, D uniform [0.75, 1.75]): trains one epoch
/// on `train_samples` fresh frames, then locates `locate_frames` frames.
/// The training seed is `derive_seed(seed, "detector", "throughput")`, the
/// located frames' `derive_seed(seed, "dataset", "throughput-locate")`.
pub fn throughput(
    arch: &CnnArchitecture,
    batch_size: usize,
    train_samples: usize,
    locate_frames: usize,
    seed: u64,
) -> anyhow::Result<Throughput> {
    let params = SimParams {
        brightness: 7.0,
        margin_px: 4.0,
        diffusion_um2_s: Distribution::Random(sim::RandomDistribution::Uniform([0.75, 1.75])),
        ..SimParams::default()
    };
    let settings = TrainingSettings {
        epochs: 1,
        batch_size,
        validation_fraction: 0.0,
        fresh_frames_per_epoch: train_samples,
        ..TrainingSettings::default()
    };
    let empty = Dataset::default();
    let started = Instant::now();
    // No validation frames: the score is never computed.
    let model = cnn::train(
        arch,
        &settings,
        &empty,
        Some(&params),
        derive_seed(seed, "detector", "throughput"),
        &metrics::paper_aucs,
        &ProgressBar::hidden(),
    )?;
    let train_seconds = started.elapsed().as_secs_f64();
    let test = sim::simulate(
        &params,
        derive_seed(seed, "dataset", "throughput-locate"),
        0..locate_frames,
        &ProgressBar::hidden(),
    )?;
    let started = Instant::now();
    model.locate(&test.frames, &ProgressBar::hidden())?;
    let locate_seconds = started.elapsed().as_secs_f64();
    Ok(Throughput {
        architecture: arch.clone(),
        batch_size,
        threads: rayon::current_num_threads(),
        train_samples_per_second: train_samples as f64 / train_seconds.max(1e-9),
        train_samples,
        locate_frames_per_second: locate_frames as f64 / locate_seconds.max(1e-9),
        locate_frames,
    })
}
