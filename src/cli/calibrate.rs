//! `scanloc calibrate`: the brightness sweep (`docs/metric.md`, "Calibrating the
//! brightness").

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use scanloc::manifest;
use scanloc::registry::Registry;
use scanloc::run::calibrate;

/// Sweep the QD brightness N_qd and report, per value, how close a
/// detector's AUC row comes to its reference row (sum of squared
/// differences over the reference cells). Every grid point is recorded as
/// a run of kind `calibrate`; datasets are cached, so a repeated sweep is
/// fast.
///
/// Why and how N_qd is calibrated: docs/metric.md.
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// The experiment manifest (needs a `reference` row for the detector).
    manifest: PathBuf,
    /// The detector to calibrate against its reference row.
    #[arg(long, default_value = "trackpy")]
    detector: String,
    /// Brightness values (N_qd) to try, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "5,6,6.5,7,7.5,8,9")]
    brightness: Vec<f64>,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    registry: super::RegistryDir,
}

pub fn run(args: CalibrateArgs) -> anyhow::Result<ExitCode> {
    let manifest = manifest::load(&args.manifest)?;
    let mut registry = Registry::open(&args.registry)?;
    let json = args.json;
    if !json {
        println!("{:>10} {:>10} {:>14}  run", "N_qd", "SSE", "cells ≤ 0.05");
    }
    let result = calibrate::calibrate(
        &mut registry,
        &manifest,
        &args.detector,
        &args.brightness,
        |point| {
            if !json {
                println!(
                    "{:>10} {:>10.4} {:>11}/{:<2}  {}",
                    point.brightness, point.sse, point.cells_within_0_05, point.cells, point.run
                );
            }
        },
    )?;
    if json {
        println!("{}", serde_json::to_string(&result)?);
    } else {
        println!(
            "best N_qd for {}: {}",
            result.detector, result.best_brightness
        );
    }
    Ok(ExitCode::SUCCESS)
}
