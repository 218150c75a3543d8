//! CNN benchmarks: `scanloc bench train` (training and inference
//! throughput) and `scanloc bench cnn-locate` (a saved model's AUC table and
//! inference speed on fresh test sets). Thin wrappers over
//! `crate::bench::cnn`.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::bench;
use crate::detect::cnn::{self, CnnArchitecture, TrainedCnn, TrainingSettings};
use clap::Args;

/// Measure CNN training and inference throughput on paper-sized frames,
/// against PyTorch on the same network.
///
/// scanloc trains one epoch of `--samples` fresh frames (N_qd 7, margin 4,
/// D uniform [0.75, 1.75]) and locates `--locate-frames` frames in batches
/// of 256. The PyTorch reference (`--reference`, run with `--python` when
/// `torch` imports; eager float32 on the CPU, with glibc's malloc keeping
/// its buffers) trains and runs the same network on synthetic batches of
/// the same size. The two alternate `--repeats` times at each `--threads`
/// count; medians and scanloc/torch ratios are printed. Without torch,
/// scanloc's figures are printed alone. The frames are the microscope's
/// the flags describe: by default the paper's with brightness 7, a margin
/// of 4 px and D uniform in [0.75, 1.75] µm²/s.
#[derive(Debug, Args)]
#[command(
    mut_arg("brightness", |arg| arg.default_value("7")),
    mut_arg("margin_px", |arg| arg.default_value("4")),
    mut_arg("diffusion", |arg| arg.default_value("uniform:0.75,1.75"))
)]
pub(super) struct BenchTrainArgs {
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
    /// The microscope of the training and located frames.
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
    /// Thread counts to measure at, comma-separated (scanloc's rayon pool,
    /// torch's intra-op threads).
    #[arg(long, value_delimiter = ',', default_value = "1,2")]
    threads: Vec<usize>,
    /// Alternating scanloc/torch repetitions per thread count; medians are
    /// reported.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Python interpreter with torch (the comparison is skipped if missing).
    #[arg(long, default_value = "python3")]
    python: String,
    /// The PyTorch reference script.
    #[arg(long, default_value = "benches/reference/torch_train.py")]
    reference: PathBuf,
    /// Measure scanloc alone.
    #[arg(long)]
    no_reference: bool,
}

/// Most thread counts and repetitions `bench train` accepts.
const MAX_BENCH_THREADS: usize = 256;
const MAX_REPEATS: usize = 100;

pub(super) fn run_train(args: BenchTrainArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    super::microscope::paper_sized("--samples", args.samples)?;
    super::microscope::paper_sized("--locate-frames", args.locate_frames)?;
    if args.samples == 0 || args.locate_frames == 0 {
        crate::bail_input!("--samples and --locate-frames: must be ≥ 1");
    }
    if args.threads.is_empty()
        || args
            .threads
            .iter()
            .any(|&t| t == 0 || t > MAX_BENCH_THREADS)
    {
        crate::bail_input!(
            "--threads: each must be in 1..={MAX_BENCH_THREADS}, got {:?}",
            args.threads
        );
    }
    if args.repeats == 0 || args.repeats > MAX_REPEATS {
        crate::bail_input!(
            "--repeats: must be in 1..={MAX_REPEATS}, got {}",
            args.repeats
        );
    }
    let defaults = CnnArchitecture::default();
    let arch = CnnArchitecture {
        channels: args.channels.unwrap_or(defaults.channels),
        dilations: args.dilations.unwrap_or(defaults.dilations),
        ..defaults
    };
    arch.validate()?;
    let settings = TrainingSettings {
        batch_size: args.batch_size,
        ..TrainingSettings::default()
    };
    settings.validate()?;
    let reference = (!args.no_reference).then(|| bench::cnn::TorchReference {
        python: args.python.clone(),
        script: args.reference.clone(),
    });
    let params = args.microscope.params()?;
    params
        .validate()
        .map_err(|e| crate::error::input_error(format!("invalid simulation parameter: {e}")))?;
    // The located frames are held at once, like a simulated dataset's.
    crate::limits::check_dataset_size(
        "--locate-frames",
        args.locate_frames,
        params.height,
        params.width,
    )?;
    let comparisons = bench::cnn::compare_with_torch(
        &arch,
        &params,
        args.batch_size,
        args.samples,
        args.locate_frames,
        args.seed,
        &args.threads,
        args.repeats,
        reference.as_ref(),
    )?;
    writeln!(
        stdout,
        "channels {} dilations {:?} batch {}; training {} samples, inference {} frames (batch {}); medians of {} alternating runs",
        arch.channels,
        arch.dilations,
        args.batch_size,
        args.samples,
        args.locate_frames,
        cnn::inference::INFERENCE_BATCH,
        args.repeats
    )?;
    print_table(&comparisons, "/s", stdout, |r| {
        (r.train_samples_per_second, r.frames_per_second)
    })?;
    writeln!(
        stdout,
        "per CPU second of the process (on a loaded machine, the 1-thread rows estimate the idle rates):"
    )?;
    print_table(&comparisons, "/cpu-s", stdout, |r| {
        (r.train_samples_per_cpu_second, r.frames_per_cpu_second)
    })?;
    if let Some(reason) = comparisons.iter().find_map(|c| c.torch_skipped.as_ref()) {
        writeln!(stdout, "torch reference skipped: {reason}")?;
    }
    Ok(ExitCode::SUCCESS)
}

