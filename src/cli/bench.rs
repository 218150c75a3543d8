//! `scanloc bench`: throughput benchmarks, reported against a reference
//! measured in the same run where one is available.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::bench;
use crate::sim::{Distribution, SimParams};
use clap::{Args, Subcommand};

/// Measure throughput (frames/s) of scanloc's stages.
#[derive(Debug, Args)]
pub(super) struct BenchArgs {
    #[command(subcommand)]
    command: BenchCommand,
}

#[derive(Debug, Subcommand)]
enum BenchCommand {
    /// Simulator frames/s on the paper's 36,688 frames (the paper's
    /// microscope, D uniform in [0.75, 1.75], margin 4, unless the
    /// microscope flags say otherwise; the numpy reference always simulates
    /// the paper's).
    Simulate(SimulateBench),
    /// Crocker–Grier frames/s against TrackPy 0.7 on the same frames (the
    /// paper's microscope, D = 1 µm²/s, N_qd 7, margin 4, unless the
    /// microscope flags say otherwise; diameter 7, minmass 0).
    Locate(LocateBench),
    /// Run time against error for the simulator (substeps, PSF cut-off),
    /// Crocker–Grier (diameter, preprocessing) and the CNN (width, depth,
    /// epochs), with the Cramér–Rao floor; tables on stdout, CSV and plots
    /// (Pareto front marked) in --out.
    Tradeoffs(TradeoffArgs),
    /// CNN training samples/s and inference frames/s on paper-sized frames.
    Train(super::bench_cnn::BenchTrainArgs),
    /// A saved CNN's AUC table and inference speed on fresh test sets.
    CnnLocate(super::bench_cnn::BenchLocateArgs),
    /// `scanloc link --linker trackpy` against TrackPy 0.7's link on the same
    /// random walks (localisations/s, the ratio, and whether the
    /// trajectories are the same).
    Link(super::link::LinkBench),
}

/// A stage of `scanloc bench tradeoffs`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Stage {
    /// Substeps 1…16 × PSF cut-off none…2σ: frames/s against the largest
    /// expected-image error.
    Simulator,
    /// Diameter 3…11 × preprocessing: frames/s against RMSE (and AUC).
    CrockerGrier,
    /// Width × depth × epochs: training time and frames/s against RMSE (and
    /// AUC). The slow one: minutes.
    Cnn,
}

#[derive(Debug, Args)]
struct TradeoffArgs {
    /// Folder for the CSV tables and plots.
    #[arg(long, default_value = "reports/bench")]
    out: PathBuf,
    /// Stages to sweep, comma-separated.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [Stage::Simulator, Stage::CrockerGrier, Stage::Cnn])]
    stages: Vec<Stage>,
    /// Frames per simulator timing and of the D = 1 µm²/s test set.
    #[arg(long, default_value_t = 2410)]
    frames: usize,
    /// Frames of the static-QD (D = 0) test set scored against the
    /// Cramér–Rao floor.
    #[arg(long, default_value_t = 1000)]
    static_frames: usize,
    /// N_qd of the test and training sets and of the Cramér–Rao bound, one
    /// fixed number (default: the paper experiment's calibrated value).
    #[arg(long, default_value = "7.5")]
    brightness: Distribution,
    /// CNN: frames of the training set (D uniform in [0.75, 1.75]).
    #[arg(long, default_value_t = 3000)]
    cnn_train_frames: usize,
    /// CNN: hidden conv channels to try, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "8,16,32")]
    cnn_channels: Vec<usize>,
    /// CNN: hidden layer counts to try (2…8; 6 is the default network).
    #[arg(long, value_delimiter = ',', default_value = "3,6,8")]
    cnn_depths: Vec<usize>,
    /// CNN: epoch counts to try (each a training run of its own).
    #[arg(long, value_delimiter = ',', default_value = "1,3")]
    cnn_epochs: Vec<usize>,
}

