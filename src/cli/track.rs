//! `scanloc track`: a recording in, trajectories and D out
//! (docs/recording.md).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::error::input_error;
use crate::run::track_recording::outputs::FILES;
use crate::run::track_recording::{
    OnStderr, TrackMethod, TrackOptions, TrackResult, check_stated, read_recording,
    track_named_recording,
};
use crate::track::pipeline::StoredEstimate;
use clap::Args;

use super::microscope::MicroscopeArgs;

/// Localise, link and read D from a recording in one command: the
/// localiser's threshold, the linker's search range and the ensemble's box
/// are chosen for the microscope by simulation of it (each can be given),
/// the tracks relinked with their own D, and the ensemble D corrected for
/// the pipeline's bias by simulation (docs/recording.md).
///
/// Writes DIR/tracks.csv (frame,x,y,…,particle: TrackPy's columns),
/// DIR/diffusion.csv (as `scanloc diffusion` writes it: one ml row per
/// track, the ensemble and, with the correction, ensemble-corrected) and
/// DIR/settings.json (every setting used), and prints a summary.
#[derive(Debug, Args)]
pub(super) struct TrackArgs {
    /// The recording: FILE.npy ((n, H, W) photon counts) or a multi-page
    /// TIFF of counts.
    recording: PathBuf,
    /// The folder to write into (created; it must not hold the recording).
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    microscope: MicroscopeArgs,
    /// The localiser.
    #[arg(long, value_enum, default_value = "crocker-grier")]
    method: MethodArg,
    /// The crocker-grier diameter, px (odd; default: the smallest odd
    /// number ≥ 2 σxy/pixel + 1).
    #[arg(long)]
    diameter: Option<usize>,
    /// Link only localisations scoring at least this (crocker-grier: the
    /// mass); default: the F1-best on a recording of this microscope
    /// simulated at the pilot D.
    #[arg(long)]
    min_score: Option<f64>,
    /// The first linking pass's search range, px (3 σ of a step; default:
    /// from --max-diffusion and the frame period, at most half the field).
    #[arg(long)]
    search_range: Option<f64>,
    /// The longest gap the linker closes, frames (default 2).
    #[arg(long)]
    max_gap: Option<usize>,
    /// The ML ensemble takes its steps this far inside the field's edges,
    /// px (default: σxy in pixels, rounded).
    #[arg(long)]
    ensemble_margin_px: Option<f64>,
    /// The largest D, µm²/s, the first linking pass must follow.
    #[arg(long, default_value_t = 3.0)]
    max_diffusion: f64,
    /// Tracks with fewer localisations get no D of their own.
    #[arg(long, default_value_t = 3)]
    min_points: usize,
    /// Report the ensemble D as read, without the bias correction by
    /// simulation.
    #[arg(long)]
    no_bias_correction: bool,
    /// Recordings as long as this one the bias correction simulates.
    #[arg(long, default_value_t = 2)]
    bias_recordings: usize,
    /// Time between a frame's last line and the next frame's first, ms.
    #[arg(long, default_value_t = 0.0)]
    dead_time_ms: f64,
    /// The seed every simulation derives from.
    #[arg(long, default_value_t = 20261207)]
    seed: u64,
    /// Print the summary as JSON (the ensemble's d_um2_s, standard_error,
    /// low_95, high_95, and the settings).
    #[arg(long)]
    json: bool,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum MethodArg {
    /// TrackPy's locate (score: the mass).
    CrockerGrier,
}

pub(super) fn run(args: TrackArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let microscope = args.microscope.resolve()?;
    check_stated(&microscope.stated)?;
    let microscope = microscope.params;
    let options = TrackOptions {
        method: match args.method {
            MethodArg::CrockerGrier => TrackMethod::CrockerGrier,
        },
        diameter_px: args.diameter,
        min_score: args.min_score,
        search_range_px: args.search_range,
        max_gap: args.max_gap,
        ensemble_margin_px: args.ensemble_margin_px,
        max_diffusion_um2_s: args.max_diffusion,
        min_points: args.min_points,
        bias_correction: !args.no_bias_correction,
        bias_recordings: args.bias_recordings,
        dead_time_ms: args.dead_time_ms,
        seed: args.seed,
        ..TrackOptions::default()
    };
    options.check(&microscope)?;
    let frames = read_recording(&args.recording)?;
    check_out(&args.out, &args.recording)?;
    let result = track_named_recording(
        &args.recording.display().to_string(),
        &frames,
        &microscope,
        &options,
        &OnStderr,
    )?;
    write_outputs(&args.out, &result)?;
    if args.json {
        writeln!(
            stdout,
            "{}",
            serde_json::to_string_pretty(&result.summary_json())?
        )?;
    } else {
        write_summary(stdout, &result, &args.out)?;
    }
    Ok(ExitCode::SUCCESS)
}

/// Refuses an output folder that holds (or is) the recording.
fn check_out(out: &Path, recording: &Path) -> anyhow::Result<()> {
    let recording = std::fs::canonicalize(recording)
        .map_err(|e| input_error(format!("{}: {e}", recording.display())))?;
    let absolute = if out.is_absolute() {
        out.to_path_buf()
    } else {
        std::env::current_dir()?.join(out)
    };
    let resolved = std::fs::canonicalize(&absolute).unwrap_or(absolute);
    if recording.starts_with(&resolved) {
        return Err(input_error(format!(
            "--out {}: the folder holds the recording {}; write the results elsewhere",
            out.display(),
            recording.display()
        )));
    }
    if resolved.exists() && !resolved.is_dir() {
        return Err(input_error(format!(
            "--out {}: exists and is not a folder",
            out.display()
        )));
    }
    Ok(())
}

fn write_outputs(out: &Path, result: &TrackResult) -> anyhow::Result<()> {
    std::fs::create_dir_all(out)
        .map_err(|e| input_error(format!("--out {}: {e}", out.display())))?;
    for (name, contents) in result.files()? {
        std::fs::write(out.join(name), contents)?;
    }
    Ok(())
}

fn write_summary(out: &mut dyn Write, result: &TrackResult, dir: &Path) -> anyhow::Result<()> {
    let s = &result.settings;
    writeln!(
        out,
        "{} frames: {} localisations, {} linked (score ≥ {:.4}{}), {} tracks ({} with a D of their own)",
        result.frames,
        result.localisations.len(),
        result.linked,
        s.min_score,
        match (s.calibration_f1, s.calibration_d_um2_s) {
            (Some(f1), Some(d)) =>
                format!(": the F1-best, {f1:.2}, on this microscope simulated at D = {d:.3} µm²/s"),
            _ => ", given".to_string(),
        },
        result.tracks.len(),
        result.per_track.len(),
    )?;
    let interval = |e: &StoredEstimate| {
        format!(
            "D = {:.4} µm²/s ± {:.4} (95 %: {:.4} to {}), {} steps",
            e.d,
            e.standard_error,
            e.low,
            e.high.map_or("∞".to_string(), |h| format!("{h:.4}")),
            e.steps
        )
    };
    match (&result.ensemble, &result.corrected) {
        (Some(raw), Some(corrected)) => {
            writeln!(
                out,
                "ensemble (bias-corrected): {}",
                interval(&corrected.estimate)
            )?;
            writeln!(
                out,
                "  as read: D = {:.4}; the pipeline read {:.4} on {} simulated frames at D = {:.4}",
                raw.d, corrected.simulated.d, corrected.simulated_frames, raw.d
            )?;
        }
        (Some(raw), None) => {
            writeln!(out, "ensemble (not bias-corrected): {}", interval(raw))?;
        }
        (None, _) => {}
    }
    for warning in result.warnings() {
        writeln!(out, "warning: {warning}")?;
    }
    writeln!(out, "wrote {} ({})", dir.display(), FILES.join(", "))?;
    Ok(())
}