/// Prints one row per thread count: scanloc's and torch's (training,
/// inference) `figures` and their ratios; `unit` names them.
fn print_table(
    comparisons: &[bench::cnn::Comparison],
    unit: &str,
    stdout: &mut dyn Write,
    figures: fn(&bench::cnn::Rates) -> (f64, f64),
) -> anyhow::Result<()> {
    writeln!(
        stdout,
        "threads  {:>19}  {:>17}  ratio   {:>20}  {:>18}  ratio",
        format!("scanloc train{unit}"),
        format!("torch train{unit}"),
        format!("scanloc frames{unit}"),
        format!("torch frames{unit}"),
    )?;
    for c in comparisons {
        let (train, frames) = figures(&c.scanloc);
        let torch = c.torch.as_ref().map(figures);
        let show = |v: Option<f64>, ratio: bool| match v {
            Some(v) if ratio => format!("{v:.2}×"),
            Some(v) => format!("{v:.1}"),
            None => "-".to_string(),
        };
        writeln!(
            stdout,
            "{:>7}  {:>19.1}  {:>17}  {:>5}   {:>20.1}  {:>18}  {:>5}",
            c.threads,
            train,
            show(torch.map(|t| t.0), false),
            show(torch.map(|t| train / t.0), true),
            frames,
            show(torch.map(|t| t.1), false),
            show(torch.map(|t| frames / t.1), true),
        )?;
    }
    Ok(())
}

/// Score a saved CNN on fresh simulated test sets and time its inference.
///
/// Simulates `--frames` frames per `--test-diffusion` value (the microscope
/// the flags describe, by default the paper's with a margin of 4 px; each
/// set's seed is derived from `--seed` and its D) and prints the AUC at ε = 1, 2, 3 px
/// beside the paper's FCNN row, with frames/s. Inference options may be
/// overridden to compare post-processing without retraining.
#[derive(Debug, Args)]
#[command(
    allow_negative_numbers = true,
    mut_arg("margin_px", |arg| arg.default_value("4")),
    mut_arg("diffusion", |arg| arg.default_value("uniform:0.75,1.75"))
)]
pub(super) struct BenchLocateArgs {
    /// Model folder written by `scanloc train`.
    #[arg(long)]
    model: PathBuf,
    /// Test frames per test diffusion coefficient.
    #[arg(long, default_value_t = 2000)]
    frames: usize,
    #[command(flatten)]
    test_diffusion: super::TestDiffusionArgs,
    /// Master seed of the test sets.
    #[arg(long, default_value_t = 1_000_003)]
    seed: u64,
    /// The microscope of the test sets (but for D).
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
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

pub(super) fn run_locate(
    args: BenchLocateArgs,
    stdout: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let params = super::microscope::bench_microscope(&args.microscope, "--frames", args.frames)?;
    args.test_diffusion.checked()?;
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
    let rows = bench::cnn::auc_table(
        &model,
        &params,
        args.test_diffusion.checked()?,
        args.frames,
        args.seed,
    )?;
    write!(stdout, "{}", bench::cnn::format_auc_table(&rows))?;
    for row in &rows {
        writeln!(
            stdout,
            "D {:.2}: {:.0} frames/s (batch {})",
            row.diffusion,
            row.frames_per_second,
            cnn::inference::INFERENCE_BATCH
        )?;
    }
    Ok(ExitCode::SUCCESS)
}
