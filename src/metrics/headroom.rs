//! Where the AUC is lost (`docs/metric.md`, "Headroom"): how the AUC of a
//! detector compares with the AUC of the same frames' top predictions
//! ranked by their true error (the best any score could do with those
//! localisations) and ranked at random (what a score that knows nothing
//! would do).

use serde::{Deserialize, Serialize};

use super::{TruthByFrame, nearest_squared_distance, top_predictions, walk};
use crate::types::Prediction;

/// The ranking headroom at one radius ε.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Headroom {
    /// Top predictions: one per frame that has a prediction (its first in
    /// ranking order).
    pub top_predictions: usize,
    /// Top predictions within ε of a ground truth of their frame.
    pub top_within_eps: usize,
    /// `top_within_eps / top_predictions`; `None` without predictions.
    pub fraction_top_within_eps: Option<f64>,
    /// The AUC of the top predictions ranked by their distance to the
    /// nearest ground truth of their frame, ascending (the oracle-rank
    /// AUC): every one within ε comes first, so it is
    /// `top_within_eps / G`.
    pub oracle_auc: f64,
    /// The expected AUC of the top predictions ranked in a uniformly random
    /// order (every one of the `n!` orders equally likely), in closed form:
    /// see [`expected_random_rank_auc`].
    pub random_auc: f64,
    /// `(AUC − random) / (oracle − random)` as stored, where AUC is the
    /// detector's own AUC over all its predictions: it exceeds 1 when
    /// predictions other than the top ones find QDs (a ranked list's
    /// lower guesses), where it is no share of anything. What the tables
    /// print is [`Headroom::share_of`] the best guesses' AUC, the share of
    /// the headroom the score's ranking of these same top predictions
    /// uses. `None` when
    /// `oracle − random` is below [`MIN_HEADROOM`] (no top prediction, or
    /// all of them, within ε): a share of no headroom is undefined, and
    /// dividing by a difference of rounding errors would give any number.
    pub share_used: Option<f64>,
}

impl Headroom {
    /// The share of the headroom an AUC of these top predictions uses,
    /// `(auc − random) / (oracle − random)`; `None` when `oracle − random`
    /// is below [`MIN_HEADROOM`]. Given the AUC of each frame's best guess
    /// alone (`auc_best_per_frame`: the same top predictions in the score's
    /// order), it lies between 0 and 1 up to the random order's being an
    /// expectation: the oracle's order is the best order of them, and the
    /// random one what a score that knows nothing gets on average. This is
    /// the share for ranked lists and single guesses alike.
    pub fn share_of(&self, auc: f64) -> Option<f64> {
        let gap = self.oracle_auc - self.random_auc;
        (gap >= MIN_HEADROOM).then(|| (auc - self.random_auc) / gap)
    }

    /// [`Headroom::share_of`] the best guesses' AUC where the evaluation
    /// has it, else of `auc` (evaluations stored before the best guess's
    /// AUC existed, whose top predictions were all their predictions).
    pub fn share_used_by_best_guesses(
        &self,
        auc: f64,
        auc_best_per_frame: Option<f64>,
    ) -> Option<f64> {
        self.share_of(auc_best_per_frame.unwrap_or(auc))
    }
}

/// The smallest `oracle − random` a share of the headroom is computed
/// over. A real gap is at least of order 1/G (one top prediction more or
/// less within ε); rounding in the sums is of order 1e-16 per term, so
/// this separates the two for any test set below 10⁷ truths.
pub(crate) const MIN_HEADROOM: f64 = 1e-9;

