//! `scanloc score`: the paper's precision–recall AUC of a localisation file,
//! where it is lost, and the scene and calibration figures.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::io::{self, csv_tables};
use crate::limits::check_frame_count;
use crate::metrics::paired::{self, AucSpread, PairedDifference};
use crate::metrics::{self, Score, ScoreReading};
use clap::{ArgGroup, Args};

/// Score localisations against ground truth (docs/metric.md).
///
/// Prints, for each matching radius ε, the AUC of the precision–recall
/// curve, the oracle-rank and random-rank AUC of each frame's top
/// prediction with the share of that headroom the score uses, the fraction
/// of top predictions within ε, and recall, precision, Jaccard index and
/// RMSE of the localisations at or above the score threshold; then the
/// RMSE of each frame's top-scoring prediction, the fraction of frames
/// without a prediction, the false localisations per frame without truth,
/// with --probability the reliability diagram and its expected
/// calibration error, and for localisations with `sigma_x,sigma_y` columns
/// how well that uncertainty describes their error. The test set's frames are 0 to the largest frame
/// index of the truth file, or --frames. A truth file without rows (a set
/// of empty frames) needs --frames; its figures per ε are then undefined.
///
/// Frame numbers may be written as whole floats (`3.0`, as pandas writes
/// them) and must be below 10,000,000; empty optional cells are missing
/// values. Localisations none of which is on a frame of the truth file are
/// refused (exit 2) rather than scored 0.
///
/// With --compare, also the paired bootstrap of the difference between the
/// AUC of --locs and that of --compare (another detector's localisations
/// on the same frames): the difference, its standard error and a 95 %
/// interval per ε, from --resamples resamples of the frames drawn with
/// replacement (docs/metric.md, "Comparing two detectors"). With
/// --bootstrap, each AUC's own standard error and 95 % interval from the
/// same resamples: how far a new test set of the same size would move it
/// (docs/metric.md, "The test set's luck").
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("resampling").args(["compare", "bootstrap"]).multiple(true)))]
pub(super) struct ScoreArgs {
    /// Ground truth CSV (needs columns frame,x,y).
    #[arg(long)]
    truth: PathBuf,
    /// Localisations CSV (needs columns frame,x,y and the score column).
    #[arg(long)]
    locs: PathBuf,
    /// The column of --locs that ranks the localisations, e.g. `mass` for
    /// TrackPy's own output.
    #[arg(long, default_value = "score")]
    score_column: String,
    /// Matching radii in pixels, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    eps: Vec<f64>,
    /// The number of frames of the test set (frames 0 to N − 1): frames
    /// with no truth row are empty frames. Default: the largest frame
    /// index of the truth file + 1.
    #[arg(long)]
    frames: Option<u64>,
    /// The score is a probability that the localisation is within 1 px of
    /// a QD (as the CNN's): also print its reliability diagram and expected
    /// calibration error; the default --threshold becomes 0.5.
    #[arg(long)]
    probability: bool,
    /// Localisations with a score at or above this count for recall,
    /// precision, Jaccard index, RMSE of matched localisations and false
    /// localisations per empty frame. Default: 0.5 with --probability,
    /// else every localisation counts.
    #[arg(long, allow_negative_numbers = true)]
    threshold: Option<f64>,
    #[command(flatten)]
    format: super::JsonFlag,
    /// Also write the precision–recall curve points to this CSV
    /// (eps_px,k,score,precision,recall).
    #[arg(long)]
    curve: Option<PathBuf>,
    /// A second localisations CSV of the same test set to compare with:
    /// prints the paired bootstrap of AUC(--locs) − AUC(--compare).
    #[arg(long)]
    compare: Option<PathBuf>,
    /// The column of --compare that ranks its localisations. Default: the
    /// --score-column.
    #[arg(long, requires = "compare")]
    compare_score_column: Option<String>,
    /// Also print each AUC's bootstrap standard error and 95 % interval over
    /// the frames (the test set's luck).
    #[arg(long)]
    bootstrap: bool,
    /// Resamples of the bootstrap (1 to 100,000), for --compare and
    /// --bootstrap.
    #[arg(long, default_value_t = 1000, requires = "resampling")]
    resamples: u64,
    /// Seed of the bootstrap's draws of frames: the same seed and files
    /// give the same figures.
    #[arg(long, default_value_t = 0, requires = "resampling")]
    seed: u64,
}

