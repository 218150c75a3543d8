//! The Table-1 metric (docs/metric.md) on cases worked out by hand.

use scanloc::metrics::{ScoreReading, score, score_read_as};
use scanloc::types::{Prediction, TruthRow};

fn truth(frame: usize, x: f64, y: f64) -> TruthRow {
    TruthRow::stationary(frame, x, y)
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

/// One QD per frame at the origin; top predictions at 2, 0.5, 3 and 0.2 px
/// in score order, and a late second prediction on frame 1.
fn headroom_case() -> (Vec<TruthRow>, Vec<Prediction>) {
    let truths = (0..4).map(|frame| truth(frame, 0.0, 0.0)).collect();
    let predictions = vec![
        prediction(0, 2.0, 0.0, 0.9),
        prediction(1, 0.0, 0.5, 0.8),
        prediction(2, 3.0, 0.0, 0.7),
        prediction(3, 0.2, 0.0, 0.6),
        prediction(1, 0.1, 0.0, 0.1), // not a top prediction: a duplicate
    ];
    (truths, predictions)
}

#[test]
fn headroom_on_a_hand_worked_case() {
    let (truths, predictions) = headroom_case();
    let result = score(&predictions, &truths, 4, &[1.0, 2.5], false).unwrap();

    // ε = 1: hits at ranks 2 and 4 → AUC = ¼ (½ + 2/4) = ¼.
    let at1 = &result.per_eps[0];
    assert!(close(at1.auc, 0.25), "{}", at1.auc);
    let headroom = at1.headroom.unwrap();
    assert_eq!((headroom.top_predictions, headroom.top_within_eps), (4, 2));
    assert!(close(headroom.fraction_top_within_eps.unwrap(), 0.5));
    // Oracle: the two hits first → ¼ (1 + 1) = ½.
    assert!(close(headroom.oracle_auc, 0.5));
    // Random: the 6 placements of 2 hits among 4 give G·AUC = 2, 5/3, 3/2,
    // 7/6, 1, 5/6; mean 49/36, so AUC = 49/144.
    assert!(
        close(headroom.random_auc, 49.0 / 144.0),
        "{}",
        headroom.random_auc
    );
    // This score ranks worse than chance: (36 − 49) / (72 − 49).
    assert!(close(headroom.share_used.unwrap(), -13.0 / 23.0));

    // ε = 2.5: hits at ranks 1, 2, 4 → ¼ (1 + 1 + ¾) = 11/16.
    let at25 = &result.per_eps[1];
    assert!(close(at25.auc, 11.0 / 16.0));
    let headroom = at25.headroom.unwrap();
    assert_eq!(headroom.top_within_eps, 3);
    assert!(close(headroom.oracle_auc, 0.75));
    // Random, 3 hits among 4: the miss at rank 1, 2, 3 or 4 gives G·AUC =
    // 1/2 + 2/3 + 3/4, 1 + 2/3 + 3/4, 1 + 1 + 3/4, 1 + 1 + 1; mean
    // 121/48, so AUC = 121/192.
    assert!(close(headroom.random_auc, 121.0 / 192.0));
    assert!(close(headroom.share_used.unwrap(), 11.0 / 23.0));
}

#[test]
fn headroom_is_undefined_when_oracle_and_random_agree() {
    let truths = [truth(0, 0.0, 0.0), truth(1, 0.0, 0.0)];
    // Both top predictions within ε: any order is the oracle's.
    let predictions = [prediction(0, 0.1, 0.0, 0.2), prediction(1, 0.0, 0.1, 0.9)];
    let result = score(&predictions, &truths, 2, &[1.0], false).unwrap();
    let headroom = result.per_eps[0].headroom.unwrap();
    assert!(close(headroom.oracle_auc, 1.0) && close(headroom.random_auc, 1.0));
    assert_eq!(headroom.share_used, None);
    // No prediction at all: no top prediction, nothing to share.
    let result = score(&[], &truths, 2, &[1.0], false).unwrap();
    let headroom = result.per_eps[0].headroom.unwrap();
    assert_eq!(headroom.top_predictions, 0);
    assert_eq!(headroom.fraction_top_within_eps, None);
    assert_eq!((headroom.oracle_auc, headroom.random_auc), (0.0, 0.0));
}

#[test]
fn reliability_and_calibration_error_on_a_hand_worked_case() {
    // One QD per frame at the origin, except the empty frame 5.
    let truths: Vec<TruthRow> = (0..5).map(|frame| truth(frame, 0.0, 0.0)).collect();
    let predictions = [
        prediction(0, 0.5, 0.0, 0.9),  // bin [0.9, 1]: within 1 px
        prediction(1, 0.0, 1.0, 1.0),  // bin [0.9, 1]: exactly 1 px counts
        prediction(2, 0.6, 0.0, 0.2),  // bin [0.2, 0.3): within
        prediction(3, 1.5, 0.0, 0.25), // bin [0.2, 0.3): 1.5 px, outside
        prediction(5, 0.0, 0.0, 0.0),  // bin [0, 0.1): a frame without truth
    ];
    let reading = ScoreReading {
        threshold: None,
        probability: true,
    };
    let result = score_read_as(&predictions, &truths, 6, &[1.0], false, reading).unwrap();
    let reliability = result.reliability.unwrap();
    assert_eq!(reliability.bins.len(), 10);
    assert_eq!(reliability.localisations, 5);
    let counts: Vec<usize> = reliability.bins.iter().map(|b| b.count).collect();
    assert_eq!(counts, [1, 0, 2, 0, 0, 0, 0, 0, 0, 2]);
    let top = &reliability.bins[9];
    assert!(close(top.mean_score.unwrap(), 0.95));
    assert!(close(top.observed_frequency.unwrap(), 1.0));
    let low = &reliability.bins[2];
    assert!(close(low.mean_score.unwrap(), 0.225));
    assert!(close(low.observed_frequency.unwrap(), 0.5));
    assert_eq!(reliability.bins[1].mean_score, None);
    // ECE = 2/5 · 0.05 + 2/5 · 0.275 + 1/5 · 0 = 0.13.
    assert!(close(reliability.expected_calibration_error.unwrap(), 0.13));

    // Not a probability: no diagram; a score above 1 is refused as one.
    let plain = score(&predictions, &truths, 6, &[1.0], false).unwrap();
    assert_eq!(plain.reliability, None);
    let mass = [prediction(0, 0.0, 0.0, 250.0)];
    let error = score_read_as(&mass, &truths, 6, &[1.0], false, reading).unwrap_err();
    assert_eq!(scanloc::error::exit_code(&error), 2);
    assert!(error.to_string().contains("not a probability"), "{error}");
}

#[test]
fn scene_figures_on_a_hand_worked_case_with_empty_frames() {
    use scanloc::metrics::{ScoreReading, score_read_as};
    // Frame 0: QDs A (0, 0) and B (5, 0); frame 1: C (10, 10); frames 2
    // and 3: empty.
    let truths = [truth(0, 0.0, 0.0), truth(0, 5.0, 0.0), truth(1, 10.0, 10.0)];
    let predictions = [
        prediction(0, 0.3, 0.4, 0.9),   // A at 0.5 px
        prediction(0, 5.0, 0.6, 0.8),   // B at 0.6 px
        prediction(0, 0.1, 0.0, 0.7),   // A again: a duplicate
        prediction(1, 10.0, 11.0, 0.6), // C at exactly 1 px
        prediction(2, 3.0, 3.0, 0.5),   // empty frame, at the threshold: counts
        prediction(3, 4.0, 4.0, 0.4),   // empty frame, below the threshold
        prediction(1, 10.0, 10.0, 0.2), // below the threshold
    ];
    let reading = ScoreReading {
        threshold: Some(0.5),
        probability: false,
    };
    let result = score_read_as(&predictions, &truths, 4, &[1.0, 0.55], false, reading).unwrap();
    assert_eq!(result.reading, Some(reading));

    // ε = 1: 5 kept, A, B, C matched; the duplicate and the empty frame's
    // localisation are false.
    let at1 = result.per_eps[0].at_threshold.unwrap();
    assert_eq!(at1.localisations, 5);
    assert_eq!(
        (at1.true_positives, at1.false_positives, at1.false_negatives),
        (3, 2, 0)
    );
    assert!(close(at1.recall, 1.0));
    assert!(close(at1.precision.unwrap(), 0.6));
    assert!(close(at1.jaccard, 0.6));
    // √((0.25 + 0.36 + 1) / 3)
    assert!(close(at1.rmse_matched_px.unwrap(), (1.61f64 / 3.0).sqrt()));

    // ε = 0.55: only A is matched.
    let at055 = result.per_eps[1].at_threshold.unwrap();
    assert_eq!(
        (
            at055.true_positives,
            at055.false_positives,
            at055.false_negatives
        ),
        (1, 4, 2)
    );
    assert!(close(at055.recall, 1.0 / 3.0));
    assert!(close(at055.precision.unwrap(), 0.2));
    assert!(close(at055.jaccard, 1.0 / 7.0));
    assert!(close(at055.rmse_matched_px.unwrap(), 0.5));

    // Two empty frames, one localisation at or above the threshold on them.
    let empty = result.empty_frames.unwrap();
    assert_eq!((empty.frames, empty.localisations), (2, 1));
    assert!(close(empty.false_localisations_per_frame.unwrap(), 0.5));

    // Without a threshold every localisation counts: C's second one is a
    // duplicate, frame 3's is false too.
    let all = score(&predictions, &truths, 4, &[1.0], false).unwrap();
    let at1 = all.per_eps[0].at_threshold.unwrap();
    assert_eq!(
        (at1.true_positives, at1.false_positives, at1.false_negatives),
        (3, 4, 0)
    );
    assert!(close(at1.jaccard, 3.0 / 7.0));
    let empty = all.empty_frames.unwrap();
    assert_eq!((empty.frames, empty.localisations), (2, 2));
    assert!(close(empty.false_localisations_per_frame.unwrap(), 1.0));

    // A threshold above every score keeps nothing: recall 0, precision
    // undefined, no RMSE.
    let none = ScoreReading {
        threshold: Some(2.0),
        probability: false,
    };
    let result = score_read_as(&predictions, &truths, 4, &[1.0], false, none).unwrap();
    let at1 = result.per_eps[0].at_threshold.unwrap();
    assert_eq!((at1.localisations, at1.false_negatives), (0, 3));
    assert_eq!((at1.precision, at1.rmse_matched_px), (None, None));
    assert!(close(at1.jaccard, 0.0));
    // The AUC does not depend on the reading.
    assert_eq!(
        result.per_eps[0].auc.to_bits(),
        all.per_eps[0].auc.to_bits()
    );
}

#[test]
fn score_prints_the_headroom_scene_and_calibration_figures() {
    use crate::common::{scanloc, stderr, stdout};
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.csv");
    let locs = dir.path().join("locs.csv");
    // The hand-worked scene: two QDs on frame 0, one on frame 1; frames 2
    // and 3 (the last one named only by --frames) empty.
    std::fs::write(&truth, "frame,x,y\n0,0,0\n0,5,0\n1,10,10\n").unwrap();
    std::fs::write(
        &locs,
        "frame,x,y,score\n0,0.3,0.4,0.9\n0,5,0.6,0.8\n0,0.1,0,0.7\n1,10,11,0.6\n2,3,3,0.5\n3,4,4,0.4\n1,10,10,0.2\n",
    )
    .unwrap();
    let (truth, locs) = (truth.to_str().unwrap(), locs.to_str().unwrap());
    let base = ["score", "--truth", truth, "--locs", locs, "--eps", "1"];
    let json = |extra: &[&str]| {
        let output = scanloc(&[&base[..], extra, &["--json"]].concat());
        assert!(output.status.success(), "{}", stderr(&output));
        serde_json::from_str::<serde_json::Value>(&stdout(&output)).unwrap()
    };
    let score = json(&["--frames", "4", "--probability"]);
    let at = &score["per_eps"][0]["at_threshold"];
    assert_eq!(at["true_positives"], 3);
    assert_eq!(at["false_positives"], 2);
    assert!(close(at["jaccard"].as_f64().unwrap(), 0.6));
    assert_eq!(score["empty_frames"]["frames"], 2);
    assert_eq!(score["empty_frames"]["localisations"], 1);
    assert_eq!(score["reading"]["threshold"], 0.5);
    assert_eq!(
        score["reliability"]["bins"].as_array().unwrap().len(),
        10,
        "{score}"
    );
    // --threshold overrides the default; without --probability there is
    // no reliability diagram.
    let score = json(&["--frames", "4", "--threshold", "0.55"]);
    assert_eq!(score["empty_frames"]["frames"], 2);
    assert_eq!(score["empty_frames"]["localisations"], 0);
    assert_eq!(score["per_eps"][0]["at_threshold"]["localisations"], 4);
    assert!(score["reliability"].is_null());
    // The table names every figure.
    let output = scanloc(&[&base[..], &["--frames", "4", "--probability"]].concat());
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    for expected in [
        "oracle",
        "random",
        "share",
        "top_within",
        "localisations with score >= 0.5:",
        "Jaccard",
        "empty frames (no truth): 2 of 4; localisations on them: 1 (0.5000 per empty frame)",
        "expected calibration error",
    ] {
        assert!(text.contains(expected), "{expected:?} in\n{text}");
    }
    // Bad flags: exit 2 with the flag named.
    for (extra, named) in [
        (&["--frames", "1"][..], "--frames"),
        (&["--frames", "0"][..], "--frames"),
        (&["--threshold", "nan"][..], "--threshold"),
    ] {
        let output = scanloc(&[&base[..], extra].concat());
        assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
        assert!(stderr(&output).contains(named), "{}", stderr(&output));
    }
    // A score above 1 is not a probability.
    std::fs::write(dir.path().join("mass.csv"), "frame,x,y,score\n0,0,0,250\n").unwrap();
    let mass = dir.path().join("mass.csv");
    let output = scanloc(&[
        "score",
        "--truth",
        truth,
        "--locs",
        mass.to_str().unwrap(),
        "--probability",
    ]);
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    assert!(
        stderr(&output).contains("not a probability"),
        "{}",
        stderr(&output)
    );
}

#[test]
fn a_set_of_empty_frames_has_only_its_false_localisations() {
    use scanloc::metrics::{ScoreReading, score_read_as};
    let predictions = [
        prediction(0, 1.0, 1.0, 0.9),
        prediction(2, 3.0, 3.0, 0.7),
        prediction(2, 5.0, 5.0, 0.3),
    ];
    let reading = ScoreReading {
        threshold: Some(0.5),
        probability: true,
    };
    let result = score_read_as(&predictions, &[], 4, &[1.0, 2.0], false, reading).unwrap();
    // No ground truth: recall, and so everything per ε, is undefined.
    assert!(result.per_eps.is_empty());
    assert_eq!(result.ground_truths, 0);
    let empty = result.empty_frames.unwrap();
    assert_eq!((empty.frames, empty.localisations), (4, 2));
    assert!(close(empty.false_localisations_per_frame.unwrap(), 0.5));
    // Every localisation is wrong: ECE = (0.9 + 0.7 + 0.3) / 3.
    let reliability = result.reliability.unwrap();
    assert!(close(
        reliability.expected_calibration_error.unwrap(),
        1.9 / 3.0
    ));
    // The AUC alone is refused there, as before.
    let error = score(&predictions, &[], 4, &[1.0], false).unwrap_err();
    assert!(error.to_string().contains("no ground truth"), "{error}");
}

#[test]
fn score_scores_a_truth_file_of_empty_frames_given_their_count() {
    use crate::common::{scanloc, stderr, stdout};
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.csv");
    let locs = dir.path().join("locs.csv");
    std::fs::write(&truth, "frame,x,y\n").unwrap();
    std::fs::write(&locs, "frame,x,y,score\n0,1,1,0.9\n2,3,3,0.7\n2,5,5,0.3\n").unwrap();
    let (truth, locs) = (truth.to_str().unwrap(), locs.to_str().unwrap());
    let base = ["score", "--truth", truth, "--locs", locs, "--probability"];
    let output = scanloc(&[&base[..], &["--frames", "4"]].concat());
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    assert!(
        text.contains(
            "empty frames (no truth): 4 of 4; localisations on them: 2 (0.5000 per empty frame)"
        ),
        "{text}"
    );
    assert!(
        text.contains("AUC, recall and precision are undefined"),
        "{text}"
    );
    // Without --frames the set's size is unknown.
    let output = scanloc(&base);
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    assert!(stderr(&output).contains("--frames"), "{}", stderr(&output));
}

#[test]
fn a_manifest_threshold_changes_only_its_detectors_evaluation_keys() {
    use scanloc::run::{Action, Plan};
    let smoke = std::fs::read_to_string(crate::common::smoke()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let with_threshold = smoke.replace(
        "metrics:\n  eps_px: [1, 2, 3]\n",
        "metrics:\n  eps_px: [1, 2, 3]\n  score_thresholds: {cnn: 0.7}\n",
    );
    assert_ne!(with_threshold, smoke);
    let plan_of = |text: &str, name: &str| {
        let path = crate::common::write_manifest(dir.path(), name, text);
        Plan::from_manifest(&scanloc::manifest::load(&path).unwrap()).unwrap()
    };
    let (before, after) = (
        plan_of(&smoke, "smoke.yaml"),
        plan_of(&with_threshold, "threshold.yaml"),
    );
    assert_eq!(before.steps.len(), after.steps.len());
    for (a, b) in before.steps.iter().zip(&after.steps) {
        assert_eq!(a.id, b.id);
        let changed = a.id.to_string().starts_with("evaluation/cnn@");
        assert_eq!(a.key != b.key, changed, "{}", a.id);
        if let (Action::Score { reading: ra, .. }, Action::Score { reading: rb, .. }) =
            (&a.action, &b.action)
        {
            // The CNN's score is a probability (default threshold 0.5);
            // trackpy's mass is not (no threshold).
            let cnn = a.id.to_string().starts_with("evaluation/cnn@");
            assert_eq!(ra.probability, cnn);
            assert_eq!(ra.threshold, cnn.then_some(0.5));
            assert_eq!(rb.threshold, cnn.then_some(0.7).or(ra.threshold));
        }
    }
}

#[test]
fn score_compares_two_detectors_with_a_paired_bootstrap() {
    use crate::common::{scanloc, stderr, stdout};
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    // 200 frames of one QD: `exact` finds each; `half` misses every other
    // one by 1.5 px and ranks its hits first (its AUC at 1 px is 1/2, at 2
    // px 1).
    let mut truth = String::from("frame,x,y\n");
    let mut exact = String::from("frame,x,y,score\n");
    let mut half = String::from("frame,x,y,mass\n");
    for frame in 0..200 {
        truth.push_str(&format!("{frame},5,5\n"));
        exact.push_str(&format!("{frame},5,5,0.9\n"));
        let (x, mass) = if frame % 2 == 0 {
            (5.0, 9.0)
        } else {
            (6.5, 1.0)
        };
        half.push_str(&format!("{frame},{x},5,{mass}\n"));
    }
    std::fs::write(path("truth.csv"), truth).unwrap();
    std::fs::write(path("exact.csv"), exact).unwrap();
    std::fs::write(path("half.csv"), half).unwrap();
    let (truth, exact, half) = (path("truth.csv"), path("exact.csv"), path("half.csv"));
    let compare = [
        "score",
        "--truth",
        &truth,
        "--locs",
        &exact,
        "--compare",
        &half,
        "--compare-score-column",
        "mass",
        "--eps",
        "1,2",
    ];
    let output = scanloc(&[&compare[..], &["--json"]].concat());
    assert!(output.status.success(), "{}", stderr(&output));
    let json: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    // The score of --locs is unchanged; the comparison is beside it.
    assert!(close(json["per_eps"][0]["auc"].as_f64().unwrap(), 1.0));
    let comparison = json["comparison"].as_array().unwrap();
    assert_eq!(comparison.len(), 2);
    let at_1 = &comparison[0];
    assert!(close(at_1["auc_compared"].as_f64().unwrap(), 0.5));
    assert!(close(at_1["difference"].as_f64().unwrap(), 0.5));
    assert_eq!(at_1["resamples"], 1000);
    // √(½ · ½ / 200) = 0.035; 1,000 resamples estimate it within ≈ 2.2 %,
    // the tolerance is 15 %.
    let standard_error = at_1["standard_error"].as_f64().unwrap();
    assert!((standard_error - 0.0354).abs() < 0.0053, "{standard_error}");
    let interval = at_1["interval_95"].as_array().unwrap();
    assert!(interval[0].as_f64().unwrap() > 0.4 && interval[1].as_f64().unwrap() < 0.6);
    assert!(close(comparison[1]["difference"].as_f64().unwrap(), 0.0));
    // The same seed gives the same figures; the table names them.
    let again = scanloc(&[&compare[..], &["--json"]].concat());
    assert_eq!(stdout(&again), stdout(&output));
    let table = stdout(&scanloc(&compare));
    for expected in [
        "paired comparison",
        "1000 resamples, seed 0",
        "95% interval",
        "+0.5000",
    ] {
        assert!(table.contains(expected), "{expected:?} in\n{table}");
    }
    // Bad input: exit 2 naming the flag or the file.
    std::fs::write(path("elsewhere.csv"), "frame,x,y,mass\n500,5,5,1\n").unwrap();
    let elsewhere = compare.map(|arg| {
        if arg == half {
            path("elsewhere.csv")
        } else {
            arg.to_string()
        }
    });
    let elsewhere: Vec<&str> = elsewhere.iter().map(String::as_str).collect();
    for (args, named) in [
        (
            [&compare[..], &["--resamples", "0"]].concat(),
            "--resamples",
        ),
        (
            [&compare[..], &["--resamples", "100001"]].concat(),
            "--resamples",
        ),
        (elsewhere, "elsewhere.csv"),
    ] {
        let output = scanloc(&args);
        assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
        assert!(stderr(&output).contains(named), "{}", stderr(&output));
    }
    // The bootstrap's options need --compare or --bootstrap.
    let output = scanloc(&["score", "--truth", &truth, "--locs", &exact, "--seed", "3"]);
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));

    // One detector's own spread: `half` alone on the same resamples has
    // the paired difference's standard error (1 − its AUC has its spread).
    let alone = [
        "score",
        "--truth",
        &truth,
        "--locs",
        &half,
        "--score-column",
        "mass",
        "--eps",
        "1,2",
        "--bootstrap",
    ];
    let output = scanloc(&[&alone[..], &["--json"]].concat());
    assert!(output.status.success(), "{}", stderr(&output));
    let json: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert!(json.get("comparison").is_none(), "{json}");
    let spread = json["spread"].as_array().unwrap();
    assert_eq!(spread.len(), 2);
    assert!(close(spread[0]["auc"].as_f64().unwrap(), 0.5));
    let own = spread[0]["standard_error"].as_f64().unwrap();
    assert!(
        (own - standard_error).abs() < 1e-12,
        "{own} vs {standard_error}"
    );
    assert!(close(spread[1]["standard_error"].as_f64().unwrap(), 0.0));
    // With --compare too, one set of resamples serves both: the same spread,
    // and the difference from `exact` spreads as `half`'s AUC does.
    let with_exact = ["--compare", &exact, "--compare-score-column", "score"];
    let both = scanloc(&[&alone[..], &with_exact, &["--json"]].concat());
    assert!(both.status.success(), "{}", stderr(&both));
    let both: serde_json::Value = serde_json::from_str(&stdout(&both)).unwrap();
    assert_eq!(both["spread"], json["spread"]);
    let difference = &both["comparison"][0];
    assert!(close(difference["difference"].as_f64().unwrap(), -0.5));
    let paired = difference["standard_error"].as_f64().unwrap();
    assert!((paired - own).abs() < 1e-12, "{paired} vs {own}");
    let table = stdout(&scanloc(&alone));
    assert!(table.contains("bootstrap of the AUC"), "{table}");
    assert!(!table.contains("paired comparison"), "{table}");
}

