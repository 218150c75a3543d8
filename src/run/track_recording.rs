//! A user's recording in, trajectories and D out (`scanloc track`,
//! docs/recording.md): localise, link with the relink pass, estimate D per
//! track and for the ensemble, and correct the ensemble for the
//! pipeline's bias by simulation of the same microscope.
//!
//! No setting is tuned for one field: the detector's size follows the
//! PSF, its threshold is the F1-best on a recording simulated with the
//! user's microscope at the pilot D̂, the linker's first search range
//! follows the largest D asked for, the ensemble's box the PSF; each is
//! recorded in [`TrackSettings`] and can be given instead
//! ([`TrackOptions`]). Plain types in and out, so the command line and
//! the Python package call the same function; [`outputs`] renders the
//! result as the command's files and summary for both.

use std::collections::BTreeSet;
use std::path::Path;

use anyhow::Context;
use indicatif::ProgressBar;
use serde::{Deserialize, Serialize};

use crate::detect::crocker_grier::{CrockerGrierParams, locate_stack, to_predictions};
use crate::error::input_error;
use crate::io::StackSelection;
use crate::sim::SimParams;
use crate::sim::recording::{RecordingParams, simulate_recording_stoppable};
use crate::track::diffusion::{Method, ScanGeometry, estimate_recording};
use crate::track::pipeline::evaluate::track_estimates;
use crate::track::pipeline::{
    BiasSetup, CorrectedEnsemble, LapSettings, LinkerSpec, StoredEstimate, TrackEstimate,
    TrackScoring, correct_ensemble, link_predictions, ml_ensemble_of, recording_geometry,
    scores_at_least, series_of,
};
use crate::types::{FrameStack, Prediction, RecordingTruthRow, Track, derive_seed};

pub mod outputs;

/// Version of `track_recording`'s recipe (the rules that choose the
/// settings, the calibration recordings and their seeds).
pub const TRACK_RECORDING_VERSION: &str = "scanloc-track-recording/1";

/// The localiser `track` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum TrackMethod {
    /// TrackPy's `locate`, its score the mass.
    #[default]
    CrockerGrier,
}

/// What the caller may set; every `None` is chosen from simulation of the
/// microscope (and recorded in [`TrackSettings`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackOptions {
    pub method: TrackMethod,
    /// The detector's feature diameter, px (odd).
    pub diameter_px: Option<usize>,
    /// Localisations scoring below this are not linked.
    pub min_score: Option<f64>,
    /// The first linking pass's search range, px (3 σ of a step).
    pub search_range_px: Option<f64>,
    /// The longest gap closed, frames.
    pub max_gap: Option<usize>,
    /// The ML ensemble's box: this far inside the field's edges, px.
    pub ensemble_margin_px: Option<f64>,
    /// The largest D the first linking pass must follow, µm²/s.
    pub max_diffusion_um2_s: f64,
    /// Tracks with fewer localisations get no D of their own.
    pub min_points: usize,
    /// Correct the ensemble for the pipeline's bias by simulation.
    pub bias_correction: bool,
    /// Recordings simulated by the bias correction.
    pub bias_recordings: usize,
    /// Frames of each recording that chooses the threshold (at most the
    /// recording's).
    pub calibration_frames: usize,
    /// QDs per µm³ assumed by the simulations before the recording's own
    /// rate of localisations sets their number.
    pub density_per_um3: f64,
    /// The simulated volume reaches this far beyond the field, µm.
    pub lateral_margin_um: f64,
    /// … and this deep on either side of focus, µm.
    pub half_depth_um: f64,
    /// Time between a frame's last line and the next frame, ms.
    pub dead_time_ms: f64,
    /// Every simulation's seed derives from it.
    pub seed: u64,
}

impl Default for TrackOptions {
    fn default() -> Self {
        Self {
            method: TrackMethod::CrockerGrier,
            diameter_px: None,
            min_score: None,
            search_range_px: None,
            max_gap: None,
            ensemble_margin_px: None,
            max_diffusion_um2_s: 3.0,
            min_points: 3,
            bias_correction: true,
            bias_recordings: 2,
            calibration_frames: 2000,
            density_per_um3: 0.05,
            lateral_margin_um: 1.5,
            half_depth_um: 4.0,
            dead_time_ms: 0.0,
            seed: 20261207,
        }
    }
}