impl TradeoffArgs {
    /// Refuses settings that would make an empty or meaningless sweep;
    /// returns the brightness.
    fn validate(&self) -> anyhow::Result<f64> {
        use crate::error::input_error;
        super::microscope::paper_sized("--frames", self.frames)?;
        super::microscope::paper_sized("--static-frames", self.static_frames)?;
        let brightness = self
            .brightness
            .require_fixed("--brightness", "the Cramér–Rao bound")
            .map_err(|e| input_error(e.to_string()))?;
        if !(brightness.is_finite() && brightness > 0.0) {
            return Err(input_error(format!(
                "--brightness: must be a finite number > 0, got {brightness}"
            )));
        }
        if self.stages.contains(&Stage::Cnn) {
            super::microscope::paper_sized("--cnn-train-frames", self.cnn_train_frames)?;
            if self.cnn_epochs.contains(&0) {
                return Err(input_error("--cnn-epochs: each must be ≥ 1"));
            }
            for &depth in &self.cnn_depths {
                bench::tradeoff::dilations_for_depth(depth)?;
            }
            for &channels in &self.cnn_channels {
                if !(1..=1024).contains(&channels) {
                    return Err(input_error(format!(
                        "--cnn-channels: each must be in 1..=1024, got {channels}"
                    )));
                }
            }
        }
        Ok(brightness)
    }
}

#[derive(Debug, Args)]
#[command(mut_arg("margin_px", |arg| arg.default_value("4")))]
struct LocateBench {
    /// Frames to locate.
    #[arg(long, default_value_t = 6850)]
    frames: usize,
    /// Frames given to TrackPy (it is slow; the rate is per frame).
    #[arg(long, default_value_t = 1000)]
    reference_frames: usize,
    /// Timed repeats; the best is reported.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Python interpreter with trackpy 0.7 (skipped if missing).
    #[arg(long, default_value = "python3")]
    python: String,
    /// The TrackPy reference script.
    #[arg(long, default_value = "benches/reference/trackpy_locate.py")]
    reference: PathBuf,
    /// The microscope of the frames located.
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
}

#[derive(Debug, Args)]
#[command(
    mut_arg("margin_px", |arg| arg.default_value("4")),
    mut_arg("diffusion", |arg| arg.default_value("uniform:0.75,1.75"))
)]
struct SimulateBench {
    /// Frames per repeat.
    #[arg(long, default_value_t = bench::simulate::PAPER_FRAMES)]
    frames: usize,
    /// Timed repeats; the best is reported.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
    /// Also time the numpy reference implementation with this Python
    /// interpreter (skipped if it or numpy is missing).
    #[arg(long, default_value = "python3")]
    python: String,
    /// The numpy reference script.
    #[arg(long, default_value = "benches/reference/numpy_sim.py")]
    reference: PathBuf,
    /// The microscope simulated.
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
}

pub(super) fn run(args: BenchArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    match args.command {
        BenchCommand::Simulate(args) => simulate(args, stdout),
        BenchCommand::Locate(args) => locate(args, stdout),
        BenchCommand::Tradeoffs(args) => tradeoffs(args, stdout),
        BenchCommand::Train(args) => super::bench_cnn::run_train(args, stdout),
        BenchCommand::CnnLocate(args) => super::bench_cnn::run_locate(args, stdout),
        BenchCommand::Link(args) => super::link::bench(args, stdout),
    }
}

