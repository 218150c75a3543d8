//! Command-line definitions: one module per subcommand, each only parsing
//! its arguments and calling the library.

mod bench;
mod bench_cnn;
mod calibrate;
mod check;
mod cv;
mod diffusion;
mod fit_microscope;
mod link;
mod locate;
mod microscope;
mod registry;
mod report;
mod reproduce;
mod run;
mod score;
mod score_tracks;
mod simulate;
mod simulate_recording;
mod sweep;
mod track;
mod train;

use std::ffi::OsString;
use std::io::Write;
use std::ops::Deref;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::env_vars;
use clap::{Args, Parser, Subcommand};

pub use microscope::{MicroscopeArgs, ScanGeometryArgs};

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
    Link(link::LinkArgs),
    SimulateRecording(simulate_recording::SimulateRecordingArgs),
    Diffusion(diffusion::DiffusionArgs),
    ScoreTracks(score_tracks::ScoreTracksArgs),
    Track(track::TrackArgs),
    FitMicroscope(fit_microscope::FitMicroscopeArgs),
}

/// The whole command: parses `args` (the program name first), runs the
/// command and returns its exit code (0 success, 1 a check failed, 2 bad
/// input). Results a command prints go to `stdout`; a refusal is one
/// `error: …` line on `stderr`, as are clap's usage errors (help and
/// `--version` go to `stdout`, exit 0). `styled` keeps clap's colours, for
/// a terminal.
///
/// Every command writes through `stdout` and `stderr`; only progress bars
/// and log warnings go to the process's standard error. `main` passes the
/// process's streams; the in-process tests pass buffers.
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
    let outcome = run(cli, &mut *stdout, &mut *stderr);
    // Nothing to report a failed flush to (a closed stream).
    let _ = stdout.flush();
    match outcome {
        Ok(code) => code,
        Err(error) => {
            // One line: the context chain joined by ": ".
            let _ = writeln!(stderr, "error: {error:#}").and_then(|_| stderr.flush());
            ExitCode::from(crate::error::exit_code(&error) as u8)
        }
    }
}

/// Runs the parsed command: results it prints go to `stdout`, its notes
/// (training epochs, a shard that failed to import, `check`'s "ok") to
/// `stderr`.
pub fn run(cli: Cli, stdout: &mut dyn Write, stderr: &mut dyn Write) -> anyhow::Result<ExitCode> {
    // Before the thread pool is first built: rayon would try to start
    // every thread RAYON_NUM_THREADS asks for.
    let threads = crate::env_vars::RAYON_NUM_THREADS;
    if let Some(value) = std::env::var_os(threads) {
        crate::limits::check_thread_count(threads, &value)?;
    }
    for name in crate::env_vars::BOOLEAN_FLAGS {
        crate::env_vars::flag(name).map_err(crate::error::input_error)?;
    }
    match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Bench(args) => bench::run(args, stdout),
        Command::Locate(args) => locate::run(args, stdout),
        Command::Score(args) => score::run(args, stdout),
        Command::Train(args) => train::run(args, stdout, stderr),
        Command::Run(args) => run::run(args, stdout),
        Command::Check(args) => check::run(args, stdout, stderr),
        Command::Reproduce(args) => reproduce::run(args, stdout, stderr),
        Command::Registry(args) => registry::run(args, stdout, stderr),
        Command::Report(args) => report::run(args, stdout),
        Command::Calibrate(args) => calibrate::run(args, stdout),
        Command::Cv(args) => cv::run(args, stdout),
        Command::Sweep(args) => sweep::run(args, stdout),
        Command::Link(args) => link::run(args, stdout),
        Command::SimulateRecording(args) => simulate_recording::run(args),
        Command::Diffusion(args) => diffusion::run(args, stdout, stderr),
        Command::ScoreTracks(args) => score_tracks::run(args, stdout),
        Command::Track(args) => track::run(args, stdout),
        Command::FitMicroscope(args) => fit_microscope::run(args, stdout),
    }
}

/// The `--registry DIR` option, shared by every subcommand that reads or
/// writes the registry (flattened into their arguments).
///
/// Dereferences to the folder's path, so a subcommand passes
/// `&args.registry` wherever a `&Path` is wanted.
#[derive(Debug, Clone, Args)]
pub(crate) struct RegistryDir {
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

/// The `--json` flag of every command that can print JSON instead of text
/// (flattened into their arguments; `registry` and `sweep` make it global
/// with `mut_arg`, so it may follow their subcommand). What each command's
/// JSON holds: its `--help`.
#[derive(Debug, Clone, Copy, Args)]
pub(crate) struct JsonFlag {
    /// Print JSON on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Parses a whole-number flag (frames, counts, seeds): a negative or
/// fractional value is answered as out of range, not as clap's "unexpected
/// argument" or a parse error of the digits.
pub(crate) fn whole_number<T: std::str::FromStr>(text: &str) -> Result<T, String> {
    text.trim()
        .parse::<T>()
        .map_err(|_| match text.trim().parse::<f64>() {
            Ok(value) if value < 0.0 => format!(
                "out of range: must be a whole number ≥ 0, got {}",
                crate::error::readable(value)
            ),
            Ok(value) if value.fract() != 0.0 => format!(
                "must be a whole number ≥ 0, got {}",
                crate::error::readable(value)
            ),
            Ok(value) => format!(
                "out of range: too large, got {}",
                crate::error::readable(value)
            ),
            Err(_) => format!("must be a whole number ≥ 0, got {text:?}"),
        })
}

/// The diffusion coefficients of the test sets a command simulates
/// (`train --test-frames`, `bench cnn-locate`), one test set per value.
#[derive(Debug, Clone, Args)]
pub(crate) struct TestDiffusionArgs {
    /// Diffusion coefficients of the test sets in µm²/s, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "0.75,1.0,1.75")]
    pub test_diffusion: Vec<f64>,
}

impl TestDiffusionArgs {
    /// The coefficients, each checked to be a finite number ≥ 0.
    pub(crate) fn checked(&self) -> anyhow::Result<&[f64]> {
        for &d in &self.test_diffusion {
            crate::error::require_non_negative("--test-diffusion", d)?;
        }
        Ok(&self.test_diffusion)
    }
}