/// The settings a run used, chosen or given.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackSettings {
    pub recipe: String,
    pub method: TrackMethod,
    pub detector: CrockerGrierParams,
    pub min_score: f64,
    /// Whether the threshold was chosen (else given).
    pub min_score_chosen: bool,
    /// The in-focus F1 the chosen threshold reached on the calibration
    /// recording.
    pub calibration_f1: Option<f64>,
    /// The D the calibration recording was simulated at (the pilot D̂).
    pub calibration_d_um2_s: Option<f64>,
    pub linker: LinkerSpec,
    pub ensemble_margin_px: f64,
    pub min_points: usize,
    pub bias_correction: bool,
    pub bias_recordings: usize,
    pub seed: u64,
}

/// The outcome: localisations, tracks, D per track and for the ensemble
/// ([`outputs`] writes it as the command's files and summary).
#[derive(Debug, Clone, PartialEq)]
pub struct TrackResult {
    pub frames: usize,
    pub localisations: Vec<Prediction>,
    /// Localisations linked (at or above the threshold).
    pub linked: usize,
    pub tracks: Vec<Track>,
    /// ML per track (tracks of at least `min_points` localisations).
    pub per_track: Vec<TrackEstimate>,
    /// The ML ensemble as read.
    pub ensemble: Option<StoredEstimate>,
    /// The ML ensemble corrected for the pipeline's bias.
    pub corrected: Option<CorrectedEnsemble>,
    pub settings: TrackSettings,
}

impl TrackResult {
    /// The ensemble D to report: corrected where there is a correction.
    pub fn d(&self) -> Option<StoredEstimate> {
        self.corrected.map(|c| c.estimate).or(self.ensemble)
    }
}

/// How [`track_recording`] shows its progress and learns that its caller
/// wants it to stop.
pub trait TrackMonitor {
    /// The progress bar of a phase of `len` steps labelled `label`.
    fn bar(&self, len: u64, label: &str) -> ProgressBar;
    /// Whether the caller asked the work to stop; checked before each
    /// phase and each stack of frames located, the work then failing with
    /// [`Stopped`].
    fn stop_requested(&self) -> bool;
}

/// The command line's monitor: bars on standard error
/// ([`crate::progress::bar`]), never stopped.
#[derive(Debug, Clone, Copy, Default)]
pub struct OnStderr;

impl TrackMonitor for OnStderr {
    fn bar(&self, len: u64, label: &str) -> ProgressBar {
        crate::progress::bar(len, label)
    }

    fn stop_requested(&self) -> bool {
        false
    }
}

/// Why [`track_recording`] stopped early: its monitor asked it to.
pub use crate::error::Stopped;

/// The microscope's fields a recording cannot be tracked without: its
/// frame size and its scan's timing (no default fits another microscope).
pub const REQUIRED_FIELDS: [&str; 5] =
    ["height", "width", "pixel_size_um", "dwell_us", "retrace_ms"];

/// Refuses a microscope that does not state every one of
/// [`REQUIRED_FIELDS`] (`stated`: the fields its user set, by a flag or in
/// its file).
pub fn check_stated(stated: &BTreeSet<String>) -> anyhow::Result<()> {
    match REQUIRED_FIELDS
        .iter()
        .find(|field| !stated.contains(**field))
    {
        Some(field) => Err(input_error(format!(
            "{field}: the microscope must state it (--microscope FILE.yaml or --{}); docs/recording.md",
            field.replace('_', "-")
        ))),
        None => Ok(()),
    }
}