fn locate(args: LocateBench, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let params = super::microscope::bench_microscope(&args.microscope, "--frames", args.frames)?;
    super::microscope::bench_microscope(
        &args.microscope,
        "--reference-frames",
        args.reference_frames,
    )?;
    let dataset = crate::sim::simulate(&params, 7, 0..args.frames, &crate::progress::hidden())?;
    let detector = crate::detect::crocker_grier::CrockerGrierParams {
        minmass: Some(0.0),
        ..Default::default()
    };
    let fps = bench::locate::time_crocker_grier(&dataset.frames, &detector, args.repeats)?;
    writeln!(
        stdout,
        "scanloc crocker-grier: {} frames of {}×{} at {fps:.0} frames/s on {} threads",
        dataset.frames.n,
        dataset.frames.height,
        dataset.frames.width,
        rayon::current_num_threads()
    )?;
    let folder = tempfile::tempdir()?;
    let file = folder.path().join("frames.npy");
    let subset = crate::sim::simulate(
        &params,
        7,
        0..args.reference_frames.min(args.frames),
        &crate::progress::hidden(),
    )?;
    crate::io::write_frames(&file, &subset.frames)?;
    let file_arg = file.to_string_lossy().into_owned();
    match bench::reference::run_python(&args.python, &args.reference, &["--input", &file_arg]) {
        Ok(reference_fps) => writeln!(
            stdout,
            "trackpy 0.7 locate: {reference_fps:.0} frames/s; scanloc is {:.0}× faster",
            fps / reference_fps
        )?,
        Err(reason) => writeln!(stdout, "trackpy reference skipped: {reason}")?,
    }
    Ok(ExitCode::SUCCESS)
}

fn simulate(args: SimulateBench, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let params = super::microscope::bench_microscope(&args.microscope, "--frames", args.frames)?;
    let timing = bench::simulate::time_simulator(&params, args.frames, args.repeats)?;
    writeln!(
        stdout,
        "scanloc simulate: {} frames in {:.3} s on {} threads = {:.0} frames/s",
        timing.frames, timing.seconds, timing.threads, timing.frames_per_second
    )?;
    match bench::reference::run_python(
        &args.python,
        &args.reference,
        &["--frames", &args.frames.min(20_000).to_string()],
    ) {
        Ok(reference_fps) => writeln!(
            stdout,
            "numpy reference: {reference_fps:.0} frames/s; scanloc is {:.1}× faster",
            timing.frames_per_second / reference_fps
        )?,
        Err(reason) => writeln!(stdout, "numpy reference skipped: {reason}")?,
    }
    Ok(ExitCode::SUCCESS)
}

fn print_sweep(
    title: &str,
    error_label: &str,
    points: &[bench::tradeoff::TradeoffPoint],
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    writeln!(stdout, "\n{title}")?;
    writeln!(
        stdout,
        "{:<40} {:>12} {:>14}  extra",
        "setting", "frames/s", error_label
    )?;
    for p in points {
        let extra: Vec<String> = p.extra.iter().map(|(k, v)| format!("{k}={v:.3}")).collect();
        writeln!(
            stdout,
            "{:<40} {:>12.0} {:>14.4}{} {}",
            p.setting,
            p.frames_per_second,
            p.error,
            if p.pareto { " *" } else { "  " },
            extra.join(" ")
        )?;
    }
    if let Some(reference) = points.iter().find(|p| p.reference) {
        writeln!(
            stdout,
            "(*_vs_reference: ratios against '{}', timed in this run)",
            reference.setting
        )?;
    }
    Ok(())
}

