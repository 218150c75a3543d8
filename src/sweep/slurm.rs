//! The Slurm executor: one job array with a task per missing point (array
//! index = point index) and an aggregation job that waits for it
//! (`--dependency=afterok:ARRAY --kill-on-invalid-dep=yes`) and imports the
//! tasks' shards with a single writer. Both batch scripts are written into
//! the sweep's folder (`task.sh`, `aggregate.sh`), where a user can read and
//! resubmit them; logs go to its `logs/` folder.
//!
//! Job states come from `scontrol -o show job` (`sacct` needs slurmdbd,
//! which a cluster may not run). If a task fails, Slurm cancels the
//! aggregation job (its dependency can never be met); `--wait` then runs
//! the aggregation itself, which imports the shards that finished and
//! reports the points that did not, with their logs. Finished jobs vanish
//! from `scontrol` after the cluster's MinJobAge; the sweep's folder and
//! registry still say where every point stands.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::{
    Point, PointState, PointStatus, RESULT_FILE, SweepFile, SweepResult, aggregate,
    import_and_aggregate, import_shards, point_is_stored, shard_failure, shard_run,
};
use crate::error::input_error;
use crate::manifest::Manifest;
use crate::registry::{Registry, RunStatus, utc_now};

/// Options of `--executor slurm`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SlurmOptions {
    /// At most this many tasks at once (`--array=…%N`).
    pub max_parallel: Option<usize>,
    pub partition: Option<String>,
    /// Time limit per task, in any form sbatch accepts (`1:00:00`).
    pub time: Option<String>,
    pub cpus_per_task: Option<usize>,
    /// Memory per task, in any form sbatch accepts (`4G`).
    pub mem: Option<String>,
    /// Further sbatch options, one per entry (`--account=lab`), written into
    /// both batch scripts.
    pub sbatch_args: Vec<String>,
    /// Follow the jobs to the end and aggregate, instead of returning after
    /// the submission.
    pub wait: bool,
}

/// One submission of a sweep.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Submission {
    pub array_job: String,
    pub aggregate_job: String,
    /// The points submitted (array indices).
    pub points: Vec<usize>,
    pub submitted_at: String,
}

/// States in which a Slurm job will not change any more.
fn is_terminal(state: &str) -> bool {
    matches!(
        state,
        "COMPLETED"
            | "FAILED"
            | "CANCELLED"
            | "TIMEOUT"
            | "NODE_FAIL"
            | "PREEMPTED"
            | "OUT_OF_MEMORY"
            | "BOOT_FAIL"
            | "DEADLINE"
    )
}

/// `text` as one single-quoted shell word.
fn shell_quote(text: &str) -> String {
    format!("'{}'", text.replace('\'', r"'\''"))
}

/// Array indices as sbatch's `--array` wants them (`0-2,4,6-7`).
fn array_list(indices: &[usize]) -> String {
    let mut parts = Vec::new();
    let mut iter = indices.iter().copied().peekable();
    while let Some(start) = iter.next() {
        let mut end = start;
        while iter.peek() == Some(&(end + 1)) {
            end = iter.next().expect("peeked");
        }
        parts.push(if end == start {
            start.to_string()
        } else {
            format!("{start}-{end}")
        });
    }
    parts.join(",")
}

/// Parses an `ArrayTaskId` value (`3`, `0-4%2`, `1,3-5`) into indices.
fn parse_array_ids(text: &str) -> Vec<usize> {
    let text = text.split('%').next().unwrap_or("");
    let mut ids = Vec::new();
    for part in text.split(',') {
        let (range, step) = part.split_once(':').unwrap_or((part, "1"));
        let step: usize = step.parse().unwrap_or(1).max(1);
        match range.split_once('-') {
            Some((a, b)) => {
                if let (Ok(a), Ok(b)) = (a.parse::<usize>(), b.parse::<usize>()) {
                    ids.extend((a..=b).step_by(step));
                }
            }
            None => ids.extend(range.parse::<usize>().ok()),
        }
    }
    ids
}

/// One record of `scontrol -o show job`: its fields.
fn fields(line: &str) -> BTreeMap<&str, &str> {
    line.split_whitespace()
        .filter_map(|word| word.split_once('='))
        .collect()
}

