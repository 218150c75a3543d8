//! `scanloc report`: a Markdown report of a recorded run, with figures.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::registry::{Found, Registry, RunKind};
use clap::Args;

/// Write a Markdown report of a run: the AUC table beside the reference
/// (the paper's Table 1), localisation quality, where the AUC is lost, each
/// detector's gap to the attainable bound (a likelihood detector on the
/// same frames) with its bootstrap uncertainty, the scene and calibration
/// figures, precision–recall curves, reliability diagrams, example frames
/// with trajectories, localisation panels and error histograms (PNG and
/// SVG).
///
/// The metric and the paper's table: docs/metric.md. Figures are drawn with
/// the embedded Roboto font, or the TrueType file named by SCANLOC_FONT.
#[derive(Debug, Args)]
pub(super) struct ReportArgs {
    /// The run id (a unique prefix is enough), or `latest` for the most
    /// recent finished run of kind `run`.
    run: String,
    /// Output folder, written whole or not at all: a new path, or a report
    /// folder (report.md and figures), which is replaced; a folder holding
    /// anything else (a link, a FIFO, another file) is refused and left as
    /// it is.
    #[arg(long, default_value = "reports/latest")]
    out: PathBuf,
    #[command(flatten)]
    registry: super::RegistryDir,
}

pub(super) fn run(args: ReportArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let registry = Registry::open_existing(&args.registry)?;
    let run_id = if args.run == "latest" {
        registry
            .latest_done_run(RunKind::Run)?
            .map(|run| run.id)
            .ok_or_else(|| {
                crate::error::input_error(format!(
                    "{}: no finished run to report on",
                    args.registry.display()
                ))
            })?
    } else {
        match registry.resolve_id(&args.run)? {
            Found::Run(id) => id,
            _ => {
                return Err(crate::error::input_error(format!(
                    "{}: not a run",
                    args.run
                )));
            }
        }
    };
    let path = crate::report::run_report::write_report(&registry, &run_id, &args.out)?;
    writeln!(stdout, "{}", path.display())?;
    Ok(ExitCode::SUCCESS)
}
