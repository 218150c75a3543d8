//! A tracking pipeline's settings as a manifest names them: the linker
//! ([`LinkerSpec`]), how tracks are scored ([`TrackScoring`]) and the bias
//! correction ([`BiasCorrection`]), each checked with the field at fault.

use serde::{Deserialize, Serialize};

use crate::metrics::tracking::{DEFAULT_GATE_PX, TruthPosition, TruthSelection};
use crate::track::diffusion::{ENSEMBLE_GATE, MAX_ENSEMBLE_GATE};

/// Version of the linking step (the linkers of
/// [`trackpy`](crate::track::trackpy) and [`lap`](crate::track::lap) and the tracks table they make).
/// 5: the relink pass's D̂ from the faster likelihood search.
pub const LINK_VERSION: &str = "scanloc-link/5";

/// Version of the scoring of tracks ([`evaluate`](super::evaluate()) and its JSON).
/// 7: the maximum-likelihood fit searches D and σ² by Brent's method, its
/// estimates moved by about 10⁻⁶ of their standard errors.
pub const TRACK_METRIC_VERSION: &str = "scanloc-track-metric/8";

/// A linker as a manifest names it: `{trackpy: {search_range: 10, memory:
/// 2}}` or `{lap: {search_range: 10, max_gap: 2}}` (or `{lap:
/// {diffusion_um2_s: 1.75, max_gap: 2}}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum LinkerSpec {
    /// TrackPy 0.7's `link` ([`trackpy`](crate::track::trackpy)).
    Trackpy(TrackpySettings),
    /// Frame-to-frame LAP and gap closing ([`lap`](crate::track::lap)).
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
    /// its steps ([`within_gates`](crate::track::diffusion::within_gates)): at
    /// most 1/√2, or 1 for every step.
    #[serde(default = "default_ensemble_gate")]
    pub ensemble_gate: f64,
    /// The ML ensemble takes its steps within the box this far inside the
    /// field's edges, px ([`within_margin`](crate::track::diffusion::within_margin));
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
