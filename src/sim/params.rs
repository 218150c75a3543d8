//! Parameters of the simulated microscope and scene (`docs/simulator.md`).
//!
//! Units: micrometres, seconds (as named in each field), photons. Every field
//! has the paper's default, so an empty YAML mapping is the paper's
//! microscope with `N_qd = 7`.

use std::fmt;
use std::str::FromStr;

use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, require_finite, require_non_negative, require_positive};

pub use crate::types::{Distribution, RandomDistribution};

/// The number of QDs in a frame: fixed or drawn once per frame.
///
/// In YAML: a whole number (`2`), or a mapping `{choice: [0, 1, 2, 3]}`
/// (each count equally likely) with optional relative `weights: [1, 2, 2,
/// 2]` (one per count, ≥ 0, not all 0). On the command line: `2`,
/// `choice:0,1,2,3` or `choice:0,1,2,3/weights:1,2,2,2`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum EmitterCount {
    /// The same count in every frame.
    Fixed(u32),
    /// Drawn per frame.
    Random(CountChoice),
}

/// A per-frame draw of a count from a list of counts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CountChoice {
    /// The possible counts (a count listed twice is twice as likely
    /// without weights).
    pub choice: Vec<u32>,
    /// Relative weight of each entry of `choice`; absent: all equal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub weights: Option<Vec<f64>>,
}

impl From<u32> for EmitterCount {
    fn from(count: u32) -> Self {
        EmitterCount::Fixed(count)
    }
}

impl EmitterCount {
    /// Draws one count. A fixed count consumes no randomness (so datasets
    /// with a fixed count are the same frames as before counts could be
    /// drawn); a choice consumes one uniform.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> u32 {
        match self {
            EmitterCount::Fixed(count) => *count,
            EmitterCount::Random(CountChoice { choice, weights }) => {
                let weight = |i: usize| weights.as_ref().map_or(1.0, |w| w[i]);
                let total: f64 = (0..choice.len()).map(weight).sum();
                let mut target = total * rng.random::<f64>();
                for (i, &count) in choice.iter().enumerate() {
                    target -= weight(i);
                    if target < 0.0 {
                        return count;
                    }
                }
                // Rounding left the target at the end: the last entry
                // with a weight.
                (0..choice.len())
                    .rev()
                    .find(|&i| weight(i) > 0.0)
                    .map_or(0, |i| choice[i])
            }
        }
    }

    /// The largest count a frame can have.
    pub fn max(&self) -> u32 {
        match self {
            EmitterCount::Fixed(count) => *count,
            EmitterCount::Random(CountChoice { choice, .. }) => {
                choice.iter().copied().max().unwrap_or(0)
            }
        }
    }

    /// Whether every frame is empty: a fixed 0, or a choice whose counts
    /// of positive weight are all 0.
    pub fn always_empty(&self) -> bool {
        match self {
            EmitterCount::Fixed(count) => *count == 0,
            EmitterCount::Random(CountChoice { choice, weights }) => {
                choice.iter().enumerate().all(|(i, &count)| {
                    count == 0
                        || weights
                            .as_ref()
                            .and_then(|w| w.get(i))
                            .is_some_and(|&w| w <= 0.0)
                })
            }
        }
    }

    /// The count of every frame, if it is fixed.
    pub fn fixed(&self) -> Option<u32> {
        match self {
            EmitterCount::Fixed(count) => Some(*count),
            EmitterCount::Random(_) => None,
        }
    }

    /// Checks the counts (at most `max_count`) and weights, naming the
    /// parameter `name` in the error.
    pub fn validate(&self, name: &str, max_count: u32) -> Result<(), FieldError> {
        let counts: &[u32] = match self {
            EmitterCount::Fixed(count) => std::slice::from_ref(count),
            EmitterCount::Random(CountChoice { choice, weights }) => {
                if choice.is_empty() {
                    return Err(FieldError::new(name, "choice must list at least one count"));
                }
                if let Some(weights) = weights {
                    if weights.len() != choice.len() {
                        return Err(FieldError::new(
                            name,
                            format!(
                                "weights must give one weight per count: {} counts, {} weights",
                                choice.len(),
                                weights.len()
                            ),
                        ));
                    }
                    for &w in weights {
                        require_non_negative(name, w)?;
                    }
                    if weights.iter().sum::<f64>() <= 0.0 {
                        return Err(FieldError::new(name, "weights must not all be 0"));
                    }
                    if !weights.iter().sum::<f64>().is_finite() {
                        return Err(FieldError::new(name, "weights must have a finite sum"));
                    }
                }
                choice
            }
        };
        if let Some(&count) = counts.iter().find(|&&c| c > max_count) {
            return Err(FieldError::new(
                name,
                format!("must be at most {max_count}, got {count}"),
            ));
        }
        Ok(())
    }
}