/// The best (smallest) finite value of `values`, with the setting it came from.
fn best(
    points: &[bench::tradeoff::TradeoffPoint],
    value: impl Fn(&bench::tradeoff::TradeoffPoint) -> f64,
) -> Option<(String, f64)> {
    points
        .iter()
        .map(|p| (p.setting.clone(), value(p)))
        .filter(|(_, v)| v.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
}

fn tradeoffs(args: TradeoffArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    use bench::tradeoff;
    let brightness = args.validate()?;
    let floor_params = SimParams {
        brightness: brightness.into(),
        ..SimParams::default()
    };
    let floor = tradeoff::cramer_rao_rmse_px(&floor_params, 5)?;
    writeln!(
        stdout,
        "Cramér–Rao floor (static QD, N_qd {brightness}, Poisson): RMSE {floor:.4} px"
    )?;
    if args.stages.contains(&Stage::Simulator) {
        let simulator = tradeoff::simulator_sweep(args.frames)?;
        print_sweep(
            "simulator (* = Pareto front)",
            "max |Δμ| (ph)",
            &simulator,
            stdout,
        )?;
        tradeoff::write_sweep(
            &args.out,
            "simulator",
            "max expected-image error (photons)",
            &simulator,
            None,
        )?;
    }
    let locators = args.stages.contains(&Stage::CrockerGrier) || args.stages.contains(&Stage::Cnn);
    if !locators {
        writeln!(stdout, "tables and plots in {}", args.out.display())?;
        return Ok(ExitCode::SUCCESS);
    }
    let tests = tradeoff::TestSets::simulate(args.frames, args.static_frames, brightness)?;
    let mut closest = Vec::new();
    if args.stages.contains(&Stage::CrockerGrier) {
        closest.push((
            "crocker-grier",
            crocker_grier_tradeoff(&args, &tests, floor, stdout)?,
        ));
    }
    if args.stages.contains(&Stage::Cnn) {
        closest.push((
            "cnn",
            cnn_tradeoff(&args, brightness, &tests, floor, stdout)?,
        ));
    }
    for (method, best) in closest {
        match best {
            Some((setting, rmse)) => writeln!(
                stdout,
                "closest to the floor, {method}: precision {rmse:.3} px on a static QD ({setting}; RMSE of the top predictions within 3 px) = {:.2}× the Cramér–Rao floor",
                rmse / floor
            )?,
            None => writeln!(
                stdout,
                "{method}: no setting located anything in the static set"
            )?,
        }
    }
    writeln!(stdout, "tables and plots in {}", args.out.display())?;
    Ok(ExitCode::SUCCESS)
}

/// The Crocker–Grier sweep: its table, CSV and plot; the setting closest
/// to the Cramér–Rao `floor`.
fn crocker_grier_tradeoff(
    args: &TradeoffArgs,
    tests: &bench::tradeoff::TestSets,
    floor: f64,
    stdout: &mut dyn Write,
) -> anyhow::Result<Option<(String, f64)>> {
    use bench::tradeoff::{self, extra};
    let locator = tradeoff::crocker_grier_sweep(tests)?;
    print_sweep(
        "crocker-grier, RMSE at D = 1 (* = Pareto front)",
        "RMSE (px)",
        &locator,
        stdout,
    )?;
    tradeoff::write_sweep(
        &args.out,
        crate::types::DetectorKind::CrockerGrier.as_str(),
        "RMSE of top prediction, D = 1 (px)",
        &locator,
        Some(floor),
    )?;
    Ok(best(&locator, |p| extra(p, "precision_static_px")))
}

/// The CNN sweep: its table, CSVs and plots; the setting closest to the
/// Cramér–Rao `floor`.
fn cnn_tradeoff(
    args: &TradeoffArgs,
    brightness: f64,
    tests: &bench::tradeoff::TestSets,
    floor: f64,
    stdout: &mut dyn Write,
) -> anyhow::Result<Option<(String, f64)>> {
    use bench::tradeoff::{self, extra};
    let sweep = tradeoff::CnnSweep {
        train_frames: args.cnn_train_frames,
        channels: args.cnn_channels.clone(),
        depths: args.cnn_depths.clone(),
        epochs: args.cnn_epochs.clone(),
        brightness,
    };
    let progress = crate::progress::bar(0, "cnn sweep");
    let cnn = tradeoff::cnn_sweep(&sweep, tests, &progress)?;
    progress.finish_and_clear();
    print_sweep(
        "cnn, RMSE at D = 1 (* = Pareto front of inference frames/s; training time and its front in the extras)",
        "RMSE (px)",
        &cnn,
        stdout,
    )?;
    let label = "RMSE of top prediction, D = 1 (px)";
    tradeoff::write_sweep(&args.out, "cnn", label, &cnn, Some(floor))?;
    tradeoff::write_training_plot(&args.out, "cnn", label, &cnn, Some(floor))?;
    Ok(best(&cnn, |p| extra(p, "precision_static_px")))
}