pub(super) fn run(args: ScoreArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    if let Some(curve) = &args.curve {
        let mut inputs = vec![("--truth", args.truth.as_path()), ("--locs", &args.locs)];
        inputs.extend(
            args.compare
                .as_deref()
                .map(|compare| ("--compare", compare)),
        );
        io::refuse_shared_paths(&inputs, &[("--curve", curve)])?;
    }
    let resamples = paired::check_resamples("--resamples", args.resamples)?;
    metrics::check_radii("--eps", &args.eps)?;
    let truth = csv_tables::read_truth(&args.truth)?;
    let predictions = csv_tables::read_predictions_scored_by(&args.locs, &args.score_column)?;
    // --compare's file and its localisations.
    let compared = match &args.compare {
        Some(path) => Some((
            path,
            csv_tables::read_predictions_scored_by(
                path,
                args.compare_score_column
                    .as_deref()
                    .unwrap_or(&args.score_column),
            )?,
        )),
        None => None,
    };
    let frames = test_set_frames(&args, &truth)?;
    refuse_disjoint_frames(&args.locs, &args.truth, &truth, &predictions)?;
    if let Some((path, compared)) = &compared {
        refuse_disjoint_frames(path, &args.truth, &truth, compared)?;
    }
    let reading = score_reading(&args)?;
    let score = metrics::score_read_as(
        &predictions,
        &truth,
        frames,
        &args.eps,
        args.curve.is_some(),
        reading,
    )
    .map_err(|e| input_error(format!("{}: {e}", args.locs.display())))?;
    let compared = compared
        .as_ref()
        .map(|(path, c)| (path.as_path(), c.as_slice()));
    let (comparison, spread) = resample(&args, &predictions, compared, &truth, frames, resamples)?;
    if let Some(path) = &args.curve {
        write_curve(path, &score)?;
    }
    if args.format.json {
        write_json(stdout, &score, spread.as_deref(), comparison.as_deref())?;
    } else {
        write_table(stdout, &score)?;
        if let Some(spread) = &spread {
            write_spread(stdout, spread, args.seed)?;
        }
        if let (Some(comparison), Some((path, _))) = (&comparison, compared) {
            write_comparison(stdout, comparison, &args.locs, path, args.seed)?;
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The number of frames of the test set: --frames, checked against the
/// truth, else the largest frame index of the truth + 1.
fn test_set_frames(args: &ScoreArgs, truth: &[crate::types::TruthRow]) -> anyhow::Result<usize> {
    // Frame numbers are below MAX_FRAMES (checked by the readers), so this
    // cannot overflow.
    let frames_with_truth = truth.iter().map(|t| t.frame + 1).max().unwrap_or(0);
    let frames = match args.frames {
        Some(frames) => {
            let frames = check_frame_count("--frames", frames)?;
            if frames < frames_with_truth {
                return Err(input_error(format!(
                    "--frames: {frames}, but {} has truth on frame {}",
                    args.truth.display(),
                    frames_with_truth - 1
                )));
            }
            frames
        }
        None if truth.is_empty() => {
            return Err(input_error(format!(
                "{}: no ground truth rows; give --frames N to score a test set of N empty frames",
                args.truth.display()
            )));
        }
        None => frames_with_truth,
    };
    Ok(frames)
}

/// How the scores are read: the --threshold (checked), or 0.5 with
/// --probability.
fn score_reading(args: &ScoreArgs) -> anyhow::Result<ScoreReading> {
    if let Some(threshold) = args.threshold
        && !threshold.is_finite()
    {
        return Err(input_error(format!(
            "--threshold: must be a finite score, got {threshold}"
        )));
    }
    Ok(ScoreReading {
        threshold: args.threshold.or(args
            .probability
            .then_some(ScoreReading::PROBABILITY_THRESHOLD)),
        probability: args.probability,
    })
}

/// The paired differences of --compare and the spread of --bootstrap,
/// each where asked for.
type Resampled = (Option<Vec<PairedDifference>>, Option<Vec<AucSpread>>);

/// With --compare, one bootstrap gives the paired difference and, for
/// --bootstrap, the spread of --locs' own AUC (the same resamples).
fn resample(
    args: &ScoreArgs,
    predictions: &[crate::types::Prediction],
    compared: Option<(&std::path::Path, &[crate::types::Prediction])>,
    truth: &[crate::types::TruthRow],
    frames: usize,
    resamples: usize,
) -> anyhow::Result<Resampled> {
    Ok(match compared {
        Some((path, compared)) => {
            let (comparison, spread) = paired::paired_bootstrap_with_spread(
                predictions,
                compared,
                truth,
                frames,
                &args.eps,
                resamples,
                args.seed,
            )
            .map_err(|e| input_error(format!("{}: {e}", path.display())))?;
            (Some(comparison), args.bootstrap.then_some(spread))
        }
        None if args.bootstrap => {
            let spread =
                paired::bootstrap_auc(predictions, truth, frames, &args.eps, resamples, args.seed)
                    .map_err(|e| input_error(format!("{}: {e}", args.locs.display())))?;
            (None, Some(spread))
        }
        None => (None, None),
    })
}

/// The precision–recall curve points as CSV (eps_px,k,score,precision,recall).
fn write_curve(path: &std::path::Path, score: &Score) -> anyhow::Result<()> {
    let rows = score.per_eps.iter().flat_map(|per_eps| {
        per_eps.curve.iter().map(|point| {
            vec![
                per_eps.eps_px.to_string(),
                point.k.to_string(),
                point.score.to_string(),
                point.precision.to_string(),
                point.recall.to_string(),
            ]
        })
    });
    csv_tables::write_table(path, &["eps_px", "k", "score", "precision", "recall"], rows)
}

/// `score` as one JSON object on one line, without the curve points, with
/// the bootstrap's `spread` and `comparison` where they were computed.
fn write_json(
    stdout: &mut dyn Write,
    score: &Score,
    spread: Option<&[AucSpread]>,
    comparison: Option<&[PairedDifference]>,
) -> anyhow::Result<()> {
    let mut summary = score.clone();
    for per_eps in &mut summary.per_eps {
        per_eps.curve.clear();
    }
    let mut json = serde_json::to_value(&summary)?;
    if let Some(object) = json.as_object_mut() {
        if let Some(spread) = spread {
            object.insert("spread".into(), serde_json::to_value(spread)?);
        }
        if let Some(comparison) = comparison {
            object.insert("comparison".into(), serde_json::to_value(comparison)?);
        }
    }
    serde_json::to_writer(&mut *stdout, &json)?;
    writeln!(stdout)?;
    Ok(())
}

/// Refuses localisations none of which is on a frame with ground truth:
/// frame numbers counted from 1 in one file and from 0 in the other, or
/// the files of two different recordings, would otherwise score an AUC of
/// 0 without a word.
fn refuse_disjoint_frames(
    locs: &std::path::Path,
    truth_path: &std::path::Path,
    truth: &[crate::types::TruthRow],
    predictions: &[crate::types::Prediction],
) -> anyhow::Result<()> {
    // Without truth (a set of empty frames, --frames given) every frame
    // is a frame of the set.
    if predictions.is_empty() || truth.is_empty() {
        return Ok(());
    }
    let truth_frames: std::collections::HashSet<usize> = truth.iter().map(|t| t.frame).collect();
    if predictions.iter().any(|p| truth_frames.contains(&p.frame)) {
        return Ok(());
    }
    let range = |frames: &mut dyn Iterator<Item = usize>| {
        let (low, high) = frames.fold((usize::MAX, 0), |(lo, hi), f| (lo.min(f), hi.max(f)));
        format!("{low}–{high}")
    };
    Err(input_error(format!(
        "{}: no localisation is on a frame of {} (localisations on frames {}, truth on frames {}); are both from the same recording, numbered from the same first frame?",
        locs.display(),
        truth_path.display(),
        range(&mut predictions.iter().map(|p| p.frame)),
        range(&mut truth.iter().map(|t| t.frame)),
    )))
}

/// A value with 4 decimals, or `n/a`.
fn maybe(value: Option<f64>) -> String {
    value.map_or("n/a".to_string(), |v| format!("{v:.4}"))
}

/// The human-readable form of `score` (docs/metric.md names each figure).
fn write_table(out: &mut dyn Write, score: &Score) -> anyhow::Result<()> {
    writeln!(
        out,
        "{:>8} {:>8} {:>9} {:>6} {:>6} {:>8} {:>8} {:>8} {:>10}",
        "eps_px", "AUC", "AUC_best", "TP", "FP", "oracle", "random", "share", "top_within"
    )?;
    if score.per_eps.is_empty() {
        writeln!(
            out,
            "(no ground truth: AUC, recall and precision are undefined)"
        )?;
    }
    for per_eps in &score.per_eps {
        let headroom = per_eps.headroom.as_ref();
        writeln!(
            out,
            "{:>8} {:>8.4} {:>9} {:>6} {:>6} {:>8} {:>8} {:>8} {:>10}",
            per_eps.eps_px,
            per_eps.auc,
            maybe(per_eps.auc_best_per_frame),
            per_eps.true_positives,
            per_eps.false_positives,
            maybe(headroom.map(|h| h.oracle_auc)),
            maybe(headroom.map(|h| h.random_auc)),
            maybe(headroom.and_then(|h| {
                h.share_used_by_best_guesses(per_eps.auc, per_eps.auc_best_per_frame)
            })),
            maybe(headroom.and_then(|h| h.fraction_top_within_eps)),
        )?;
    }
    match score.rmse_top_px {
        Some(rmse) => writeln!(out, "RMSE of top prediction: {rmse:.4} px")?,
        None => writeln!(
            out,
            "RMSE of top prediction: n/a (no frame has a prediction)"
        )?,
    }
    writeln!(
        out,
        "frames without prediction: {} of {} ({:.4})",
        score.frames_without_prediction, score.frames, score.fraction_without_prediction
    )?;
    write_threshold_rows(out, score)?;
    if let Some(empty) = &score.empty_frames {
        writeln!(
            out,
            "empty frames (no truth): {} of {}; localisations on them: {} ({} per empty frame)",
            empty.frames,
            score.frames,
            empty.localisations,
            maybe(empty.false_localisations_per_frame)
        )?;
    }
    write_calibration(out, score)
}

/// The figures of the localisations at or above the score threshold, per ε.
fn write_threshold_rows(out: &mut dyn Write, score: &Score) -> anyhow::Result<()> {
    let threshold = score.reading.and_then(|r| r.threshold);
    match threshold {
        Some(t) => writeln!(out, "localisations with score >= {t}:")?,
        None => writeln!(out, "every localisation (no score threshold):")?,
    }
    writeln!(
        out,
        "{:>8} {:>6} {:>6} {:>6} {:>8} {:>9} {:>8} {:>12}",
        "eps_px", "TP", "FP", "FN", "recall", "precision", "Jaccard", "RMSE_px"
    )?;
    for per_eps in &score.per_eps {
        if let Some(at) = &per_eps.at_threshold {
            writeln!(
                out,
                "{:>8} {:>6} {:>6} {:>6} {:>8.4} {:>9} {:>8.4} {:>12}",
                per_eps.eps_px,
                at.true_positives,
                at.false_positives,
                at.false_negatives,
                at.recall,
                maybe(at.precision),
                at.jaccard,
                maybe(at.rmse_matched_px),
            )?;
        }
    }
    Ok(())
}

/// A reliability diagram's bins, one line each, under a header line.
fn write_bins(
    out: &mut dyn Write,
    reliability: &crate::metrics::calibration::Reliability,
) -> anyhow::Result<()> {
    writeln!(
        out,
        "{:>12} {:>8} {:>10} {:>9}",
        "score_bin", "count", "mean_score", "observed"
    )?;
    for bin in &reliability.bins {
        writeln!(
            out,
            "{:>12} {:>8} {:>10} {:>9}",
            format!("[{:.1}, {:.1})", bin.lower, bin.upper),
            bin.count,
            maybe(bin.mean_score),
            maybe(bin.observed_frequency)
        )?;
    }
    Ok(())
}

/// The reliability diagram of probability scores and the calibration of
/// the localisations' own σ, where the localisations have them.
fn write_calibration(out: &mut dyn Write, score: &Score) -> anyhow::Result<()> {
    if let Some(reliability) = &score.reliability {
        writeln!(
            out,
            "reliability (observed frequency within {} px), {} localisations; expected calibration error {}",
            reliability.radius_px,
            reliability.localisations,
            maybe(reliability.expected_calibration_error)
        )?;
        write_bins(out, reliability)?;
    }
    for by_rank in &score.reliability_by_rank {
        let reliability = &by_rank.reliability;
        writeln!(
            out,
            "reliability of rank {} (observed frequency of a QD within {} px that no higher guess is within), {} guesses; expected calibration error {}",
            by_rank.rank,
            reliability.radius_px,
            reliability.localisations,
            maybe(reliability.expected_calibration_error)
        )?;
        write_bins(out, reliability)?;
    }
    if let Some(u) = &score.uncertainty {
        writeln!(
            out,
            "uncertainty (sigma_x, sigma_y of each frame's top prediction), {} localisations: \
             RMS of error/sigma x {:.3}, y {:.3} (1 if calibrated); within 1 sigma {:.3} \
             (0.683 if Gaussian); rank correlation of sigma with the error {}",
            u.localisations,
            u.rms_normalised_error_x,
            u.rms_normalised_error_y,
            u.within_one_sigma,
            maybe(u.rank_correlation)
        )?;
    }
    Ok(())
}

/// Each AUC's bootstrap under the table: per ε, the AUC, its standard
/// error and 95 % interval.
fn write_spread(out: &mut dyn Write, spread: &[AucSpread], seed: u64) -> anyhow::Result<()> {
    let resamples = spread.first().map_or(0, |s| s.resamples);
    writeln!(
        out,
        "bootstrap of the AUC: frames resampled with replacement ({resamples} resamples, seed {seed})"
    )?;
    writeln!(
        out,
        "{:>8} {:>8} {:>9} {:>19}",
        "eps_px", "AUC", "std_err", "95% interval"
    )?;
    for s in spread {
        writeln!(
            out,
            "{:>8} {:>8.4} {:>9.4} {:>19}",
            s.eps_px,
            s.auc,
            s.standard_error,
            format!("[{:.4}, {:.4}]", s.interval_95.0, s.interval_95.1),
        )?;
    }
    Ok(())
}

/// The paired comparison under the table: per ε, both AUCs, their
/// difference, its bootstrap standard error and 95 % interval.
fn write_comparison(
    out: &mut dyn Write,
    comparison: &[PairedDifference],
    locs: &std::path::Path,
    compared: &std::path::Path,
    seed: u64,
) -> anyhow::Result<()> {
    let resamples = comparison.first().map_or(0, |c| c.resamples);
    writeln!(
        out,
        "paired comparison: AUC of {} minus AUC of {}, frames resampled with replacement ({resamples} resamples, seed {seed})",
        locs.display(),
        compared.display()
    )?;
    writeln!(
        out,
        "{:>8} {:>8} {:>11} {:>10} {:>9} {:>19}",
        "eps_px", "AUC", "AUC_compare", "difference", "std_err", "95% interval"
    )?;
    for c in comparison {
        writeln!(
            out,
            "{:>8} {:>8.4} {:>11.4} {:>+10.4} {:>9.4} {:>19}",
            c.eps_px,
            c.auc,
            c.auc_compared,
            c.difference,
            c.standard_error,
            format!("[{:+.4}, {:+.4}]", c.interval_95.0, c.interval_95.1),
        )?;
    }
    Ok(())
}
