//! The paper's precision–recall AUC (`docs/metric.md`), plus the RMSE of each
//! frame's top prediction and the fraction of frames with no prediction. The
//! layer names only the shared types and errors.
//!
//! For one test set, the predictions of all frames are pooled and sorted by
//! score, descending (ties: frame index, then x, then y, ascending). Walking
//! the list, a prediction is a true positive if a ground truth of its own
//! frame is still unmatched within distance ε (the nearest such one is then
//! matched); otherwise it is a false positive (too far, or a duplicate).
//! With k predictions taken, `precision_k = TP_k / k`,
//! `recall_k = TP_k / G` (G = number of ground truths), and
//! `AUC = Σ_k (recall_k − recall_(k−1)) · precision_k`.
//!
//! Every AUC is given twice: over all predictions (for a detector giving a
//! ranked list of guesses per frame, the whole list) and over each frame's
//! best alone (its rank-1 candidate, or its top score). The scene figures
//! leave out the guesses ranked below a frame's best.
//!
//! Beside the AUC: where it is lost ([`headroom`]: the AUC of each frame's
//! top prediction ranked by its true error and at random), how well a
//! probability score is calibrated ([`calibration`]: reliability diagram
//! and expected calibration error), and the figures of scenes with several
//! or no QDs per frame at a score threshold ([`scenes`]: recall, precision,
//! Jaccard index, RMSE of matched localisations, false localisations per
//! empty frame), and whether one detector beats another by more than the
//! test set's luck ([`paired`]: a paired bootstrap over frames).

pub(crate) mod calibration;
pub(crate) mod diffusion;
pub(crate) mod headroom;
pub(crate) mod paired;
pub(crate) mod scenes;
pub(crate) mod tracking;

use std::cmp::Ordering;
use std::collections::{HashMap, HashSet};

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
    /// The AUC of every prediction (for a ranked list: the whole list).
    pub auc: f64,
    /// The AUC of each frame's best prediction alone: its rank-1
    /// candidate, or its top-scoring prediction when it has no ranks
    /// (absent in evaluations stored before it existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub auc_best_per_frame: Option<f64>,
    pub true_positives: usize,
    pub false_positives: usize,
    /// Precision and recall after each prediction, in ranking order.
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub curve: Vec<CurvePoint>,
    /// The AUC of the frames' top predictions ranked by their true error
    /// and at random (absent in evaluations stored before it existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub headroom: Option<headroom::Headroom>,
    /// Recall, precision, Jaccard index and RMSE of the localisations at or
    /// above the score threshold (absent in evaluations stored before it
    /// existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub at_threshold: Option<scenes::AtThreshold>,
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
    /// How the score was read: the threshold of the scene figures and
    /// whether it is a probability (absent in evaluations stored before it
    /// existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reading: Option<ScoreReading>,
    /// The empty frames (frames of the set without any ground truth): their
    /// count and the localisations at or above the threshold on them
    /// (absent in evaluations stored before it existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub empty_frames: Option<scenes::EmptyFrames>,
    /// Reliability diagram and expected calibration error of a probability
    /// score (absent for other scores, and in evaluations stored before it
    /// existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reliability: Option<calibration::Reliability>,
    /// For ranked lists with a probability score: one reliability diagram
    /// per candidate rank (empty otherwise, and left out).
    #[serde(skip_serializing_if = "Vec::is_empty", default)]
    pub reliability_by_rank: Vec<calibration::RankReliability>,
    /// How well the localisations' σ describes their error (absent when no
    /// top prediction carries a σ, and in evaluations stored before it
    /// existed).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub uncertainty: Option<calibration::UncertaintyCalibration>,
}

/// How a detector's score is read beyond ranking (`docs/metric.md`,
/// "Scenes" and "Calibration").
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct ScoreReading {
    /// Localisations with a score at or above this count for the scene
    /// figures (recall, precision, Jaccard index, RMSE, false
    /// localisations per empty frame); `None`: every localisation counts.
    pub threshold: Option<f64>,
    /// The score is a probability (in [0, 1]) that the localisation is
    /// within 1 px of a QD: its reliability diagram is computed.
    pub probability: bool,
}

