//! How well a probability score is calibrated (`docs/metric.md`,
//! "Calibration"): the reliability diagram of the score against the
//! observed frequency of localisations within 1 px of a QD, and its
//! expected calibration error (ECE).

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use super::{TruthByFrame, nearest_squared_distance, nearest_truth};
use crate::error::input_error;
use crate::types::Prediction;

/// The event a probability score predicts: the localisation lies within
/// this distance (px) of a ground truth of its frame.
pub(crate) const RELIABILITY_RADIUS_PX: f64 = 1.0;

/// Equal-width bins of the reliability diagram over [0, 1].
pub(crate) const RELIABILITY_BINS: usize = 10;

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

/// Most candidate ranks given a reliability diagram of their own: the
/// lists measured hold a handful of guesses, and the ranks beyond hold
/// too few guesses per set for a diagram to say anything.
pub(crate) const MAX_RELIABILITY_RANKS: u32 = 8;

/// The reliability diagram of the guesses of one rank of ranked lists.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RankReliability {
    /// The candidate rank (1 = each frame's best guess).
    pub rank: u32,
    pub reliability: Reliability,
}

/// For ranked lists (`Prediction::candidate`), one reliability diagram per
/// rank present (up to [`MAX_RELIABILITY_RANKS`]), of the guesses' scores
/// against the event a guess's posterior mass is the probability of: it
/// lies within [`RELIABILITY_RADIUS_PX`] of a ground truth of its frame
/// that no higher-ranked guess of the frame lies within that radius of
/// (the mass a disc *newly* covers; the metric too matches a QD once).
/// Empty when no prediction has a rank. Scores are checked by
/// [`reliability`] first.
pub(super) fn reliability_by_rank(
    ranked: &[Prediction],
    truth_by_frame: &TruthByFrame,
) -> Vec<RankReliability> {
    let radius2 = RELIABILITY_RADIUS_PX * RELIABILITY_RADIUS_PX;
    let mut by_frame: HashMap<usize, Vec<&Prediction>> = HashMap::new();
    for p in ranked.iter().filter(|p| p.candidate.is_some()) {
        by_frame.entry(p.frame).or_default().push(p);
    }
    let mut outcomes: Vec<Vec<(f64, bool)>> = Vec::new();
    for p in ranked {
        let Some(rank) = p
            .candidate
            .filter(|&r| (1..=MAX_RELIABILITY_RANKS).contains(&r))
        else {
            continue;
        };
        let near =
            |q: &Prediction, (x, y): (f64, f64)| (q.x - x).powi(2) + (q.y - y).powi(2) <= radius2;
        let higher = &by_frame[&p.frame];
        let hit = truth_by_frame.of(p.frame).iter().any(|&t| {
            near(p, t)
                && !higher
                    .iter()
                    .any(|q| q.candidate.is_some_and(|r| r < rank) && near(q, t))
        });
        let slot = rank as usize - 1;
        if outcomes.len() <= slot {
            outcomes.resize(slot + 1, Vec::new());
        }
        outcomes[slot].push((p.score, hit));
    }
    (1..)
        .zip(outcomes)
        .filter(|(_, o)| !o.is_empty())
        .map(|(rank, o)| RankReliability {
            rank,
            reliability: reliability_of(&o),
        })
        .collect()
}

/// The reliability diagram of `(probability, event happened)` pairs, the
/// probabilities in [0, 1].
pub(crate) fn reliability_of(outcomes: &[(f64, bool)]) -> Reliability {
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

/// How well the localisations' own uncertainty (`sigma_x`, `sigma_y`, the
/// expected error per axis) describes their real error (`docs/metric.md`,
/// "Calibration of the uncertainty"), over each frame's top prediction
/// that carries a σ and has a ground truth in its frame, against the
/// nearest ground truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct UncertaintyCalibration {
    /// Top predictions counted.
    pub localisations: usize,
    /// Root mean square of the normalised errors (x − x_true) / σx and
    /// (y − y_true) / σy: 1 when σ is the error's true standard deviation,
    /// above 1 when σ is too small.
    pub rms_normalised_error_x: f64,
    pub rms_normalised_error_y: f64,
    /// The fraction of the per-axis errors (x and y pooled) within 1 σ:
    /// 0.683 for a calibrated Gaussian error.
    pub within_one_sigma: f64,
    /// Spearman's rank correlation between σ (the geometric mean of σx and
    /// σy) and the distance to the truth: how well σ orders the
    /// localisations from precise to imprecise (1 = perfectly); `None`
    /// when fewer than two localisations are counted or either side is
    /// constant.
    pub rank_correlation: Option<f64>,
}

