//! `scanloc sweep`: parameter grids, and the executor options every sweep
//! front end (`cv`, `calibrate`, `sweep run`) shares.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::registry::Registry;
use crate::sweep::{self, Executor, SweepKind, SweepSpec, slurm::SlurmOptions};
use clap::{Args, Subcommand, ValueEnum};

/// Where a sweep's points run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub(super) enum ExecutorName {
    /// This machine (`--jobs` processes at a time).
    Local,
    /// A Slurm cluster: one job array, then an aggregation job.
    Slurm,
}

/// How to execute a sweep (cv folds, calibration points, grid points).
#[derive(Debug, Clone, Args)]
pub(super) struct ExecutorArgs {
    /// Where the points run: here, or as a Slurm job array (see README,
    /// "Running on a cluster").
    #[arg(long, value_enum, default_value = "local")]
    executor: ExecutorName,
    /// Local executor: points run at once, each in its own process.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=256))]
    jobs: u16,
    /// Slurm: at most this many array tasks at once (`--array=…%N`).
    #[arg(long)]
    max_parallel: Option<usize>,
    /// Slurm: the partition.
    #[arg(long)]
    partition: Option<String>,
    /// Slurm: time limit per task (`--time`, e.g. 2:00:00).
    #[arg(long)]
    time: Option<String>,
    /// Slurm: CPUs per task; the task uses that many threads.
    #[arg(long)]
    cpus_per_task: Option<usize>,
    /// Slurm: memory per task (`--mem`, e.g. 4G).
    #[arg(long)]
    mem: Option<String>,
    /// Slurm: any other sbatch option, one per use (`--sbatch-arg=--account=lab`).
    #[arg(long = "sbatch-arg", allow_hyphen_values = true)]
    sbatch_args: Vec<String>,
    /// Slurm: follow the jobs to the end, then print the table (without
    /// it, scanloc returns after submitting; see `scanloc sweep status`).
    #[arg(long)]
    wait: bool,
}

impl ExecutorArgs {
    /// Whether any executor option was given (other than the default
    /// local executor with one job).
    pub(super) fn is_not_default(&self) -> bool {
        self.executor != ExecutorName::Local
            || self.jobs != 1
            || self.max_parallel.is_some()
            || self.partition.is_some()
            || self.time.is_some()
            || self.cpus_per_task.is_some()
            || self.mem.is_some()
            || !self.sbatch_args.is_empty()
            || self.wait
    }

    /// The library's executor.
    pub(super) fn executor(&self) -> Executor {
        match self.executor {
            ExecutorName::Local => Executor::Local {
                jobs: self.jobs as usize,
            },
            ExecutorName::Slurm => Executor::Slurm(SlurmOptions {
                max_parallel: self.max_parallel,
                partition: self.partition.clone(),
                time: self.time.clone(),
                cpus_per_task: self.cpus_per_task,
                mem: self.mem.clone(),
                sbatch_args: self.sbatch_args.clone(),
                wait: self.wait,
            }),
        }
    }
}