/// One job, or one task of an array, as `scontrol` reports it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct JobRecord {
    /// The array index, for a task of an array.
    pub task: Option<usize>,
    /// `PENDING`, `RUNNING`, `COMPLETED`, `FAILED`, `CANCELLED`, …
    pub state: String,
    /// Why it is in that state (`DependencyNeverSatisfied`, …).
    pub reason: String,
}

/// What `scontrol -o show job ID` says: a record per job or array task;
/// `None` if Slurm no longer knows the job.
pub(crate) fn job_states(job: &str) -> anyhow::Result<Option<Vec<JobRecord>>> {
    let output = Command::new("scontrol")
        .args(["-o", "show", "job", job])
        .output()
        .context("running scontrol (is Slurm installed here?)")?;
    if !output.status.success() {
        let message = String::from_utf8_lossy(&output.stderr);
        if message.contains("Invalid job id") {
            return Ok(None);
        }
        anyhow::bail!("scontrol show job {job}: {}", message.trim());
    }
    let mut records = Vec::new();
    for line in String::from_utf8_lossy(&output.stdout).lines() {
        let fields = fields(line);
        let record = |task| JobRecord {
            task,
            state: fields
                .get("JobState")
                .copied()
                .unwrap_or("UNKNOWN")
                .to_string(),
            reason: fields.get("Reason").copied().unwrap_or("None").to_string(),
        };
        match fields.get("ArrayTaskId") {
            Some(ids) => records.extend(parse_array_ids(ids).into_iter().map(Some).map(record)),
            None => records.push(record(None)),
        }
    }
    Ok(Some(records))
}

/// Submits `script` with `sbatch --parsable` and returns the job id.
fn sbatch(script: &Path, extra: &[String]) -> anyhow::Result<String> {
    let output = Command::new("sbatch")
        .arg("--parsable")
        .args(extra)
        .arg(script)
        .output()
        .context("running sbatch (is Slurm installed here?)")?;
    if !output.status.success() {
        // Usually a bad option (partition, time, …): the user's input.
        return Err(input_error(format!(
            "sbatch {}: {}",
            script.display(),
            String::from_utf8_lossy(&output.stderr)
                .lines()
                .map(str::trim)
                .filter(|line| !line.is_empty())
                .collect::<Vec<_>>()
                .join("; ")
        )));
    }
    let text = String::from_utf8_lossy(&output.stdout);
    // `--parsable` prints `ID` or `ID;CLUSTER`.
    let id = text.trim().split(';').next().unwrap_or("").to_string();
    anyhow::ensure!(
        !id.is_empty() && id.chars().all(|c| c.is_ascii_digit()),
        "sbatch printed no job id: {text:?}"
    );
    Ok(id)
}

/// The `#SBATCH` lines every script of the sweep shares.
fn common_directives(options: &SlurmOptions) -> String {
    let mut lines = String::new();
    if let Some(partition) = &options.partition {
        lines.push_str(&format!("#SBATCH --partition={partition}\n"));
    }
    if let Some(time) = &options.time {
        lines.push_str(&format!("#SBATCH --time={time}\n"));
    }
    for arg in &options.sbatch_args {
        lines.push_str(&format!("#SBATCH {arg}\n"));
    }
    lines
}

fn check_options(options: &SlurmOptions) -> anyhow::Result<()> {
    let one_word = |name: &str, value: &str| {
        if value.is_empty() || value.contains(char::is_whitespace) {
            Err(input_error(format!(
                "{name}: one word without spaces, got {value:?}"
            )))
        } else {
            Ok(())
        }
    };
    for (name, value) in [
        ("--partition", &options.partition),
        ("--time", &options.time),
        ("--mem", &options.mem),
    ] {
        if let Some(value) = value {
            one_word(name, value)?;
        }
    }
    for arg in &options.sbatch_args {
        if !arg.starts_with('-') || arg.contains('\n') {
            return Err(input_error(format!(
                "--sbatch-arg: one sbatch option such as --account=lab, got {arg:?}"
            )));
        }
    }
    if options.max_parallel == Some(0) || options.cpus_per_task == Some(0) {
        return Err(input_error("--max-parallel, --cpus-per-task: must be ≥ 1"));
    }
    Ok(())
}