impl fmt::Display for EmitterCount {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let list = |values: &mut dyn Iterator<Item = String>| values.collect::<Vec<_>>().join(",");
        match self {
            EmitterCount::Fixed(count) => write!(f, "{count}"),
            EmitterCount::Random(CountChoice { choice, weights }) => {
                write!(f, "choice:{}", list(&mut choice.iter().map(u32::to_string)))?;
                if let Some(weights) = weights {
                    write!(
                        f,
                        "/weights:{}",
                        list(&mut weights.iter().map(f64::to_string))
                    )?;
                }
                Ok(())
            }
        }
    }
}

impl FromStr for EmitterCount {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        const FORMS: &str = "N, choice:N,N,... or choice:N,N,.../weights:W,W,...";
        let text = text.trim();
        let Some(rest) = text.strip_prefix("choice:") else {
            return text
                .parse::<u32>()
                .map(EmitterCount::Fixed)
                .map_err(|_| format!("expected {FORMS}, got {text:?}"));
        };
        let (counts, weights) = match rest.split_once('/') {
            None => (rest, None),
            Some((counts, weights)) => match weights.strip_prefix("weights:") {
                Some(weights) => (counts, Some(weights)),
                None => return Err(format!("expected {FORMS}, got {text:?}")),
            },
        };
        let choice = counts
            .split(',')
            .map(|c| {
                c.trim()
                    .parse::<u32>()
                    .map_err(|_| format!("not a whole number: {c:?} (expected {FORMS})"))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let weights = weights
            .map(|w| {
                w.split(',')
                    .map(|v| {
                        v.trim()
                            .parse::<f64>()
                            .map_err(|_| format!("not a number: {v:?} (expected {FORMS})"))
                    })
                    .collect::<Result<Vec<_>, _>>()
            })
            .transpose()?;
        Ok(EmitterCount::Random(CountChoice { choice, weights }))
    }
}

/// How recorded counts are drawn from the expected photon number.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum DetectorNoise {
    /// Shot noise only: count ~ Poisson(N) (the paper).
    #[default]
    Poisson,
    /// A photomultiplier tube with multiplicative excess noise.
    ///
    /// Each photoelectron is amplified by a random gain; the sum of `n`
    /// gamma-distributed gains of mean 1 is Gamma(n / (F² − 1), F² − 1), so the
    /// output has mean N and variance F²·N, the excess-noise factor model of
    /// Mortensen et al., Nat. Methods 7:377 (2010) for EMCCDs
    /// (F² = 2) and of the Hamamatsu PMT handbook (4th ed., §4.2.7) for
    /// dynode multipliers (F² ≈ 1.1–1.5 for GaAsP). Outputs are rounded to
    /// whole photon-equivalent counts.
    Pmt {
        /// The excess-noise factor F² (> 1; 1 would be plain Poisson).
        excess_noise_factor: f64,
    },
}

