//! A tracking pipeline as a manifest runs it (`docs/tracking.md`, "The
//! tracking experiment"): a detector's localisations on a recording,
//! linked by a [`LinkerSpec`] into tracks, scored against the recording's
//! truth ([`evaluate`]): the tracking measures of
//! [`metrics::tracking`](crate::metrics::tracking) and, per estimator, D
//! for the ensemble and per track with the D metrics of
//! [`metrics::diffusion`](crate::metrics::diffusion).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::diffusion::{
    ENSEMBLE_GATE, Estimate, MAX_ENSEMBLE_GATE, Method, ScanGeometry, Series,
    attach_detection_profile, estimate_recording, ml, within_gates,
};
use super::{Detection, Linking, lap, trackpy};
use crate::error::input_error;
use crate::metrics::diffusion::{DiffusionInterval, DiffusionScore, score_diffusion};
use crate::metrics::tracking::{
    DEFAULT_GATE_PX, TrackingScore, TruthPosition, TruthSelection, score_tracks, truth_tracks,
};
use crate::types::{Prediction, RecordingTruthRow, Track, TrackPoint};

/// Version of the linking step (the linkers of [`super::trackpy`] and
/// [`super::lap`] and the tracks table they make).
pub const LINK_VERSION: &str = "scanloc-link/4";

/// Version of the scoring of tracks ([`evaluate`] and its JSON).
pub const TRACK_METRIC_VERSION: &str = "scanloc-track-metric/6";

/// A linker as a manifest names it: `{trackpy: {search_range: 10, memory:
/// 2}}` or `{lap: {search_range: 10, max_gap: 2}}` (or `{lap:
/// {diffusion_um2_s: 1.75, max_gap: 2}}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum LinkerSpec {
    /// TrackPy 0.7's `link` ([`trackpy`]).
    Trackpy(TrackpySettings),
    /// Frame-to-frame LAP and gap closing ([`lap`]).
    Lap(LapSettings),
}

/// `trackpy` linker settings, TrackPy's names.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackpySettings {
    /// The largest displacement between frames, px.
    pub search_range: f64,
    /// Frames a particle may vanish for and still be linked.
    #[serde(default)]
    pub memory: usize,
}

/// `lap` linker settings: the step variance from a search range (3 standard
/// deviations) or from a diffusion coefficient and the recording's frame
/// period and pixel size (exactly one of the two).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LapSettings {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub search_range: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub diffusion_um2_s: Option<f64>,
    /// The longest gap closed, in frames without the particle.
    #[serde(default = "default_max_gap")]
    pub max_gap: usize,
    /// The gate: the largest Mahalanobis distance of a link's displacement
    /// (3 when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gate_sigmas: Option<f64>,
    /// Link twice: the second time with the step of the D the first
    /// pass's tracks give (ML, the ensemble), so the costs follow the
    /// recording's own diffusion when D is not known beforehand.
    #[serde(default, skip_serializing_if = "is_false")]
    pub relink: bool,
}

fn is_false(value: &bool) -> bool {
    !*value
}

fn default_max_gap() -> usize {
    2
}

