//! `scanloc calibrate`: the brightness sweep (`docs/metric.md`, "Calibrating the
//! brightness").

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::manifest;
use crate::sweep::{SweepKind, SweepSpec};
use clap::Args;

use super::sweep::{ExecutorArgs, run_sweep};

/// Sweep the QD brightness N_qd and report, per value, how close a
/// detector's AUC row comes to its reference row (sum of squared
/// differences over the reference cells). Every grid point is recorded as
/// a run of kind `calibrate`; datasets are cached, so a repeated sweep is
/// fast.
///
/// Why and how N_qd is calibrated: docs/metric.md.
#[derive(Debug, Args)]
pub(super) struct CalibrateArgs {
    /// The experiment manifest (needs a `reference` row for the detector).
    manifest: PathBuf,
    /// The detector to calibrate against its reference row.
    #[arg(long, default_value = "trackpy")]
    detector: String,
    /// Brightness values (N_qd) to try, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "5,6,6.5,7,7.5,8,9")]
    brightness: Vec<f64>,
    #[command(flatten)]
    format: super::JsonFlag,
    #[command(flatten)]
    registry: super::RegistryDir,
    /// Where the grid points run (each a recorded run, then the table).
    #[command(flatten)]
    executor: ExecutorArgs,
}

pub(super) fn run(args: CalibrateArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let manifest = manifest::load(&args.manifest)?;
    let spec = SweepSpec {
        kind: SweepKind::Calibrate {
            detector: args.detector,
            brightness: args.brightness,
        },
        manifest_path: manifest.source.clone(),
        manifest_text: manifest.text.clone(),
    };
    run_sweep(
        &args.registry,
        spec,
        &args.executor,
        false,
        args.format.json,
        stdout,
    )
}
