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
//! other front ends call the same function.

use anyhow::Context;
use serde::{Deserialize, Serialize};

use crate::detect::crocker_grier::{CrockerGrierParams, locate_stack, to_predictions};
use crate::error::input_error;
use crate::sim::SimParams;
use crate::sim::recording::{RecordingParams, simulate_recording_with_progress};
use crate::track::diffusion::{Method, ScanGeometry, estimate_recording};
use crate::track::pipeline::{
    BiasSetup, CorrectedEnsemble, LapSettings, LinkerSpec, StoredEstimate, TrackEstimate,
    TrackScoring, correct_ensemble, link_predictions, ml_ensemble_of, recording_geometry,
    scores_at_least, series_of,
};
use crate::types::{FrameStack, Prediction, RecordingTruthRow, Track, derive_seed};

/// Version of `track_recording`'s recipe (the rules that choose the
/// settings, the calibration recordings and their seeds).
pub(crate) const TRACK_RECORDING_VERSION: &str = "scanloc-track-recording/1";

/// The localiser `track` runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub(crate) enum TrackMethod {
    /// TrackPy's `locate`, its score the mass.
    #[default]
    CrockerGrier,
}

/// What the caller may set; every `None` is chosen from simulation of the
/// microscope (and recorded in [`TrackSettings`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct TrackOptions {
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
pub(crate) struct TrackSettings {
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

/// The outcome: localisations, tracks, D per track and for the ensemble.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct TrackResult {
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
    pub(crate) fn d(&self) -> Option<StoredEstimate> {
        self.corrected.map(|c| c.estimate).or(self.ensemble)
    }
}