/// Submits the missing points of the sweep (after importing shards left by
/// an earlier submission) and, with `wait`, follows the jobs and returns
/// the result. With nothing missing, aggregates at once without Slurm.
pub(crate) fn submit(
    registry: &mut Registry,
    mut file: SweepFile,
    base: &Arc<Manifest>,
    points: &[Point],
    options: &SlurmOptions,
) -> anyhow::Result<(SweepFile, Option<SweepResult>)> {
    check_options(options)?;
    refuse_while_queued(&file)?;
    import_shards(registry, &file, points)?;
    let mut missing = Vec::new();
    for point in points {
        if !point_is_stored(registry, point)? {
            missing.push(point.index);
        }
    }
    if missing.is_empty() {
        crate::progress::note(format_args!(
            "sweep {}: every point is in the registry already; aggregating",
            file.id
        ));
        let result = aggregate(registry, &file, base, points, None)?;
        return Ok((file, Some(result)));
    }
    let submission = submit_jobs(&file, missing, options)?;
    crate::progress::note(format_args!(
        "sweep {}: submitted array job {} ({} of {} points: {}) and aggregation job {}; logs in {}",
        file.id,
        submission.array_job,
        submission.points.len(),
        points.len(),
        array_list(&submission.points),
        submission.aggregate_job,
        file.dir().join("logs").display()
    ));
    file.submissions.push(submission.clone());
    file.save()?;
    if !options.wait {
        return Ok((file, None));
    }
    follow(&file, &submission, points.len())?;
    let result = wait_for_result(registry, &file, &submission)?;
    Ok((file, Some(result)))
}

/// Refuses to submit while a job of the sweep's last submission is still
/// queued or running.
fn refuse_while_queued(file: &SweepFile) -> anyhow::Result<()> {
    let Some(last) = file.submissions.last() else {
        return Ok(());
    };
    for job in [&last.array_job, &last.aggregate_job] {
        if let Some(records) = job_states(job)?
            && records.iter().any(|r| !is_terminal(&r.state))
        {
            return Err(input_error(format!(
                "sweep {}: job {job} of its last submission is still queued or running; \
                 wait for it (scanloc sweep status {}) or cancel it (scancel {job})",
                file.id, file.id
            )));
        }
    }
    Ok(())
}

/// Writes the batch scripts and submits the array of the `missing` points
/// and the aggregation job that depends on it.
fn submit_jobs(
    file: &SweepFile,
    missing: Vec<usize>,
    options: &SlurmOptions,
) -> anyhow::Result<Submission> {
    let dir = file.dir();
    let task_script = dir.join("task.sh");
    let task = task_script_text(file, &missing, options);
    crate::io::write_bytes_atomically(&task_script, task.as_bytes())?;
    let array_job = sbatch(&task_script, &[])?;
    let aggregate_script = dir.join("aggregate.sh");
    let aggregate_text = aggregate_script_text(file, &array_job, options);
    crate::io::write_bytes_atomically(&aggregate_script, aggregate_text.as_bytes())?;
    let aggregate_job = match sbatch(&aggregate_script, &[]) {
        Ok(id) => id,
        Err(error) => {
            // An array nobody will import: take it back.
            let _ = Command::new("scancel").arg(&array_job).status();
            return Err(error.context(format!("array job {array_job} cancelled")));
        }
    };
    Ok(Submission {
        array_job,
        aggregate_job,
        points: missing,
        submitted_at: utc_now(),
    })
}

