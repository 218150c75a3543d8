//! `scanloc locate`: localise QDs in a frame file.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, ValueEnum};
use scanloc::detect::crocker_grier::{self, CrockerGrierParams};
use scanloc::error::input_error;
use scanloc::io::{self, csv_tables};

/// Localise QDs in every frame of a .npy or .tif stack and write a CSV.
///
/// With `--method crocker-grier` (TrackPy's `locate`, same parameters and
/// defaults) the columns are frame,x,y,mass,size,ecc,signal,raw_mass,ep,score
/// (score = mass), ordered by frame then descending mass. With `--method cnn
/// --model DIR` (a model saved by `scanloc train`) the columns are
/// frame,x,y,sigma_x,sigma_y,score: sigma_x, sigma_y are the network's
/// estimate of each localisation's error in pixels (filter on them as on an
/// SMLM localisation precision), score as the model's `architecture.score`.
///
/// Frames are photon counts: integers, or floats whose values are whole
/// and ≥ 0, for both methods. A multi-channel ImageJ hyperstack needs
/// `--channel`. The CNN goes through the frames in batches of at most 2¹⁸
/// pixels, so its memory beyond the frames themselves does not grow with
/// the recording.
///
/// Both methods and their parameters: docs/detectors.md.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub struct LocateArgs {
    /// Localisation method.
    #[arg(long, value_enum, default_value_t = Method::CrockerGrier)]
    method: Method,
    /// Input frames: FILE.npy (shape (n, H, W) or (H, W)) or FILE.tif.
    #[arg(long)]
    input: PathBuf,
    /// Output CSV.
    #[arg(long)]
    out: PathBuf,
    /// The channel to localise in (0-based), required for a multi-channel
    /// stack (an ImageJ hyperstack with channels).
    #[arg(long)]
    channel: Option<usize>,
    /// With `--method cnn`: the model folder written by `scanloc train`.
    #[arg(long, required_if_eq("method", "cnn"))]
    model: Option<PathBuf>,
    /// Feature diameter in pixels (odd, ≥ 3).
    #[arg(long, default_value_t = 7)]
    diameter: usize,
    /// Minimum integrated brightness (features need mass > minmass).
    #[arg(long)]
    minmass: Option<f64>,
    /// Maximum radius of gyration.
    #[arg(long)]
    maxsize: Option<f64>,
    /// Minimum separation between features [default: diameter + 1].
    #[arg(long)]
    separation: Option<f64>,
    /// Width of the Gaussian low pass in pixels.
    #[arg(long, default_value_t = 1.0)]
    noise_size: f64,
    /// Side of the boxcar background in pixels, odd [default: diameter].
    #[arg(long)]
    smoothing_size: Option<usize>,
    /// Band-pass values below this are set to 0 [default: 1].
    #[arg(long)]
    threshold: Option<f64>,
    /// Peaks must be brighter than this percentile of non-zero pixels.
    #[arg(long, default_value_t = 64.0)]
    percentile: f64,
    /// Keep only the N brightest features per frame.
    #[arg(long)]
    topn: Option<usize>,
    /// Maximum centroid refinement steps.
    #[arg(long, default_value_t = 10)]
    max_iterations: usize,
    /// Band-pass the frames before finding peaks (default).
    #[arg(long, overrides_with = "no_preprocess")]
    preprocess: bool,
    /// Find peaks in the raw frames.
    #[arg(long)]
    no_preprocess: bool,
}

/// Localisation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Method {
    /// The Crocker–Grier algorithm of TrackPy's `locate`.
    CrockerGrier,
    /// A CNN trained on simulated frames (needs --model).
    Cnn,
}

pub fn run(args: LocateArgs) -> anyhow::Result<ExitCode> {
    let mut inputs = vec![("--input", args.input.as_path())];
    inputs.extend(args.model.as_deref().map(|model| ("--model", model)));
    io::refuse_shared_paths(&inputs, &[("--out", &args.out)])?;
    match args.method {
        Method::CrockerGrier => {
            let params = CrockerGrierParams {
                diameter: args.diameter,
                minmass: args.minmass,
                maxsize: args.maxsize,
                separation: args.separation,
                noise_size: args.noise_size,
                smoothing_size: args.smoothing_size,
                threshold: args.threshold,
                percentile: args.percentile,
                topn: args.topn,
                preprocess: !args.no_preprocess,
                max_iterations: args.max_iterations,
            };
            params
                .validate()
                .map_err(|e| input_error(format!("invalid crocker-grier parameter: {e}")))?;
            let frames = io::read_frames_of_channel(&args.input, args.channel)?;
            let bar = scanloc::progress::bar(frames.n as u64, "locating");
            let features = crocker_grier::locate_stack(&frames, &params, &bar)?;
            bar.finish_and_clear();
            csv_tables::write_localisations(
                &args.out,
                crocker_grier::FEATURE_COLUMNS,
                features
                    .iter()
                    .map(|(frame, f)| (f.prediction(*frame), f.column_values())),
            )?;
        }
        Method::Cnn => {
            let model_dir = args
                .model
                .as_deref()
                .ok_or_else(|| input_error("--model: required with --method cnn"))?;
            let model = scanloc::detect::cnn::TrainedCnn::load(model_dir)?;
            let frames = io::read_frames_of_channel(&args.input, args.channel)?;
            let bar = scanloc::progress::bar(frames.n as u64, "locating");
            let predictions = model.locate(&frames, &bar)?;
            bar.finish_and_clear();
            csv_tables::write_predictions(&args.out, &predictions)?;
        }
    }
    Ok(ExitCode::SUCCESS)
}