impl TrackOptions {
    /// Checks the options against `microscope` (the field the diameter
    /// must fit); the error names the command's flag.
    pub fn check(&self, microscope: &SimParams) -> anyhow::Result<()> {
        crate::track::pipeline::check_min_points("--min-points", self.min_points)?;
        let most = crate::track::pipeline::MAX_BIAS_RECORDINGS;
        if !(1..=most).contains(&self.bias_recordings) {
            return Err(input_error(format!(
                "--bias-recordings: must be 1 to {most}, got {}",
                self.bias_recordings
            )));
        }
        crate::limits::check_positive_at_most(
            "--max-diffusion",
            self.max_diffusion_um2_s,
            crate::limits::MAX_DIFFUSION_UM2_S,
        )
        .map_err(|e| input_error(e.to_string()))?;
        if let Some(d) = self.diameter_px
            && (d < 1 || d.is_multiple_of(2) || d > microscope.height.max(microscope.width))
        {
            return Err(input_error(format!(
                "--diameter: must be an odd number of pixels within the field, got {d}"
            )));
        }
        if let Some(score) = self.min_score
            && !score.is_finite()
        {
            return Err(input_error(format!(
                "--min-score: must be a finite number, got {score}"
            )));
        }
        Ok(())
    }
}

/// Reads a recording to track from `.npy` or TIFF
/// ([`read_recording_file`](crate::io::read_recording_file), one plane of
/// one channel) as photon counts; the error names the file.
pub fn read_recording(path: &Path) -> anyhow::Result<FrameStack> {
    crate::io::read_recording_file(path, &StackSelection::default())?
        .frames
        .into_counts()
        .map_err(|e| input_error(format!("{}: {e:#}", path.display())))
}

/// Checks `frames` against `microscope` before anything is computed; the
/// error names the field.
pub fn check_recording(frames: &FrameStack, microscope: &SimParams) -> anyhow::Result<()> {
    if (frames.height, frames.width) != (microscope.height, microscope.width) {
        return Err(input_error(format!(
            "height/width: the recording's frames are {} × {} px, the microscope's {} × {}",
            frames.height, frames.width, microscope.height, microscope.width
        )));
    }
    if frames.n < 2 {
        return Err(input_error(format!(
            "frames: a recording needs at least 2 frames to track, got {}",
            frames.n
        )));
    }
    let first = frames.data.first().copied().unwrap_or(0);
    if frames.data.iter().all(|&v| v == first) {
        return Err(input_error(format!(
            "frames: every pixel of the recording is {first}; there is nothing to track"
        )));
    }
    microscope
        .validate()
        .map_err(|e| input_error(format!("microscope: {e}")))?;
    for (name, distribution) in [
        ("brightness", &microscope.brightness),
        ("background", &microscope.background),
    ] {
        distribution
            .require_fixed(name, "tracking a recording")
            .map_err(|e| input_error(format!("microscope: {e}")))?;
    }
    Ok(())
}

/// The detector's diameter for a PSF of `sigma_px`: the smallest odd
/// number of pixels ≥ 2σ + 1, at least 3.
pub fn diameter_for(sigma_px: f64) -> usize {
    let d = (2.0 * sigma_px + 1.0).ceil().max(3.0) as usize;
    if d.is_multiple_of(2) { d + 1 } else { d }
}

/// [`track_recording`] of the recording `name` (its file, or what the
/// caller calls it): an input error names it first.
pub fn track_named_recording(
    name: &str,
    frames: &FrameStack,
    microscope: &SimParams,
    options: &TrackOptions,
    monitor: &dyn TrackMonitor,
) -> anyhow::Result<TrackResult> {
    track_recording(frames, microscope, options, monitor).map_err(|error| {
        if crate::error::exit_code(&error) == 2 {
            input_error(format!("{name}: {error:#}"))
        } else {
            error
        }
    })
}

