//! CNN benchmarks: `scanloc bench train` (training and inference
//! throughput) and `scanloc bench cnn-locate` (a saved model's AUC table and
//! inference speed on fresh test sets). Thin wrappers over
//! `scanloc::bench::cnn`.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use scanloc::bench;
use scanloc::detect::cnn::{self, CnnArchitecture, TrainedCnn};
use scanloc::sim::{Distribution, RandomDistribution, SimParams};

/// Measure CNN training and inference throughput on paper-sized frames.
///
/// Trains one epoch of `--samples` fresh frames (N_qd 7, margin 4, D uniform
/// [0.75, 1.75]) and locates `--locate-frames` frames in batches of 256.
/// Threads: rayon's (RAYON_NUM_THREADS).
#[derive(Debug, Args)]
pub struct BenchTrainArgs {
    /// Training samples to time.
    #[arg(long, default_value_t = 2000)]
    samples: usize,
    /// Frames to locate.
    #[arg(long, default_value_t = 2048)]
    locate_frames: usize,
    /// Frames per optimiser step.
    #[arg(long, default_value_t = 64)]
    batch_size: usize,
    /// Hidden conv channels (default: the library's).
    #[arg(long)]
    channels: Option<usize>,
    /// Dilations, comma-separated (default: the library's).
    #[arg(long, value_delimiter = ',')]
    dilations: Option<Vec<usize>>,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

pub fn run_train(args: BenchTrainArgs) -> anyhow::Result<ExitCode> {
    let defaults = CnnArchitecture::default();
    let arch = CnnArchitecture {
        channels: args.channels.unwrap_or(defaults.channels),
        dilations: args.dilations.unwrap_or(defaults.dilations),
        ..defaults
    };
    arch.validate()?;
    let result = bench::cnn::throughput(
        &arch,
        args.batch_size,
        args.samples,
        args.locate_frames,
        args.seed,
    )?;
    println!(
        "channels {} dilations {:?} batch {} threads {}: training {:.1} samples/s ({} samples), inference {:.1} frames/s ({} frames, batch 256)",
        result.architecture.channels,
        result.architecture.dilations,
        result.batch_size,
        result.threads,
        result.train_samples_per_second,
        result.train_samples,
        result.locate_frames_per_second,
        result.locate_frames
    );
    Ok(ExitCode::SUCCESS)
}

/// Score a saved CNN on fresh simulated test sets and time its inference.
///
/// Simulates `--frames` frames per `--diffusion` value (the paper's
/// microscope with the given brightness and margin; each set's seed is
/// derived from `--seed` and its D) and prints the AUC at ε = 1, 2, 3 px
/// beside the paper's FCNN row, with frames/s. Inference options may be
/// overridden to compare post-processing without retraining.
#[derive(Debug, Args)]
pub struct BenchLocateArgs {
    /// Model folder written by `scanloc train`.
    #[arg(long)]
    model: PathBuf,
    #[arg(long, default_value_t = 2000)]
    frames: usize,
    #[arg(long, value_delimiter = ',', default_value = "0.75,1.0,1.75")]
    diffusion: Vec<f64>,
    #[arg(long, default_value_t = 7.0)]
    brightness: f64,
    #[arg(long, default_value_t = 4.0)]
    margin_px: f64,
    #[arg(long, default_value_t = 1_000_003)]
    seed: u64,
    /// Override the model's peak window radius.
    #[arg(long)]
    peak_radius_px: Option<usize>,
    /// Override the model's position refinement radius.
    #[arg(long)]
    refine_radius_px: Option<usize>,
    /// Override the model's score floor.
    #[arg(long)]
    score_floor: Option<f64>,
}

pub fn run_locate(args: BenchLocateArgs) -> anyhow::Result<ExitCode> {
    let mut model = TrainedCnn::load(&args.model)?;
    if let Some(r) = args.peak_radius_px {
        model.architecture.peak_radius_px = r;
    }
    if let Some(r) = args.refine_radius_px {
        model.architecture.refine_radius_px = r;
    }
    if let Some(f) = args.score_floor {
        model.settings.score_floor = f;
    }
    model.architecture.validate()?;
    model.settings.validate()?;
    let params = SimParams {
        brightness: args.brightness,
        margin_px: args.margin_px,
        diffusion_um2_s: Distribution::Random(RandomDistribution::Uniform([0.75, 1.75])),
        ..SimParams::default()
    };
    params.validate()?;
    let rows = bench::cnn::auc_table(&model, &params, &args.diffusion, args.frames, args.seed)?;
    print!("{}", bench::cnn::format_auc_table(&rows));
    for row in &rows {
        println!(
            "D {:.2}: {:.0} frames/s (batch {})",
            row.diffusion,
            row.frames_per_second,
            cnn::inference::INFERENCE_BATCH
        );
    }
    Ok(ExitCode::SUCCESS)
}
