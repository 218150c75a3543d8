//! How well diffusion coefficients were estimated (`docs/tracking.md`):
//! over estimates `D̂ₖ` of a true `D`, the relative bias
//! `mean(D̂ₖ/D − 1)`, the relative RMSE `√mean((D̂ₖ/D − 1)²)` and the
//! coverage of the reported 95 % intervals (the share with
//! `lowₖ ≤ D ≤ highₖ`, which should be 0.95).

use serde::{Deserialize, Serialize};

/// One estimate of D with its 95 % interval, µm²/s.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct DiffusionInterval {
    pub d: f64,
    pub low: f64,
    pub high: f64,
}

/// The D metrics of a set of estimates of one true D.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DiffusionScore {
    /// Estimates scored.
    pub count: usize,
    /// `mean(D̂/D − 1)`.
    pub relative_bias: f64,
    /// `√mean((D̂/D − 1)²)`.
    pub relative_rmse: f64,
    /// Share of the 95 % intervals holding the true D.
    pub coverage: f64,
}

/// Scores `estimates` of the true `truth` (> 0); `None` for no estimates.
pub(crate) fn score_diffusion(
    estimates: &[DiffusionInterval],
    truth: f64,
) -> Option<DiffusionScore> {
    if estimates.is_empty() {
        return None;
    }
    let n = estimates.len() as f64;
    let errors = estimates.iter().map(|e| e.d / truth - 1.0);
    let relative_bias = errors.clone().sum::<f64>() / n;
    let relative_rmse = (errors.map(|e| e * e).sum::<f64>() / n).sqrt();
    let covered = estimates
        .iter()
        .filter(|e| e.low <= truth && truth <= e.high)
        .count();
    Some(DiffusionScore {
        count: estimates.len(),
        relative_bias,
        relative_rmse,
        coverage: covered as f64 / n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hand_worked_scores() {
        // D = 2: estimates 1.5, 2.5, 3 → errors −0.25, 0.25, 0.5;
        // bias 0.5/3 = 0.1667; RMSE √((0.0625 + 0.0625 + 0.25)/3) = √0.125;
        // the intervals [1, 1.9], [2, 3], [1.5, 4] hold 2 in two of three.
        let estimates = [
            DiffusionInterval {
                d: 1.5,
                low: 1.0,
                high: 1.9,
            },
            DiffusionInterval {
                d: 2.5,
                low: 2.0,
                high: 3.0,
            },
            DiffusionInterval {
                d: 3.0,
                low: 1.5,
                high: 4.0,
            },
        ];
        let score = score_diffusion(&estimates, 2.0).unwrap();
        assert_eq!(score.count, 3);
        assert!((score.relative_bias - 1.0 / 6.0).abs() < 1e-12);
        assert!((score.relative_rmse - 0.125f64.sqrt()).abs() < 1e-12);
        assert!((score.coverage - 2.0 / 3.0).abs() < 1e-12);
        assert_eq!(score_diffusion(&[], 1.0), None);
    }
}