impl LinkerSpec {
    /// Checks the settings; the error names the field.
    pub fn validate(&self) -> Result<(), crate::error::FieldError> {
        use crate::error::FieldError;
        use crate::limits::{
            MAX_DIFFUSION_UM2_S, MAX_GATE_SIGMAS, MAX_SEARCH_RANGE, check_positive_at_most,
        };
        let frames = |name: &str, value: usize| {
            if value <= crate::limits::MAX_FRAMES {
                Ok(())
            } else {
                Err(FieldError::new(
                    name,
                    format!(
                        "must be at most {} frames, got {value}",
                        crate::limits::MAX_FRAMES
                    ),
                ))
            }
        };
        match self {
            LinkerSpec::Trackpy(s) => {
                check_positive_at_most("search_range", s.search_range, MAX_SEARCH_RANGE)?;
                frames("memory", s.memory)
            }
            LinkerSpec::Lap(s) => {
                match (s.search_range, s.diffusion_um2_s) {
                    (Some(range), None) => {
                        check_positive_at_most("search_range", range, MAX_SEARCH_RANGE)?;
                    }
                    (None, Some(d)) => {
                        check_positive_at_most("diffusion_um2_s", d, MAX_DIFFUSION_UM2_S)?;
                    }
                    _ => {
                        return Err(FieldError::new(
                            "search_range",
                            "give exactly one of search_range (px) and diffusion_um2_s (µm²/s)",
                        ));
                    }
                }
                if let Some(gate) = s.gate_sigmas {
                    check_positive_at_most("gate_sigmas", gate, MAX_GATE_SIGMAS)?;
                }
                frames("max_gap", s.max_gap)
            }
        }
    }

    /// The linker's name as written (`trackpy`, `lap`).
    pub fn kind_name(&self) -> &'static str {
        match self {
            LinkerSpec::Trackpy(_) => "trackpy",
            LinkerSpec::Lap(_) => "lap",
        }
    }

    /// Links `detections` of a recording with scan `geometry` (whose frame
    /// period and pixel size turn a diffusion coefficient into a step).
    pub fn link(
        &self,
        detections: &[Detection],
        geometry: &ScanGeometry,
    ) -> anyhow::Result<Linking> {
        match self {
            LinkerSpec::Trackpy(s) => trackpy::link(
                detections,
                &trackpy::TrackpyParams {
                    search_range: s.search_range,
                    memory: s.memory,
                },
            ),
            LinkerSpec::Lap(s) => {
                let gated = |params: lap::LapParams| lap::LapParams {
                    gate_sigmas: s.gate_sigmas.unwrap_or(lap::GATE_SIGMAS),
                    ..params
                };
                let with_diffusion = |d: f64| {
                    gated(lap::LapParams::from_diffusion(
                        d,
                        geometry.frame_period_s() * 1e3,
                        geometry.pixel_size_um,
                        s.max_gap,
                    ))
                };
                let params = match (s.search_range, s.diffusion_um2_s) {
                    (Some(range), _) => gated(lap::LapParams::from_search_range(range, s.max_gap)),
                    (None, Some(d)) => with_diffusion(d),
                    (None, None) => {
                        return Err(input_error(
                            "the lap linker needs search_range or diffusion_um2_s",
                        ));
                    }
                };
                let first = lap::link(detections, &params)?;
                if !s.relink {
                    return Ok(first);
                }
                // The second pass, with the first pass's D; if it gives
                // none (no step), the first pass stands.
                let tracks = tracks_of(detections, &first);
                match ensemble_ml(&tracks, geometry) {
                    Some(d) if d.is_finite() && d > 0.0 => {
                        lap::link(detections, &with_diffusion(d))
                    }
                    _ => Ok(first),
                }
            }
        }
    }
}

/// The ML ensemble's D (µm²/s) over all `tracks` as `scanloc diffusion`
/// reads it with its defaults: σ² profiled, the tracks' detection
/// profile, steps within [`ENSEMBLE_GATE`] of their gates, each run
/// given its first step.
fn ensemble_ml(tracks: &[Track], geometry: &ScanGeometry) -> Option<f64> {
    let series = within_gates(&series_of(tracks, geometry), ENSEMBLE_GATE);
    let all: Vec<&Series> = series.iter().filter(|s| s.len() > 1).collect();
    ml::ensemble_estimate(&all).map(|e| e.d)
}

/// `tracks` prepared for the D estimators, with the exposure the scan
/// implies, their localisations' own σ left out ([`Track::without_sigma`]):
/// σ² is profiled. Each series carries the detection profile of all the
/// tracks' localisations.
fn series_of(tracks: &[Track], geometry: &ScanGeometry) -> Vec<Series> {
    let exposure = geometry.auto_exposure();
    let mut series: Vec<Series> = tracks
        .iter()
        .map(|track| Series::new(&track.without_sigma(), geometry, exposure))
        .collect();
    attach_detection_profile(&mut series, geometry.pixel_size_um);
    series
}