/// The calibration of the σ of the top predictions of `ranked` (the
/// metric's order); `None` if no frame's top prediction has both a σ and
/// a ground truth in its frame.
pub(super) fn uncertainty_calibration(
    ranked: &[Prediction],
    truth_by_frame: &TruthByFrame,
) -> Option<UncertaintyCalibration> {
    // (σx, σy, error x, error y) per counted top prediction, in ranking order.
    let counted: Vec<(f64, f64, f64, f64)> = super::top_predictions(ranked)
        .iter()
        .filter_map(|p| {
            let sigma = p.sigma?;
            let ((tx, ty), _) = nearest_truth(p, truth_by_frame)?;
            Some((sigma.x, sigma.y, p.x - tx, p.y - ty))
        })
        .collect();
    if counted.is_empty() {
        return None;
    }
    let n = counted.len() as f64;
    let rms =
        |values: &mut dyn Iterator<Item = f64>| (values.map(|v| v * v).sum::<f64>() / n).sqrt();
    let within = counted
        .iter()
        .map(|&(sx, sy, ex, ey)| usize::from(ex.abs() <= sx) + usize::from(ey.abs() <= sy))
        .sum::<usize>();
    let sigmas: Vec<f64> = counted
        .iter()
        .map(|&(sx, sy, _, _)| (sx * sy).sqrt())
        .collect();
    let errors: Vec<f64> = counted.iter().map(|&(_, _, ex, ey)| ex.hypot(ey)).collect();
    Some(UncertaintyCalibration {
        localisations: counted.len(),
        rms_normalised_error_x: rms(&mut counted.iter().map(|&(sx, _, ex, _)| ex / sx)),
        rms_normalised_error_y: rms(&mut counted.iter().map(|&(_, sy, _, ey)| ey / sy)),
        within_one_sigma: within as f64 / (2.0 * n),
        rank_correlation: spearman(&sigmas, &errors),
    })
}

/// Spearman's rank correlation of two equally long samples (ties share
/// their mean rank); `None` for fewer than two pairs or a constant side.
pub(crate) fn spearman(a: &[f64], b: &[f64]) -> Option<f64> {
    debug_assert_eq!(a.len(), b.len());
    if a.len() < 2 {
        return None;
    }
    let (ra, rb) = (ranks(a), ranks(b));
    let mean = (a.len() as f64 + 1.0) / 2.0;
    let (mut covariance, mut var_a, mut var_b) = (0.0, 0.0, 0.0);
    for (x, y) in ra.iter().zip(&rb) {
        covariance += (x - mean) * (y - mean);
        var_a += (x - mean).powi(2);
        var_b += (y - mean).powi(2);
    }
    (var_a > 0.0 && var_b > 0.0).then(|| covariance / (var_a * var_b).sqrt())
}

