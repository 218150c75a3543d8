//! `scanloc diffusion`: D per track and for the ensemble from a tracks
//! table (docs/tracking.md).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::readable;
use crate::track::diffusion::tables::{TableSettings, estimate_table};
use crate::track::diffusion::{ENSEMBLE_GATE, Estimate, Exposure, Method};
use clap::{Args, ValueEnum};

/// Which part of the scan a localisation averages (docs/tracking.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ExposureArg {
    /// whole-frame for a field at most 10 σxy tall, else rows.
    Auto,
    /// The trajectory centroid over the whole frame (the simulator's truth).
    WholeFrame,
    /// What the beam saw: the rows within the PSF of the particle.
    Rows,
    /// The frame index alone, no blur (for comparison).
    FrameIndex,
    /// The frame index with a camera's uniform exposure, R = 1/6 (for comparison).
    UniformFrame,
}

/// Estimate diffusion coefficients from trajectories: per track and for
/// the ensemble, by the covariance-based estimator (cve), an MSD fit with
/// the optimal number of points (msd) and maximum likelihood (ml), each
/// with its standard error, 95 % interval and localisation variance.
///
/// Time stamps and motion blur come from the scan (the flags below, in the
/// units of the manifest's microscope section), or the table's `time`
/// column (s) where present. The localisation variance is estimated with
/// D (the table's sigma_x, sigma_y only with --given-sigma): ml estimates
/// each track with the ensemble's; with 1,000
/// localisations or more, ml conditions on where the localiser finds
/// particles, read off their density near the field's edges, and the ml
/// ensemble takes each track given its first step, which leans inwards
/// where a blurred track entered the field (docs/tracking.md, "The field
/// selects the steps"). Where the tracks'
/// ml estimates scatter more than their likelihood says (wrong links,
/// heavy-tailed errors), each track's interval is widened by that
/// dispersion, measured over 20 tracks or more and named on stderr.
/// Output: CSV on stdout, one row per track and method, then the ensemble
/// rows (particle `ensemble`).
///
/// Tracks that cannot come from the stated scan are refused (exit code 2,
/// nothing written): a localisation further outside the field (--height,
/// --width) than the PSF reaches (3 σxy), or a `time` step that differs
/// from its frames' distance on the frame clock by more than a frame
/// period. An estimate that is not a finite number is refused too.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct DiffusionArgs {
    /// Tracks CSV: frame,x,y,particle (px), optional sigma_x,sigma_y (px) and time (s: in every row
    /// of a track or in none, each step longer than its two localisations' blur).
    #[arg(long)]
    tracks: PathBuf,
    /// The scan the localisations come from.
    #[command(flatten)]
    scan: super::ScanGeometryArgs,
    /// Which part of the scan a localisation averages.
    #[arg(long, value_enum, default_value_t = ExposureArg::Auto)]
    exposure: ExposureArg,
    /// Tracks with fewer localisations get no row of their own (they still
    /// count in the ensemble).
    #[arg(long, default_value_t = 3, value_parser = super::whole_number::<usize>)]
    min_points: usize,
    /// Condition ml on the field alone, not on where the localiser finds
    /// particles: for samples whose particles are not spread uniformly
    /// over the field (the detection profile reads their density as the
    /// localiser's efficiency).
    #[arg(long)]
    no_detection_profile: bool,
    /// The share of each link's gate (the table's gate_x, gate_y, as `scanloc
    /// link --linker lap` writes them) within which the ml ensemble takes
    /// its steps, conditioned on it: steps between two particles a linker
    /// joined where they are dense fall outside far more often than the
    /// particle's own (docs/tracking.md, "Wrong links"). At most 0.707 (the
    /// box inside the elliptic gate), or 1 for every step. Tables without
    /// gates are used whole.
    #[arg(long, default_value_t = ENSEMBLE_GATE, allow_hyphen_values = true)]
    ensemble_gate: f64,
    /// The ml ensemble takes its steps within the box this many pixels
    /// inside the field's edges, each run of localisations inside it a
    /// series conditioned on the box: for a localiser whose chance of
    /// finding a particle near an edge depends on how it moved, at the
    /// cost of the steps near the edges (docs/tracking.md, "Near the
    /// field's edges": 2 for the recordings' CNN). 0: the whole field;
    /// less than half the field's shorter side.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    ensemble_margin_px: f64,
    /// Take the table's sigma_x, sigma_y as each localisation's known
    /// standard error (ml then reads D through the blur), for a localiser
    /// whose σ is calibrated against the truth. Without it σ² is estimated
    /// with D, as `scanloc run` does: the CNN and other localisers that
    /// report a posterior mean err with their estimate, not with their σ
    /// (docs/tracking.md, "The estimators").
    #[arg(long)]
    given_sigma: bool,
}

fn row(
    out: &mut dyn Write,
    label: &str,
    points: usize,
    method: Method,
    e: &Estimate,
) -> std::io::Result<()> {
    writeln!(
        out,
        "{label},{points},{},{},{},{},{},{},{}",
        method.name(),
        readable(e.d),
        readable(e.standard_error),
        readable(e.low),
        readable(e.high),
        readable(e.localisation_variance),
        e.interval_valid
    )
}

pub(super) fn run(
    args: DiffusionArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let geometry = args.scan.geometry()?;
    let exposure = match args.exposure {
        ExposureArg::Auto => geometry.auto_exposure(),
        ExposureArg::WholeFrame => Exposure::WholeFrame,
        ExposureArg::Rows => Exposure::Rows,
        ExposureArg::FrameIndex => Exposure::FrameIndex,
        ExposureArg::UniformFrame => Exposure::UniformFrame,
    };
    let settings = TableSettings {
        exposure,
        min_points: args.min_points,
        detection_profile: !args.no_detection_profile,
        ensemble_gate: args.ensemble_gate,
        ensemble_margin_px: args.ensemble_margin_px,
        given_sigma: args.given_sigma,
    };
    settings.check(&geometry)?;
    let tracks = crate::io::tracks::read_tracks(&args.tracks)?;
    let table = estimate_table(
        tracks,
        &geometry,
        &settings,
        &args.tracks.display().to_string(),
    )?;
    writeln!(
        stdout,
        "particle,points,method,d_um2_s,standard_error,low_95,high_95,localisation_variance_um2,interval_valid"
    )?;
    // One row per track and method, tracks in table order.
    for (index, track) in table.tracks.iter().enumerate() {
        for (method, e) in &table.estimates {
            if let Some(estimate) = &e.per_track[index] {
                row(
                    stdout,
                    &track.particle.to_string(),
                    table.points[index],
                    *method,
                    estimate,
                )?;
            }
        }
    }
    for note in &table.notes {
        writeln!(stderr, "{note}")?;
    }
    for (method, e) in &table.estimates {
        if let Some(estimate) = &e.ensemble {
            row(stdout, "ensemble", table.ensemble_points, *method, estimate)?;
        }
    }
    Ok(ExitCode::SUCCESS)
}
