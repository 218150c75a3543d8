//! The microscope on the command line: one flag per field of a manifest's
//! `microscope` section (the same names, with `-` for `_`, and the same
//! units), and `--microscope FILE.yaml` to take the section from a file.
//!
//! Flattened into `simulate`, `train`, `locate` (for `--method
//! likelihood`) and the benches that simulate, so each flag is spelt,
//! documented and converted once. Each command's defaults are the paper's
//! microscope ([`SimParams::default`]) unless it changes one with
//! `mut_arg` (`train`: margin 4, D uniform:0.75,1.75), so `--help` shows
//! its own.
//!
//! The precedence, field by field: a flag given on the command line, else
//! the file's field, else the command's default. Knowing which flags were
//! given needs clap's `ArgMatches`, which the derived parser hides, so
//! [`MicroscopeArgs`] wraps the derived [`MicroscopeFlags`] and records
//! the flags' value sources itself.

use std::collections::BTreeSet;
use std::path::PathBuf;

use crate::error::input_error;
use crate::sim::recording::MAX_DEAD_TIME_MS;
use crate::sim::{DetectorNoise, Distribution, EmitterCount, SimParams};
use crate::track::diffusion::ScanGeometry;
use clap::parser::ValueSource;
use clap::{ArgMatches, Args, Command, FromArgMatches};

/// Every microscope field as a flag. Per-frame parameters are a number or
/// `uniform:LOW,HIGH` (drawn once per frame, docs/simulator.md); for the
/// likelihood detector a distribution is a prior it marginalises.
#[derive(Debug, Clone, Args)]
pub(super) struct MicroscopeFlags {
    /// Take the microscope from the `microscope:` section of this
    /// manifest-style YAML file (other sections are ignored): the flags
    /// below override its fields, and fields it leaves out keep the
    /// command's defaults.
    #[arg(long = "microscope", value_name = "FILE.yaml")]
    pub file: Option<PathBuf>,
    #[command(flatten)]
    pub scan: ScanFlags,
    /// Axial PSF standard deviation in µm.
    #[arg(long, default_value_t = 1.36)]
    pub sigma_z_um: f64,
    /// Diffusion coefficient D in µm²/s (the manifest's diffusion_um2_s): a
    /// number or uniform:LOW,HIGH (per frame).
    #[arg(long, visible_alias = "diffusion-um2-s", default_value = "1.0")]
    pub diffusion: Distribution,
    /// N_qd, photons of an in-focus QD (PSF normalisation): a number or
    /// uniform:LOW,HIGH (per frame).
    #[arg(long, default_value = "7")]
    pub brightness: Distribution,
    /// N_bkg, expected background photons per pixel: a number or
    /// uniform:LOW,HIGH (per frame).
    #[arg(long, default_value = "8.4")]
    pub background: Distribution,
    /// Start depth relative to focus in µm: a number or uniform:LOW,HIGH
    /// (per frame).
    #[arg(long, default_value = "0")]
    pub z_start: Distribution,
    /// Start positions are uniform over the field shrunk by this many pixels
    /// (negative: grown, so QDs start up to that far outside the field;
    /// write it as --margin-px=-3).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub margin_px: f64,
    /// PSF samples per pixel dwell (1 = the paper).
    #[arg(long, default_value_t = 1)]
    pub substeps: u32,
    /// QDs per frame: N, or drawn per frame with choice:N,N,... (optionally
    /// /weights:W,W,...), e.g. choice:0,1,2,3 for scenes of no, one or
    /// several QDs.
    #[arg(long, default_value = "1")]
    pub emitters: EmitterCount,
    /// Detector noise: `poisson`, or `pmt:F2` for a PMT with excess-noise factor F² > 1.
    #[arg(long, default_value = "poisson", value_parser = parse_detector_noise)]
    pub detector_noise: DetectorNoise,
    /// Lateral PSF cut-off in σ_xy (samples farther from the beam add nothing),
    /// or `none` to evaluate the PSF everywhere.
    #[arg(long, default_value = "6", value_parser = parse_cutoff)]
    pub psf_cutoff_sigma: Cutoff,
}