/// Tracks `frames`, a recording taken with `microscope` (its frame size,
/// pixel, timing, PSF, brightness and background), under `options`,
/// showing progress and checking for a stop through `monitor`.
pub fn track_recording(
    frames: &FrameStack,
    microscope: &SimParams,
    options: &TrackOptions,
    monitor: &dyn TrackMonitor,
) -> anyhow::Result<TrackResult> {
    check_recording(frames, microscope)?;
    options.check(microscope)?;
    let plan = Plan::new(frames.n, microscope, options, monitor)?;
    let localisations = plan.locate("locating", frames)?;
    let threshold = plan.threshold(&localisations)?;
    plan.stop_point()?;
    let progress = monitor.bar(1, "linking");
    let tracks = link_predictions(
        &localisations,
        Some(threshold.min_score),
        &plan.linker,
        &plan.geometry,
    )
    .context("linking the recording's localisations")?;
    progress.inc(1);
    progress.finish_and_clear();
    let linked = localisations
        .iter()
        .filter(|p| scores_at_least(p, Some(threshold.min_score)))
        .count();
    let (ensemble, per_track) = estimate_d(&tracks, &plan.geometry, &plan.scoring);
    let corrected = match (options.bias_correction, ensemble) {
        (true, Some(recorded)) => plan.correct(&recorded, linked, threshold.min_score)?,
        _ => None,
    };
    Ok(TrackResult {
        frames: frames.n,
        localisations,
        linked,
        tracks,
        per_track,
        ensemble,
        corrected,
        settings: plan.settings(&threshold),
    })
}

/// The steps the bars of [`track_recording`]'s monitor add up to for a
/// recording of `frames` frames under `options` when every phase runs
/// (the recording located; the two calibration recordings simulated and
/// located; the linking; the bias correction's pilot and recordings
/// simulated and located): a front end's one bar for the whole run.
pub fn planned_steps(frames: usize, options: &TrackOptions) -> u64 {
    let calibration = match options.min_score {
        Some(_) => 0,
        None => 4 * calibration_frames(options, frames),
    };
    let bias = match options.bias_correction {
        true => 2 * (frames.div_ceil(4) + options.bias_recordings * frames),
        false => 0,
    };
    (frames + calibration + 1 + bias) as u64
}

/// The frames of each calibration recording.
fn calibration_frames(options: &TrackOptions, frames: usize) -> usize {
    options.calibration_frames.clamp(1, frames.max(1))
}

/// What a run derives from the microscope and the options before it
/// reads the recording.
struct Plan<'a> {
    options: &'a TrackOptions,
    monitor: &'a dyn TrackMonitor,
    /// The recording as the simulator would make it.
    template: RecordingParams,
    geometry: ScanGeometry,
    detector: CrockerGrierParams,
    linker: LinkerSpec,
    scoring: TrackScoring,
}

/// The threshold a run links at, given or chosen.
struct Threshold {
    min_score: f64,
    /// The calibration's F1 and D where it was chosen.
    f1: Option<f64>,
    d: Option<f64>,
}

impl<'a> Plan<'a> {
    /// The detector's size follows the PSF; the linker's first pass is
    /// wide enough for the largest D asked for (3 σ of a frame's step, at
    /// most the field's half), then relinked with the D its tracks give;
    /// the ensemble's box follows the PSF.
    fn new(
        frames: usize,
        microscope: &SimParams,
        options: &'a TrackOptions,
        monitor: &'a dyn TrackMonitor,
    ) -> anyhow::Result<Self> {
        let template = RecordingParams {
            microscope: microscope.clone(),
            frames,
            density_per_um3: options.density_per_um3,
            qd_count: None,
            lateral_margin_um: options.lateral_margin_um,
            half_depth_um: options.half_depth_um,
            blinking: None,
            dead_time_ms: options.dead_time_ms,
        };
        template
            .validate()
            .map_err(|e| input_error(format!("microscope: {e}")))?;
        let geometry = recording_geometry(&template);
        let sigma_px = microscope.sigma_xy_um / microscope.pixel_size_um;
        let detector = CrockerGrierParams {
            diameter: options
                .diameter_px
                .unwrap_or_else(|| diameter_for(sigma_px)),
            ..CrockerGrierParams::default()
        };
        let step_px = (2.0 * options.max_diffusion_um2_s * geometry.frame_period_s()).sqrt()
            / microscope.pixel_size_um;
        let half_field = microscope.height.max(microscope.width) as f64 / 2.0;
        let linker = LinkerSpec::Lap(LapSettings {
            search_range: Some(
                options
                    .search_range_px
                    .unwrap_or_else(|| (3.0 * step_px).clamp(1.0, half_field.max(1.0))),
            ),
            diffusion_um2_s: None,
            max_gap: options.max_gap.unwrap_or(2),
            gate_sigmas: None,
            relink: true,
        });
        linker
            .validate()
            .map_err(|e| input_error(format!("linker: {e}")))?;
        let margin = options.ensemble_margin_px.unwrap_or_else(|| {
            sigma_px
                .round()
                .min((microscope.height.min(microscope.width) as f64 / 4.0).floor())
        });
        crate::track::pipeline::check_ensemble_margin(margin, microscope.height, microscope.width)
            .map_err(|e| input_error(format!("ensemble margin: {e}")))?;
        let scoring = TrackScoring {
            ensemble_margin_px: margin,
            min_points: options.min_points,
            ..TrackScoring::default()
        };
        Ok(Self {
            options,
            monitor,
            template,
            geometry,
            detector,
            linker,
            scoring,
        })
    }

