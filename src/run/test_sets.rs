//! A trained CNN scored on freshly simulated test sets, one per diffusion
//! coefficient, beside the paper's FCNN row: what `scanloc train
//! --test-frames` and `scanloc bench cnn` print. Simulate ([`crate::sim`]),
//! locate ([`crate::detect`]), score ([`crate::metrics`]).
//!
//! Seeds: the test set of D = d draws from
//! `derive_seed(seed, "dataset", "test-D{d}")`.

use std::time::Instant;

use indicatif::ProgressBar;
use serde::Serialize;

use crate::detect::cnn::TrainedCnn;
use crate::metrics::{self, PAPER_EPS_PX};
use crate::sim::{self, Distribution, SimParams};
use crate::types::derive_seed;

/// The paper's FCNN row of Table 1 (AUC at ε = 1, 2, 3 px for D = 0.75,
/// 1.0, 1.75 µm²/s).
pub(crate) const PAPER_FCNN: [(f64, [f64; 3]); 3] = [
    (0.75, [0.48, 0.91, 0.99]),
    (1.0, [0.41, 0.87, 0.98]),
    (1.75, [0.26, 0.72, 0.92]),
];

/// AUCs of a model on one test set.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct TestRow {
    pub diffusion: f64,
    pub frames: usize,
    /// Seed the test set was simulated with.
    pub seed: u64,
    /// AUC at ε = 1, 2, 3 px (of every prediction: a ranked list whole).
    pub auc: [f64; 3],
    /// AUC at ε = 1, 2, 3 px of each frame's best guess alone, for a model
    /// that gives ranked lists (the categorical head); `None` otherwise.
    pub auc_best_per_frame: Option<[f64; 3]>,
    pub rmse_top_px: Option<f64>,
    pub fraction_without_prediction: f64,
    /// Inference throughput on this set, frames per second.
    pub frames_per_second: f64,
}

/// Simulates one test set per `diffusions` value (the microscope of
/// `params`, fixed D; the set of D = d µm²/s with seed
/// [`test_set_seed`]`(seed, d)`) of `frames` frames and scores `model` on
/// each.
pub(crate) fn auc_table(
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
        let mut best = [0.0; 3];
        for ((slot, best), per_eps) in auc.iter_mut().zip(&mut best).zip(&score.per_eps) {
            *slot = per_eps.auc;
            *best = per_eps.auc_best_per_frame.unwrap_or(per_eps.auc);
        }
        let ranked = predictions.iter().any(|p| p.candidate.is_some());
        rows.push(TestRow {
            diffusion,
            frames,
            seed: test_seed,
            auc,
            auc_best_per_frame: ranked.then_some(best),
            rmse_top_px: score.rmse_top_px,
            fraction_without_prediction: score.fraction_without_prediction,
            frames_per_second: frames as f64 / seconds.max(1e-9),
        });
    }
    Ok(rows)
}

/// The seed of [`auc_table`]'s test set of D = `diffusion` µm²/s:
/// `derive_seed(seed, "dataset", "test-D{diffusion}")`.
pub(crate) fn test_set_seed(seed: u64, diffusion: f64) -> u64 {
    derive_seed(seed, "dataset", &format!("test-D{diffusion}"))
}

/// The table as text, with the paper's FCNN row beside each D it has.
pub(crate) fn format_auc_table(rows: &[TestRow]) -> String {
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
        if let Some(best) = row.auc_best_per_frame {
            out.push_str(&format!(
                "  best guess per frame  {:>8.3} {:>5.3} {:>5.3}\n",
                best[0], best[1], best[2]
            ));
        }
    }
    out
}
