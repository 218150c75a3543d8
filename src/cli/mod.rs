//! Command-line definitions: one module per subcommand, each only parsing
//! its arguments and calling the library.

mod bench;
mod bench_cnn;
mod calibrate;
mod check;
mod cv;
mod locate;
mod registry;
mod report;
mod reproduce;
mod run;
mod score;
mod simulate;
mod train;

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
}

/// Runs the parsed command.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Locate(args) => locate::run(args),
        Command::Score(args) => score::run(args),
        Command::Train(args) => train::run(args),
        Command::Run(args) => run::run(args),
        Command::Check(args) => check::run(args),
        Command::Reproduce(args) => reproduce::run(args),
        Command::Registry(args) => registry::run(args),
        Command::Report(args) => report::run(args),
        Command::Calibrate(args) => calibrate::run(args),
        Command::Cv(args) => cv::run(args),
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
