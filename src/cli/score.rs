//! `scanloc score`: the paper's precision–recall AUC of a localisation file.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use scanloc::error::input_error;
use scanloc::io::{self, csv_tables};
use scanloc::metrics;

/// Score localisations against ground truth (docs/metric.md).
///
/// Prints the AUC of the precision–recall curve for each matching radius ε,
/// the RMSE of each frame's top-scoring prediction, and the fraction of
/// frames without a prediction. The test set's frames are those named in the
/// truth file (0 to the largest frame index).
///
/// Frame numbers may be written as whole floats (`3.0`, as pandas writes
/// them) and must be below 10,000,000; empty optional cells are missing
/// values. Localisations none of which is on a frame of the truth file are
/// refused (exit 2) rather than scored 0.
#[derive(Debug, Args)]
pub struct ScoreArgs {
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
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
    /// Also write the precision–recall curve points to this CSV
    /// (eps_px,k,score,precision,recall).
    #[arg(long)]
    curve: Option<PathBuf>,
}

pub fn run(args: ScoreArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    if let Some(curve) = &args.curve {
        io::refuse_shared_paths(
            &[("--truth", &args.truth), ("--locs", &args.locs)],
            &[("--curve", curve)],
        )?;
    }
    let truth = csv_tables::read_truth(&args.truth)?;
    let predictions = csv_tables::read_predictions_scored_by(&args.locs, &args.score_column)?;
    // Frame numbers are below MAX_FRAMES (checked by the readers), so this
    // cannot overflow.
    let frames = truth.iter().map(|t| t.frame + 1).max().unwrap_or(0);
    refuse_disjoint_frames(&args, &truth, &predictions)?;
    let score = metrics::score(
        &predictions,
        &truth,
        frames,
        &args.eps,
        args.curve.is_some(),
    )
    .map_err(|e| input_error(format!("{}: {e}", args.locs.display())))?;
    if let Some(path) = &args.curve {
        io::write_atomically(path, |writer| {
            let mut csv = csv::Writer::from_writer(writer);
            csv.write_record(["eps_px", "k", "score", "precision", "recall"])?;
            for per_eps in &score.per_eps {
                for point in &per_eps.curve {
                    csv.write_record([
                        per_eps.eps_px.to_string(),
                        point.k.to_string(),
                        point.score.to_string(),
                        point.precision.to_string(),
                        point.recall.to_string(),
                    ])?;
                }
            }
            csv.flush()?;
            Ok(())
        })?;
    }
    if args.json {
        let mut summary = score.clone();
        for per_eps in &mut summary.per_eps {
            per_eps.curve.clear();
        }
        serde_json::to_writer(&mut *stdout, &summary)?;
        writeln!(stdout)?;
    } else {
        writeln!(
            stdout,
            "{:>8} {:>8} {:>6} {:>6}",
            "eps_px", "AUC", "TP", "FP"
        )?;
        for per_eps in &score.per_eps {
            writeln!(
                stdout,
                "{:>8} {:>8.4} {:>6} {:>6}",
                per_eps.eps_px, per_eps.auc, per_eps.true_positives, per_eps.false_positives
            )?;
        }
        match score.rmse_top_px {
            Some(rmse) => writeln!(stdout, "RMSE of top prediction: {rmse:.4} px")?,
            None => writeln!(
                stdout,
                "RMSE of top prediction: n/a (no frame has a prediction)"
            )?,
        }
        writeln!(
            stdout,
            "frames without prediction: {} of {} ({:.4})",
            score.frames_without_prediction, score.frames, score.fraction_without_prediction
        )?;
    }
    Ok(ExitCode::SUCCESS)
}

/// Refuses localisations none of which is on a frame with ground truth:
/// frame numbers counted from 1 in one file and from 0 in the other, or
/// the files of two different recordings, would otherwise score an AUC of
/// 0 without a word.
fn refuse_disjoint_frames(
    args: &ScoreArgs,
    truth: &[scanloc::types::TruthRow],
    predictions: &[scanloc::types::Prediction],
) -> anyhow::Result<()> {
    if predictions.is_empty() {
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
        args.locs.display(),
        args.truth.display(),
        range(&mut predictions.iter().map(|p| p.frame)),
        range(&mut truth.iter().map(|t| t.frame)),
    )))
}
