//! Whether one detector's AUC beats another's on the same test set by more
//! than the test set's luck (`docs/metric.md`, "Comparing two detectors"):
//! a paired bootstrap over frames.
//!
//! Both detectors' predictions are scored on the same resampled frames:
//! each resample draws the set's frames with data (a truth or a prediction
//! of either detector; a frame with neither adds nothing to an AUC), as
//! many as there are, with replacement (a frame drawn twice counts twice,
//! with its truth and both detectors' predictions), so
//! what varies from resample to resample is which frames the set happens to
//! hold, and the difference's spread says how much of it a new test set of
//! the same size would change. Frames hard for both detectors move both
//! AUCs together, which is why a paired difference is much tighter than
//! the two AUCs' own standard errors suggest.

use rand::{RngExt as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{check_radii, checked_truth_by_frame, ranking, refuse_without_truth, walk};
use crate::error::FieldError;
use crate::types::{Prediction, TruthRow};

/// Most resamples a comparison may ask for: the differences are kept to
/// sort them for the interval (8 bytes × resamples × radii).
pub(crate) const MAX_RESAMPLES: usize = 100_000;

/// The paired difference of two detectors' AUC at one radius ε.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct PairedDifference {
    pub eps_px: f64,
    /// The first detector's AUC on the test set itself.
    pub auc: f64,
    /// The second detector's AUC on the test set itself.
    pub auc_compared: f64,
    /// `auc − auc_compared`.
    pub difference: f64,
    /// The standard deviation of the difference over the resamples: its
    /// standard error (NaN from fewer than two resamples).
    pub standard_error: f64,
    /// The 2.5 % and 97.5 % quantiles of the difference over the resamples
    /// (the percentile interval; each the order statistic at
    /// ⌊q · resamples⌋, counted from 0; NaN without resamples).
    pub interval_95: (f64, f64),
    /// Resamples that held a ground truth (a resample without one has no
    /// AUC and is left out; with most frames holding a QD there are none).
    pub resamples: usize,
}

/// Checks a resample count (`name` names the field or flag): 1 to
/// [`MAX_RESAMPLES`].
pub(crate) fn check_resamples(name: &str, resamples: u64) -> Result<usize, FieldError> {
    if resamples == 0 || resamples > MAX_RESAMPLES as u64 {
        return Err(FieldError::new(
            name,
            format!("must be between 1 and {MAX_RESAMPLES}, got {resamples}"),
        ));
    }
    Ok(resamples as usize)
}

/// One detector's AUC at one radius ε with its spread over a bootstrap of
/// the frames: how much a new test set of the same size would move it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct AucSpread {
    pub eps_px: f64,
    /// The AUC on the test set itself.
    pub auc: f64,
    /// The standard deviation of the AUC over the resamples: its standard
    /// error (NaN from fewer than two resamples).
    pub standard_error: f64,
    /// The 2.5 % and 97.5 % quantiles of the AUC over the resamples (as in
    /// [`PairedDifference::interval_95`]).
    pub interval_95: (f64, f64),
    /// Resamples that held a ground truth.
    pub resamples: usize,
}

/// The bootstrap of the AUC of `predictions`, made on a test set of
/// `frames` frames with `truth`, at each radius of `eps_px`: the frames
/// resampled exactly as [`paired_bootstrap`] resamples them (same seed,
/// same resamples, as long as the other detector has no prediction on a
/// frame where this one has none and there is no truth), so this is the
/// spread of either side of that paired difference.
///
/// Refuses what [`paired_bootstrap`] refuses.
pub(crate) fn bootstrap_auc(
    predictions: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    resamples: usize,
    seed: u64,
) -> anyhow::Result<Vec<AucSpread>> {
    let resampled = resampled_aucs(&[predictions], truth, frames, eps_px, resamples, seed)?;
    Ok(resampled.spreads(0, eps_px))
}

/// The paired bootstrap of the AUC of `predictions` minus the AUC of
/// `compared`, both made on a test set of `frames` frames with `truth`, at
/// each radius of `eps_px`: `resamples` resamples of the frames drawn with
/// replacement from ChaCha8 seeded by `seed` (the same seed, inputs and
/// program give the same figures).
///
/// Refuses what [`score`](super::score) refuses (for either detector), a
/// resample count outside 1 to [`MAX_RESAMPLES`], and frame counts of 0.
pub(crate) fn paired_bootstrap(
    predictions: &[Prediction],
    compared: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    resamples: usize,
    seed: u64,
) -> anyhow::Result<Vec<PairedDifference>> {
    let resampled = resampled_aucs(
        &[predictions, compared],
        truth,
        frames,
        eps_px,
        resamples,
        seed,
    )?;
    Ok(resampled.differences(eps_px))
}