/// The tracks of `detections` as `linking` labelled them: one per label,
/// in label order, points in frame order, with the gates that admitted
/// their steps.
fn tracks_of(detections: &[Detection], linking: &Linking) -> Vec<Track> {
    let mut by_particle: BTreeMap<usize, Vec<TrackPoint>> = BTreeMap::new();
    for (i, (detection, &label)) in detections.iter().zip(&linking.particle).enumerate() {
        let gate = linking.gates.as_ref().and_then(|gates| gates[i]);
        by_particle.entry(label).or_default().push(TrackPoint {
            frame: detection.frame,
            x: detection.x,
            y: detection.y,
            sigma: detection.sigma.map(|s| (s.x, s.y)),
            time_s: None,
            gate: gate.map(|[x, y]| (x, y)),
        });
    }
    by_particle
        .into_iter()
        .map(|(label, mut points)| {
            points.sort_by_key(|p| p.frame);
            Track {
                particle: i64::try_from(label).unwrap_or(i64::MAX),
                points,
            }
        })
        .collect()
}

/// Whether `prediction` is linked under the score threshold `min_score`
/// (it scores at least that; every prediction without one).
pub fn scores_at_least(prediction: &Prediction, min_score: Option<f64>) -> bool {
    min_score.is_none_or(|least| prediction.score >= least)
}

/// Links the predictions scoring at least `min_score` (all when `None`)
/// into tracks: one per particle, labelled 0, 1, … in the linker's order,
/// points in frame order with the predictions' uncertainty.
pub fn link_predictions(
    predictions: &[Prediction],
    min_score: Option<f64>,
    linker: &LinkerSpec,
    geometry: &ScanGeometry,
) -> anyhow::Result<Vec<Track>> {
    let kept: Vec<&Prediction> = predictions
        .iter()
        .filter(|p| scores_at_least(p, min_score))
        .collect();
    let detections: Vec<Detection> = kept
        .iter()
        .map(|p| Detection {
            frame: p.frame,
            x: p.x,
            y: p.y,
            sigma: p.sigma,
        })
        .collect();
    let linking = linker.link(&detections, geometry)?;
    Ok(tracks_of(&detections, &linking))
}

/// How tracks are scored: the truth they are scored against, the gate,
/// and the shortest track whose D is estimated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrackScoring {
    /// The gate ε of the tracking measures, px.
    #[serde(default = "default_gate_px")]
    pub gate_px: f64,
    /// Truth rows counted: `|z_mean| ≤` this, µm (all depths when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_depth_um: Option<f64>,
    /// Truth rows counted: `on_fraction ≥` this (all when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_on_fraction: Option<f64>,
    /// A truth track is split where its QD is missing for more than this
    /// many frames (never when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub split_gaps_over: Option<usize>,
    /// Tracks with fewer localisations get no D of their own (they still
    /// count in the ensemble).
    #[serde(default = "default_min_points")]
    pub min_points: usize,
    /// The share of each link's gate within which the ML ensemble takes
    /// its steps ([`within_gates`](super::diffusion::within_gates)): at
    /// most 1/√2, or 1 for every step.
    #[serde(default = "default_ensemble_gate")]
    pub ensemble_gate: f64,
    /// The ML ensemble takes its steps within the box this far inside the
    /// field's edges, px ([`within_margin`](super::diffusion::within_margin));
    /// 0 (the default, left out of the JSON): the whole field.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub ensemble_margin_px: f64,
    /// Whether the ML ensemble is also given corrected for the pipeline's
    /// own bias ([`BiasCorrection`]); none by default (left out of the
    /// JSON).
    #[serde(
        default,
        skip_serializing_if = "BiasCorrection::is_none",
        with = "serde_yaml::with::singleton_map"
    )]
    pub bias_correction: BiasCorrection,
}