    /// Fails with [`Stopped`] if the monitor asks for a stop.
    fn stop_point(&self) -> anyhow::Result<()> {
        match self.monitor.stop_requested() {
            true => Err(anyhow::Error::new(Stopped)),
            false => Ok(()),
        }
    }

    /// The localiser's predictions in `frames`, its progress under `label`.
    fn locate(&self, label: &str, frames: &FrameStack) -> anyhow::Result<Vec<Prediction>> {
        self.stop_point()?;
        let progress = self.monitor.bar(frames.n as u64, label);
        let features = locate_stack(frames, &self.detector, &progress)?;
        progress.finish_and_clear();
        Ok(to_predictions(&features))
    }

    /// The threshold: given, or the F1-best on a recording of this
    /// microscope simulated at the pilot D̂ (read with the F1-best
    /// threshold at `max_diffusion_um2_s / 3` first).
    fn threshold(&self, localisations: &[Prediction]) -> anyhow::Result<Threshold> {
        if let Some(min_score) = self.options.min_score {
            return Ok(Threshold {
                min_score,
                f1: None,
                d: None,
            });
        }
        let prior = self.options.max_diffusion_um2_s / 3.0;
        let (first, _) = self.calibration_threshold(prior, "calibration-prior")?;
        self.stop_point()?;
        let pilot = link_predictions(localisations, Some(first), &self.linker, &self.geometry)?;
        let pilot_d = ml_ensemble_of(&pilot, &self.geometry, &self.scoring)
            .map(|e| e.d)
            .filter(|d| d.is_finite() && *d > 0.0)
            .unwrap_or(prior);
        let (min_score, f1) = self.calibration_threshold(pilot_d, "calibration-pilot")?;
        Ok(Threshold {
            min_score,
            f1: Some(f1),
            d: Some(pilot_d),
        })
    }

    /// The ML ensemble `recorded` (of `linked` localisations at
    /// `min_score`) corrected for the pipeline's bias by simulation.
    fn correct(
        &self,
        recorded: &StoredEstimate,
        linked: usize,
        min_score: f64,
    ) -> anyhow::Result<Option<CorrectedEnsemble>> {
        let setup = BiasSetup {
            recording: &self.template,
            seed: derive_seed(self.options.seed, "track-recording", "bias-correction"),
            recordings: self.options.bias_recordings,
            min_score: Some(min_score),
            linker: &self.linker,
            scoring: &self.scoring,
            bar: &|len, label| self.monitor.bar(len, label),
            stop: &|| self.monitor.stop_requested(),
        };
        let mut localise = |label: &str, frames: &FrameStack| self.locate(label, frames);
        correct_ensemble(
            "bias correction",
            &setup,
            recorded,
            linked,
            f64::NAN,
            &mut localise,
        )
    }

