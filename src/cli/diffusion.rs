//! `scanloc diffusion`: D per track and for the ensemble from a tracks
//! table (docs/tracking.md).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, ValueEnum};
use scanloc::error::{input_error, readable};
use scanloc::track::diffusion::{
    ENSEMBLE_GATE, Estimate, Exposure, Method, RecordingEstimates, Series,
    attach_detection_profile, estimate_recording,
};

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
pub struct DiffusionArgs {
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

pub fn run(
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
    if !(args.ensemble_margin_px.is_finite() && args.ensemble_margin_px >= 0.0) {
        return Err(input_error(format!(
            "--ensemble-margin-px: must be a finite number ≥ 0, got {}",
            readable(args.ensemble_margin_px)
        )));
    }
    scanloc::track::pipeline::check_ensemble_margin(
        args.ensemble_margin_px,
        geometry.height,
        geometry.width,
    )
    .map_err(|e| input_error(format!("--ensemble-margin-px: {e}")))?;
    scanloc::track::pipeline::check_min_points("--min-points", args.min_points)?;
    if !scanloc::track::pipeline::valid_ensemble_gate(args.ensemble_gate) {
        return Err(input_error(format!(
            "--ensemble-gate: must be a share of the gate in (0, 0.707] or 1 (every step), got {}",
            readable(args.ensemble_gate)
        )));
    }
    let mut tracks = scanloc::io::tracks::read_tracks(&args.tracks)?;
    refuse_foreign_tracks(&args.tracks, &tracks, &geometry)?;
    if !args.given_sigma && tracks.iter().any(|t| t.has_sigma()) {
        tracks = tracks.iter().map(|t| t.without_sigma()).collect();
        writeln!(
            stderr,
            "the table's sigma_x, sigma_y are not used: the localisation variance is estimated with D (--given-sigma uses them)"
        )?;
    }
    let mut series: Vec<Series> = tracks
        .iter()
        .map(|track| Series::new(track, &geometry, exposure))
        .collect();
    for (track, s) in tracks.iter().zip(&series) {
        if let Some(i) = s.first_step_shorter_than_blur() {
            return Err(input_error(format!(
                "{}: particle {}: column time: the step from frame {} to frame {} lasts {} s, not more than the two localisations' blur ({} s): time stamps must increase with the frame, in seconds",
                args.tracks.display(),
                track.particle,
                s.frames[i],
                s.frames[i + 1],
                readable(s.times[i + 1] - s.times[i]),
                readable(s.blur[i] + s.blur[i + 1]),
            )));
        }
    }
    if series.iter().all(|s| s.len() < 2) {
        return Err(input_error(format!(
            "{}: no track has two localisations",
            args.tracks.display()
        )));
    }
    if !args.no_detection_profile {
        attach_detection_profile(&mut series, geometry.pixel_size_um);
    }
    let estimates: Vec<(Method, RecordingEstimates)> = Method::ALL
        .into_iter()
        .map(|method| {
            (
                method,
                estimate_recording(
                    &series,
                    method,
                    args.min_points,
                    args.ensemble_gate,
                    args.ensemble_margin_px * geometry.pixel_size_um,
                ),
            )
        })
        .collect();
    refuse_non_finite(&args.tracks, &tracks, &estimates)?;
    writeln!(
        stdout,
        "particle,points,method,d_um2_s,standard_error,low_95,high_95,localisation_variance_um2,interval_valid"
    )?;
    // One row per track and method, tracks in table order.
    for (index, track) in tracks.iter().enumerate() {
        for (method, e) in &estimates {
            if let Some(estimate) = &e.per_track[index] {
                row(
                    stdout,
                    &track.particle.to_string(),
                    series[index].len(),
                    *method,
                    estimate,
                )?;
            }
        }
    }
    for (method, e) in &estimates {
        if let Some(phi) = e.dispersion.filter(|&phi| phi > 1.0) {
            writeln!(
                stderr,
                "{}: the tracks' estimates scatter {phi:.2} times as much as the likelihood says; each track's interval is widened by that (docs/tracking.md, \"The estimators\")",
                method.name()
            )?;
        }
        if let Some(phi) = e.ensemble_dispersion.filter(|&phi| phi > 1.0) {
            writeln!(
                stderr,
                "{}: the ensemble's runs scatter {phi:.2} times as much as the likelihood says; the ensemble's interval is widened by that (docs/tracking.md, \"The estimators\")",
                method.name()
            )?;
        }
    }
    let points: usize = series.iter().filter(|s| s.len() > 1).map(Series::len).sum();
    for (method, e) in &estimates {
        match &e.ensemble {
            Some(estimate) => row(stdout, "ensemble", points, *method, estimate)?,
            None => writeln!(
                stderr,
                "{}: no ensemble estimate: too few steps{}",
                method.name(),
                if *method == Method::Ml && args.ensemble_margin_px > 0.0 {
                    " inside the ensemble's margin (--ensemble-margin-px)"
                } else {
                    ""
                }
            )?,
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// How far outside the field a localisation may lie, in σxy of the PSF:
/// beyond it no pixel of the field sees the particle.
const FIELD_REACH_SIGMAS: f64 = 3.0;

/// Refuses tracks that cannot come from the scan `geometry` describes: a
/// localisation further outside the field than the PSF reaches (tracks of a
/// larger field analysed as a smaller one, whose D would come out far too
/// low), or a step whose `time` stamps differ from its frames' distance on
/// the frame clock by more than a frame period.
fn refuse_foreign_tracks(
    source: &std::path::Path,
    tracks: &[scanloc::types::Track],
    geometry: &scanloc::track::diffusion::ScanGeometry,
) -> anyhow::Result<()> {
    let reach = FIELD_REACH_SIGMAS * geometry.sigma_xy_um / geometry.pixel_size_um;
    let period = geometry.frame_period_s();
    for track in tracks {
        for point in &track.points {
            for (name, value, size, flag) in [
                ("x", point.x, geometry.width, "--width"),
                ("y", point.y, geometry.height, "--height"),
            ] {
                let (low, high) = (-0.5 - reach, size as f64 - 0.5 + reach);
                if !(low..=high).contains(&value) {
                    return Err(input_error(format!(
                        "{}: particle {}: frame {}: column {name}: {} px is outside the {} × {} px field \
                         (by more than the PSF's reach, {} px); give the recording's {flag}",
                        source.display(),
                        track.particle,
                        point.frame,
                        readable(value),
                        geometry.height,
                        geometry.width,
                        readable(reach),
                    )));
                }
            }
        }
        for pair in track.points.windows(2) {
            let (Some(t0), Some(t1)) = (pair[0].time_s, pair[1].time_s) else {
                continue;
            };
            let frames = pair[1].frame as f64 - pair[0].frame as f64;
            if ((t1 - t0) - frames * period).abs() > period {
                return Err(input_error(format!(
                    "{}: particle {}: column time: the step from frame {} to frame {} lasts {} s, \
                     where the frame clock gives {} s ± one frame period ({} s)",
                    source.display(),
                    track.particle,
                    pair[0].frame,
                    pair[1].frame,
                    readable(t1 - t0),
                    readable(frames * period),
                    readable(period),
                )));
            }
        }
    }
    Ok(())
}

/// Refuses results that are not finite numbers (the upper end of an
/// interval, and so its standard error, excepted, which may be infinite):
/// never a row of NaN, or an infinite D, with exit code 0.
fn refuse_non_finite(
    source: &std::path::Path,
    tracks: &[scanloc::types::Track],
    estimates: &[(Method, RecordingEstimates)],
) -> anyhow::Result<()> {
    // An interval open above (high = +∞, and so its standard error) is
    // documented; anything else must be a finite number.
    let finite = |e: &Estimate| {
        [e.d, e.low, e.localisation_variance]
            .iter()
            .all(|v| v.is_finite())
            && !(e.high.is_nan() || e.standard_error.is_nan())
    };
    for (method, e) in estimates {
        let per_track = tracks
            .iter()
            .zip(&e.per_track)
            .filter_map(|(track, estimate)| Some((track.particle.to_string(), estimate.as_ref()?)));
        let ensemble = e
            .ensemble
            .as_ref()
            .map(|estimate| ("ensemble".to_string(), estimate));
        if let Some((label, _)) = per_track.chain(ensemble).find(|(_, e)| !finite(e)) {
            return Err(input_error(format!(
                "{}: particle {label}: the {} estimate is not a finite number: the tracks do not \
                 fit the stated scan (--height, --width, --pixel-size-um, timing)",
                source.display(),
                method.name()
            )));
        }
    }
    Ok(())
}
