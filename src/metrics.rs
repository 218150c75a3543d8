//! The paper's precision–recall AUC (`docs/metric.md`), plus the RMSE of each
//! frame's top prediction and the fraction of frames with no prediction.
//!
//! For one test set, the predictions of all frames are pooled and sorted by
//! score, descending (ties: frame index, then x, then y, ascending). Walking
//! the list, a prediction is a true positive if a ground truth of its own
//! frame is still unmatched within distance ε (the nearest such one is then
//! matched); otherwise it is a false positive (too far, or a duplicate).
//! With k predictions taken, `precision_k = TP_k / k`,
//! `recall_k = TP_k / G` (G = number of ground truths), and
//! `AUC = Σ_k (recall_k − recall_(k−1)) · precision_k`.

use std::cmp::Ordering;

use serde::{Deserialize, Serialize};

use crate::error::input_error;
use crate::types::{Dataset, Prediction, TruthRow};

/// The paper's matching radii in pixels (70, 140, 210 nm at 0.07 µm/px).
pub const PAPER_EPS_PX: [f64; 3] = [1.0, 2.0, 3.0];

/// One point of the precision–recall curve: after the `k`-th prediction.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    pub k: usize,
    pub score: f64,
    pub precision: f64,
    pub recall: f64,
}

/// The result for one matching radius ε.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpsScore {
    pub eps_px: f64,
    pub auc: f64,
    pub true_positives: usize,
    pub false_positives: usize,
    /// Precision and recall after each prediction, in ranking order.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub curve: Vec<CurvePoint>,
}

/// Everything the metric reports for one detector on one test set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Score {
    pub per_eps: Vec<EpsScore>,
    /// Root-mean-square distance (px) from each frame's top-scoring
    /// prediction to the nearest ground truth of that frame, over frames
    /// that have both; `None` if no frame has both.
    pub rmse_top_px: Option<f64>,
    pub frames: usize,
    pub frames_without_prediction: usize,
    pub fraction_without_prediction: f64,
    pub predictions: usize,
    pub ground_truths: usize,
}

impl Score {
    /// The AUC at radius `eps_px`, if it was computed.
    pub fn auc(&self, eps_px: f64) -> Option<f64> {
        self.per_eps
            .iter()
            .find(|s| s.eps_px == eps_px)
            .map(|s| s.auc)
    }
}

/// Orders predictions for the walk: score descending, then frame, x, y
/// ascending. Scores are finite (checked before sorting).
fn ranking(a: &Prediction, b: &Prediction) -> Ordering {
    b.score
        .total_cmp(&a.score)
        .then(a.frame.cmp(&b.frame))
        .then(a.x.total_cmp(&b.x))
        .then(a.y.total_cmp(&b.y))
}

/// Checks predictions and truth (finite, on frames `0..frames`, some truth)
/// and groups the truth by frame.
fn checked_truth_by_frame(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
) -> anyhow::Result<Vec<Vec<(f64, f64)>>> {
    for p in predictions {
        if !(p.x.is_finite() && p.y.is_finite() && p.score.is_finite()) {
            return Err(input_error(format!(
                "prediction on frame {} has a non-finite x, y or score",
                p.frame
            )));
        }
        if p.frame >= frames {
            return Err(input_error(format!(
                "prediction on frame {}, but the test set has {frames} frames",
                p.frame
            )));
        }
    }
    let mut truth_by_frame: Vec<Vec<(f64, f64)>> = vec![Vec::new(); frames];
    for t in truth {
        if !(t.x.is_finite() && t.y.is_finite()) {
            return Err(input_error(format!(
                "ground truth on frame {} has a non-finite x or y",
                t.frame
            )));
        }
        match truth_by_frame.get_mut(t.frame) {
            Some(list) => list.push((t.x, t.y)),
            None => {
                return Err(input_error(format!(
                    "ground truth on frame {}, but the test set has {frames} frames",
                    t.frame
                )));
            }
        }
    }
    if truth.is_empty() {
        return Err(input_error(
            "the test set has no ground truth, so recall and AUC are undefined",
        ));
    }
    Ok(truth_by_frame)
}

/// For each frame, the squared distance from its top prediction (the first
/// met in ranking order) to the nearest ground truth of that frame; None
/// if the frame has no prediction or no truth.
fn top_squared_errors(
    ranked: &[Prediction],
    truth_by_frame: &[Vec<(f64, f64)>],
) -> Vec<Option<f64>> {
    let mut top: Vec<Option<&Prediction>> = vec![None; truth_by_frame.len()];
    for p in ranked {
        top[p.frame].get_or_insert(p);
    }
    truth_by_frame
        .iter()
        .zip(&top)
        .map(|(frame_truth, top)| match (top, frame_truth.is_empty()) {
            (Some(p), false) => Some(
                frame_truth
                    .iter()
                    .map(|&(x, y)| (p.x - x).powi(2) + (p.y - y).powi(2))
                    .fold(f64::INFINITY, f64::min),
            ),
            _ => None,
        })
        .collect()
}