    /// The settings the run used.
    fn settings(&self, threshold: &Threshold) -> TrackSettings {
        let options = self.options;
        TrackSettings {
            recipe: TRACK_RECORDING_VERSION.to_string(),
            method: options.method,
            detector: self.detector.clone(),
            min_score: threshold.min_score,
            min_score_chosen: options.min_score.is_none(),
            calibration_f1: threshold.f1,
            calibration_d_um2_s: threshold.d,
            linker: self.linker.clone(),
            ensemble_margin_px: self.scoring.ensemble_margin_px,
            min_points: options.min_points,
            bias_correction: options.bias_correction,
            bias_recordings: options.bias_recordings,
            seed: options.seed,
        }
    }

    /// The F1-best score threshold of the localiser on a recording of the
    /// microscope simulated at D = `d` (its in-focus QDs the truth, a
    /// localisation right within σxy or 1 px), and that F1.
    fn calibration_threshold(&self, d: f64, name: &str) -> anyhow::Result<(f64, f64)> {
        self.stop_point()?;
        let template = &self.template;
        let mut microscope = template.microscope.clone();
        microscope.diffusion_um2_s = d.into();
        let params = RecordingParams {
            microscope,
            frames: calibration_frames(self.options, template.frames),
            ..template.clone()
        };
        let seed = derive_seed(self.options.seed, "track-recording", name);
        let progress = self
            .monitor
            .bar(params.frames as u64, &format!("simulating {name}"));
        let stop = || self.monitor.stop_requested();
        let made = simulate_recording_stoppable(&params, seed, true, &progress, &stop)
            .with_context(|| format!("simulating {name}"))?;
        progress.finish_and_clear();
        let predictions = self.locate(&format!("locating {name}"), &made.frames)?;
        let gate = (template.microscope.sigma_xy_um / template.microscope.pixel_size_um).max(1.0);
        let sigma_z = template.microscope.sigma_z_um;
        let truth: Vec<&RecordingTruthRow> = made
            .truth
            .iter()
            .filter(|r| r.z_mean.abs() <= sigma_z && r.on_fraction >= 0.5)
            .collect();
        Ok(best_f1_threshold(&predictions, &truth, gate))
    }
}

/// The ML ensemble and per-track estimates of `tracks`.
fn estimate_d(
    tracks: &[Track],
    geometry: &ScanGeometry,
    scoring: &TrackScoring,
) -> (Option<StoredEstimate>, Vec<TrackEstimate>) {
    let series = series_of(tracks, geometry);
    let estimates = estimate_recording(
        &series,
        Method::Ml,
        scoring.min_points,
        scoring.ensemble_gate,
        scoring.ensemble_margin_px * geometry.pixel_size_um,
    );
    let per_track = track_estimates(tracks, &series, estimates.per_track);
    (estimates.ensemble.map(StoredEstimate::from), per_track)
}