/// A ranked list of guesses per frame, scored by hand (docs/metric.md, "A
/// ranked list of guesses"): one QD per frame at the origin, ε = 1 px,
/// G = 4.
///
/// | frame | rank 1 (score, hit?) | rank 2 |
/// |---|---|---|
/// | 0 | 0.9 hit | — |
/// | 1 | 0.6 miss | 0.3 hit |
/// | 2 | 0.5 hit | 0.2 miss (its QD is taken) |
/// | 3 | 0.4 miss | 0.1 miss |
///
/// The whole list in score order: TP at k = 1, 3, 5, so
/// AUC = (1/1 + 2/3 + 3/5) / 4 = 34/60; the best per frame alone
/// (0.9, 0.6, 0.5, 0.4): TP at k = 1, 3, AUC = (1 + 2/3) / 4 = 5/12. At a
/// threshold of 0.25 the scene figures keep the four rank-1 guesses only
/// (TP 2, FP 2, FN 2); unranked, the same localisations would count as
/// five QDs' worth (the 0.3 guess a third TP).
#[test]
fn a_ranked_list_scores_both_aucs_and_only_its_best_guesses_in_the_scene_figures() {
    let guess = |frame, x, y, score, rank| Prediction {
        candidate: Some(rank),
        ..prediction(frame, x, y, score)
    };
    let ranked = [
        guess(0, 0.5, 0.0, 0.9, 1),
        guess(1, 3.0, 0.0, 0.6, 1),
        guess(1, 0.2, 0.0, 0.3, 2),
        guess(2, 0.0, 0.5, 0.5, 1),
        guess(2, 0.0, 4.0, 0.2, 2),
        guess(3, 5.0, 5.0, 0.4, 1),
        guess(3, 6.0, 6.0, 0.1, 2),
    ];
    let truths: Vec<TruthRow> = (0..4).map(|frame| truth(frame, 0.0, 0.0)).collect();
    let reading = ScoreReading {
        threshold: Some(0.25),
        probability: true,
    };
    let score = score_read_as(&ranked, &truths, 4, &[1.0], false, reading).unwrap();
    let at_one = &score.per_eps[0];
    assert!(close(at_one.auc, 34.0 / 60.0), "{}", at_one.auc);
    assert!(close(at_one.auc_best_per_frame.unwrap(), 5.0 / 12.0));
    let scene = at_one.at_threshold.unwrap();
    assert_eq!(
        (
            scene.localisations,
            scene.true_positives,
            scene.false_positives,
            scene.false_negatives
        ),
        (4, 2, 2, 2)
    );
    // Unranked (a scene's separate QDs, or a file without the column):
    // the same AUCs (the top score per frame is its best), but every
    // localisation at or above the threshold counts in the scene figures.
    let unranked: Vec<Prediction> = ranked
        .iter()
        .map(|p| Prediction {
            candidate: None,
            ..*p
        })
        .collect();
    let score = score_read_as(&unranked, &truths, 4, &[1.0], false, reading).unwrap();
    let at_one = &score.per_eps[0];
    assert!(close(at_one.auc, 34.0 / 60.0));
    assert!(close(at_one.auc_best_per_frame.unwrap(), 5.0 / 12.0));
    let scene = at_one.at_threshold.unwrap();
    assert_eq!((scene.localisations, scene.true_positives), (5, 3));
    // A frame's rank 1 is its best even when a lower rank scores higher.
    let mut swapped = ranked;
    swapped[1].score = 0.2;
    let score = score_read_as(&swapped, &truths, 4, &[1.0], false, reading).unwrap();
    // Best per frame: 0.9 hit, 0.5 hit, 0.4 miss, 0.2 miss: (1 + 1) / 4.
    assert!(close(score.per_eps[0].auc_best_per_frame.unwrap(), 0.5));
}