/// The scan geometry's flags, one group shared by the microscope's flags
/// and [`ScanGeometryArgs`]: what decides when the beam sees each pixel,
/// and the PSF's lateral width.
#[derive(Debug, Clone, Args)]
pub struct ScanFlags {
    /// Frame height in pixels (rows).
    #[arg(long, default_value_t = 24)]
    pub height: usize,
    /// Frame width in pixels (columns).
    #[arg(long, default_value_t = 25)]
    pub width: usize,
    /// Pixel size in µm.
    #[arg(long, default_value_t = 0.07)]
    pub pixel_size_um: f64,
    /// Pixel dwell time in µs.
    #[arg(long, default_value_t = 2.0)]
    pub dwell_us: f64,
    /// Line retrace time in ms.
    #[arg(long, default_value_t = 1.1)]
    pub retrace_ms: f64,
    /// Lateral PSF standard deviation in µm.
    #[arg(long, default_value_t = 0.21)]
    pub sigma_xy_um: f64,
}

/// A microscope field a flag sets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Field {
    Height,
    Width,
    PixelSizeUm,
    DwellUs,
    RetraceMs,
    SigmaXyUm,
    SigmaZUm,
    Diffusion,
    Brightness,
    Background,
    ZStart,
    MarginPx,
    Substeps,
    Emitters,
    DetectorNoise,
    PsfCutoffSigma,
}

impl Field {
    /// Every field, in the flags' order.
    const ALL: [Field; 16] = [
        Field::Height,
        Field::Width,
        Field::PixelSizeUm,
        Field::DwellUs,
        Field::RetraceMs,
        Field::SigmaXyUm,
        Field::SigmaZUm,
        Field::Diffusion,
        Field::Brightness,
        Field::Background,
        Field::ZStart,
        Field::MarginPx,
        Field::Substeps,
        Field::Emitters,
        Field::DetectorNoise,
        Field::PsfCutoffSigma,
    ];

    /// The flag's clap id (its field name in [`MicroscopeFlags`] or
    /// [`ScanFlags`]), by which clap says whether it was given.
    fn id(self) -> &'static str {
        match self {
            Field::Diffusion => "diffusion",
            other => other.manifest_name(),
        }
    }

    /// The name of the manifest's `microscope` field it sets.
    fn manifest_name(self) -> &'static str {
        match self {
            Field::Height => "height",
            Field::Width => "width",
            Field::PixelSizeUm => "pixel_size_um",
            Field::DwellUs => "dwell_us",
            Field::RetraceMs => "retrace_ms",
            Field::SigmaXyUm => "sigma_xy_um",
            Field::SigmaZUm => "sigma_z_um",
            Field::Diffusion => "diffusion_um2_s",
            Field::Brightness => "brightness",
            Field::Background => "background",
            Field::ZStart => "z_start",
            Field::MarginPx => "margin_px",
            Field::Substeps => "substeps",
            Field::Emitters => "emitters",
            Field::DetectorNoise => "detector_noise",
            Field::PsfCutoffSigma => "psf_cutoff_sigma",
        }
    }
}

impl MicroscopeFlags {
    /// Sets `field` of `params` to this flag's value: the one conversion of
    /// a flag into a simulator parameter.
    fn set(&self, params: &mut SimParams, field: Field) {
        let scan = &self.scan;
        match field {
            Field::Height => params.height = scan.height,
            Field::Width => params.width = scan.width,
            Field::PixelSizeUm => params.pixel_size_um = scan.pixel_size_um,
            Field::DwellUs => params.dwell_us = scan.dwell_us,
            Field::RetraceMs => params.retrace_ms = scan.retrace_ms,
            Field::SigmaXyUm => params.sigma_xy_um = scan.sigma_xy_um,
            Field::SigmaZUm => params.sigma_z_um = self.sigma_z_um,
            Field::Diffusion => params.diffusion_um2_s = self.diffusion,
            Field::Brightness => params.brightness = self.brightness,
            Field::Background => params.background = self.background,
            Field::ZStart => params.z_start = self.z_start,
            Field::MarginPx => params.margin_px = self.margin_px,
            Field::Substeps => params.substeps = self.substeps,
            Field::Emitters => params.emitters = self.emitters.clone(),
            Field::DetectorNoise => params.detector_noise = self.detector_noise,
            Field::PsfCutoffSigma => params.psf_cutoff_sigma = self.psf_cutoff_sigma,
        }
    }
}

pub(super) fn parse_detector_noise(text: &str) -> Result<DetectorNoise, String> {
    match text.trim() {
        "poisson" => Ok(DetectorNoise::Poisson),
        other => match other.strip_prefix("pmt:") {
            Some(factor) => factor
                .parse::<f64>()
                .map(|excess_noise_factor| DetectorNoise::Pmt {
                    excess_noise_factor,
                })
                .map_err(|_| format!("expected pmt:F2 with a number F2, got {other:?}")),
            None => Err(format!("expected `poisson` or `pmt:F2`, got {other:?}")),
        },
    }
}

