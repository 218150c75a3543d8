//! `scanloc fit-microscope`: the microscope a recording shows (background,
//! brightness, excess noise, σxy, each with a standard error), written as
//! the YAML that `--microscope FILE.yaml` reads (docs/fit-microscope.md).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::fit::{FittedMicroscope, KnownTiming, fit_microscope};
use crate::io::{self, AcquisitionMetadata, MetadataSource, StackSelection};
use crate::sim::{DetectorNoise, SimParams};
use crate::types::FrameStack;
use clap::Args;

/// Fit the microscope to a recording: background photons per pixel, QD
/// brightness N_qd, the detector's excess noise and the lateral PSF width
/// σxy, each with a standard error, from the recording's own photon
/// statistics (docs/fit-microscope.md).
///
/// The scan's timing comes from the flags or, where they are left out,
/// from the file's metadata (an ImageJ hyperstack's pixel size, ScanImage's
/// line period, fill fraction and pixels per line). The result is printed
/// and, with --out, written as a `microscope:` section for
/// `--microscope FILE.yaml`.
#[derive(Debug, Args)]
pub(super) struct FitMicroscopeArgs {
    /// The recording: a multi-page TIFF (8/16/32-bit, ImageJ hyperstack,
    /// ScanImage, BigTIFF) or a .npy (n, H, W) stack of photon counts.
    recording: PathBuf,
    /// Pixel size in µm (default: the file's, if it states one).
    #[arg(long)]
    pixel_size_um: Option<f64>,
    /// Pixel dwell time in µs (default: the file's, if it states one).
    #[arg(long)]
    dwell_us: Option<f64>,
    /// Line retrace time in ms (default: the file's, if it states one).
    #[arg(long)]
    retrace_ms: Option<f64>,
    /// Axial PSF standard deviation in µm: N_qd's normalisation needs it
    /// and a recording cannot tell it apart from N_qd.
    #[arg(long, default_value_t = 1.36)]
    sigma_z_um: f64,
    /// The channel of a multi-channel stack to read (0-based).
    #[arg(long)]
    channel: Option<usize>,
    /// The z slice of a hyperstack with several slices to read (0-based).
    #[arg(long)]
    slice: Option<usize>,
    /// Write the fitted microscope here (a `microscope:` section, as
    /// `--microscope FILE.yaml` reads it).
    #[arg(long, value_name = "FILE.yaml")]
    out: Option<PathBuf>,
}

/// The timing of the scan: from a flag, else the file's metadata.
fn timing_value(
    flag: &str,
    given: Option<f64>,
    stated: Option<f64>,
    recording: &str,
    zero_ok: bool,
    max: f64,
) -> anyhow::Result<f64> {
    let value = given.or(stated).ok_or_else(|| {
        input_error(format!(
            "{flag}: not given, and {recording} does not state it; give it on the command line"
        ))
    })?;
    if !value.is_finite() || value < 0.0 || (value == 0.0 && !zero_ok) || value > max {
        return Err(input_error(format!(
            "{flag}: {value} is not a possible value (must be {} and at most {max})",
            if zero_ok { "≥ 0" } else { "> 0" }
        )));
    }
    Ok(value)
}

/// Refuses timing that disagrees with the frames or the file.
fn check_acquisition(
    recording: &str,
    metadata: &AcquisitionMetadata,
    height: usize,
    width: usize,
    dwell_us: f64,
    retrace_ms: f64,
) -> anyhow::Result<()> {
    if metadata.bidirectional == Some(true) {
        return Err(input_error(format!(
            "{recording}: SI.hScan2D.bidirectional: lines scanned in both directions; the scan model scans every line left to right"
        )));
    }
    for (field, stated, actual) in [
        ("lines per frame", metadata.lines_per_frame, height),
        ("pixels per line", metadata.pixels_per_line, width),
    ] {
        if let Some(stated) = stated
            && stated != actual
        {
            return Err(input_error(format!(
                "{recording}: {field}: the file's metadata says {stated}, its frames have {actual}"
            )));
        }
    }
    let line_ms = width as f64 * dwell_us * 1e-3 + retrace_ms;
    let scan_ms = height as f64 * line_ms - retrace_ms;
    if let Some(period) = metadata.frame_period_ms
        && scan_ms > period * 1.001
    {
        return Err(input_error(format!(
            "{recording}: frame period: scanning {height} lines of {width} pixels at {dwell_us} µs dwell and {retrace_ms} ms retrace takes {scan_ms:.3} ms, longer than the file's frame period of {period:.3} ms"
        )));
    }
    Ok(())
}

