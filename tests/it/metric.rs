//! The Table-1 metric (docs/metric.md) on cases worked out by hand.

use scanloc::metrics::score;
use scanloc::types::{Prediction, TruthRow};

fn truth(frame: usize, x: f64, y: f64) -> TruthRow {
    TruthRow {
        frame,
        x,
        y,
        x_start: x,
        y_start: y,
        x_end: x,
        y_end: y,
        z_mean: 0.0,
        diffusion: 0.0,
    }
}

fn prediction(frame: usize, x: f64, y: f64, score: f64) -> Prediction {
    Prediction::new(frame, x, y, score)
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() < 1e-12
}

#[test]
fn duplicates_are_false_positives_and_the_boundary_counts_as_a_match() {
    let truths = [truth(0, 0.0, 0.0), truth(1, 10.0, 10.0)];
    let predictions = [
        prediction(0, 0.5, 0.0, 0.9),   // TP (0.5 px)
        prediction(0, 0.2, 0.0, 0.8),   // duplicate: FP
        prediction(1, 13.0, 10.0, 0.7), // exactly 3 px: TP only at ε = 3
    ];
    let result = score(&predictions, &truths, 2, &[1.0, 2.0, 3.0], true).unwrap();
    // ε = 1, 2: k=1 TP (P 1, R ½) → AUC ½.
    assert!(close(result.per_eps[0].auc, 0.5));
    assert!(close(result.per_eps[1].auc, 0.5));
    // ε = 3: + (R 1 − ½) · P 2/3 at k = 3 → ½ + ⅓.
    assert!(
        close(result.per_eps[2].auc, 0.5 + 1.0 / 3.0),
        "{}",
        result.per_eps[2].auc
    );
    assert_eq!(result.per_eps[2].true_positives, 2);
    assert_eq!(result.per_eps[2].false_positives, 1);
    let curve = &result.per_eps[2].curve;
    assert_eq!(curve.len(), 3);
    assert!(close(curve[1].precision, 0.5) && close(curve[1].recall, 0.5));
    assert!(close(curve[2].precision, 2.0 / 3.0) && close(curve[2].recall, 1.0));
    // Top predictions: 0.5 px in frame 0, 3 px in frame 1.
    assert!(close(
        result.rmse_top_px.unwrap(),
        ((0.25 + 9.0) / 2.0f64).sqrt()
    ));
    assert_eq!(result.frames_without_prediction, 0);
}

#[test]
fn ties_in_score_are_broken_by_frame_then_x_then_y() {
    let truths = [truth(0, 0.0, 0.0), truth(1, 5.0, 5.0)];
    // Equal scores: frame 0's miss comes first, so the hit is at k = 2:
    // AUC = ½ · ½ = ¼ (the other order would give ½).
    let predictions = [prediction(1, 5.0, 5.0, 1.0), prediction(0, 3.0, 0.0, 1.0)];
    let result = score(&predictions, &truths, 2, &[1.0], false).unwrap();
    assert!(
        close(result.per_eps[0].auc, 0.25),
        "{}",
        result.per_eps[0].auc
    );

    // Same frame, same score: smaller x first. Truth at x = 0: x = 0.8 is a
    // hit, x = 4 a miss; hit first gives AUC 1, miss first ½.
    let truths = [truth(0, 0.0, 0.0)];
    let predictions = [prediction(0, 4.0, 0.0, 2.0), prediction(0, 0.8, 0.0, 2.0)];
    let result = score(&predictions, &truths, 1, &[1.0], true).unwrap();
    // x = 0.8 ranks before x = 4.0: TP at k = 1 → AUC 1.
    assert!(close(result.per_eps[0].auc, 1.0));
    assert!(close(result.per_eps[0].curve[0].precision, 1.0));
}

#[test]
fn ties_by_y_put_the_smaller_y_first() {
    let truths = [truth(0, 0.0, 0.0)];
    // Same score and x; y = −3 (a miss) ranks before y = 0.5 (a hit):
    // hit at k = 2 → AUC ½.
    let predictions = [prediction(0, 0.0, 0.5, 1.0), prediction(0, 0.0, -3.0, 1.0)];
    let result = score(&predictions, &truths, 1, &[1.0], false).unwrap();
    assert!(
        close(result.per_eps[0].auc, 0.5),
        "{}",
        result.per_eps[0].auc
    );
}

#[test]
fn a_frame_without_prediction_lowers_recall_and_is_counted() {
    let truths = [truth(0, 1.0, 1.0), truth(1, 2.0, 2.0), truth(2, 3.0, 3.0)];
    let predictions = [prediction(0, 1.0, 1.0, 5.0), prediction(2, 3.5, 3.0, 4.0)];
    let result = score(&predictions, &truths, 3, &[1.0], false).unwrap();
    // Two hits at k = 1, 2 out of G = 3: AUC = ⅓ + ⅓.
    assert!(close(result.per_eps[0].auc, 2.0 / 3.0));
    assert_eq!(result.frames_without_prediction, 1);
    assert!(close(result.fraction_without_prediction, 1.0 / 3.0));
    assert!(close(result.rmse_top_px.unwrap(), (0.25f64 / 2.0).sqrt()));
}

