//! `scanloc simulate`: write simulated frames and their ground truth.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use scanloc::error::input_error;
use scanloc::io::{self, PendingFile};
use scanloc::sim::{self, DetectorNoise, EmitterCount, SimParams};

/// Simulate point-scanning 2PM frames of diffusing QDs (docs/simulator.md).
///
/// Every parameter defaults to the paper's microscope. Frame i of a dataset
/// depends only on (parameters, seed, i): the same frames come out whatever
/// the thread count.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub struct SimulateArgs {
    /// Number of frames (at most 10,000,000, and 2³¹ pixels in all: the
    /// limits a manifest's datasets have).
    #[arg(long, default_value_t = 100)]
    frames: usize,
    /// Master seed of the dataset.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// D, N_qd, N_bkg, start depth and margin.
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
    /// Frame height in pixels (rows).
    #[arg(long, default_value_t = 24)]
    height: usize,
    /// Frame width in pixels (columns).
    #[arg(long, default_value_t = 25)]
    width: usize,
    /// Pixel size in µm.
    #[arg(long, default_value_t = 0.07)]
    pixel_size_um: f64,
    /// Pixel dwell time in µs.
    #[arg(long, default_value_t = 2.0)]
    dwell_us: f64,
    /// Line retrace time in ms.
    #[arg(long, default_value_t = 1.1)]
    retrace_ms: f64,
    /// Lateral PSF standard deviation in µm.
    #[arg(long, default_value_t = 0.21)]
    sigma_xy_um: f64,
    /// Axial PSF standard deviation in µm.
    #[arg(long, default_value_t = 1.36)]
    sigma_z_um: f64,
    /// PSF samples per pixel dwell (1 = the paper).
    #[arg(long, default_value_t = 1)]
    substeps: u32,
    /// QDs per frame: N, or drawn per frame with choice:N,N,... (optionally
    /// /weights:W,W,...).
    #[arg(long, default_value = "1")]
    emitters: EmitterCount,
    /// Detector noise: `poisson`, or `pmt:F2` for a PMT with excess-noise factor F² > 1.
    #[arg(long, default_value = "poisson", value_parser = parse_detector_noise)]
    detector_noise: DetectorNoise,
    /// Lateral PSF cut-off in σ_xy (samples farther from the beam add nothing),
    /// or `none` to evaluate the PSF everywhere.
    #[arg(long, default_value = "6", value_parser = parse_cutoff)]
    psf_cutoff_sigma: Cutoff,
    /// Output frames: FILE.npy (uint16, or uint32 if needed; shape (n, H, W)) or FILE.tif.
    #[arg(long)]
    out: PathBuf,
    /// Output ground truth CSV: frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion.
    #[arg(long)]
    truth: Option<PathBuf>,
}

fn parse_detector_noise(text: &str) -> Result<DetectorNoise, String> {
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

pub fn run(args: SimulateArgs) -> anyhow::Result<ExitCode> {
    let params = args.microscope.apply(SimParams {
        height: args.height,
        width: args.width,
        pixel_size_um: args.pixel_size_um,
        dwell_us: args.dwell_us,
        retrace_ms: args.retrace_ms,
        sigma_xy_um: args.sigma_xy_um,
        sigma_z_um: args.sigma_z_um,
        substeps: args.substeps,
        emitters: args.emitters,
        detector_noise: args.detector_noise,
        psf_cutoff_sigma: args.psf_cutoff_sigma,
        ..SimParams::default()
    });
    params
        .validate()
        .map_err(|e| input_error(format!("invalid simulation parameter: {e}")))?;
    // The manifest's limits, checked by the same functions.
    scanloc::limits::check_dataset_size("--frames", args.frames, args.height, args.width)?;
    // The memory the dataset takes, before any of it is allocated: a
    // failed allocation would end the process without a word.
    scanloc::limits::check_memory(
        "--frames",
        sim::dataset_bytes(&params, args.frames),
        scanloc::limits::available_memory_bytes(),
    )?;
    io::FrameFormat::from_path(&args.out)?;
    let mut outputs = vec![("--out", args.out.as_path())];
    outputs.extend(args.truth.as_deref().map(|truth| ("--truth", truth)));
    io::refuse_shared_paths(&[], &outputs)?;
    // Every output is opened (and dropped) before simulating, so that an
    // unwritable destination fails now; the files are opened again only
    // once the frames are made, so that a simulation stopped part way (by
    // an error or a signal) leaves no partial file behind, and nothing is
    // renamed into place unless everything succeeded.
    let open_outputs = || -> anyhow::Result<(PendingFile, Option<PendingFile>)> {
        Ok((
            PendingFile::create(&args.out)?,
            args.truth.as_deref().map(PendingFile::create).transpose()?,
        ))
    };
    drop(open_outputs()?);

    let bar = scanloc::progress::bar(args.frames as u64, "simulating");
    let dataset = sim::simulate(&params, args.seed, 0..args.frames, &bar)?;
    bar.finish_and_clear();

    let (mut frames_out, mut truth_out) = open_outputs()?;

    io::fill_frames(&mut frames_out, &dataset.frames)?;
    if let Some(pending) = truth_out.as_mut() {
        io::csv_tables::fill_truth(pending, &dataset.truth)?;
    }
    frames_out.commit()?;
    if let Some(pending) = truth_out {
        pending.commit()?;
    }
    Ok(ExitCode::SUCCESS)
}