/// The detector model the variance-to-mean ratio points to; counts that
/// are not photons are refused.
fn detector_noise(recording: &str, fitted: &FittedMicroscope) -> anyhow::Result<DetectorNoise> {
    let ratio = fitted.excess_noise_factor;
    let margin = 3.0 * ratio.standard_error.max(0.0) + 0.02;
    if ratio.value < 1.0 - margin {
        return Err(input_error(format!(
            "{recording}: the background's variance is {:.3} × its mean (below Poisson's 1): these counts are not photon counts (scaled, offset or filtered); convert them to photons first",
            ratio.value
        )));
    }
    if ratio.value > 4.0 {
        return Err(input_error(format!(
            "{recording}: the background's variance is {:.3} × its mean: counts with a gain (not photons) or an offset; convert them to photons first",
            ratio.value
        )));
    }
    Ok(if ratio.value > 1.0 + margin {
        DetectorNoise::Pmt {
            excess_noise_factor: ratio.value,
        }
    } else {
        DetectorNoise::Poisson
    })
}

/// The `microscope:` YAML of the fitted microscope, its uncertainties as
/// comments.
fn microscope_yaml(
    recording: &str,
    params: &SimParams,
    fitted: &FittedMicroscope,
) -> anyhow::Result<String> {
    let mut section = serde_yaml::Mapping::new();
    let mut put = |key: &str, value: serde_yaml::Value| {
        section.insert(serde_yaml::Value::from(key), value);
    };
    put("height", params.height.into());
    put("width", params.width.into());
    put("pixel_size_um", params.pixel_size_um.into());
    put("dwell_us", params.dwell_us.into());
    put("retrace_ms", params.retrace_ms.into());
    put("sigma_xy_um", round(params.sigma_xy_um, 4).into());
    put("sigma_z_um", params.sigma_z_um.into());
    put("background", round(fitted.background.value, 4).into());
    put("brightness", round(fitted.brightness.value, 4).into());
    let noise = match params.detector_noise {
        DetectorNoise::Poisson => serde_yaml::Value::from("poisson"),
        DetectorNoise::Pmt {
            excess_noise_factor,
        } => {
            let mut factor = serde_yaml::Mapping::new();
            factor.insert(
                "excess_noise_factor".into(),
                round(excess_noise_factor, 4).into(),
            );
            let mut pmt = serde_yaml::Mapping::new();
            pmt.insert("pmt".into(), serde_yaml::Value::Mapping(factor));
            serde_yaml::Value::Mapping(pmt)
        }
    };
    put("detector_noise", noise);
    let mut document = serde_yaml::Mapping::new();
    document.insert("microscope".into(), serde_yaml::Value::Mapping(section));
    let body = serde_yaml::to_string(&document)?;
    let one_line = recording.replace(['\n', '\r'], " ");
    Ok(format!(
        "# Fitted by scanloc fit-microscope from {one_line} ({} frames, {} spots).\n\
         # Standard errors: background ±{:.3}, brightness ±{:.3}, sigma_xy_um ±{:.4}, variance/mean {:.3} ±{:.3}.\n\
         # brightness: {BRIGHTNESS_CAVEAT}.\n\
         # diffusion_um2_s is not fitted: give it (or let the tracker estimate it).\n{body}",
        fitted.frames_used,
        fitted.spots,
        fitted.background.standard_error,
        fitted.brightness.standard_error,
        fitted.sigma_xy_um.standard_error,
        fitted.excess_noise_factor.value,
        fitted.excess_noise_factor.standard_error,
    ))
}

/// What the brightness estimate is worth today (docs/fit-microscope.md,
/// "Accuracy"): said wherever it is printed or written.
const BRIGHTNESS_CAVEAT: &str = "NOT VALIDATED: off by -45 % to +60 % on simulated microscopes, its standard error too small; measure N_qd independently where it matters";

fn round(value: f64, digits: i32) -> f64 {
    let scale = 10f64.powi(digits);
    (value * scale).round() / scale
}

pub(super) fn run(args: FitMicroscopeArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let name = args.recording.display().to_string();
    // The destination is checked (and claimed) before the long read, so a
    // bad --out is refused at once.
    if let Some(out) = &args.out {
        io::refuse_shared_paths(&[("RECORDING", &args.recording)], &[("--out", out)])?;
    }
    let pending = args
        .out
        .as_deref()
        .map(io::PendingFile::create)
        .transpose()?;
    let selection = StackSelection {
        channel: args.channel,
        slice: args.slice,
    };
    let file = io::read_recording_file(&args.recording, &selection)?;
    let metadata = file.metadata;
    let frames = file
        .frames
        .into_counts()
        .map_err(|e| input_error(format!("{name}: {e:#}")))?;
    let timing = known_timing(&args, &name, &metadata, &frames)?;
    let fitted =
        fit_microscope(&frames, &timing).map_err(|e| input_error(format!("{name}: {e:#}")))?;
    let params = fitted_params(&name, &frames, &timing, &fitted)?;
    print_fit(stdout, &name, &metadata, &frames, &timing, &params, &fitted)?;
    if let Some(mut pending) = pending {
        let text = microscope_yaml(&name, &params, &fitted)?;
        pending.fill(|writer| Ok(writer.write_all(text.as_bytes())?))?;
        let path = pending.path().display().to_string();
        pending.commit()?;
        writeln!(stdout, "wrote {path}")?;
    }
    Ok(ExitCode::SUCCESS)
}