/// The array job's script: one task per point of `missing` (array index =
/// point index), each `scanloc sweep task` into its shard.
fn task_script_text(file: &SweepFile, missing: &[usize], options: &SlurmOptions) -> String {
    let dir = file.dir();
    let scanloc = shell_quote(&file.scanloc.display().to_string());
    let dir_word = shell_quote(&dir.display().to_string());
    let mut task = format!(
        "#!/bin/bash\n\
         # scanloc sweep {id}: one array task per point (array index = point index),\n\
         # each writing a shard registry under {dir}/shards/.\n\
         # Written by scanloc. Submitting the same scanloc command again submits\n\
         # only the points still missing; this script resubmits these points.\n\
         #SBATCH --job-name=scanloc-{id}\n\
         #SBATCH --array={array}{throttle}\n\
         #SBATCH --output={logs}/task-%a.out\n",
        id = file.id,
        dir = dir.display(),
        array = array_list(missing),
        throttle = options
            .max_parallel
            .map(|n| format!("%{n}"))
            .unwrap_or_default(),
        logs = dir.join("logs").display(),
    );
    if let Some(cpus) = options.cpus_per_task {
        task.push_str(&format!("#SBATCH --cpus-per-task={cpus}\n"));
    }
    if let Some(mem) = &options.mem {
        task.push_str(&format!("#SBATCH --mem={mem}\n"));
    }
    task.push_str(&common_directives(options));
    task.push_str(&format!(
        "# The task's threads: the CPUs Slurm gave it.\n\
         export RAYON_NUM_THREADS=\"${{SLURM_CPUS_PER_TASK:-1}}\"\n\
         exec {scanloc} sweep task {dir_word} \"$SLURM_ARRAY_TASK_ID\"\n"
    ));
    task
}

/// The aggregation job's script: after array job `array_job`, imports the
/// shards and writes the table.
fn aggregate_script_text(file: &SweepFile, array_job: &str, options: &SlurmOptions) -> String {
    let dir = file.dir();
    let scanloc = shell_quote(&file.scanloc.display().to_string());
    let dir_word = shell_quote(&dir.display().to_string());
    let mut text = format!(
        "#!/bin/bash\n\
         # scanloc sweep {id}: imports the shards of array job {array_job} into the\n\
         # registry (one writer) and writes the table to {dir}/{RESULT_FILE}.\n\
         # Slurm cancels it if a task fails; then run the same command by hand\n\
         # (or `scanloc sweep run`/`cv`/`calibrate` again with --wait).\n\
         #SBATCH --job-name=scanloc-{id}-aggregate\n\
         #SBATCH --dependency=afterok:{array_job}\n\
         #SBATCH --kill-on-invalid-dep=yes\n\
         #SBATCH --output={logs}/aggregate.out\n",
        id = file.id,
        dir = dir.display(),
        logs = dir.join("logs").display(),
    );
    text.push_str(&common_directives(options));
    text.push_str(&format!("exec {scanloc} sweep aggregate {dir_word}\n"));
    text
}

/// The sweep's result once the jobs of `submission` have ended: the
/// aggregation job's `result.json`, or if that job did not complete, an
/// aggregation here.
fn wait_for_result(
    registry: &mut Registry,
    file: &SweepFile,
    submission: &Submission,
) -> anyhow::Result<SweepResult> {
    let dir = file.dir();
    Ok(match job_states(&submission.aggregate_job)? {
        Some(records) if records.iter().all(|r| r.state == "COMPLETED") => {
            let path = dir.join(RESULT_FILE);
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("reading {}", path.display()))?;
            serde_json::from_str(&text).with_context(|| format!("reading {}", path.display()))?
        }
        other => {
            let why = other
                .and_then(|r| r.first().map(|r| format!("{} ({})", r.state, r.reason)))
                .unwrap_or_else(|| "gone".to_string());
            crate::progress::note(format_args!(
                "sweep {}: the aggregation job {} is {why}: aggregating here",
                file.id, submission.aggregate_job
            ));
            import_and_aggregate(registry, &dir)?
        }
    })
}