/// How a tracking pipeline's ML ensemble D is corrected for the bias of
/// the pipeline itself (localiser, linker and estimator together).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum BiasCorrection {
    /// The ensemble as estimated.
    #[default]
    None,
    /// Measured on simulated recordings like the one scored (its scan,
    /// blinking and number of QDs, at the D the pipeline read) put through
    /// the same localiser, linker and estimator, and divided out
    /// (docs/tracking.md, "Bias correction by simulation").
    Simulated {
        /// How many recordings as long as the scored one are simulated:
        /// their noise adds to the corrected D's, by `1/recordings` of the
        /// recording's own variance.
        #[serde(default = "default_bias_recordings")]
        recordings: usize,
    },
}

/// At most this many simulated recordings per bias correction (each as
/// long as the recording scored).
pub const MAX_BIAS_RECORDINGS: usize = 16;

fn default_bias_recordings() -> usize {
    2
}

impl BiasCorrection {
    fn is_none(&self) -> bool {
        *self == BiasCorrection::None
    }

    /// Checks the number of recordings; the error names `bias_correction`.
    pub fn validate(&self) -> Result<(), crate::error::FieldError> {
        match *self {
            BiasCorrection::Simulated { recordings }
                if !(1..=MAX_BIAS_RECORDINGS).contains(&recordings) =>
            {
                Err(crate::error::FieldError::new(
                    "bias_correction",
                    format!("recordings must be 1 to {MAX_BIAS_RECORDINGS}, got {recordings}"),
                ))
            }
            _ => Ok(()),
        }
    }
}

fn is_zero(value: &f64) -> bool {
    *value == 0.0
}

fn default_ensemble_gate() -> f64 {
    ENSEMBLE_GATE
}

/// A share in (0, 1/√2], or 1.
pub fn valid_ensemble_gate(share: f64) -> bool {
    (share > 0.0 && share <= MAX_ENSEMBLE_GATE) || share == 1.0
}

/// Checks the fewest localisations a track needs for a row of its own
/// (`name` names the field or flag): 2 (one step) to
/// [`MAX_FRAMES`](crate::limits::MAX_FRAMES).
pub fn check_min_points(name: &str, points: usize) -> Result<usize, crate::error::FieldError> {
    let limit = crate::limits::MAX_FRAMES;
    if (2..=limit).contains(&points) {
        Ok(points)
    } else {
        Err(crate::error::FieldError::new(
            name,
            format!("must be 2 to {limit}, got {points}"),
        ))
    }
}

/// Checks that an ensemble margin of `margin_px` leaves a box inside a
/// field of `height × width` px (the ML ensemble takes only the steps in
/// it; with none, it would have nothing to estimate from).
pub fn check_ensemble_margin(margin_px: f64, height: usize, width: usize) -> Result<(), String> {
    if 2.0 * margin_px < height.min(width) as f64 {
        Ok(())
    } else {
        Err(format!(
            "{margin_px} px inside each edge leaves nothing of the {height} × {width} px field \
             (a margin must be less than half its shorter side)"
        ))
    }
}

fn default_gate_px() -> f64 {
    DEFAULT_GATE_PX
}

fn default_min_points() -> usize {
    3
}

impl Default for TrackScoring {
    fn default() -> Self {
        Self {
            gate_px: default_gate_px(),
            max_depth_um: None,
            min_on_fraction: None,
            split_gaps_over: None,
            min_points: default_min_points(),
            ensemble_gate: default_ensemble_gate(),
            ensemble_margin_px: 0.0,
            bias_correction: BiasCorrection::None,
        }
    }
}