/// An optional cut-off; the alias keeps clap from treating the flag itself
/// as optional (it always has a value, possibly `none`).
type Cutoff = Option<f64>;

fn parse_cutoff(text: &str) -> Result<Cutoff, String> {
    match text.trim() {
        "none" => Ok(None),
        number => number
            .parse::<f64>()
            .map(Some)
            .map_err(|_| format!("expected a number of σ or `none`, got {number:?}")),
    }
}

/// The microscope flags with the ids of those given on the command line
/// (flatten it into a command's arguments).
#[derive(Debug, Clone)]
pub struct MicroscopeArgs {
    flags: MicroscopeFlags,
    /// The fields whose flags were given on the command line.
    given: Vec<Field>,
}

/// A resolved microscope: the simulator parameters, and the manifest names
/// of the fields the user stated (by a flag or in the file), as against
/// those left at the command's defaults.
#[derive(Debug, Clone)]
pub struct Microscope {
    pub params: SimParams,
    pub stated: BTreeSet<String>,
}

impl MicroscopeArgs {
    /// The microscope these flags describe (not yet validated: the
    /// command checks it with [`SimParams::validate`] once it is complete).
    pub fn params(&self) -> anyhow::Result<SimParams> {
        Ok(self.resolve()?.params)
    }

    /// The microscope with the fields the user stated: the command's
    /// defaults, then the `--microscope` file's section, then the flags
    /// given.
    pub fn resolve(&self) -> anyhow::Result<Microscope> {
        let mut params = SimParams::default();
        for field in Field::ALL {
            self.flags.set(&mut params, field);
        }
        let mut stated = BTreeSet::new();
        if let Some(file) = &self.flags.file {
            let (from_file, fields) = crate::manifest::load_microscope(file, &params)?;
            params = from_file;
            stated.extend(fields);
        }
        for &field in &self.given {
            self.flags.set(&mut params, field);
            stated.insert(field.manifest_name().to_string());
        }
        Ok(Microscope { params, stated })
    }
}

impl Microscope {
    /// The microscope at the size of frames of `height` × `width` pixels
    /// (a detector's input): a stated height or width must be theirs.
    pub fn at_frame_size(mut self, height: usize, width: usize) -> anyhow::Result<SimParams> {
        for (field, stated, actual) in [
            ("height", self.params.height, height),
            ("width", self.params.width, width),
        ] {
            if self.stated.contains(field) && stated != actual {
                return Err(input_error(format!(
                    "{field}: the microscope's frames have {stated} pixels, those of --input {actual}"
                )));
            }
        }
        self.params.height = height;
        self.params.width = width;
        Ok(self.params)
    }
}

impl FromArgMatches for MicroscopeArgs {
    fn from_arg_matches(matches: &ArgMatches) -> Result<Self, clap::Error> {
        let flags = MicroscopeFlags::from_arg_matches(matches)?;
        let given = Field::ALL
            .into_iter()
            .filter(|field| matches.value_source(field.id()) == Some(ValueSource::CommandLine))
            .collect();
        Ok(Self { flags, given })
    }

    fn update_from_arg_matches(&mut self, matches: &ArgMatches) -> Result<(), clap::Error> {
        *self = Self::from_arg_matches(matches)?;
        Ok(())
    }
}

impl Args for MicroscopeArgs {
    fn augment_args(command: Command) -> Command {
        MicroscopeFlags::augment_args(command)
    }

    fn augment_args_for_update(command: Command) -> Command {
        MicroscopeFlags::augment_args_for_update(command)
    }
}

/// The microscope of a bench's `flags`, checked, with `frames` of its size
/// (the flag `frames_flag`) checked against the limits a manifest's
/// datasets have.
pub(super) fn bench_microscope(
    flags: &MicroscopeArgs,
    frames_flag: &str,
    frames: usize,
) -> anyhow::Result<SimParams> {
    let params = flags.params()?;
    params
        .validate()
        .map_err(|e| crate::error::input_error(format!("invalid simulation parameter: {e}")))?;
    crate::limits::check_dataset_size(frames_flag, frames, params.height, params.width)?;
    Ok(params)
}