/// Polls the jobs of `submission` until the aggregation job has ended,
/// drawing a progress bar (or, off a terminal, a line per change).
fn follow(file: &SweepFile, submission: &Submission, total: usize) -> anyhow::Result<()> {
    let submitted = submission.points.len() as u64;
    let bar = crate::progress::bar(submitted, "tasks done");
    let terminal = std::io::stderr().is_terminal();
    let mut last_line = String::new();
    loop {
        let tasks = job_states(&submission.array_job)?.unwrap_or_default();
        let count = |wanted: &dyn Fn(&str) -> bool| {
            tasks
                .iter()
                .filter(|r| r.task.is_some() && wanted(&r.state))
                .count()
        };
        let (done, failed, running) = (
            count(&|s| s == "COMPLETED"),
            count(&|s| is_terminal(s) && s != "COMPLETED"),
            count(&|s| s == "RUNNING" || s == "COMPLETING"),
        );
        let pending = (submitted as usize).saturating_sub(done + failed + running);
        let aggregation = job_states(&submission.aggregate_job)?
            .and_then(|r| r.first().map(|r| r.state.clone()))
            .unwrap_or_else(|| "GONE".to_string());
        let line = format!(
            "sweep {} ({total} points): {done}/{submitted} tasks done, {running} running, {pending} pending, {failed} failed; aggregation {}",
            file.id,
            aggregation.to_lowercase()
        );
        bar.set_position(done as u64);
        if !terminal && line != last_line {
            crate::progress::note(&line);
        }
        last_line = line;
        if aggregation == "GONE" || is_terminal(&aggregation) {
            bar.finish_and_clear();
            return Ok(());
        }
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// Where each point of the sweep in `dir` stands: `done` (in the main
/// registry), `in shard` (finished, not yet imported), the Slurm state of
/// its task in the last submission, `failed` (with the shard's error and
/// the log), or `missing`. Also the aggregation job's state, if any.
pub fn status(dir: &Path) -> anyhow::Result<(SweepFile, Vec<PointState>, Option<String>)> {
    let file = SweepFile::load(dir)?;
    let (_, points) = super::points(&file.spec)?;
    let registry = Registry::open_existing(&file.registry)?;
    let last = file.submissions.last();
    let slurm_tasks: BTreeMap<usize, String> = match last {
        Some(submission) => job_states(&submission.array_job)
            .unwrap_or(None)
            .unwrap_or_default()
            .into_iter()
            .filter_map(|r| Some((r.task?, r.state)))
            .collect(),
        None => BTreeMap::new(),
    };
    let aggregation = last.and_then(|s| {
        let state = job_states(&s.aggregate_job).ok().flatten()?;
        state
            .first()
            .map(|r| format!("job {} {} ({})", s.aggregate_job, r.state, r.reason))
    });
    let mut states = Vec::new();
    for point in &points {
        let log = file.log(point.index);
        let log = log.is_file().then(|| log.display().to_string());
        let shard = shard_run(&file, point.index);
        let (status, run, error) = if point_is_stored(&registry, point)? {
            (PointStatus::DONE, None, None)
        } else if let Some((run, ..)) = shard
            .as_ref()
            .filter(|(_, status, _)| *status == RunStatus::Done)
        {
            (PointStatus::InShard, Some(run.clone()), None)
        } else if let Some(state) = slurm_tasks
            .get(&point.index)
            .filter(|s| !is_terminal(s) || shard.is_none())
        {
            let failed = is_terminal(state) && state != "COMPLETED";
            (
                PointStatus::Slurm(state.to_lowercase()),
                None,
                failed.then(|| format!("task {state}")),
            )
        } else if let Some((run, ..)) = shard {
            (
                PointStatus::FAILED,
                Some(run),
                Some(shard_failure(&file, point.index)),
            )
        } else {
            (PointStatus::Missing, None, None)
        };
        states.push(PointState {
            index: point.index,
            label: point.label.clone(),
            status,
            run,
            error,
            log,
            cached_steps: 0,
            computed_steps: 0,
        });
    }
    Ok((file, states, aggregation))
}

/// Whether Slurm's client commands are on the PATH and a controller
/// answers (`sinfo` succeeds).
pub fn available() -> bool {
    Command::new("sinfo")
        .arg("-h")
        .output()
        .is_ok_and(|o| o.status.success())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn array_lists_round_trip() {
        assert_eq!(array_list(&[0, 1, 2, 4, 6, 7]), "0-2,4,6-7");
        assert_eq!(parse_array_ids("0-2,4,6-7%2"), vec![0, 1, 2, 4, 6, 7]);
        assert_eq!(parse_array_ids("3"), vec![3]);
        assert_eq!(parse_array_ids("0-6:3"), vec![0, 3, 6]);
        assert_eq!(shell_quote("a'b"), r"'a'\''b'");
    }
}
