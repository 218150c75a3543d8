//! Command-line definitions: one module per subcommand, each only parsing
//! its arguments and calling the library.

mod bench;
mod bench_cnn;
mod calibrate;
mod check;
mod cv;
mod diffusion;
mod locate;
mod registry;
mod report;
mod reproduce;
mod run;
mod score;
mod simulate;
mod simulate_recording;
mod sweep;
mod train;

use std::ffi::OsString;
use std::io::Write;
use std::ops::Deref;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use scanloc::env_vars;

/// scanloc: simulate two-photon raster-scan frames of diffusing quantum dots,
/// localise the dots, and score localisations, reproducibly.
///
/// Coordinates follow TrackPy: x is the column, y the row, pixel centres at
/// integers. Exit codes: 0 success, 1 a check failed, 2 bad input.
///
/// Documentation (simulator physics, detectors, metric, manifests, registry):
/// docs/README.md in the scanloc repository.
#[derive(Debug, Parser)]
#[command(name = "scanloc", version, about, long_about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    Simulate(simulate::SimulateArgs),
    Bench(bench::BenchArgs),
    Locate(locate::LocateArgs),
    Score(score::ScoreArgs),
    Train(train::TrainArgs),
    Run(run::RunArgs),
    Check(check::CheckArgs),
    Reproduce(reproduce::ReproduceArgs),
    Registry(registry::RegistryArgs),
    Report(report::ReportArgs),
    Calibrate(calibrate::CalibrateArgs),
    Cv(cv::CvArgs),
    Sweep(sweep::SweepArgs),
    SimulateRecording(simulate_recording::SimulateRecordingArgs),
    Diffusion(diffusion::DiffusionArgs),
}

/// The whole command: parses `args` (the program name first), runs the
/// command and returns its exit code (0 success, 1 a check failed, 2 bad
/// input). Results a command prints go to `stdout`; a refusal is one
/// `error: …` line on `stderr`, as are clap's usage errors (help and
/// `--version` go to `stdout`, exit 0). `styled` keeps clap's colours, for
/// a terminal.
///
/// Progress lines and warnings still go to the process's standard error.
/// `main` passes the process's streams; the in-process fuzz tests pass
/// buffers.
pub fn main_with<I, T>(
    args: I,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
    styled: bool,
) -> ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(cli) => cli,
        Err(usage) => {
            let text = usage.render();
            let text = if styled {
                text.ansi().to_string()
            } else {
                text.to_string()
            };
            let stream: &mut dyn Write = if usage.use_stderr() {
                &mut *stderr
            } else {
                &mut *stdout
            };
            // Nothing to report a failed write to (a closed stream).
            let _ = stream
                .write_all(text.as_bytes())
                .and_then(|_| stream.flush());
            return ExitCode::from(usage.exit_code().clamp(0, 255) as u8);
        }
    };
    match run(cli, stdout) {
        Ok(code) => code,
        Err(error) => {
            // One line: the context chain joined by ": ".
            let _ = writeln!(stderr, "error: {error:#}").and_then(|_| stderr.flush());
            ExitCode::from(scanloc::error::exit_code(&error) as u8)
        }
    }
}

/// Runs the parsed command; results it prints go to `stdout`.
pub fn run(cli: Cli, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Locate(args) => locate::run(args),
        Command::Score(args) => score::run(args, stdout),
        Command::Train(args) => train::run(args),
        Command::Run(args) => run::run(args),
        Command::Check(args) => check::run(args),
        Command::Reproduce(args) => reproduce::run(args),
        Command::Registry(args) => registry::run(args),
        Command::Report(args) => report::run(args),
        Command::Calibrate(args) => calibrate::run(args),
        Command::Cv(args) => cv::run(args),
        Command::Sweep(args) => sweep::run(args),
        Command::SimulateRecording(args) => simulate_recording::run(args),
        Command::Diffusion(args) => diffusion::run(args, stdout),
    }
}

/// The `--registry DIR` option, shared by every subcommand that reads or
/// writes the registry (flattened into their arguments).
///
/// Dereferences to the folder's path, so a subcommand passes
/// `&args.registry` wherever a `&Path` is wanted.
#[derive(Debug, Clone, Args)]
pub struct RegistryDir {
    /// Registry folder (registry.sqlite and blobs/; see docs/registry.md).
    #[arg(
        id = "registry",
        long = "registry",
        value_name = "DIR",
        global = true,
        env = env_vars::SCANLOC_REGISTRY,
        default_value = "registry"
    )]
    pub dir: PathBuf,
}

impl Deref for RegistryDir {
    type Target = Path;

    fn deref(&self) -> &Path {
        &self.dir
    }
}

/// The microscope flags of the commands that simulate frames or model them
/// (`simulate`, `train`, `locate --method likelihood`), flattened into
/// their arguments so each flag is spelt, documented and converted once.
///
/// Each per-frame parameter is a number or `uniform:LOW,HIGH` (drawn once
/// per frame, docs/simulator.md); for the likelihood detector a
/// distribution is a prior it marginalises. A command whose defaults
/// differ (`train`: margin 4, D uniform:0.75,1.75) changes them with
/// `mut_arg`, so `--help` shows its own.
#[derive(Debug, Clone, Args)]
pub struct MicroscopeArgs {
    /// Diffusion coefficient D in µm²/s: a number or uniform:LOW,HIGH (per frame).
    #[arg(long, default_value = "1.0")]
    pub diffusion: scanloc::sim::Distribution,
    /// N_qd, photons of an in-focus QD (PSF normalisation): a number or
    /// uniform:LOW,HIGH (per frame).
    #[arg(long, default_value = "7")]
    pub brightness: scanloc::sim::Distribution,
    /// N_bkg, expected background photons per pixel: a number or
    /// uniform:LOW,HIGH (per frame).
    #[arg(long, default_value = "8.4")]
    pub background: scanloc::sim::Distribution,
    /// Start depth relative to focus in µm: a number or uniform:LOW,HIGH
    /// (per frame).
    #[arg(long, default_value = "0")]
    pub z_start: scanloc::sim::Distribution,
    /// Start positions are uniform over the field shrunk by this many pixels.
    #[arg(long, default_value_t = 0.0)]
    pub margin_px: f64,
}

impl MicroscopeArgs {
    /// `base` with the values of these flags (the one conversion of the
    /// shared flags into simulator parameters; not yet validated).
    pub fn apply(&self, base: scanloc::sim::SimParams) -> scanloc::sim::SimParams {
        scanloc::sim::SimParams {
            diffusion_um2_s: self.diffusion,
            brightness: self.brightness,
            background: self.background,
            z_start: self.z_start,
            margin_px: self.margin_px,
            ..base
        }
    }
}