/// [`paired_bootstrap`] and the [`bootstrap_auc`] of `predictions` at
/// once, from one set of resamples: the same figures as the two calls,
/// with `predictions` scored on each resample once instead of twice.
pub(crate) fn paired_bootstrap_with_spread(
    predictions: &[Prediction],
    compared: &[Prediction],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    resamples: usize,
    seed: u64,
) -> anyhow::Result<(Vec<PairedDifference>, Vec<AucSpread>)> {
    let resampled = resampled_aucs(
        &[predictions, compared],
        truth,
        frames,
        eps_px,
        resamples,
        seed,
    )?;
    Ok((resampled.differences(eps_px), resampled.spreads(0, eps_px)))
}

/// Each detector's AUCs on the test set itself (`observed[detector][ε]`)
/// and on every resample that held a ground truth
/// (`aucs[detector][ε][resample]`).
struct Resampled {
    observed: Vec<Vec<f64>>,
    aucs: Vec<Vec<Vec<f64>>>,
}

impl Resampled {
    /// Detector 0's AUC minus detector 1's at each radius, with the spread
    /// of that difference over the resamples.
    fn differences(&self, eps_px: &[f64]) -> Vec<PairedDifference> {
        let (observed, ours, theirs) = (&self.observed, &self.aucs[0], &self.aucs[1]);
        eps_px
            .iter()
            .enumerate()
            .map(|(k, &eps)| {
                let differences = ours[k].iter().zip(&theirs[k]).map(|(a, b)| a - b).collect();
                let spread = Spread::of(differences);
                PairedDifference {
                    eps_px: eps,
                    auc: observed[0][k],
                    auc_compared: observed[1][k],
                    difference: observed[0][k] - observed[1][k],
                    standard_error: spread.standard_error,
                    interval_95: spread.interval_95,
                    resamples: spread.resamples,
                }
            })
            .collect()
    }

    /// Detector `detector`'s AUC at each radius with its own spread over
    /// the resamples.
    fn spreads(&self, detector: usize, eps_px: &[f64]) -> Vec<AucSpread> {
        eps_px
            .iter()
            .enumerate()
            .map(|(k, &eps)| {
                let spread = Spread::of(self.aucs[detector][k].clone());
                AucSpread {
                    eps_px: eps,
                    auc: self.observed[detector][k],
                    standard_error: spread.standard_error,
                    interval_95: spread.interval_95,
                    resamples: spread.resamples,
                }
            })
            .collect()
    }
}

/// The bootstrap behind [`paired_bootstrap`] and [`bootstrap_auc`]: every
/// detector scored on the same resamples of the frames.
fn resampled_aucs(
    detectors: &[&[Prediction]],
    truth: &[TruthRow],
    frames: usize,
    eps_px: &[f64],
    resamples: usize,
    seed: u64,
) -> anyhow::Result<Resampled> {
    check_resamples("resamples", resamples as u64)?;
    refuse_without_truth(truth)?;
    check_radii("eps", eps_px)?;
    // Also the checks of the predictions and truth (finite, on frames
    // `0..frames`): the observed AUCs are computed first.
    let aucs_of = |predictions: &[Prediction], truth: &[TruthRow]| -> anyhow::Result<Vec<f64>> {
        let truth_by_frame = checked_truth_by_frame(predictions, truth, frames)?;
        let mut ranked = predictions.to_vec();
        ranked.sort_by(ranking);
        Ok(eps_px
            .iter()
            .map(|&eps| walk(&ranked, &truth_by_frame, truth.len(), eps, false).auc)
            .collect())
    };
    let observed = detectors
        .iter()
        .map(|predictions| aucs_of(predictions, truth))
        .collect::<anyhow::Result<Vec<_>>>()?;

    // Only frames with data (truth or a prediction) are resampled: a frame
    // with neither adds nothing to any AUC, so leaving them out changes no
    // figure's meaning and makes each resample cost the frames with data,
    // not the largest frame number. Rows are grouped by their frame's
    // place among them, so a resample is assembled in time proportional to
    // its size. When every frame has data, the draws are those of a
    // resample of all frames.
    let mut data_frames: Vec<usize> = truth
        .iter()
        .map(|t| t.frame)
        .chain(
            detectors
                .iter()
                .flat_map(|rows| rows.iter().map(|p| p.frame)),
        )
        .collect();
    data_frames.sort_unstable();
    data_frames.dedup();
    let place = |frame: usize| {
        data_frames
            .binary_search(&frame)
            .expect("every row's frame is among the frames with data")
    };
    let count = data_frames.len();
    let by_frame: Vec<Vec<Vec<Prediction>>> = detectors
        .iter()
        .map(|rows| {
            let mut grouped: Vec<Vec<Prediction>> = vec![Vec::new(); count];
            for p in rows.iter() {
                grouped[place(p.frame)].push(*p);
            }
            grouped
        })
        .collect();
    let mut truth_by_frame: Vec<Vec<TruthRow>> = vec![Vec::new(); count];
    for t in truth {
        truth_by_frame[place(t.frame)].push(*t);
    }

    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut aucs: Vec<Vec<Vec<f64>>> =
        vec![vec![Vec::with_capacity(resamples); eps_px.len()]; detectors.len()];
    let mut drawn: Vec<Vec<Prediction>> = vec![Vec::new(); detectors.len()];
    let mut drawn_truth = Vec::new();
    let mut draws = Vec::with_capacity(count);
    for _ in 0..resamples {
        // Draw j of the resample becomes frame j: a frame drawn twice is
        // two frames of the resample.
        draws.clear();
        draws.extend((0..count).map(|_| rng.random_range(0..count)));
        drawn_truth.clear();
        for (j, &frame) in draws.iter().enumerate() {
            drawn_truth.extend(
                truth_by_frame[frame]
                    .iter()
                    .map(|t| TruthRow { frame: j, ..*t }),
            );
        }
        if drawn_truth.is_empty() {
            continue;
        }
        for ((drawn, grouped), aucs) in drawn.iter_mut().zip(&by_frame).zip(&mut aucs) {
            drawn.clear();
            for (j, &frame) in draws.iter().enumerate() {
                drawn.extend(grouped[frame].iter().map(|p| Prediction { frame: j, ..*p }));
            }
            for (k, value) in aucs_of(drawn, &drawn_truth)?.into_iter().enumerate() {
                aucs[k].push(value);
            }
        }
    }
    Ok(Resampled { observed, aucs })
}

