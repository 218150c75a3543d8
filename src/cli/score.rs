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
#[derive(Debug, Args)]
pub struct ScoreArgs {
    /// Ground truth CSV (needs columns frame,x,y).
    #[arg(long)]
    truth: PathBuf,
    /// Localisations CSV (needs columns frame,x,y,score).
    #[arg(long)]
    locs: PathBuf,
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

pub fn run(args: ScoreArgs) -> anyhow::Result<ExitCode> {
    let truth = csv_tables::read_truth(&args.truth)?;
    let predictions = csv_tables::read_predictions(&args.locs)?;
    let frames = truth.iter().map(|t| t.frame + 1).max().unwrap_or(0);
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
    let mut stdout = std::io::stdout().lock();
    if args.json {
        let mut summary = score.clone();
        for per_eps in &mut summary.per_eps {
            per_eps.curve.clear();
        }
        serde_json::to_writer(&mut stdout, &summary)?;
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