impl TrackScoring {
    /// Checks the settings; the error names the field.
    pub fn validate(&self) -> Result<(), crate::error::FieldError> {
        use crate::error::FieldError;
        crate::limits::check_positive_at_most("gate_px", self.gate_px, crate::limits::MAX_EPS_PX)?;
        if let Some(depth) = self.max_depth_um
            && !(depth.is_finite() && depth >= 0.0)
        {
            return Err(FieldError::new(
                "max_depth_um",
                format!("must be a finite number ≥ 0, got {depth}"),
            ));
        }
        if let Some(share) = self.min_on_fraction
            && !(0.0..=1.0).contains(&share)
        {
            return Err(FieldError::new(
                "min_on_fraction",
                format!("must be between 0 and 1, got {share}"),
            ));
        }
        check_min_points("min_points", self.min_points)?;
        if !(self.ensemble_margin_px.is_finite() && self.ensemble_margin_px >= 0.0) {
            return Err(FieldError::new(
                "ensemble_margin_px",
                format!(
                    "must be a finite number ≥ 0, got {}",
                    self.ensemble_margin_px
                ),
            ));
        }
        self.bias_correction.validate()?;
        if !valid_ensemble_gate(self.ensemble_gate) {
            return Err(FieldError::new(
                "ensemble_gate",
                format!(
                    "must be a share of the gate in (0, 0.707] or 1 (every step), got {}",
                    self.ensemble_gate
                ),
            ));
        }
        Ok(())
    }

    /// The truth rows these settings count (at the whole-frame centroid).
    pub fn selection(&self) -> TruthSelection {
        TruthSelection {
            position: TruthPosition::Centroid,
            max_depth_um: self.max_depth_um,
            min_on_fraction: self.min_on_fraction,
            split_gaps_over: self.split_gaps_over,
        }
    }
}

/// One estimate of D as stored: µm²/s and µm². A value that is not a
/// finite number (the standard error of an unbounded interval) is stored
/// as `null` and read back as NaN, and is NaN in memory from the start, so
/// a stored evaluation reads back equal to the one computed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StoredEstimate {
    #[serde(deserialize_with = "null_as_nan")]
    pub d: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub standard_error: f64,
    #[serde(deserialize_with = "null_as_nan")]
    pub low: f64,
    /// `None` for an unbounded interval (JSON has no infinity).
    pub high: Option<f64>,
    #[serde(deserialize_with = "null_as_nan")]
    pub localisation_variance: f64,
    pub steps: usize,
    pub interval_valid: bool,
}

/// `null` (how JSON writes a number that is not finite) as NaN.
fn null_as_nan<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(deserializer)?.unwrap_or(f64::NAN))
}

/// `value` if finite, else NaN (what it reads back as from JSON).
fn finite_or_nan(value: f64) -> f64 {
    if value.is_finite() { value } else { f64::NAN }
}

impl From<Estimate> for StoredEstimate {
    fn from(e: Estimate) -> Self {
        Self {
            d: finite_or_nan(e.d),
            standard_error: finite_or_nan(e.standard_error),
            low: finite_or_nan(e.low),
            high: e.high.is_finite().then_some(e.high),
            localisation_variance: finite_or_nan(e.localisation_variance),
            steps: e.steps,
            interval_valid: e.interval_valid,
        }
    }
}

impl StoredEstimate {
    fn interval(&self) -> DiffusionInterval {
        DiffusionInterval {
            d: self.d,
            low: self.low,
            high: self.high.unwrap_or(f64::INFINITY),
        }
    }
}

/// One track's estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackEstimate {
    pub particle: i64,
    pub points: usize,
    pub estimate: StoredEstimate,
}