/// Everything that determines a simulated dataset except its seed and size.
///
/// Field names are the manifest's and the CLI flags' (with `-` for `_`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimParams {
    /// Frame height in pixels (rows).
    pub height: usize,
    /// Frame width in pixels (columns).
    pub width: usize,
    /// Pixel size `a` in µm.
    pub pixel_size_um: f64,
    /// Pixel dwell time δt in µs.
    pub dwell_us: f64,
    /// Line retrace time in ms (no photons recorded).
    pub retrace_ms: f64,
    /// Lateral standard deviation of the squared-intensity PSF, µm.
    pub sigma_xy_um: f64,
    /// Axial standard deviation of the squared-intensity PSF, µm.
    pub sigma_z_um: f64,
    /// N_bkg: expected background photons per pixel, fixed or drawn once
    /// per frame (the same for every pixel of the frame).
    pub background: Distribution,
    /// N_qd: total photons a QD in focus would give (PSF normalisation),
    /// fixed or drawn once per frame (the same for every QD of the frame).
    pub brightness: Distribution,
    /// D in µm²/s: fixed or per-frame distribution.
    pub diffusion_um2_s: Distribution,
    /// Start depth relative to focus in µm: fixed or per-frame distribution.
    pub z_start: Distribution,
    /// Start positions are uniform over the field shrunk by this many pixels
    /// on every side (negative: grown, QDs may start outside the field).
    pub margin_px: f64,
    /// PSF samples per pixel dwell (1 = the paper).
    pub substeps: u32,
    /// QDs per frame: fixed or drawn per frame.
    pub emitters: EmitterCount,
    /// Detector noise model.
    pub detector_noise: DetectorNoise,
    /// Lateral PSF cut-off in units of σ_xy: a sample farther than this from
    /// the beam contributes nothing. `null` evaluates the PSF everywhere.
    ///
    /// The error is bounded: a skipped sample would have added less than
    /// `N_qd / (2π σxy²) · exp(−c²/2) / √(2π σz²)` expected photons (the
    /// in-focus peak times `exp(−c²/2)`), see [`SimParams::cutoff_error_bound`].
    pub psf_cutoff_sigma: Option<f64>,
}

impl Default for SimParams {
    fn default() -> Self {
        Self {
            height: 24,
            width: 25,
            pixel_size_um: 0.07,
            dwell_us: 2.0,
            retrace_ms: 1.1,
            sigma_xy_um: 0.21,
            sigma_z_um: 1.36,
            background: Distribution::Fixed(8.4),
            brightness: Distribution::Fixed(7.0),
            diffusion_um2_s: Distribution::Fixed(1.0),
            z_start: Distribution::Fixed(0.0),
            margin_px: 0.0,
            substeps: 1,
            emitters: EmitterCount::Fixed(1),
            detector_noise: DetectorNoise::Poisson,
            psf_cutoff_sigma: Some(DEFAULT_PSF_CUTOFF_SIGMA),
        }
    }
}

/// Default lateral cut-off: at 6 σ the skipped PSF term is below
/// `exp(−18) ≈ 1.5e−8` of the in-focus peak (≈ 1e−7 photons for the paper's
/// microscope), far below one photon of shot noise.
pub(crate) const DEFAULT_PSF_CUTOFF_SIGMA: f64 = 6.0;