/// Frames of `0..frames` without any prediction.
fn count_frames_without_prediction(ranked: &[Prediction], frames: usize) -> usize {
    let mut has_prediction = vec![false; frames];
    for p in ranked {
        has_prediction[p.frame] = true;
    }
    has_prediction.iter().filter(|&&has| !has).count()
}

/// Distance (px) from each frame's top-scoring prediction to the nearest
/// ground truth of that frame (None: the frame has no prediction or no
/// truth): the errors whose root mean square is [`Score::rmse_top_px`].
/// Refuses the inputs [`score`] refuses.
pub fn top_prediction_errors(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
) -> anyhow::Result<Vec<Option<f64>>> {
    let truth_by_frame = checked_truth_by_frame(predictions, truth, frames)?;
    let mut ranked: Vec<Prediction> = predictions.to_vec();
    ranked.sort_by(ranking);
    Ok(top_squared_errors(&ranked, &truth_by_frame)
        .into_iter()
        .map(|squared| squared.map(f64::sqrt))
        .collect())
}

/// Scores `predictions` against `truth` for a test set of `frames` frames
/// (frame indices `0..frames`). `keep_curve` keeps every curve point.
///
/// Refuses non-finite coordinates or scores, predictions or truth on
/// frames outside the set, non-positive ε, and a set with no ground truth
/// (recall, and so the AUC, would be undefined).
pub fn score(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    keep_curve: bool,
) -> anyhow::Result<Score> {
    let truth_by_frame = checked_truth_by_frame(predictions, truth, frames)?;
    for &eps in eps_px {
        if !(eps.is_finite() && eps > 0.0) {
            return Err(input_error(format!(
                "eps: must be a positive number of pixels, got {eps}"
            )));
        }
    }

    let mut ranked: Vec<Prediction> = predictions.to_vec();
    ranked.sort_by(ranking);
    let ground_truths = truth.len();

    let per_eps = eps_px
        .iter()
        .map(|&eps| walk(&ranked, &truth_by_frame, ground_truths, eps, keep_curve))
        .collect();

    let top = top_squared_errors(&ranked, &truth_by_frame);
    let mut squared_sum = 0.0;
    let mut counted = 0usize;
    for squared in top.iter().flatten() {
        squared_sum += squared;
        counted += 1;
    }
    let frames_without_prediction = count_frames_without_prediction(&ranked, frames);
    Ok(Score {
        per_eps,
        rmse_top_px: (counted > 0).then(|| (squared_sum / counted as f64).sqrt()),
        frames,
        frames_without_prediction,
        fraction_without_prediction: if frames == 0 {
            0.0
        } else {
            frames_without_prediction as f64 / frames as f64
        },
        predictions: predictions.len(),
        ground_truths,
    })
}

/// The AUC at each of the paper's radii ([`PAPER_EPS_PX`], in that order)
/// of `predictions` made on `dataset`: the validation score by which CNN
/// training keeps its best epoch (callers pass this function to
/// `detect::cnn::train`). Refuses what [`score`] refuses.
pub fn paper_aucs(predictions: &[Prediction], dataset: &Dataset) -> anyhow::Result<Vec<f64>> {
    let score = score(
        predictions,
        &dataset.truth,
        dataset.frames.n,
        &PAPER_EPS_PX,
        false,
    )?;
    Ok(score.per_eps.iter().map(|e| e.auc).collect())
}

/// One greedy matching walk at radius `eps` over predictions already ranked.
fn walk(
    ranked: &[Prediction],
    truth_by_frame: &[Vec<(f64, f64)>],
    ground_truths: usize,
    eps: f64,
    keep_curve: bool,
) -> EpsScore {
    let mut matched: Vec<Vec<bool>> = truth_by_frame
        .iter()
        .map(|t| vec![false; t.len()])
        .collect();
    let eps2 = eps * eps;
    let mut true_positives = 0usize;
    let mut auc = 0.0;
    let mut curve = Vec::with_capacity(if keep_curve { ranked.len() } else { 0 });
    for (index, p) in ranked.iter().enumerate() {
        let k = index + 1;
        let candidates = &truth_by_frame[p.frame];
        let mut best: Option<(usize, f64)> = None;
        for (j, &(x, y)) in candidates.iter().enumerate() {
            if matched[p.frame][j] {
                continue;
            }
            let d2 = (p.x - x).powi(2) + (p.y - y).powi(2);
            if d2 <= eps2 && best.is_none_or(|(_, b)| d2 < b) {
                best = Some((j, d2));
            }
        }
        if let Some((j, _)) = best {
            matched[p.frame][j] = true;
            true_positives += 1;
            // recall rises by 1/G exactly at true positives.
            auc += (true_positives as f64 / k as f64) / ground_truths as f64;
        }
        if keep_curve {
            curve.push(CurvePoint {
                k,
                score: p.score,
                precision: true_positives as f64 / k as f64,
                recall: true_positives as f64 / ground_truths as f64,
            });
        }
    }
    EpsScore {
        eps_px: eps,
        auc,
        true_positives,
        false_positives: ranked.len() - true_positives,
        curve,
    }
}
