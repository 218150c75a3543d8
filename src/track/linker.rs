//! The linker a front end asks for (`scanloc link`'s flags, the Python
//! package's `link` keywords), checked once for both: which settings go
//! with which linker, each bounded, and the linker's own checks. The
//! errors name the settings as the front end calls them ([`Naming`]).

use super::lap::{self, LapParams};
use super::trackpy::{self, TrackpyParams};
use super::{Detection, Linking};
use crate::error::input_error;
use crate::limits::{
    MAX_DIFFUSION_UM2_S, MAX_GATE_SIGMAS, MAX_SEARCH_RANGE, check_positive_at_most,
};

/// The gap lap closes unless told otherwise: blinks of up to 2 frames.
pub const DEFAULT_MAX_GAP: usize = 2;

/// Which linker.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkerKind {
    /// TrackPy 0.7's link.
    Trackpy,
    /// Global assignment frame to frame and gap closing.
    Lap,
}

impl LinkerKind {
    fn name(self) -> &'static str {
        match self {
            LinkerKind::Trackpy => "trackpy",
            LinkerKind::Lap => "lap",
        }
    }
}

/// How a front end names its settings in errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Naming {
    /// The command line's flags: `--search-range`, `--linker lap`.
    Flags,
    /// Python's keywords: `search_range`, `linker="lap"`.
    Keywords,
}

impl Naming {
    /// A setting (given as its keyword, `search_range`).
    fn setting(self, keyword: &str) -> String {
        match self {
            Naming::Flags => format!("--{}", keyword.replace('_', "-")),
            Naming::Keywords => keyword.to_string(),
        }
    }

    /// The choice of `linker`.
    fn linker(self, linker: LinkerKind) -> String {
        match self {
            Naming::Flags => format!("--linker {}", linker.name()),
            Naming::Keywords => format!("linker=\"{}\"", linker.name()),
        }
    }
}

/// The settings a front end was given for linking (`None`: not given).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LinkerRequest {
    pub linker: LinkerKind,
    pub search_range: Option<f64>,
    /// trackpy: frames a particle may vanish for.
    pub memory: Option<usize>,
    /// lap: the longest gap closed.
    pub max_gap: Option<usize>,
    /// lap: D (µm²/s) giving the expected step, with the frame time and
    /// the pixel size.
    pub diffusion: Option<f64>,
    pub frame_time_ms: Option<f64>,
    pub pixel_size_um: Option<f64>,
    /// lap: the gate, σ.
    pub gate: Option<f64>,
}

/// A linker with its checked parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Linker {
    Trackpy(TrackpyParams),
    Lap(LapParams),
}

impl LinkerRequest {
    /// The linker asked for, or an input error naming the setting as
    /// `naming` does: a setting of the other linker, a missing search
    /// range, a value out of its bounds.
    pub fn configure(&self, naming: Naming) -> anyhow::Result<Linker> {
        let name = |keyword: &str| naming.setting(keyword);
        let bounded = |keyword: &str, value: f64, max: f64| -> anyhow::Result<f64> {
            Ok(check_positive_at_most(&name(keyword), value, max)?)
        };
        match self.linker {
            LinkerKind::Trackpy => {
                if self.diffusion.is_some() || self.max_gap.is_some() || self.gate.is_some() {
                    return Err(input_error(format!(
                        "{}, {} and {} are for {} (trackpy uses {} and {})",
                        name("diffusion"),
                        name("max_gap"),
                        name("gate"),
                        naming.linker(LinkerKind::Lap),
                        name("search_range"),
                        name("memory")
                    )));
                }
                let Some(search_range) = self.search_range else {
                    return Err(input_error(format!(
                        "{}: needed by {}",
                        name("search_range"),
                        naming.linker(LinkerKind::Trackpy)
                    )));
                };
                let params = TrackpyParams {
                    search_range: bounded("search_range", search_range, MAX_SEARCH_RANGE)?,
                    memory: self.memory.unwrap_or(0),
                };
                params.validate()?;
                Ok(Linker::Trackpy(params))
            }
            LinkerKind::Lap => Ok(Linker::Lap(self.lap(naming)?)),
        }
    }

