//! How well a probability score is calibrated (`docs/metric.md`,
//! "Calibration"): the reliability diagram of the score against the
//! observed frequency of localisations within 1 px of a QD, and its
//! expected calibration error (ECE).

use serde::{Deserialize, Serialize};

use super::{TruthByFrame, nearest_squared_distance};
use crate::error::input_error;
use crate::types::Prediction;

/// The event a probability score predicts: the localisation lies within
/// this distance (px) of a ground truth of its frame.
pub const RELIABILITY_RADIUS_PX: f64 = 1.0;

/// Equal-width bins of the reliability diagram over [0, 1].
pub const RELIABILITY_BINS: usize = 10;

/// One bin of the reliability diagram: the localisations whose score is in
/// `[lower, upper)` (the last bin also holds 1).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReliabilityBin {
    pub lower: f64,
    pub upper: f64,
    /// Localisations in the bin.
    pub count: usize,
    /// Their mean score (the predicted probability); `None` if empty.
    pub mean_score: Option<f64>,
    /// The fraction of them within [`RELIABILITY_RADIUS_PX`] of a ground
    /// truth of their frame (the observed frequency); `None` if empty.
    pub observed_frequency: Option<f64>,
}

/// The reliability diagram of every localisation of a test set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reliability {
    /// The radius of the predicted event ([`RELIABILITY_RADIUS_PX`]).
    pub radius_px: f64,
    /// Localisations counted (all of the test set's).
    pub localisations: usize,
    /// [`RELIABILITY_BINS`] bins, in score order.
    pub bins: Vec<ReliabilityBin>,
    /// `Σ_b (count_b / N) · |mean_score_b − observed_frequency_b|` over
    /// the non-empty bins; `None` without localisations.
    pub expected_calibration_error: Option<f64>,
}

/// The reliability diagram of `ranked` (the metric's order); refuses a
/// score outside [0, 1], which is not a probability.
pub(super) fn reliability(
    ranked: &[Prediction],
    truth_by_frame: &TruthByFrame,
) -> anyhow::Result<Reliability> {
    let radius2 = RELIABILITY_RADIUS_PX * RELIABILITY_RADIUS_PX;
    let mut outcomes = Vec::with_capacity(ranked.len());
    for p in ranked {
        if !(0.0..=1.0).contains(&p.score) {
            return Err(input_error(format!(
                "prediction on frame {} has score {}, outside [0, 1]: not a probability",
                p.frame, p.score
            )));
        }
        outcomes.push((
            p.score,
            nearest_squared_distance(p, truth_by_frame) <= radius2,
        ));
    }
    Ok(reliability_of(&outcomes))
}

/// The reliability diagram of `(probability, event happened)` pairs, the
/// probabilities in [0, 1].
pub fn reliability_of(outcomes: &[(f64, bool)]) -> Reliability {
    let mut count = [0usize; RELIABILITY_BINS];
    let mut score_sum = [0.0f64; RELIABILITY_BINS];
    let mut hits = [0usize; RELIABILITY_BINS];
    for &(probability, happened) in outcomes {
        // Scores exactly 1 belong to the last bin.
        let bin = ((probability * RELIABILITY_BINS as f64) as usize).min(RELIABILITY_BINS - 1);
        count[bin] += 1;
        score_sum[bin] += probability;
        hits[bin] += usize::from(happened);
    }
    let total = outcomes.len();
    let mut ece = 0.0;
    let bins = (0..RELIABILITY_BINS)
        .map(|b| {
            let (mean_score, observed_frequency) = if count[b] > 0 {
                let mean = score_sum[b] / count[b] as f64;
                let observed = hits[b] as f64 / count[b] as f64;
                ece += count[b] as f64 / total as f64 * (mean - observed).abs();
                (Some(mean), Some(observed))
            } else {
                (None, None)
            };
            ReliabilityBin {
                lower: b as f64 / RELIABILITY_BINS as f64,
                upper: (b + 1) as f64 / RELIABILITY_BINS as f64,
                count: count[b],
                mean_score,
                observed_frequency,
            }
        })
        .collect();
    Reliability {
        radius_px: RELIABILITY_RADIUS_PX,
        localisations: total,
        bins,
        expected_calibration_error: (total > 0).then_some(ece),
    }
}