impl SimParams {
    /// Checks every parameter; an error names the parameter and says what
    /// is allowed.
    pub fn validate(&self) -> Result<(), FieldError> {
        crate::limits::check_frame_side("height", self.height)?;
        crate::limits::check_frame_side("width", self.width)?;
        require_positive("pixel_size_um", self.pixel_size_um)?;
        require_positive("dwell_us", self.dwell_us)?;
        require_non_negative("retrace_ms", self.retrace_ms)?;
        require_positive("sigma_xy_um", self.sigma_xy_um)?;
        require_positive("sigma_z_um", self.sigma_z_um)?;
        self.background.validate("background", true)?;
        self.brightness.validate("brightness", true)?;
        self.diffusion_um2_s.validate("diffusion_um2_s", true)?;
        self.check_motion()?;
        self.z_start.validate("z_start", false)?;
        // A negative margin starts QDs up to |margin| px outside the field
        // (recordings' QDs enter and leave it); at most one frame side out,
        // so every start is near the field.
        let side = self.width.min(self.height) as f64;
        require_finite("margin_px", self.margin_px)?;
        if self.margin_px < -side {
            return Err(FieldError::new(
                "margin_px",
                format!(
                    "{} starts QDs more than the frame's smaller side ({side} px) outside it; \
                     allowed: ≥ −{side}",
                    self.margin_px
                ),
            ));
        }
        if 2.0 * self.margin_px >= side {
            return Err(FieldError::new(
                "margin_px",
                format!(
                    "{} leaves no room for start positions in a {}×{} frame",
                    self.margin_px, self.height, self.width
                ),
            ));
        }
        if self.substeps == 0 || self.substeps > 1024 {
            return Err(FieldError::new(
                "substeps",
                format!("must be between 1 and 1024, got {}", self.substeps),
            ));
        }
        self.emitters.validate("emitters", MAX_EMITTERS)?;
        if let DetectorNoise::Pmt {
            excess_noise_factor,
        } = self.detector_noise
        {
            require_finite(
                "detector_noise.pmt.excess_noise_factor",
                excess_noise_factor,
            )?;
            if excess_noise_factor <= 1.0 {
                return Err(FieldError::new(
                    "detector_noise.pmt.excess_noise_factor",
                    format!("must be > 1 (1 is plain Poisson), got {excess_noise_factor}"),
                ));
            }
        }
        if let Some(cutoff) = self.psf_cutoff_sigma {
            require_positive("psf_cutoff_sigma", cutoff)?;
        }
        // Refused here, before any frame is simulated, rather than when the
        // first oversized count is drawn.
        let (_, background) = self.background.bounds();
        if background > MAX_EXPECTED_PHOTONS_PER_PIXEL {
            return Err(FieldError::new(
                "background",
                format!(
                    "{} photons per pixel cannot be recorded in a uint32 count with its noise (at most {MAX_EXPECTED_PHOTONS_PER_PIXEL:e})",
                    readable(background)
                ),
            ));
        }
        let brightest = match self.emitters.max() {
            0 => background,
            n => f64::from(n) * self.psf_peak() + background,
        };
        if brightest.is_nan() || brightest > MAX_EXPECTED_PHOTONS_PER_PIXEL {
            return Err(FieldError::new(
                "brightness",
                format!(
                    "{} emitter(s) of brightness {} with sigma_xy_um {} and sigma_z_um {} expect up to {} photons in one pixel, more than a uint32 count holds with its noise (at most {MAX_EXPECTED_PHOTONS_PER_PIXEL:e}); lower brightness or widen the PSF",
                    self.emitters.max(),
                    readable(self.brightness.bounds().1),
                    readable(self.sigma_xy_um),
                    readable(self.sigma_z_um),
                    readable(brightest)
                ),
            ));
        }
        Ok(())
    }

    /// Refuses a diffusion coefficient above [`MAX_DIFFUSION_UM2_S`], and
    /// one that moves a QD more than [`MAX_FRAME_TRAVEL_FIELDS`] fields in
    /// one frame (RMS, along one axis: √(2 D t) over the frame time t).
    fn check_motion(&self) -> Result<(), FieldError> {
        let (_, diffusion) = self.diffusion_um2_s.bounds();
        if diffusion > MAX_DIFFUSION_UM2_S {
            return Err(FieldError::new(
                "diffusion_um2_s",
                format!(
                    "must be at most {MAX_DIFFUSION_UM2_S} µm²/s (faster than any particle in a liquid), got {}",
                    readable(diffusion)
                ),
            ));
        }
        let field_um = self.height.max(self.width) as f64 * self.pixel_size_um;
        let travel_um = (2.0 * diffusion * self.frame_time_s()).sqrt();
        // NaN travel (an infinite frame time) is refused too.
        let within_travel_limit = travel_um <= MAX_FRAME_TRAVEL_FIELDS * field_um;
        if diffusion > 0.0 && !within_travel_limit {
            return Err(FieldError::new(
                "diffusion_um2_s",
                format!(
                    "a QD of D = {} µm²/s moves about {} µm during one frame of {} s, more than {MAX_FRAME_TRAVEL_FIELDS} times the {} µm field; lower the diffusion coefficient or the frame time (dwell_us, retrace_ms)",
                    readable(diffusion),
                    readable(travel_um),
                    readable(self.frame_time_s()),
                    readable(field_um)
                ),
            ));
        }
        Ok(())
    }