/// Checks a frame count flag of paper-sized frames against the limits a
/// manifest's datasets have.
pub(super) fn paper_sized(flag: &str, frames: usize) -> anyhow::Result<()> {
    let paper = SimParams::default();
    Ok(crate::limits::check_dataset_size(
        flag,
        frames,
        paper.height,
        paper.width,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Debug, Parser)]
    struct Probe {
        #[command(flatten)]
        microscope: MicroscopeArgs,
    }

    #[test]
    fn the_defaults_are_the_papers_microscope() {
        let probe = Probe::try_parse_from(["probe"]).unwrap();
        assert_eq!(probe.microscope.params().unwrap(), SimParams::default());
        assert!(probe.microscope.resolve().unwrap().stated.is_empty());
    }

    #[test]
    fn every_flag_sets_its_field() {
        let probe = Probe::try_parse_from([
            "probe",
            "--height=30",
            "--width=40",
            "--pixel-size-um=0.1",
            "--dwell-us=5",
            "--retrace-ms=0.5",
            "--sigma-xy-um=0.3",
            "--sigma-z-um=2",
            "--diffusion-um2-s=uniform:1,2",
            "--brightness=9",
            "--background=3",
            "--z-start=0.5",
            "--margin-px=2",
            "--substeps=4",
            "--emitters=choice:0,1",
            "--detector-noise=pmt:1.5",
            "--psf-cutoff-sigma=none",
        ])
        .unwrap();
        let microscope = probe.microscope.resolve().unwrap();
        assert_eq!(microscope.stated.len(), Field::ALL.len());
        let params = microscope.params;
        let paper = SimParams::default();
        // Every field differs from the paper's.
        let differing = [
            params.height != paper.height,
            params.width != paper.width,
            params.pixel_size_um != paper.pixel_size_um,
            params.dwell_us != paper.dwell_us,
            params.retrace_ms != paper.retrace_ms,
            params.sigma_xy_um != paper.sigma_xy_um,
            params.sigma_z_um != paper.sigma_z_um,
            params.diffusion_um2_s != paper.diffusion_um2_s,
            params.brightness != paper.brightness,
            params.background != paper.background,
            params.z_start != paper.z_start,
            params.margin_px != paper.margin_px,
            params.substeps != paper.substeps,
            params.emitters != paper.emitters,
            params.detector_noise != paper.detector_noise,
            params.psf_cutoff_sigma != paper.psf_cutoff_sigma,
        ];
        assert!(differing.iter().all(|&d| d), "{differing:?}");
        assert_eq!(params.height, 30);
        assert_eq!(params.psf_cutoff_sigma, None);
    }
}

/// The scan geometry of a recording, the flags `simulate-recording` and
/// `diffusion` share (the names and units of a manifest's `microscope`
/// section, plus the dead time between frames): what decides when the beam
/// sees each pixel and how long a localisation's exposure lasts.
#[derive(Debug, Clone, Args)]
pub struct ScanGeometryArgs {
    #[command(flatten)]
    pub flags: ScanFlags,
    /// Dead time between the flyback after a frame and the next frame, ms
    /// (at most 60,000).
    #[arg(long, default_value_t = 0.0)]
    pub dead_time_ms: f64,
}

impl ScanGeometryArgs {
    /// The geometry, each flag checked (exit 2 naming the flag).
    pub fn geometry(&self) -> anyhow::Result<ScanGeometry> {
        // Upper ends far beyond any microscope, so that positions, times
        // and their squares stay well inside f64 (1e300 px would make every
        // estimate NaN).
        let checks = [
            ("--pixel-size-um", self.flags.pixel_size_um, false, 1e3),
            ("--dwell-us", self.flags.dwell_us, false, 1e6),
            ("--retrace-ms", self.flags.retrace_ms, true, 1e6),
            ("--dead-time-ms", self.dead_time_ms, true, MAX_DEAD_TIME_MS),
            ("--sigma-xy-um", self.flags.sigma_xy_um, false, 1e3),
        ];
        for (name, value, zero_ok, max) in checks {
            if !value.is_finite() || value < 0.0 || (value == 0.0 && !zero_ok) || value > max {
                return Err(input_error(format!(
                    "{name}: must be {} and at most {max}, got {value}",
                    if zero_ok { "≥ 0" } else { "> 0" }
                )));
            }
        }
        let max_side = crate::limits::MAX_FRAME_SIDE;
        if !(1..=max_side).contains(&self.flags.height)
            || !(1..=max_side).contains(&self.flags.width)
        {
            return Err(input_error(format!(
                "--height, --width: must be 1 to {max_side}, got {} × {}",
                self.flags.height, self.flags.width
            )));
        }
        Ok(ScanGeometry {
            height: self.flags.height,
            width: self.flags.width,
            pixel_size_um: self.flags.pixel_size_um,
            dwell_us: self.flags.dwell_us,
            retrace_ms: self.flags.retrace_ms,
            dead_time_ms: self.dead_time_ms,
            sigma_xy_um: self.flags.sigma_xy_um,
        })
    }
}