/// Runs sweep `spec` and prints its table (or, for a Slurm submission
/// without --wait, the job ids): the common tail of every front end.
pub(super) fn run_sweep(
    registry: &Path,
    spec: SweepSpec,
    executor: &ExecutorArgs,
    force: bool,
    json: bool,
    stdout: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let mut registry = Registry::open_to_write(registry, "sweep")?;
    let (file, result) = sweep::run(&mut registry, &spec, &executor.executor(), force)?;
    match result {
        Some(result) => {
            if json {
                writeln!(stdout, "{}", result.json)?;
            } else {
                write!(stdout, "{}", result.text)?;
            }
            result.check()?;
        }
        None => {
            let submission = file.submissions.last();
            if json {
                writeln!(
                    stdout,
                    "{}",
                    serde_json::json!({"sweep": file.id, "folder": file.dir(), "submission": submission})
                )?;
            } else if let Some(submission) = submission {
                writeln!(
                    stdout,
                    "sweep {}: array job {}, aggregation job {}\nfollow it with: scanloc sweep status {} --registry {}",
                    file.id,
                    submission.array_job,
                    submission.aggregate_job,
                    file.id,
                    file.registry.display()
                )?;
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Parameter sweeps: run the grid of a manifest's `sweep:` block (named
/// axes over manifest paths, every combination a recorded run), see where
/// a sweep stands, and the commands Slurm jobs run.
#[derive(Debug, Args)]
#[command(mut_arg("json", |arg| arg.global(true)))]
pub(super) struct SweepArgs {
    #[command(subcommand)]
    command: SweepCommand,
    #[command(flatten)]
    registry: super::RegistryDir,
    #[command(flatten)]
    format: super::JsonFlag,
}

#[derive(Debug, Subcommand)]
enum SweepCommand {
    /// Run every point of the manifest's `sweep:` grid, then print the
    /// metric per point.
    Run {
        /// The manifest, with a `sweep:` block.
        manifest: PathBuf,
        #[command(flatten)]
        executor: ExecutorArgs,
        /// Recompute every point (local executor) and check the results
        /// equal the stored ones.
        #[arg(long)]
        force: bool,
    },
    /// Where each point of a sweep stands (done, in shard, pending, running,
    /// failed with its log, missing) and its aggregation job.
    Status {
        /// The sweep id (or a unique prefix, or its folder).
        sweep: String,
    },
    /// Run one point of a sweep into its shard (what an array task runs).
    #[command(hide = true)]
    Task {
        /// The sweep's folder.
        dir: PathBuf,
        /// The point (array index).
        index: usize,
        /// Write into the main registry instead of a shard (local jobs).
        #[arg(long)]
        direct: bool,
        #[arg(long)]
        force: bool,
    },
    /// Import a sweep's shards into its registry and print its table (what
    /// the aggregation job runs; by hand after a failed task).
    Aggregate {
        /// The sweep id (or a unique prefix, or its folder).
        sweep: String,
    },
}

pub(super) fn run(args: SweepArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let json = args.format.json;
    match args.command {
        SweepCommand::Run {
            manifest,
            executor,
            force,
        } => {
            let manifest_text = std::fs::read_to_string(&manifest).map_err(|e| {
                crate::error::input_error(format!("{}: cannot read: {e}", manifest.display()))
            })?;
            let spec = SweepSpec {
                kind: SweepKind::Grid,
                manifest_path: manifest.display().to_string(),
                manifest_text,
            };
            run_sweep(&args.registry, spec, &executor, force, json, stdout)
        }
        SweepCommand::Status { sweep: id } => {
            let dir = sweep::find(&args.registry, &id)?;
            let (file, states, aggregation) = sweep::slurm::status(&dir)?;
            if json {
                writeln!(
                    stdout,
                    "{}",
                    serde_json::json!({"sweep": file.id, "folder": dir, "points": states,
                        "submissions": file.submissions, "aggregation": aggregation})
                )?;
            } else {
                writeln!(stdout, "sweep {} ({})", file.id, dir.display())?;
                for state in &states {
                    writeln!(
                        stdout,
                        "  {:>3}  {:<24} {:<10} {}{}",
                        state.index,
                        state.label,
                        state.status,
                        state.error.as_deref().unwrap_or(""),
                        state
                            .log
                            .as_ref()
                            .filter(|_| !state.status.is_done())
                            .map(|l| format!("  log {l}"))
                            .unwrap_or_default()
                    )?;
                }
                if let Some(aggregation) = aggregation {
                    writeln!(stdout, "aggregation: {aggregation}")?;
                }
            }
            Ok(ExitCode::SUCCESS)
        }
        SweepCommand::Task {
            dir,
            index,
            direct,
            force,
        } => {
            let summary = sweep::task(&dir, index, direct, force)?;
            // The last line of the log: read back by the aggregation.
            writeln!(stdout, "{}", serde_json::to_string(&summary)?)?;
            Ok(ExitCode::SUCCESS)
        }
        SweepCommand::Aggregate { sweep: id } => {
            let dir = sweep::find(&args.registry, &id)?;
            let file = sweep::SweepFile::load(&dir)?;
            let mut registry = Registry::open_existing(&file.registry)?;
            registry.refuse_read_only("sweep aggregate")?;
            let result = sweep::import_and_aggregate(&mut registry, &dir)?;
            if json {
                writeln!(stdout, "{}", result.json)?;
            } else {
                write!(stdout, "{}", result.text)?;
            }
            result.check()?;
            Ok(ExitCode::SUCCESS)
        }
    }
}