/// The scan's timing from the flags and the file's metadata, refused where
/// it is missing, impossible or disagrees with the frames or the file.
fn known_timing(
    args: &FitMicroscopeArgs,
    name: &str,
    metadata: &AcquisitionMetadata,
    frames: &FrameStack,
) -> anyhow::Result<KnownTiming> {
    let pixel_size_um = timing_value(
        "--pixel-size-um",
        args.pixel_size_um,
        metadata.pixel_size_um,
        name,
        false,
        1e3,
    )?;
    let dwell_us = timing_value(
        "--dwell-us",
        args.dwell_us,
        metadata.dwell_us,
        name,
        false,
        1e6,
    )?;
    let retrace_ms = timing_value(
        "--retrace-ms",
        args.retrace_ms,
        metadata.retrace_ms,
        name,
        true,
        1e6,
    )?;
    timing_value(
        "--sigma-z-um",
        Some(args.sigma_z_um),
        None,
        name,
        false,
        1e3,
    )?;
    check_acquisition(
        name,
        metadata,
        frames.height,
        frames.width,
        dwell_us,
        retrace_ms,
    )?;
    Ok(KnownTiming {
        pixel_size_um,
        dwell_us,
        retrace_ms,
        sigma_z_um: args.sigma_z_um,
    })
}

/// The microscope as the simulator and the estimators take it: the
/// frames' size, the known timing and the fitted values, refused if they
/// do not make a valid microscope.
fn fitted_params(
    name: &str,
    frames: &FrameStack,
    timing: &KnownTiming,
    fitted: &FittedMicroscope,
) -> anyhow::Result<SimParams> {
    let params = SimParams {
        height: frames.height,
        width: frames.width,
        pixel_size_um: timing.pixel_size_um,
        dwell_us: timing.dwell_us,
        retrace_ms: timing.retrace_ms,
        sigma_xy_um: fitted.sigma_xy_um.value,
        sigma_z_um: timing.sigma_z_um,
        background: fitted.background.value.into(),
        brightness: fitted.brightness.value.into(),
        detector_noise: detector_noise(name, fitted)?,
        ..SimParams::default()
    };
    params
        .validate()
        .map_err(|e| input_error(format!("{name}: the fitted microscope is not valid: {e}")))?;
    Ok(params)
}

/// Prints the fit: what was read, each estimate with its standard error
/// (the brightness with its caveat) and the detector model.
fn print_fit(
    stdout: &mut dyn Write,
    name: &str,
    metadata: &AcquisitionMetadata,
    frames: &FrameStack,
    timing: &KnownTiming,
    params: &SimParams,
    fitted: &FittedMicroscope,
) -> anyhow::Result<()> {
    let source = match metadata.source {
        MetadataSource::None => "flags".to_string(),
        other => format!("flags and {} metadata", other.as_str()),
    };
    let KnownTiming {
        pixel_size_um,
        dwell_us,
        retrace_ms,
        sigma_z_um,
    } = timing;
    writeln!(
        stdout,
        "{name}: {} frames of {}×{} px ({} used, {} spots); timing from {source}: pixel {pixel_size_um} µm, dwell {dwell_us} µs, retrace {retrace_ms} ms",
        frames.n, frames.height, frames.width, fitted.frames_used, fitted.spots
    )?;
    let rows = [
        ("background (photons/pixel)", fitted.background, 3),
        ("brightness N_qd (photons)", fitted.brightness, 3),
        ("sigma_xy_um", fitted.sigma_xy_um, 4),
        ("variance/mean (F²)", fitted.excess_noise_factor, 3),
    ];
    for (label, estimate, digits) in rows {
        writeln!(
            stdout,
            "  {label:<28} {:>10.digits$} ± {:.digits$}{}",
            estimate.value,
            estimate.standard_error,
            if label.starts_with("brightness") {
                format!("  ({BRIGHTNESS_CAVEAT})")
            } else {
                String::new()
            }
        )?;
    }
    let noise = match params.detector_noise {
        DetectorNoise::Poisson => "poisson".to_string(),
        DetectorNoise::Pmt {
            excess_noise_factor,
        } => format!("pmt, F² = {excess_noise_factor:.3}"),
    };
    writeln!(
        stdout,
        "  detector model: {noise}; spot height with motion blur {:.3} µm; sigma_z_um {sigma_z_um} (given)",
        fitted.blurred_height_um
    )?;
    Ok(())
}