/// The headroom of predictions `ranked` (in the metric's order) whose AUC
/// at `eps` is `auc`, against a set of `ground_truths` truths.
pub(super) fn headroom(
    ranked: &[Prediction],
    truth_by_frame: &TruthByFrame,
    ground_truths: usize,
    eps: f64,
    auc: f64,
) -> Headroom {
    let tops = top_predictions(ranked);
    let mut by_error: Vec<(f64, Prediction)> = tops
        .iter()
        .map(|p| (nearest_squared_distance(p, truth_by_frame), *p))
        .collect();
    // Stable: equal errors keep the ranking order.
    by_error.sort_by(|a, b| a.0.total_cmp(&b.0));
    let oracle_order: Vec<Prediction> = by_error.into_iter().map(|(_, p)| p).collect();
    // The same walk as the AUC: with one prediction per frame, a top
    // prediction is a true positive exactly when it is within ε.
    let oracle = walk(&oracle_order, truth_by_frame, ground_truths, eps, false);
    let n = tops.len();
    let m = oracle.true_positives;
    // m / G in one division: the walk's sum of m terms 1/G can round to
    // just above 1 when m = G. A true positive is matched to its own
    // truth, so m ≤ G.
    let oracle_auc = if ground_truths == 0 {
        0.0
    } else {
        m.min(ground_truths) as f64 / ground_truths as f64
    };
    // The expectation lies between 0 and the oracle's; clamped so that
    // rounding cannot put it outside.
    let random_auc = expected_random_rank_auc(n, m, ground_truths).clamp(0.0, oracle_auc);
    let mut headroom = Headroom {
        top_predictions: n,
        top_within_eps: m,
        fraction_top_within_eps: (n > 0).then(|| m as f64 / n as f64),
        oracle_auc,
        random_auc,
        share_used: None,
    };
    headroom.share_used = headroom.share_of(auc);
    headroom
}

/// The expected AUC of `n` predictions, one per frame, `m` of them true
/// positives, in a uniformly random order, against `ground_truths` (G)
/// truths.
///
/// The AUC is `(1/G) Σ_k [k-th is a hit] · TP_k / k`. In a random order the
/// `k`-th prediction is a hit with probability `m/n`, and given that, the
/// hits among the `k − 1` before it are hypergeometric with mean
/// `(k − 1)(m − 1)/(n − 1)`, so
///
/// `E[AUC] = (1/G) Σ_{k=1..n} (1/k) · (m/n) · (1 + (k − 1)(m − 1)/(n − 1))`,
///
/// summed in that order (for `n = 1` the bracket is 1). For large `n` and
/// `G = n` it approaches `(m/n)²`.
pub(crate) fn expected_random_rank_auc(n: usize, m: usize, ground_truths: usize) -> f64 {
    if n == 0 || m == 0 || ground_truths == 0 {
        return 0.0;
    }
    let hit = m as f64 / n as f64;
    let others = if n > 1 {
        (m as f64 - 1.0) / (n as f64 - 1.0)
    } else {
        0.0
    };
    let mut sum = 0.0;
    for k in 1..=n {
        sum += hit * (1.0 + (k as f64 - 1.0) * others) / k as f64;
    }
    sum / ground_truths as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AUC of hits (`true`) and misses in the order given.
    fn auc_of(order: &[bool], ground_truths: usize) -> f64 {
        let mut hits = 0usize;
        let mut auc = 0.0;
        for (index, &hit) in order.iter().enumerate() {
            if hit {
                hits += 1;
                auc += hits as f64 / (index + 1) as f64 / ground_truths as f64;
            }
        }
        auc
    }

    /// All distinct orders of `m` hits among `n`, each as likely as the
    /// `n!` permutations make it (every arrangement of hits is equally
    /// likely), averaged.
    fn brute_force(n: usize, m: usize, ground_truths: usize) -> f64 {
        let mut total = 0.0;
        let mut count = 0usize;
        for mask in 0u32..(1 << n) {
            if mask.count_ones() as usize != m {
                continue;
            }
            let order: Vec<bool> = (0..n).map(|i| mask >> i & 1 == 1).collect();
            total += auc_of(&order, ground_truths);
            count += 1;
        }
        total / count as f64
    }

    #[test]
    fn the_closed_form_is_the_mean_over_every_order() {
        for n in 1..=9 {
            for m in 0..=n {
                for ground_truths in [n, n + 3] {
                    let closed = expected_random_rank_auc(n, m, ground_truths);
                    let brute = brute_force(n, m, ground_truths);
                    assert!(
                        (closed - brute).abs() < 1e-12,
                        "n {n} m {m} G {ground_truths}: {closed} vs {brute}"
                    );
                }
            }
        }
        // Large n: (m/n)² plus a term of order ln(n)/n.
        let large = expected_random_rank_auc(100_000, 60_000, 100_000);
        assert!((large - 0.36).abs() < 1e-3, "{large}");
    }
}