    /// The largest expected-photon error one PSF sample can suffer from the
    /// lateral cut-off: the in-focus peak (of the brightest frame) times
    /// `exp(−c²/2)`. Zero without a
    /// cut-off. A pixel's mean over `substeps` samples, summed over emitters,
    /// is off by at most `emitters` times this.
    pub fn cutoff_error_bound(&self) -> f64 {
        match self.psf_cutoff_sigma {
            None => 0.0,
            Some(cutoff) => self.psf_peak() * (-0.5 * cutoff * cutoff).exp(),
        }
    }

    /// Expected signal photons of a pixel whose beam sits exactly on an
    /// in-focus QD of the brightest frame: `N_qd / (2π σxy²) / √(2π σz²)`
    /// at the largest N_qd `brightness` can take.
    pub fn psf_peak(&self) -> f64 {
        self.psf_peak_at(self.brightness.bounds().1)
    }

    /// [`SimParams::psf_peak`] for a frame whose N_qd is `brightness`.
    pub fn psf_peak_at(&self, brightness: f64) -> f64 {
        let two_pi = 2.0 * std::f64::consts::PI;
        brightness
            / (two_pi * self.sigma_xy_um * self.sigma_xy_um)
            / (two_pi * self.sigma_z_um * self.sigma_z_um).sqrt()
    }

    /// Scan time of one frame in seconds: every dwell plus a retrace after
    /// every row but the last.
    pub fn frame_time_s(&self) -> f64 {
        let dwell = self.dwell_us * 1e-6;
        let retrace = self.retrace_ms * 1e-3;
        (self.height * self.width) as f64 * dwell + (self.height.saturating_sub(1)) as f64 * retrace
    }
}

/// Most QDs a frame can hold.
pub(crate) const MAX_EMITTERS: u32 = 10_000;

/// Largest diffusion coefficient accepted, µm²/s: beyond small molecules
/// in water (a few hundred µm²/s; a QD's is tens at most), so no particle
/// a two-photon microscope follows in a liquid diffuses faster.
pub(crate) const MAX_DIFFUSION_UM2_S: f64 = 1_000.0;

/// Largest RMS distance, in fields (the frame's larger side), a QD may
/// move along one axis during one frame: a QD that crosses the field many
/// times per frame leaves no image to localise, and a bound keeps every
/// simulated or inferred position finite and near the field.
pub(crate) const MAX_FRAME_TRAVEL_FIELDS: f64 = 100.0;

/// `value` as plain digits when short, in scientific notation when very
/// large or small (an error quoting 1e300 stays one readable line).
fn readable(value: f64) -> String {
    if value != 0.0 && !(1e-4..1e9).contains(&value.abs()) {
        format!("{value:e}")
    } else {
        format!("{value}")
    }
}

