//! Figures for scenes with several QDs, or none, per frame
//! (`docs/metric.md`, "Scenes"), as the SMLM challenge reports them: the
//! localisations at or above a score threshold, matched to the truth by
//! the metric's own greedy matching at radius ε, give recall, precision,
//! Jaccard index and the RMSE of the matched localisations; on frames
//! without any QD every such localisation is false.

use serde::{Deserialize, Serialize};

use super::{TruthByFrame, match_in_order};
use crate::types::Prediction;

/// The localisations at or above the threshold, matched at one radius ε.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AtThreshold {
    /// Localisations at or above the threshold.
    pub localisations: usize,
    /// Of those, matched to a ground truth within ε.
    pub true_positives: usize,
    /// Of those, not matched (too far, a duplicate, or on a frame without
    /// truth).
    pub false_positives: usize,
    /// Ground truths left unmatched.
    pub false_negatives: usize,
    /// `TP / G`.
    pub recall: f64,
    /// `TP / (TP + FP)`; `None` if no localisation is kept.
    pub precision: Option<f64>,
    /// `TP / (TP + FP + FN)`.
    pub jaccard: f64,
    /// Root-mean-square distance (px) of the true positives to the ground
    /// truth each matched; `None` without true positives.
    pub rmse_matched_px: Option<f64>,
}

/// The test set's frames without ground truth, and the localisations at or
/// above the threshold on them.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EmptyFrames {
    /// Frames of the test set without any ground truth row.
    pub frames: usize,
    /// Localisations at or above the threshold on those frames.
    pub localisations: usize,
    /// `localisations / frames`; `None` if no frame is empty.
    pub false_localisations_per_frame: Option<f64>,
}

/// How many of `ranked` (score descending) are at or above `threshold`:
/// they are its first ones. All of them without a threshold.
pub(super) fn kept_count(ranked: &[Prediction], threshold: Option<f64>) -> usize {
    match threshold {
        Some(threshold) => ranked.partition_point(|p| p.score >= threshold),
        None => ranked.len(),
    }
}

/// The figures of the kept localisations `kept` (in ranking order) at `eps`.
pub(super) fn at_threshold(
    kept: &[Prediction],
    truth_by_frame: &TruthByFrame,
    ground_truths: usize,
    eps: f64,
) -> AtThreshold {
    let mut true_positives = 0usize;
    let mut squared_sum = 0.0;
    match_in_order(kept, truth_by_frame, eps, |_, matched| {
        if let Some(d2) = matched {
            true_positives += 1;
            squared_sum += d2;
        }
    });
    let false_positives = kept.len() - true_positives;
    let false_negatives = ground_truths - true_positives;
    AtThreshold {
        localisations: kept.len(),
        true_positives,
        false_positives,
        false_negatives,
        recall: true_positives as f64 / ground_truths as f64,
        precision: (!kept.is_empty()).then(|| true_positives as f64 / kept.len() as f64),
        jaccard: true_positives as f64
            / (true_positives + false_positives + false_negatives) as f64,
        rmse_matched_px: (true_positives > 0).then(|| (squared_sum / true_positives as f64).sqrt()),
    }
}

/// The empty frames of a set of `frames` frames and the kept localisations
/// on them.
pub(super) fn empty_frames(
    kept: &[Prediction],
    truth_by_frame: &TruthByFrame,
    frames: usize,
) -> EmptyFrames {
    // Truth is on frames 0..frames (checked), so this does not underflow.
    let empty = frames - truth_by_frame.points.len();
    let localisations = kept
        .iter()
        .filter(|p| truth_by_frame.of(p.frame).is_empty())
        .count();
    EmptyFrames {
        frames: empty,
        localisations,
        false_localisations_per_frame: (empty > 0).then(|| localisations as f64 / empty as f64),
    }
}
