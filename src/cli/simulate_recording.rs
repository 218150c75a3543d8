//! `scanloc simulate-recording`: a continuous recording of QDs diffusing
//! through the field, and its ground truth (docs/tracking.md).

use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::io::{self, PendingFile};
use crate::sim::SimParams;
use crate::sim::recording::{Blinking, RecordingParams, simulate_recording_with_progress};
use clap::Args;

/// Simulate a continuous recording: frames scanned back to back on one
/// clock while QDs diffuse in 3D through a periodic volume larger than the
/// field (so they enter and leave the field and the focal volume), with
/// optional blinking (docs/tracking.md).
///
/// The microscope flags are those of `scanloc simulate` (paper defaults);
/// D, N_qd and N_bkg are fixed numbers here.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct SimulateRecordingArgs {
    /// Number of frames.
    #[arg(long, default_value_t = 200, value_parser = super::whole_number::<usize>)]
    frames: usize,
    /// Seed of the recording.
    #[arg(long, default_value_t = 0, value_parser = super::whole_number::<u64>)]
    seed: u64,
    /// Diffusion coefficient D in µm²/s.
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    diffusion: f64,
    /// N_qd, photons of an in-focus QD (PSF normalisation).
    #[arg(long, default_value_t = 7.0, allow_hyphen_values = true)]
    brightness: f64,
    /// N_bkg, expected background photons per pixel.
    #[arg(long, default_value_t = 8.4, allow_hyphen_values = true)]
    background: f64,
    /// The scan: frame size, pixel size, timing and lateral PSF.
    #[command(flatten)]
    scan: super::ScanGeometryArgs,
    /// Axial PSF standard deviation in µm.
    #[arg(long, default_value_t = 1.36, allow_hyphen_values = true)]
    sigma_z_um: f64,
    /// PSF samples per pixel dwell (1 = the paper).
    #[arg(long, default_value_t = 1, value_parser = super::whole_number::<u32>)]
    substeps: u32,
    /// QDs per µm³ of the simulated volume (their number is a Poisson draw
    /// of density × volume).
    #[arg(long, default_value_t = 0.05, allow_hyphen_values = true)]
    qd_density: f64,
    /// Exactly this many QDs in the volume, instead of the Poisson draw of
    /// --qd-density (e.g. a recording with as many QDs as another).
    #[arg(long, conflicts_with = "qd_density", value_parser = super::whole_number::<u64>)]
    qd_count: Option<u64>,
    /// How far the volume reaches beyond the field on every side, µm (the
    /// default is beyond the PSF cut-off, so QDs wrap around unseen).
    #[arg(long, default_value_t = 1.5, allow_hyphen_values = true)]
    margin_um: f64,
    /// The volume spans depths ±this around the focal plane, µm.
    #[arg(long, default_value_t = 4.0, allow_hyphen_values = true)]
    half_depth_um: f64,
    /// Mean on time of blinking QDs, ms (with --blink-off-ms).
    #[arg(long, requires = "blink_off_ms", allow_hyphen_values = true)]
    blink_on_ms: Option<f64>,
    /// Mean off time of blinking QDs, ms (with --blink-on-ms).
    #[arg(long, requires = "blink_on_ms", allow_hyphen_values = true)]
    blink_off_ms: Option<f64>,
    /// Detector noise: `poisson`, or `pmt:F2` for a PMT with excess-noise
    /// factor F² > 1 (as `scanloc simulate`'s).
    #[arg(long, default_value = "poisson", value_parser = super::microscope::parse_detector_noise)]
    detector_noise: crate::sim::DetectorNoise,
    /// Output frames: FILE.npy or FILE.tif.
    #[arg(long)]
    out: PathBuf,
    /// Output truth CSV: frame,qd,x,y,z_mean,on_fraction,x_seen,y_seen,t_mid,t_beam,t_seen,diffusion.
    #[arg(long)]
    truth: Option<PathBuf>,
}

pub(super) fn run(args: SimulateRecordingArgs) -> anyhow::Result<ExitCode> {
    let params = RecordingParams {
        microscope: SimParams {
            height: args.scan.flags.height,
            width: args.scan.flags.width,
            pixel_size_um: args.scan.flags.pixel_size_um,
            dwell_us: args.scan.flags.dwell_us,
            retrace_ms: args.scan.flags.retrace_ms,
            sigma_xy_um: args.scan.flags.sigma_xy_um,
            sigma_z_um: args.sigma_z_um,
            substeps: args.substeps,
            brightness: args.brightness.into(),
            background: args.background.into(),
            diffusion_um2_s: args.diffusion.into(),
            detector_noise: args.detector_noise,
            ..SimParams::default()
        },
        frames: args.frames,
        density_per_um3: args.qd_density,
        qd_count: args.qd_count,
        lateral_margin_um: args.margin_um,
        half_depth_um: args.half_depth_um,
        blinking: match (args.blink_on_ms, args.blink_off_ms) {
            (Some(on_ms), Some(off_ms)) => Some(Blinking { on_ms, off_ms }),
            _ => None,
        },
        dead_time_ms: args.scan.dead_time_ms,
    };
    params
        .validate()
        .map_err(|e| input_error(format!("invalid recording parameter: {e}")))?;
    // The memory the recording takes, before any of it is allocated (as
    // `simulate` checks its dataset's).
    crate::limits::check_memory(
        "--frames",
        params.dataset_bytes(),
        crate::limits::available_memory_bytes(),
    )?;
    io::FrameFormat::from_path(&args.out)?;
    let mut outputs = vec![("--out", args.out.as_path())];
    outputs.extend(args.truth.as_deref().map(|truth| ("--truth", truth)));
    io::refuse_shared_paths(&[], &outputs)?;
    let mut frames_out = PendingFile::create(&args.out)?;
    let mut truth_out = args.truth.as_deref().map(PendingFile::create).transpose()?;

    let progress = crate::progress::bar(params.frames as u64, "simulating");
    let recording = simulate_recording_with_progress(&params, args.seed, true, &progress)?;
    progress.finish_and_clear();

    io::fill_frames(&mut frames_out, &recording.frames)?;
    if let Some(pending) = truth_out.as_mut() {
        io::tracks::fill_recording_truth(pending, &recording.truth)?;
    }
    frames_out.commit()?;
    if let Some(pending) = truth_out {
        pending.commit()?;
    }
    Ok(ExitCode::SUCCESS)
}
