//! `scanloc score-tracks`: trajectories against a recording's ground truth
//! (docs/tracking.md#tracking-metrics).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::io::tracks;
use crate::metrics::tracking::{self, TrackingScore, TruthPosition, TruthSelection};
use clap::{Args, ValueEnum};

/// Which position of the truth the tracks should follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum TruthPositionArg {
    /// The trajectory centroid over the whole frame (columns x, y).
    Centroid,
    /// What the beam saw (columns x_seen, y_seen): for large fields.
    Seen,
}

/// Score trajectories against a recording's ground truth with the particle
/// tracking challenge's measures (Chenouard et al. 2014) and link
/// precision and recall (docs/tracking.md#tracking-metrics).
///
/// Truth tracks are the truth file's rows grouped by QD id. Each truth
/// track is paired with at most one estimated track so that the summed
/// distance, point by point with each distance capped at the gate ε (a
/// missing point counts ε), is least. Prints α (1 = perfect), β (α
/// penalised by spurious tracks), the Jaccard indices of detections and of
/// tracks, and link precision and recall, with their counts; --json prints
/// them as one JSON object instead.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct ScoreTracksArgs {
    /// Tracks CSV (frame,x,y,particle in px; other columns ignored), as
    /// `scanloc link` writes it.
    #[arg(long)]
    tracks: PathBuf,
    /// Recording truth CSV, as `scanloc simulate-recording --truth` writes it.
    #[arg(long)]
    truth: PathBuf,
    /// The gate ε, px: points of one frame closer than this match, and a
    /// distance counts at most this much.
    #[arg(long, default_value_t = tracking::DEFAULT_GATE_PX, allow_hyphen_values = true)]
    gate_px: f64,
    /// Which truth position the tracks should follow.
    #[arg(long, value_enum, default_value_t = TruthPositionArg::Centroid)]
    truth_position: TruthPositionArg,
    /// Only truth rows with a mean depth |z_mean| at most this, µm (QDs far
    /// out of focus that no detector can see are left out).
    #[arg(long, allow_hyphen_values = true)]
    max_depth_um: Option<f64>,
    /// Only truth rows of QDs on for at least this share of the frame
    /// (with blinking).
    #[arg(long, allow_hyphen_values = true)]
    min_on_fraction: Option<f64>,
    /// Split a QD's truth track where it is missing (out of the field, or
    /// left out by --max-depth-um or --min-on-fraction) for more than this
    /// many frames: a linker cannot be asked to bridge a QD's absence of
    /// any length [default: no split].
    #[arg(long, value_parser = super::whole_number::<usize>)]
    split_gaps_over: Option<usize>,
    #[command(flatten)]
    format: super::JsonFlag,
}

pub(super) fn run(args: ScoreTracksArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let gate = crate::limits::check_positive_at_most(
        "--gate-px",
        args.gate_px,
        crate::limits::MAX_EPS_PX,
    )?;
    if let Some(depth) = args.max_depth_um
        && !(depth.is_finite() && depth >= 0.0)
    {
        return Err(input_error(format!(
            "--max-depth-um: must be a finite number ≥ 0, got {}",
            crate::error::readable(depth)
        )));
    }
    if let Some(share) = args.min_on_fraction
        && !(0.0..=1.0).contains(&share)
    {
        return Err(input_error(format!(
            "--min-on-fraction: must be a number from 0 to 1, got {}",
            crate::error::readable(share)
        )));
    }
    let selection = TruthSelection {
        position: match args.truth_position {
            TruthPositionArg::Centroid => TruthPosition::Centroid,
            TruthPositionArg::Seen => TruthPosition::Seen,
        },
        max_depth_um: args.max_depth_um,
        min_on_fraction: args.min_on_fraction,
        split_gaps_over: args.split_gaps_over,
    };
    let rows = tracks::read_recording_truth(&args.truth)?;
    let truth = tracking::truth_tracks(&rows, &selection);
    if truth.is_empty() {
        return Err(input_error(format!(
            "{}: no truth rows{} to score against",
            args.truth.display(),
            if rows.is_empty() {
                ""
            } else {
                " left by --max-depth-um and --min-on-fraction"
            }
        )));
    }
    let estimated = tracks::read_tracks(&args.tracks)?;
    let score = tracking::score_tracks(&truth, &estimated, gate)?;
    if args.format.json {
        writeln!(stdout, "{}", serde_json::to_string(&score)?)?;
    } else {
        print_table(&score, stdout)?;
    }
    Ok(ExitCode::SUCCESS)
}

fn print_table(s: &TrackingScore, out: &mut dyn Write) -> std::io::Result<()> {
    let value = |v: Option<f64>| v.map_or_else(|| "—".to_string(), |v| format!("{v:.4}"));
    writeln!(
        out,
        "{} truth tracks ({} points), {} estimated tracks ({} points); gate ε = {} px",
        s.truth_tracks, s.truth_points, s.estimated_tracks, s.estimated_points, s.gate_px
    )?;
    writeln!(out, "measure             value   counts")?;
    let rows = [
        (
            "alpha",
            s.alpha,
            format!(
                "d(X,Y) = {:.2} px of d(X,∅) = {:.2} px",
                s.distance_px, s.distance_to_nothing_px
            ),
        ),
        (
            "beta",
            s.beta,
            format!("{} points in spurious tracks", s.spurious_track_points),
        ),
        (
            "jaccard_detections",
            s.jaccard_detections,
            format!(
                "TP {}, FN {}, FP {}",
                s.matched_points, s.missed_points, s.false_points
            ),
        ),
        (
            "jaccard_tracks",
            s.jaccard_tracks,
            format!(
                "paired {}, missed {}, spurious {}",
                s.paired_tracks, s.missed_tracks, s.spurious_tracks
            ),
        ),
        (
            "link_precision",
            s.link_precision,
            format!("{} true of {} links", s.true_links, s.estimated_links),
        ),
        (
            "link_recall",
            s.link_recall,
            format!(
                "{} recovered of {} truth links",
                s.recovered_links, s.truth_links
            ),
        ),
    ];
    for (name, v, counts) in rows {
        writeln!(out, "{name:<19} {:<7} {counts}", value(v))?;
    }
    Ok(())
}