/// The score threshold with the best F1 of `predictions` against `truth`
/// (a prediction is right if within `gate` px of a QD of its frame not
/// matched by a higher-scoring one), and that F1; the lowest score and 0
/// where nothing matches.
pub fn best_f1_threshold(
    predictions: &[Prediction],
    truth: &[&RecordingTruthRow],
    gate: f64,
) -> (f64, f64) {
    let mut ranked: Vec<&Prediction> = predictions.iter().collect();
    ranked.sort_by(|a, b| {
        b.score
            .total_cmp(&a.score)
            .then(a.frame.cmp(&b.frame))
            .then(a.x.total_cmp(&b.x))
            .then(a.y.total_cmp(&b.y))
    });
    let mut by_frame: std::collections::BTreeMap<usize, Vec<(f64, f64, bool)>> =
        std::collections::BTreeMap::new();
    for row in truth {
        by_frame
            .entry(row.frame)
            .or_default()
            .push((row.x, row.y, false));
    }
    let total = truth.len() as f64;
    let (mut right, mut wrong) = (0.0, 0.0);
    let mut best = (
        ranked.last().map(|p| p.score).unwrap_or(f64::NEG_INFINITY),
        0.0,
    );
    for (index, p) in ranked.iter().enumerate() {
        let hit = by_frame.get_mut(&p.frame).and_then(|rows| {
            rows.iter_mut()
                .filter(|r| !r.2)
                .map(|r| ((r.0 - p.x).hypot(r.1 - p.y), r))
                .filter(|(distance, _)| *distance <= gate)
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, r)| r)
        });
        match hit {
            Some(row) => {
                row.2 = true;
                right += 1.0;
            }
            None => wrong += 1.0,
        }
        // A threshold between equal scores is no threshold.
        if ranked
            .get(index + 1)
            .is_some_and(|next| next.score == p.score)
        {
            continue;
        }
        let f1 = 2.0 * right / (right + wrong + total);
        if f1 > best.1 {
            best = (p.score, f1);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_best_f1_threshold_drops_the_false_localisations() {
        let row = |frame: usize, x: f64, y: f64| RecordingTruthRow {
            frame,
            qd: 0,
            x,
            y,
            z_mean: 0.0,
            on_fraction: 1.0,
            x_seen: x,
            y_seen: y,
            t_mid: 0.0,
            t_beam: 0.0,
            t_seen: 0.0,
            diffusion: 1.0,
        };
        let truth = [row(0, 5.0, 5.0), row(1, 6.0, 5.0)];
        let truth: Vec<&RecordingTruthRow> = truth.iter().collect();
        let predictions = vec![
            Prediction::new(0, 5.2, 5.0, 90.0),
            Prediction::new(1, 6.1, 5.0, 80.0),
            Prediction::new(1, 15.0, 15.0, 30.0),
            Prediction::new(0, 1.0, 1.0, 20.0),
        ];
        let (threshold, f1) = best_f1_threshold(&predictions, &truth, 1.0);
        assert_eq!(threshold, 80.0);
        assert_eq!(f1, 1.0);
    }

    /// A monitor that counts the steps its bars were given and stops
    /// when told to.
    struct Counting {
        bars: std::sync::Mutex<Vec<ProgressBar>>,
        stop: bool,
    }

    impl TrackMonitor for Counting {
        fn bar(&self, len: u64, _label: &str) -> ProgressBar {
            let bar = ProgressBar::hidden();
            bar.set_length(len);
            self.bars.lock().unwrap().push(bar.clone());
            bar
        }

        fn stop_requested(&self) -> bool {
            self.stop
        }
    }

    fn small_recording() -> (FrameStack, SimParams) {
        let microscope = SimParams {
            height: 32,
            width: 32,
            pixel_size_um: 0.1,
            dwell_us: 4.0,
            retrace_ms: 0.6,
            brightness: 7.5.into(),
            diffusion_um2_s: 0.5.into(),
            ..SimParams::default()
        };
        let params = RecordingParams {
            microscope: microscope.clone(),
            frames: 120,
            density_per_um3: 0.05,
            qd_count: None,
            lateral_margin_um: 1.5,
            half_depth_um: 4.0,
            blinking: None,
            dead_time_ms: 0.0,
        };
        let made = crate::sim::recording::simulate_recording(&params, 3, true).unwrap();
        (made.frames, microscope)
    }

    #[test]
    fn the_bars_add_up_to_the_planned_steps_and_a_stop_stops() {
        let (frames, microscope) = small_recording();
        let options = TrackOptions::default();
        let monitor = Counting {
            bars: Default::default(),
            stop: false,
        };
        let result = track_recording(&frames, &microscope, &options, &monitor).unwrap();
        assert!(result.corrected.is_some(), "every phase ran");
        let steps: u64 = monitor
            .bars
            .lock()
            .unwrap()
            .iter()
            .map(|b| b.position().min(b.length().unwrap()))
            .sum();
        assert_eq!(steps, planned_steps(frames.n, &options));
        let stopping = Counting {
            bars: Default::default(),
            stop: true,
        };
        let error = track_recording(&frames, &microscope, &options, &stopping).unwrap_err();
        assert!(error.is::<Stopped>(), "{error:#}");
        assert!(stopping.bars.lock().unwrap().is_empty());
    }

    #[test]
    fn diameters_follow_the_psf() {
        assert_eq!(diameter_for(3.0), 7);
        assert_eq!(diameter_for(2.1), 7);
        assert_eq!(diameter_for(4.2), 11);
        assert_eq!(diameter_for(0.3), 3);
    }
}