    fn lap(&self, naming: Naming) -> anyhow::Result<LapParams> {
        let name = |keyword: &str| naming.setting(keyword);
        let bounded = |keyword: &str, value: f64, max: f64| -> anyhow::Result<f64> {
            Ok(check_positive_at_most(&name(keyword), value, max)?)
        };
        if self.memory.is_some_and(|memory| memory > 0) {
            return Err(input_error(format!(
                "{} is for {} (lap closes gaps up to {})",
                name("memory"),
                naming.linker(LinkerKind::Trackpy),
                name("max_gap")
            )));
        }
        let max_gap = self.max_gap.unwrap_or(DEFAULT_MAX_GAP);
        let mut params = match (self.diffusion, self.search_range) {
            (Some(d), _) => LapParams::from_diffusion(
                bounded("diffusion", d, MAX_DIFFUSION_UM2_S)?,
                bounded(
                    "frame_time_ms",
                    self.frame_time_ms.unwrap_or(f64::NAN),
                    f64::MAX,
                )?,
                bounded(
                    "pixel_size_um",
                    self.pixel_size_um.unwrap_or(f64::NAN),
                    f64::MAX,
                )?,
                max_gap,
            ),
            (None, Some(r)) => {
                LapParams::from_search_range(bounded("search_range", r, MAX_SEARCH_RANGE)?, max_gap)
            }
            (None, None) => {
                return Err(input_error(format!(
                    "{} needs {} or {} (with {} and {})",
                    naming.linker(LinkerKind::Lap),
                    name("search_range"),
                    name("diffusion"),
                    name("frame_time_ms"),
                    name("pixel_size_um")
                )));
            }
        };
        if let Some(gate) = self.gate {
            params.gate_sigmas = bounded("gate", gate, MAX_GATE_SIGMAS)?;
        }
        params.validate()?;
        Ok(params)
    }
}

impl Linker {
    /// Links `detections` (any order).
    pub fn link(&self, detections: &[Detection]) -> anyhow::Result<Linking> {
        match self {
            Linker::Trackpy(params) => trackpy::link(detections, params),
            Linker::Lap(params) => lap::link(detections, params),
        }
    }

    /// The linker and its settings, in a few words.
    pub fn describe(&self) -> String {
        match self {
            Linker::Trackpy(p) => format!(
                "trackpy, search range {} px, memory {}",
                p.search_range, p.memory
            ),
            Linker::Lap(p) => format!(
                "lap, step variance {:.4} px², gate {} σ, max gap {}",
                p.step_variance, p.gate_sigmas, p.max_gap
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(linker: LinkerKind) -> LinkerRequest {
        LinkerRequest {
            linker,
            search_range: None,
            memory: None,
            max_gap: None,
            diffusion: None,
            frame_time_ms: None,
            pixel_size_um: None,
            gate: None,
        }
    }

    #[test]
    fn errors_name_the_settings_as_the_front_end_does() {
        let lap = LinkerRequest {
            memory: Some(2),
            ..request(LinkerKind::Lap)
        };
        let message = |r: &LinkerRequest, naming| format!("{:#}", r.configure(naming).unwrap_err());
        assert_eq!(
            message(&lap, Naming::Flags),
            "--memory is for --linker trackpy (lap closes gaps up to --max-gap)"
        );
        assert_eq!(
            message(&lap, Naming::Keywords),
            "memory is for linker=\"trackpy\" (lap closes gaps up to max_gap)"
        );
        let trackpy = request(LinkerKind::Trackpy);
        assert_eq!(
            message(&trackpy, Naming::Flags),
            "--search-range: needed by --linker trackpy"
        );
        let negative = LinkerRequest {
            search_range: Some(-1.0),
            ..trackpy
        };
        assert!(message(&negative, Naming::Keywords).starts_with("search_range: must be"));
    }

    #[test]
    fn each_linker_gets_its_settings() {
        let trackpy = LinkerRequest {
            search_range: Some(4.0),
            memory: Some(1),
            ..request(LinkerKind::Trackpy)
        };
        assert_eq!(
            trackpy.configure(Naming::Flags).unwrap(),
            Linker::Trackpy(TrackpyParams {
                search_range: 4.0,
                memory: 1
            })
        );
        let lap = LinkerRequest {
            search_range: Some(3.0),
            memory: Some(0),
            gate: Some(2.5),
            ..request(LinkerKind::Lap)
        };
        let Linker::Lap(params) = lap.configure(Naming::Keywords).unwrap() else {
            panic!("not lap");
        };
        assert_eq!(params.max_gap, DEFAULT_MAX_GAP);
        assert_eq!(params.gate_sigmas, 2.5);
    }
}