impl ScoreReading {
    /// The threshold of a probability score when none is declared: a
    /// localisation counts if it is more likely right than wrong.
    pub const PROBABILITY_THRESHOLD: f64 = 0.5;
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

/// The ground truth grouped by frame, holding only frames that have
/// truth: memory grows with the rows given, never with the frame numbers.
struct TruthByFrame {
    /// Frame number → position in `points`.
    slot: HashMap<usize, usize>,
    /// Per frame with truth, its points `(x, y)` in input order.
    points: Vec<Vec<(f64, f64)>>,
}

impl TruthByFrame {
    /// The truth of `frame` (empty if it has none).
    fn of(&self, frame: usize) -> &[(f64, f64)] {
        self.slot
            .get(&frame)
            .map_or(&[], |&slot| &self.points[slot])
    }
}

/// Checks predictions and truth (finite, on frames `0..frames`) and groups
/// the truth by frame.
fn checked_truth_by_frame(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
) -> anyhow::Result<TruthByFrame> {
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
    let mut by_frame = TruthByFrame {
        slot: HashMap::new(),
        points: Vec::new(),
    };
    for t in truth {
        if !(t.x.is_finite() && t.y.is_finite()) {
            return Err(input_error(format!(
                "ground truth on frame {} has a non-finite x or y",
                t.frame
            )));
        }
        if t.frame >= frames {
            return Err(input_error(format!(
                "ground truth on frame {}, but the test set has {frames} frames",
                t.frame
            )));
        }
        let next = by_frame.points.len();
        let slot = *by_frame.slot.entry(t.frame).or_insert(next);
        if slot == next {
            by_frame.points.push(Vec::new());
        }
        by_frame.points[slot].push((t.x, t.y));
    }
    Ok(by_frame)
}

/// For each frame with both a prediction and truth, the squared distance
/// from its top prediction (the first met in ranking order) to the nearest
/// ground truth of that frame.
fn top_squared_errors(ranked: &[Prediction], truth: &TruthByFrame) -> HashMap<usize, f64> {
    let mut errors = HashMap::new();
    for p in ranked {
        let frame_truth = truth.of(p.frame);
        if frame_truth.is_empty() {
            continue;
        }
        errors
            .entry(p.frame)
            .or_insert_with(|| nearest_squared_distance(p, truth));
    }
    errors
}

/// Squared distance from `p` to the nearest ground truth of its frame
/// (infinite if the frame has none).
fn nearest_squared_distance(p: &Prediction, truth: &TruthByFrame) -> f64 {
    nearest_truth(p, truth).map_or(f64::INFINITY, |(_, squared)| squared)
}

/// The ground truth of `p`'s frame nearest to it (the first of equally
/// near ones) and its squared distance; `None` if the frame has none.
fn nearest_truth(p: &Prediction, truth: &TruthByFrame) -> Option<((f64, f64), f64)> {
    truth
        .of(p.frame)
        .iter()
        .map(|&(x, y)| ((x, y), (p.x - x).powi(2) + (p.y - y).powi(2)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

/// Each frame's top prediction (the first met in ranking order), in
/// ranking order.
fn top_predictions(ranked: &[Prediction]) -> Vec<Prediction> {
    let mut seen = HashSet::new();
    ranked
        .iter()
        .filter(|p| seen.insert(p.frame))
        .copied()
        .collect()
}

/// Each frame's best prediction, in ranking order: its rank-1 candidate
/// if it has one, otherwise its first in ranking order (a frame's top
/// score stands for rank 1 when the detector gives no ranks).
fn best_per_frame(ranked: &[Prediction]) -> Vec<Prediction> {
    let with_rank_one: HashSet<usize> = ranked
        .iter()
        .filter(|p| p.candidate == Some(1))
        .map(|p| p.frame)
        .collect();
    let mut seen = HashSet::new();
    ranked
        .iter()
        .filter(|p| !with_rank_one.contains(&p.frame) || p.candidate == Some(1))
        .filter(|p| seen.insert(p.frame))
        .copied()
        .collect()
}

/// Frames of `0..frames` without any prediction (predictions are on
/// frames `0..frames`, checked before).
fn count_frames_without_prediction(ranked: &[Prediction], frames: usize) -> usize {
    let with_prediction: HashSet<usize> = ranked.iter().map(|p| p.frame).collect();
    frames - with_prediction.len()
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
    refuse_without_truth(truth)?;
    let mut ranked: Vec<Prediction> = predictions.to_vec();
    ranked.sort_by(ranking);
    let squared = top_squared_errors(&ranked, &truth_by_frame);
    Ok((0..frames)
        .map(|frame| squared.get(&frame).map(|s| s.sqrt()))
        .collect())
}

/// Scores `predictions` against `truth` for a test set of `frames` frames
/// (frame indices `0..frames`). `keep_curve` keeps every curve point. The
/// score is read as [`ScoreReading::default`]: no threshold, not a
/// probability.
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
    checked_truth_by_frame(predictions, truth, frames)?;
    refuse_without_truth(truth)?;
    score_read_as(
        predictions,
        truth,
        frames,
        eps_px,
        keep_curve,
        ScoreReading::default(),
    )
}

/// Refuses a matching radius that is not a positive number of pixels up to
/// [`MAX_EPS_PX`](crate::limits::MAX_EPS_PX), and more than
/// [`MAX_RADII`](crate::limits::MAX_RADII) radii: the bounds a manifest's
/// `metrics.eps_px` has. `name` names the setting in the error.
pub fn check_radii(name: &str, eps_px: &[f64]) -> anyhow::Result<()> {
    use crate::limits::MAX_RADII;
    if eps_px.len() > MAX_RADII {
        return Err(input_error(format!(
            "{name}: at most {MAX_RADII} radii, got {}",
            eps_px.len()
        )));
    }
    for &eps in eps_px {
        crate::limits::check_radius(eps).map_err(|e| input_error(format!("{name}: {e}")))?;
    }
    Ok(())
}

/// Refuses a test set without ground truth, where recall and the AUC are
/// undefined.
fn refuse_without_truth(truth: &[TruthRow]) -> anyhow::Result<()> {
    if truth.is_empty() {
        return Err(input_error(
            "the test set has no ground truth, so recall and AUC are undefined",
        ));
    }
    Ok(())
}

/// [`score`], with the score read as `reading`: the scene figures at its
/// threshold, the reliability diagram if it is a probability. Refuses
/// also a non-finite threshold, and a probability score outside [0, 1].
///
/// Unlike [`score`], it scores a test set without any ground truth (only
/// empty frames): everything per ε (AUC, headroom, recall, ...) is then
/// undefined and `per_eps` is empty, while the empty-frame figures and the
/// reliability diagram are computed.
pub fn score_read_as(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    keep_curve: bool,
    reading: ScoreReading,
) -> anyhow::Result<Score> {
    let truth_by_frame = checked_truth_by_frame(predictions, truth, frames)?;
    check_radii("eps", eps_px)?;
    if let Some(threshold) = reading.threshold
        && !threshold.is_finite()
    {
        return Err(input_error(format!(
            "threshold: must be a finite score, got {threshold}"
        )));
    }

    let mut ranked: Vec<Prediction> = predictions.to_vec();
    ranked.sort_by(ranking);
    let ground_truths = truth.len();
    let best = best_per_frame(&ranked);
    // A guess ranked below a frame's best is not a second QD: the scene
    // figures leave it out (unranked localisations, a scene's QDs, count).
    let scene: Vec<Prediction> = ranked
        .iter()
        .filter(|p| p.candidate.is_none_or(|rank| rank == 1))
        .copied()
        .collect();
    let kept = scenes::kept_count(&scene, reading.threshold);

    // Without ground truth nothing per ε is defined (recall divides by G).
    let radii = if ground_truths == 0 { &[][..] } else { eps_px };
    let per_eps = radii
        .iter()
        .map(|&eps| {
            let mut per_eps = walk(&ranked, &truth_by_frame, ground_truths, eps, keep_curve);
            per_eps.auc_best_per_frame =
                Some(walk(&best, &truth_by_frame, ground_truths, eps, false).auc);
            per_eps.headroom = Some(headroom::headroom(
                &ranked,
                &truth_by_frame,
                ground_truths,
                eps,
                per_eps.auc,
            ));
            per_eps.at_threshold = Some(scenes::at_threshold(
                &scene[..kept],
                &truth_by_frame,
                ground_truths,
                eps,
            ));
            per_eps
        })
        .collect();

    let top = top_squared_errors(&ranked, &truth_by_frame);
    // Summed in frame order, as before the truth was stored sparsely, so
    // the RMSE keeps its last bit.
    let mut top: Vec<(usize, f64)> = top.into_iter().collect();
    top.sort_unstable_by_key(|&(frame, _)| frame);
    let mut squared_sum = 0.0;
    let mut counted = 0usize;
    for (_, squared) in &top {
        squared_sum += squared;
        counted += 1;
    }
    let frames_without_prediction = count_frames_without_prediction(&ranked, frames);
    let (reliability, reliability_by_rank) = if reading.probability {
        (
            Some(calibration::reliability(&ranked, &truth_by_frame)?),
            calibration::reliability_by_rank(&ranked, &truth_by_frame),
        )
    } else {
        (None, Vec::new())
    };
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
        reading: Some(reading),
        empty_frames: Some(scenes::empty_frames(
            &scene[..kept],
            &truth_by_frame,
            frames,
        )),
        reliability,
        reliability_by_rank,
        uncertainty: calibration::uncertainty_calibration(&ranked, &truth_by_frame),
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

/// The greedy matching of `docs/metric.md` at radius `eps`, over
/// predictions in the order given: calls `visit(k, matched)` after the
/// `k`-th prediction (from 1) with the squared distance to the ground
/// truth it matched, or `None` for a false positive.
fn match_in_order<'a>(
    ordered: impl IntoIterator<Item = &'a Prediction>,
    truth_by_frame: &TruthByFrame,
    eps: f64,
    mut visit: impl FnMut(usize, Option<f64>),
) {
    let mut matched: Vec<Vec<bool>> = truth_by_frame
        .points
        .iter()
        .map(|t| vec![false; t.len()])
        .collect();
    let eps2 = eps * eps;
    for (index, p) in ordered.into_iter().enumerate() {
        let mut best: Option<(usize, usize, f64)> = None;
        // A frame without truth has no candidates: a false positive.
        if let Some(&slot) = truth_by_frame.slot.get(&p.frame) {
            for (j, &(x, y)) in truth_by_frame.points[slot].iter().enumerate() {
                if matched[slot][j] {
                    continue;
                }
                let d2 = (p.x - x).powi(2) + (p.y - y).powi(2);
                if d2 <= eps2 && best.is_none_or(|(_, _, b)| d2 < b) {
                    best = Some((slot, j, d2));
                }
            }
        }
        if let Some((slot, j, _)) = best {
            matched[slot][j] = true;
        }
        visit(index + 1, best.map(|(_, _, d2)| d2));
    }
}

/// One greedy matching walk at radius `eps` over predictions already ranked.
fn walk(
    ranked: &[Prediction],
    truth_by_frame: &TruthByFrame,
    ground_truths: usize,
    eps: f64,
    keep_curve: bool,
) -> EpsScore {
    let mut true_positives = 0usize;
    let mut auc = 0.0;
    let mut curve = Vec::with_capacity(if keep_curve { ranked.len() } else { 0 });
    match_in_order(ranked, truth_by_frame, eps, |k, matched| {
        if matched.is_some() {
            true_positives += 1;
            // recall rises by 1/G exactly at true positives.
            auc += (true_positives as f64 / k as f64) / ground_truths as f64;
        }
        if keep_curve {
            curve.push(CurvePoint {
                k,
                score: ranked[k - 1].score,
                precision: true_positives as f64 / k as f64,
                recall: true_positives as f64 / ground_truths as f64,
            });
        }
    });
    EpsScore {
        eps_px: eps,
        auc,
        true_positives,
        false_positives: ranked.len() - true_positives,
        curve,
        auc_best_per_frame: None,
        headroom: None,
        at_threshold: None,
    }
}