/// Largest expected photon number of one pixel (every emitter in focus on
/// it, plus the background) accepted: counts are stored as uint32
/// (at most 4.29e9), and this leaves room for the noise of the draw.
pub(crate) const MAX_EXPECTED_PHOTONS_PER_PIXEL: f64 = 1e9;

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    proptest! {
        #[test]
        fn a_fixed_value_draws_nothing_and_a_uniform_stays_in_its_bounds(
            value in 0.0..1e6f64,
            low in 0.0..1e6f64,
            width in 0.0..1e6f64,
            seed in any::<u64>(),
        ) {
            // Fixed: the value, and the stream is where it was.
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            prop_assert_eq!(Distribution::Fixed(value).sample(&mut rng), value);
            prop_assert_eq!(rng.random::<u64>(), ChaCha8Rng::seed_from_u64(seed).random::<u64>());
            // Uniform: within [low, high], the same for the same seed.
            let uniform = Distribution::Random(RandomDistribution::Uniform([low, low + width]));
            let draw = uniform.sample(&mut ChaCha8Rng::seed_from_u64(seed));
            prop_assert!(draw >= low && draw <= low + width, "{} not in [{}, {}]", draw, low, low + width);
            prop_assert_eq!(draw, uniform.sample(&mut ChaCha8Rng::seed_from_u64(seed)));
            prop_assert!(uniform.validate("brightness", true).is_ok());
        }
    }

    #[test]
    fn brightness_and_background_parse_print_and_refuse_bad_bounds() {
        for text in ["7", "7.5", "uniform:5,10", "uniform:0,0.5"] {
            let value: Distribution = text.parse().unwrap();
            assert_eq!(value.to_string(), text);
        }
        // A fixed value serialises as the bare number it always was, so
        // content keys do not move.
        assert_eq!(
            serde_json::to_string(&Distribution::Fixed(7.5)).unwrap(),
            "7.5"
        );
        let uniform: Distribution = serde_yaml::from_str("{uniform: [5, 10]}").unwrap();
        assert_eq!(uniform, "uniform:5,10".parse::<Distribution>().unwrap());
        let refused = |field: &str, text: &str| {
            let value: Distribution = text.parse().unwrap();
            let params = match field {
                "brightness" => SimParams {
                    brightness: value,
                    ..SimParams::default()
                },
                _ => SimParams {
                    background: value,
                    ..SimParams::default()
                },
            };
            let error = params.validate().unwrap_err();
            assert_eq!(error.field(), field, "{text}: {error}");
            error.to_string()
        };
        for field in ["brightness", "background"] {
            assert!(refused(field, "uniform:-1,5").contains("must be ≥ 0, got -1"));
            assert!(refused(field, "uniform:1,inf").contains("finite"));
            assert!(refused(field, "uniform:1,NaN").contains("finite"));
            assert!(refused(field, "uniform:5,1").contains("ordered"));
            assert!(refused(field, "-2").contains("must be ≥ 0"));
        }
        // The largest value bounds the brightest pixel.
        assert!(refused("background", "uniform:1,2e9").contains("uint32"));
        assert!(refused("brightness", "uniform:1,1e12").contains("uint32"));
        for bad in ["uniform:1", "uniform:a,2", "normal:1,2", ""] {
            assert!(bad.parse::<Distribution>().is_err(), "{bad}");
        }
    }

    #[test]
    fn diffusion_beyond_any_liquid_or_crossing_the_field_per_frame_is_refused() {
        let with = |diffusion: &str, retrace_ms: f64| SimParams {
            diffusion_um2_s: diffusion.parse().unwrap(),
            retrace_ms,
            ..SimParams::default()
        };
        for (diffusion, retrace_ms) in [
            ("1e300", 1.1),
            ("uniform:0,1e308", 1.1),
            ("1000.5", 1.1),
            ("uniform:0.75,1e4", 1.1),
            // Within the bound on D, but a frame that lasts for ever.
            ("1", 1e300),
            ("0.5", 1e12),
        ] {
            let error = with(diffusion, retrace_ms).validate().unwrap_err();
            assert_eq!(error.field(), "diffusion_um2_s", "{diffusion}: {error}");
        }
        for (diffusion, retrace_ms) in [("1000", 1.1), ("uniform:0,1000", 1.1), ("0", 1e300)] {
            assert!(
                with(diffusion, retrace_ms).validate().is_ok(),
                "{diffusion}"
            );
        }
    }

    #[test]
    fn only_fixed_photometry_makes_one_static_image() {
        let spread = SimParams {
            brightness: "uniform:5,10".parse().unwrap(),
            ..SimParams::default()
        };
        let error = spread
            .brightness
            .require_fixed("brightness", "the Cramér–Rao bound")
            .unwrap_err();
        assert_eq!(
            error.to_string(),
            "brightness: the Cramér–Rao bound needs one fixed number, got the distribution uniform:5,10"
        );
        assert_eq!(SimParams::default().brightness.fixed(), Some(7.0));
        // psf_peak is the brightest frame's.
        assert_eq!(spread.psf_peak(), spread.psf_peak_at(10.0));
    }
}