/// The standard deviation and 95 % percentile interval of resampled values.
struct Spread {
    standard_error: f64,
    interval_95: (f64, f64),
    resamples: usize,
}

impl Spread {
    fn of(mut values: Vec<f64>) -> Self {
        let n = values.len();
        let mean = values.iter().sum::<f64>() / n.max(1) as f64;
        // Undefined (NaN, `null` in JSON) from fewer than two resamples.
        let variance = if n < 2 {
            f64::NAN
        } else {
            values.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1) as f64
        };
        values.sort_by(f64::total_cmp);
        let quantile = |q: f64| {
            values
                .get(((q * n as f64).floor() as usize).min(n.saturating_sub(1)))
                .copied()
                .unwrap_or(f64::NAN)
        };
        Spread {
            standard_error: variance.sqrt(),
            interval_95: (quantile(0.025), quantile(0.975)),
            resamples: n,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn truth(frame: usize) -> TruthRow {
        TruthRow::stationary(frame, 10.0, 10.0)
    }

    fn prediction(frame: usize, dx: f64, score: f64) -> Prediction {
        Prediction {
            frame,
            x: 10.0 + dx,
            y: 10.0,
            score,
            sigma: None,
            candidate: None,
        }
    }

    /// A detector that misses by 1.5 px on every other frame and ranks its
    /// hits first: its AUC at ε = 1 px is the fraction it hits, 1/2.
    fn half_hitting(frames: usize) -> Vec<Prediction> {
        (0..frames)
            .map(|f| {
                if f % 2 == 0 {
                    prediction(f, 0.0, 0.9)
                } else {
                    prediction(f, 1.5, 0.1)
                }
            })
            .collect()
    }

    /// 400 frames of one QD: the first detector finds every one exactly;
    /// the second misses by 1.5 px on every other frame and ranks its hits
    /// first, so its AUC at ε = 1 px is the fraction it hits, 1/2, and the
    /// difference 1 − p̂ has the binomial standard error √(p(1 − p)/n) =
    /// 0.025.
    #[test]
    fn the_standard_error_of_a_difference_of_hit_rates_is_binomial() {
        let frames = 400;
        let truth: Vec<TruthRow> = (0..frames).map(truth).collect();
        let perfect: Vec<Prediction> = (0..frames).map(|f| prediction(f, 0.0, 1.0)).collect();
        let half = half_hitting(frames);
        let result = paired_bootstrap(&perfect, &half, &truth, frames, &[1.0, 2.0], 2000, 7)
            .expect("valid inputs");
        let at_1 = result[0];
        // Sums of 400 precision terms: exact up to rounding.
        assert!((at_1.auc - 1.0).abs() < 1e-12 && (at_1.auc_compared - 0.5).abs() < 1e-12);
        assert_eq!(at_1.difference, at_1.auc - at_1.auc_compared);
        assert_eq!(at_1.resamples, 2000);
        // 2,000 resamples estimate a standard deviation to ≈ 1/√(2·2000) =
        // 1.6 % of itself: 10 % is six of those.
        assert!(
            (at_1.standard_error - 0.025).abs() < 0.0025,
            "standard error {}",
            at_1.standard_error
        );
        // The normal interval ±1.96 SE about 0.5, within the same tolerance.
        assert!((at_1.interval_95.0 - (0.5 - 1.96 * 0.025)).abs() < 0.006);
        assert!((at_1.interval_95.1 - (0.5 + 1.96 * 0.025)).abs() < 0.006);
        // At ε = 2 px both find every QD: no difference in any resample.
        let at_2 = result[1];
        assert!(at_2.difference.abs() < 1e-12, "{at_2:?}");
        assert!(at_2.standard_error < 1e-12, "{at_2:?}");
        assert!(at_2.interval_95.0.abs() < 1e-12 && at_2.interval_95.1.abs() < 1e-12);
    }

    /// One detector's AUC on its own: the half-hitting detector of the test
    /// above has AUC 1/2 at ε = 1 px with the binomial standard error 0.025,
    /// and its spread is the paired difference's against a detector that is
    /// right on every frame (1 − AUC has the AUC's spread), draw for draw.
    #[test]
    fn the_standard_error_of_one_auc_is_that_of_its_hit_rate() {
        let frames = 400;
        let truth: Vec<TruthRow> = (0..frames).map(truth).collect();
        let perfect: Vec<Prediction> = (0..frames).map(|f| prediction(f, 0.0, 1.0)).collect();
        let half = half_hitting(frames);
        let alone = bootstrap_auc(&half, &truth, frames, &[1.0], 2000, 7).expect("valid inputs");
        let paired =
            paired_bootstrap(&perfect, &half, &truth, frames, &[1.0], 2000, 7).expect("valid");
        let at_1 = alone[0];
        assert!((at_1.auc - 0.5).abs() < 1e-12, "{at_1:?}");
        assert_eq!(at_1.resamples, 2000);
        // 2,000 resamples: the standard deviation to ≈ 1.6 % of itself.
        assert!(
            (at_1.standard_error - 0.025).abs() < 0.0025,
            "standard error {}",
            at_1.standard_error
        );
        assert!(at_1.interval_95.0 < at_1.auc && at_1.auc < at_1.interval_95.1);
        assert!((at_1.standard_error - paired[0].standard_error).abs() < 1e-12);
        let mirrored = (1.0 - paired[0].interval_95.1, 1.0 - paired[0].interval_95.0);
        assert!(
            (at_1.interval_95.0 - mirrored.0).abs() < 1e-12,
            "{at_1:?} {mirrored:?}"
        );
        assert!(
            (at_1.interval_95.1 - mirrored.1).abs() < 1e-12,
            "{at_1:?} {mirrored:?}"
        );
        let error = bootstrap_auc(&half, &truth, frames, &[1.0], 0, 7).unwrap_err();
        assert!(error.to_string().contains("resamples"), "{error}");
    }

    #[test]
    fn the_same_seed_gives_the_same_figures_and_another_seed_others() {
        let frames = 50;
        let truth: Vec<TruthRow> = (0..frames).map(truth).collect();
        let a: Vec<Prediction> = (0..frames)
            .map(|f| prediction(f, (f % 3) as f64 * 0.6, f as f64 / 50.0))
            .collect();
        let b: Vec<Prediction> = (0..frames)
            .map(|f| prediction(f, (f % 4) as f64 * 0.4, 1.0 - f as f64 / 50.0))
            .collect();
        let run = |seed| paired_bootstrap(&a, &b, &truth, frames, &[1.0], 300, seed).unwrap();
        assert_eq!(run(1), run(1));
        assert_ne!(run(1)[0].standard_error, run(2)[0].standard_error);
        assert_eq!(run(1)[0].difference, run(2)[0].difference);
    }

    #[test]
    fn bad_resample_counts_and_frames_outside_the_set_are_refused() {
        let truth = vec![truth(0)];
        let a = vec![prediction(0, 0.0, 1.0)];
        for resamples in [0, MAX_RESAMPLES + 1] {
            let error = paired_bootstrap(&a, &a, &truth, 1, &[1.0], resamples, 0).unwrap_err();
            assert!(error.to_string().contains("resamples"), "{error}");
        }
        let outside = vec![prediction(3, 0.0, 1.0)];
        let error = paired_bootstrap(&a, &outside, &truth, 1, &[1.0], 10, 0).unwrap_err();
        assert!(error.to_string().contains("frame 3"), "{error}");
    }
}