/// The 1-based ranks of `values`, ties given their mean rank.
fn ranks(values: &[f64]) -> Vec<f64> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&i, &j| values[i].total_cmp(&values[j]));
    let mut ranks = vec![0.0; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && values[order[end]] == values[order[start]] {
            end += 1;
        }
        // Positions start..end (0-based) share the mean of ranks start+1..=end.
        let rank = (start + end + 1) as f64 / 2.0;
        for &i in &order[start..end] {
            ranks[i] = rank;
        }
        start = end;
    }
    ranks
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::{LocalisationSigma, TruthRow};

    fn located(frame: usize, x: f64, y: f64, score: f64, sigma: (f64, f64)) -> Prediction {
        Prediction {
            sigma: Some(LocalisationSigma {
                x: sigma.0,
                y: sigma.1,
            }),
            ..Prediction::new(frame, x, y, score)
        }
    }

    #[test]
    fn the_uncertainty_calibration_of_a_hand_worked_case() {
        // Truth at (10, 10) in frames 0–2 and at (10, 10) and (30, 30) in
        // frame 3. Top predictions (highest score per frame):
        //   frame 0: error (0.5, 0),   σ (1, 1)   → z (0.5, 0),  both within
        //   frame 1: error (0, −2),    σ (1, 0.5) → z (0, −4),   x within
        //   frame 2: error (3, 4),     σ (2, 2)   → z (1.5, 2),  neither
        //   frame 3: error (0.2, 0.1) from (30, 30), σ (0.5, 0.5) → z (0.4, 0.2)
        // frame 0's second prediction (lower score, far off) is not a top one.
        let mut truth: Vec<TruthRow> = (0..4)
            .map(|f| TruthRow::stationary(f, 10.0, 10.0))
            .collect();
        truth.push(TruthRow::stationary(3, 30.0, 30.0));
        let predictions = vec![
            located(0, 10.5, 10.0, 0.9, (1.0, 1.0)),
            located(0, 20.0, 20.0, 0.1, (0.1, 0.1)),
            located(1, 10.0, 8.0, 0.8, (1.0, 0.5)),
            located(2, 13.0, 14.0, 0.7, (2.0, 2.0)),
            located(3, 30.2, 30.1, 0.6, (0.5, 0.5)),
        ];
        let score = crate::metrics::score(&predictions, &truth, 4, &[1.0], false).unwrap();
        let u = score.uncertainty.expect("σ reported");
        assert_eq!(u.localisations, 4);
        let rms = |z: [f64; 4]| (z.iter().map(|v| v * v).sum::<f64>() / 4.0).sqrt();
        assert!((u.rms_normalised_error_x - rms([0.5, 0.0, 1.5, 0.4])).abs() < 1e-12);
        assert!((u.rms_normalised_error_y - rms([0.0, 4.0, 2.0, 0.2])).abs() < 1e-12);
        // Within 1 σ: frame 0 both, frame 1 x, frame 3 both: 5 of 8.
        assert!((u.within_one_sigma - 5.0 / 8.0).abs() < 1e-12);
        // σ (geometric mean) 1, 0.707, 2, 0.5 ranks 3, 2, 4, 1; errors
        // 0.5, 2, 5, 0.224 rank 2, 3, 4, 1: d² = 1 + 1 + 0 + 0 = 2, so
        // ρ = 1 − 6 · 2 / (4 · 15) = 0.8.
        assert!((u.rank_correlation.unwrap() - 0.8).abs() < 1e-12);

        // Without σ (Crocker–Grier, the likelihood detector) nothing is reported.
        let plain: Vec<Prediction> = predictions
            .iter()
            .map(|p| Prediction { sigma: None, ..*p })
            .collect();
        let score = crate::metrics::score(&plain, &truth, 4, &[1.0], false).unwrap();
        assert_eq!(score.uncertainty, None);
    }

    #[test]
    fn spearman_gives_ties_their_mean_rank() {
        assert_eq!(ranks(&[3.0, 1.0, 3.0, 2.0]), vec![3.5, 1.0, 3.5, 2.0]);
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[10.0, 20.0, 30.0]), Some(1.0));
        assert_eq!(spearman(&[1.0, 2.0, 3.0], &[3.0, 2.0, 1.0]), Some(-1.0));
        // A constant side, or a single pair, has no rank correlation.
        assert_eq!(spearman(&[1.0, 1.0, 1.0], &[1.0, 2.0, 3.0]), None);
        assert_eq!(spearman(&[1.0], &[2.0]), None);
    }
}