/// One estimator's D over a recording's tracks.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EstimatorScore {
    pub method: Method,
    /// The estimator over all tracks at once; `None` if it gave none.
    pub ensemble: Option<StoredEstimate>,
    /// `D̂/D − 1` of the ensemble estimate.
    pub ensemble_relative_error: Option<f64>,
    /// The D metrics over the tracks of at least `min_points` whose
    /// estimate's stated condition holds; `None` when there is none.
    pub per_track: Option<DiffusionScore>,
    /// Every track of at least `min_points` localisations that got an
    /// estimate, by particle.
    pub tracks: Vec<TrackEstimate>,
    /// ML: how much more the tracks' estimates scatter than the likelihood
    /// says (each track's interval is widened by it where it exceeds 1;
    /// docs/tracking.md, "The estimators"). Absent for the other methods,
    /// and in evaluations made before `scanloc-track-metric/4`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dispersion: Option<f64>,
    /// ML: how much more the ensemble's runs scatter than the likelihood
    /// says (the ensemble's interval is widened by it where it exceeds 1).
    /// Absent for the other methods, and in evaluations made before
    /// `scanloc-track-metric/5`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble_dispersion: Option<f64>,
}

/// A tracking pipeline's scores on one recording (`score.json` of a
/// tracking evaluation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackEvaluation {
    /// The tracking measures against the selected truth.
    pub tracking: TrackingScore,
    /// The recording's true D, µm²/s.
    pub true_diffusion_um2_s: f64,
    pub scoring: TrackScoring,
    /// One entry per estimator (CVE, MSD fit, ML).
    pub diffusion: Vec<EstimatorScore>,
    /// The ML ensemble corrected for the pipeline's bias, with
    /// [`BiasCorrection::Simulated`] (absent otherwise, and where the
    /// pipeline gave no ensemble).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub corrected_ensemble: Option<CorrectedEnsemble>,
}

/// The ML ensemble corrected for a pipeline's bias by simulation
/// ([`BiasCorrection::Simulated`]): the pipeline read `D̂` on the recording
/// and `D̂ₛ` on a simulated one at D = `D̂`, so it reads D high by `D̂ₛ/D̂`
/// there, and the corrected D is `D̂ · D̂/D̂ₛ`, its relative standard error
/// the two estimates' added in quadrature.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CorrectedEnsemble {
    /// The corrected D with its standard error and 95 % interval
    /// (`D ± 1.96 SE`); its localisation variance and steps are the
    /// recording's ensemble's.
    pub estimate: StoredEstimate,
    /// `D/D_true − 1` of the corrected D.
    pub relative_error: f64,
    /// QDs in each simulated recording: as many as give them the
    /// recording's localisations per frame, by a pilot with `pilot_qds`.
    pub simulated_qds: u64,
    pub pilot_qds: u64,
    /// The simulated recordings' frames, all together.
    pub simulated_frames: usize,
    /// The ML ensemble the pipeline read on the simulated recordings' tracks
    /// together, whose true D is the recording's ensemble D̂.
    pub simulated: StoredEstimate,
}

impl CorrectedEnsemble {
    /// The correction of `recording`'s ensemble estimate (true D `true_d`)
    /// by `simulated`, the pipeline's estimate on a recording simulated at
    /// D = `recording.d`; `None` where either is not a positive finite D.
    pub fn new(
        recording: &StoredEstimate,
        simulated: &StoredEstimate,
        true_d: f64,
        qds: (u64, u64),
        simulated_frames: usize,
    ) -> Option<Self> {
        let positive = |e: &StoredEstimate| e.d.is_finite() && e.d > 0.0;
        if !(positive(recording) && positive(simulated)) {
            return None;
        }
        let d = recording.d * recording.d / simulated.d;
        let relative_se =
            (recording.standard_error / recording.d).hypot(simulated.standard_error / simulated.d);
        let standard_error = d * relative_se;
        let half_width = 1.96 * standard_error;
        let estimate = StoredEstimate {
            d,
            standard_error: finite_or_nan(standard_error),
            low: finite_or_nan(d - half_width),
            high: (d + half_width).is_finite().then_some(d + half_width),
            ..*recording
        };
        Some(Self {
            estimate,
            relative_error: d / true_d - 1.0,
            simulated_qds: qds.1,
            pilot_qds: qds.0,
            simulated_frames,
            simulated: *simulated,
        })
    }
}