/// Checks `frames` against `microscope` before anything is computed; the
/// error names the field.
pub(crate) fn check_recording(frames: &FrameStack, microscope: &SimParams) -> anyhow::Result<()> {
    if (frames.height, frames.width) != (microscope.height, microscope.width) {
        return Err(input_error(format!(
            "height/width: the microscope's frames are {} × {} px, the recording's {} × {}",
            microscope.height, microscope.width, frames.height, frames.width
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
pub(crate) fn diameter_for(sigma_px: f64) -> usize {
    let d = (2.0 * sigma_px + 1.0).ceil().max(3.0) as usize;
    if d.is_multiple_of(2) { d + 1 } else { d }
}

/// Tracks `frames`, a recording taken with `microscope` (its frame size,
/// pixel, timing, PSF, brightness and background), under `options`.
pub(crate) fn track_recording(
    frames: &FrameStack,
    microscope: &SimParams,
    options: &TrackOptions,
) -> anyhow::Result<TrackResult> {
    check_recording(frames, microscope)?;
    let template = RecordingParams {
        microscope: microscope.clone(),
        frames: frames.n,
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
    let locate = |label: &str, frames: &FrameStack| -> anyhow::Result<Vec<Prediction>> {
        let progress = crate::progress::bar(frames.n as u64, label);
        let features = locate_stack(frames, &detector, &progress)?;
        progress.finish_and_clear();
        Ok(to_predictions(&features))
    };

    // The linker: a first pass wide enough for the largest D asked for
    // (3 σ of a frame's step, at most the field's half), then relinked with
    // the D its tracks give.
    let frame_s = geometry.frame_period_s();
    let step_px = (2.0 * options.max_diffusion_um2_s * frame_s).sqrt() / microscope.pixel_size_um;
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

    let localisations = locate("locating", frames)?;
    // The threshold: given, or the F1-best on a recording of this
    // microscope simulated at the pilot D̂ (read with the F1-best
    // threshold at `max_diffusion_um2_s / 3` first).
    let (min_score, f1, calibration_d) = match options.min_score {
        Some(score) => (score, None, None),
        None => {
            let calibrate = |d: f64, name: &str| -> anyhow::Result<(f64, f64)> {
                calibration_threshold(&template, d, options, name, &locate)
            };
            let prior = options.max_diffusion_um2_s / 3.0;
            let (first, _) = calibrate(prior, "calibration-prior")?;
            let pilot = link_predictions(&localisations, Some(first), &linker, &geometry)?;
            let pilot_d = ml_ensemble_of(&pilot, &geometry, &scoring)
                .map(|e| e.d)
                .filter(|d| d.is_finite() && *d > 0.0)
                .unwrap_or(prior);
            let (threshold, f1) = calibrate(pilot_d, "calibration-pilot")?;
            (threshold, Some(f1), Some(pilot_d))
        }
    };

    let progress = crate::progress::heartbeat("linking");
    let tracks = link_predictions(&localisations, Some(min_score), &linker, &geometry)
        .context("linking the recording's localisations")?;
    progress.finish_and_clear();
    let linked = localisations
        .iter()
        .filter(|p| scores_at_least(p, Some(min_score)))
        .count();
    let (ensemble, per_track) = estimate_d(&tracks, &geometry, &scoring);

    let corrected = match (options.bias_correction, ensemble) {
        (true, Some(recorded)) => {
            let setup = BiasSetup {
                recording: &template,
                seed: derive_seed(options.seed, "track-recording", "bias-correction"),
                recordings: options.bias_recordings,
                min_score: Some(min_score),
                linker: &linker,
                scoring: &scoring,
            };
            let mut localise = |label: &str, frames: &FrameStack| locate(label, frames);
            correct_ensemble(
                "bias correction",
                &setup,
                &recorded,
                linked,
                f64::NAN,
                &mut localise,
            )?
        }
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
        settings: TrackSettings {
            recipe: TRACK_RECORDING_VERSION.to_string(),
            method: options.method,
            detector,
            min_score,
            min_score_chosen: options.min_score.is_none(),
            calibration_f1: f1,
            calibration_d_um2_s: calibration_d,
            linker,
            ensemble_margin_px: margin,
            min_points: options.min_points,
            bias_correction: options.bias_correction,
            bias_recordings: options.bias_recordings,
            seed: options.seed,
        },
    })
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
    let per_track = estimates
        .per_track
        .into_iter()
        .enumerate()
        .filter_map(|(index, e)| {
            e.map(|e| TrackEstimate {
                particle: tracks[index].particle,
                points: series[index].len(),
                estimate: e.into(),
            })
        })
        .collect();
    (estimates.ensemble.map(StoredEstimate::from), per_track)
}

/// The F1-best score threshold of the localiser on a recording of
/// `template`'s microscope simulated at D = `d` (its in-focus QDs the
/// truth, a localisation right within σxy or 1 px), and that F1.
fn calibration_threshold(
    template: &RecordingParams,
    d: f64,
    options: &TrackOptions,
    name: &str,
    locate: &dyn Fn(&str, &FrameStack) -> anyhow::Result<Vec<Prediction>>,
) -> anyhow::Result<(f64, f64)> {
    let mut microscope = template.microscope.clone();
    microscope.diffusion_um2_s = d.into();
    let params = RecordingParams {
        microscope,
        frames: options.calibration_frames.clamp(1, template.frames.max(1)),
        ..template.clone()
    };
    let seed = derive_seed(options.seed, "track-recording", name);
    let progress = crate::progress::bar(params.frames as u64, &format!("simulating {name}"));
    let made = simulate_recording_with_progress(&params, seed, true, &progress)
        .with_context(|| format!("simulating {name}"))?;
    progress.finish_and_clear();
    let predictions = locate(&format!("locating {name}"), &made.frames)?;
    let gate = (template.microscope.sigma_xy_um / template.microscope.pixel_size_um).max(1.0);
    let sigma_z = template.microscope.sigma_z_um;
    let truth: Vec<&RecordingTruthRow> = made
        .truth
        .iter()
        .filter(|r| r.z_mean.abs() <= sigma_z && r.on_fraction >= 0.5)
        .collect();
    Ok(best_f1_threshold(&predictions, &truth, gate))
}

/// The score threshold with the best F1 of `predictions` against `truth`
/// (a prediction is right if within `gate` px of a QD of its frame not
/// matched by a higher-scoring one), and that F1; the lowest score and 0
/// where nothing matches.
pub(crate) fn best_f1_threshold(
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

    #[test]
    fn diameters_follow_the_psf() {
        assert_eq!(diameter_for(3.0), 7);
        assert_eq!(diameter_for(2.1), 7);
        assert_eq!(diameter_for(4.2), 11);
        assert_eq!(diameter_for(0.3), 3);
    }
}