#[test]
fn several_qds_match_the_nearest_unmatched_one() {
    let truths = [truth(0, 0.0, 0.0), truth(0, 2.0, 0.0)];
    // The first prediction is within 1.5 px of both; it takes the nearer
    // (x = 2). The second then matches x = 0. Matching the first unmatched
    // instead would leave the second 2.4 px from x = 2: a miss.
    let predictions = [prediction(0, 1.2, 0.0, 1.0), prediction(0, -0.4, 0.0, 0.5)];
    let result = score(&predictions, &truths, 1, &[1.5], false).unwrap();
    assert!(
        close(result.per_eps[0].auc, 1.0),
        "{}",
        result.per_eps[0].auc
    );
}

#[test]
fn empty_predictions_score_zero_and_empty_truth_is_refused() {
    let truths = [truth(0, 0.0, 0.0)];
    let result = score(&[], &truths, 1, &[1.0, 2.0], false).unwrap();
    assert!(result.per_eps.iter().all(|s| s.auc == 0.0));
    assert_eq!(result.rmse_top_px, None);
    assert!(close(result.fraction_without_prediction, 1.0));

    let error = score(&[prediction(0, 0.0, 0.0, 1.0)], &[], 1, &[1.0], false).unwrap_err();
    assert_eq!(scanloc::error::exit_code(&error), 2);
    assert!(error.to_string().contains("no ground truth"));
}

#[test]
fn non_finite_values_and_bad_radii_are_refused() {
    let truths = [truth(0, 0.0, 0.0)];
    for bad in [
        prediction(0, f64::NAN, 0.0, 1.0),
        prediction(0, 0.0, f64::INFINITY, 1.0),
        prediction(0, 0.0, 0.0, f64::NAN),
        prediction(3, 0.0, 0.0, 1.0),
    ] {
        let error = score(&[bad], &truths, 1, &[1.0], false).unwrap_err();
        assert_eq!(scanloc::error::exit_code(&error), 2, "{error}");
    }
    let nan_truth = [truth(0, f64::NAN, 0.0)];
    let error = score(&[], &nan_truth, 1, &[1.0], false).unwrap_err();
    assert_eq!(scanloc::error::exit_code(&error), 2, "{error}");
    for eps in [0.0, -1.0, f64::NAN] {
        let error = score(&[], &truths, 1, &[eps], false).unwrap_err();
        assert_eq!(scanloc::error::exit_code(&error), 2, "ε {eps}: {error}");
    }
}

#[test]
fn a_perfect_detector_scores_one_and_a_random_one_scores_little() {
    let truths: Vec<TruthRow> = (0..100)
        .map(|f| truth(f, (f % 20) as f64, (f % 7) as f64))
        .collect();
    let perfect: Vec<Prediction> = truths
        .iter()
        .map(|t| prediction(t.frame, t.x + 0.3, t.y, 1.0))
        .collect();
    let result = score(&perfect, &truths, 100, &[1.0], false).unwrap();
    assert!(close(result.per_eps[0].auc, 1.0));
    // Every prediction 5 px off: nothing matches at ε = 1.
    let off: Vec<Prediction> = truths
        .iter()
        .map(|t| prediction(t.frame, t.x + 5.0, t.y, 1.0))
        .collect();
    let result = score(&off, &truths, 100, &[1.0], false).unwrap();
    assert_eq!(result.per_eps[0].auc, 0.0);
}

#[test]
fn top_prediction_errors_are_per_frame_and_root_mean_square_to_the_rmse() {
    use scanloc::metrics::top_prediction_errors;
    let truths = [truth(0, 0.0, 0.0), truth(1, 10.0, 10.0), truth(2, 5.0, 5.0)];
    let predictions = [
        prediction(0, 3.0, 4.0, 0.9), // top of frame 0: 5 px
        prediction(0, 0.0, 0.0, 0.1), // exact but ranked lower: ignored
        prediction(1, 10.0, 11.0, 0.5),
        // frame 2: nothing
    ];
    let errors = top_prediction_errors(&predictions, &truths, 3).unwrap();
    assert_eq!(errors, vec![Some(5.0), Some(1.0), None]);
    let result = score(&predictions, &truths, 3, &[1.0], false).unwrap();
    assert!(close(result.rmse_top_px.unwrap(), (26.0f64 / 2.0).sqrt()));
    assert_eq!(result.frames_without_prediction, 1);
    // The same refusals as the score.
    let nan = [prediction(0, f64::NAN, 0.0, 1.0)];
    for error in [
        top_prediction_errors(&nan, &truths, 3).unwrap_err(),
        top_prediction_errors(&predictions, &[], 3).unwrap_err(),
        top_prediction_errors(&predictions, &truths, 1).unwrap_err(),
    ] {
        assert_eq!(scanloc::error::exit_code(&error), 2, "{error}");
    }
}