impl TrackEvaluation {
    /// The entry of estimator `method`.
    pub fn estimator(&self, method: Method) -> Option<&EstimatorScore> {
        self.diffusion.iter().find(|e| e.method == method)
    }
}

/// Scores `tracks` against a recording's `truth` (true D `true_d`, scan
/// `geometry`, the exposure [`ScanGeometry::auto_exposure`] picks; σ²
/// profiled by every estimator, see [`series_of`]).
pub fn evaluate(
    truth: &[RecordingTruthRow],
    tracks: &[Track],
    geometry: &ScanGeometry,
    scoring: &TrackScoring,
    true_d: f64,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<TrackEvaluation> {
    progress.set_length(1 + Method::ALL.len() as u64);
    let truth_tracks = truth_tracks(truth, &scoring.selection());
    let tracking = score_tracks(&truth_tracks, tracks, scoring.gate_px)?;
    progress.inc(1);
    let series = series_of(tracks, geometry);
    let diffusion = Method::ALL
        .into_iter()
        .map(|method| {
            let estimates = estimate_recording(
                &series,
                method,
                scoring.min_points,
                scoring.ensemble_gate,
                scoring.ensemble_margin_px * geometry.pixel_size_um,
            );
            let ensemble = estimates.ensemble.map(StoredEstimate::from);
            let per_track: Vec<TrackEstimate> = estimates
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
            let valid: Vec<DiffusionInterval> = per_track
                .iter()
                .filter(|t| t.estimate.interval_valid)
                .map(|t| t.estimate.interval())
                .collect();
            progress.inc(1);
            EstimatorScore {
                method,
                ensemble_relative_error: ensemble.map(|e| e.d / true_d - 1.0),
                ensemble,
                per_track: score_diffusion(&valid, true_d),
                tracks: per_track,
                dispersion: estimates.dispersion,
                ensemble_dispersion: estimates.ensemble_dispersion,
            }
        })
        .collect();
    Ok(TrackEvaluation {
        tracking,
        true_diffusion_um2_s: true_d,
        scoring: *scoring,
        diffusion,
        corrected_ensemble: None,
    })
}

/// The ML ensemble of `tracks` as [`evaluate`] takes it under `scoring`
/// (its gate share and margin), without the truth: what a bias correction
/// measures on a simulated recording.
pub fn ml_ensemble_of(
    tracks: &[Track],
    geometry: &ScanGeometry,
    scoring: &TrackScoring,
) -> Option<StoredEstimate> {
    let series = series_of(tracks, geometry);
    let (estimate, _) = super::diffusion::ml_ensemble(
        &series,
        scoring.ensemble_gate,
        scoring.ensemble_margin_px * geometry.pixel_size_um,
    )?;
    Some(estimate.into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::SimParams;
    use crate::sim::recording::{RecordingParams, simulate_recording};

    fn geometry(params: &SimParams) -> ScanGeometry {
        ScanGeometry {
            height: params.height,
            width: params.width,
            pixel_size_um: params.pixel_size_um,
            dwell_us: params.dwell_us,
            retrace_ms: params.retrace_ms,
            dead_time_ms: 0.0,
            sigma_xy_um: params.sigma_xy_um,
        }
    }

    #[test]
    fn true_positions_linked_by_either_linker_give_good_tracks_and_d() {
        // The truth positions of a recording (no detector): the pipeline
        // must find nearly every link and an ensemble D within a few
        // standard errors of the truth.
        let params = RecordingParams {
            microscope: SimParams {
                diffusion_um2_s: 1.0.into(),
                ..SimParams::default()
            },
            frames: 1500,
            density_per_um3: 0.05,
            qd_count: None,
            lateral_margin_um: 0.3,
            half_depth_um: 4.0,
            blinking: None,
            dead_time_ms: 0.0,
        };
        let recording = simulate_recording(&params, 5, false).unwrap();
        let scoring = TrackScoring {
            gate_px: 1.0,
            max_depth_um: Some(1.36),
            split_gaps_over: Some(2),
            ..TrackScoring::default()
        };
        let predictions: Vec<Prediction> = recording
            .truth
            .iter()
            .filter(|r| r.z_mean.abs() <= 1.36)
            .map(|r| Prediction::new(r.frame, r.x, r.y, 1.0))
            .collect();
        let geometry = geometry(&params.microscope);
        for linker in [
            LinkerSpec::Trackpy(TrackpySettings {
                search_range: 10.0,
                memory: 2,
            }),
            LinkerSpec::Lap(LapSettings {
                gate_sigmas: None,
                search_range: None,
                diffusion_um2_s: Some(1.0),
                max_gap: 2,
                relink: false,
            }),
            LinkerSpec::Lap(LapSettings {
                gate_sigmas: None,
                search_range: Some(10.0),
                diffusion_um2_s: None,
                max_gap: 2,
                relink: true,
            }),
        ] {
            let tracks = link_predictions(&predictions, None, &linker, &geometry).unwrap();
            let scored = evaluate(
                &recording.truth,
                &tracks,
                &geometry,
                &scoring,
                1.0,
                &crate::progress::hidden(),
            )
            .unwrap();
            let recall = scored.tracking.link_recall.unwrap();
            assert!(recall > 0.9, "{linker:?}: link recall {recall}");
            let ml = scored.estimator(Method::Ml).unwrap();
            let ensemble = ml.ensemble.unwrap();
            let error = ml.ensemble_relative_error.unwrap();
            // Tolerance: 4 standard errors of the ensemble estimate.
            assert!(
                error.abs() < 4.0 * ensemble.standard_error,
                "{linker:?}: D {} (SE {})",
                ensemble.d,
                ensemble.standard_error
            );
            let per_track = ml.per_track.unwrap();
            assert!(per_track.count >= 5, "{per_track:?}");
            // Round trip through the stored JSON (NaN ≠ NaN, so compared
            // as JSON).
            let json = serde_json::to_vec(&scored).unwrap();
            let back: TrackEvaluation = serde_json::from_slice(&json).unwrap();
            assert_eq!(serde_json::to_vec(&back).unwrap(), json);
        }
    }

    #[test]
    fn a_score_threshold_drops_predictions_before_linking() {
        let predictions = vec![
            Prediction::new(0, 5.0, 5.0, 0.9),
            Prediction::new(1, 5.5, 5.0, 0.9),
            Prediction::new(1, 15.0, 15.0, 0.1),
        ];
        let geometry = geometry(&SimParams::default());
        let linker = LinkerSpec::Trackpy(TrackpySettings {
            search_range: 3.0,
            memory: 0,
        });
        let all = link_predictions(&predictions, None, &linker, &geometry).unwrap();
        assert_eq!(all.len(), 2);
        let kept = link_predictions(&predictions, Some(0.5), &linker, &geometry).unwrap();
        assert_eq!(kept.len(), 1);
        assert_eq!(kept[0].points.len(), 2);
    }

    #[test]
    fn linker_settings_are_checked() {
        let bad = LinkerSpec::Lap(LapSettings {
            gate_sigmas: None,
            search_range: Some(3.0),
            diffusion_um2_s: Some(1.0),
            max_gap: 2,
            relink: false,
        });
        assert!(bad.validate().is_err());
        let bad = LinkerSpec::Trackpy(TrackpySettings {
            search_range: f64::NAN,
            memory: 0,
        });
        assert!(bad.validate().is_err());
        let good: LinkerSpec = serde_yaml::from_str("!lap {search_range: 10}").unwrap();
        assert!(good.validate().is_ok());
        assert!(serde_yaml::from_str::<LinkerSpec>("!lap {range: 10}").is_err());
    }
}
