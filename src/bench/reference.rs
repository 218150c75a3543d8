//! Running a Python reference implementation for a same-run comparison.

use std::path::Path;
use std::process::Command;

/// Runs `python script args…` and parses the last line of its stdout as
/// `frames_per_second=<number>`. Errors say why the reference could not run
/// (no interpreter, missing package, bad output), so benchmarks can report
/// it as skipped rather than fail.
pub(crate) fn run_python(python: &str, script: &Path, args: &[&str]) -> Result<f64, String> {
    let [fps] = run_python_figures(python, script, args, &[], ["frames_per_second"])?;
    Ok(fps)
}

/// Runs `python script args…` with the extra environment variables `env`
/// and reads, for each of `keys`, the last line of its stdout of the form
/// `key=<number>`. Errors as [`run_python`].
pub(crate) fn run_python_figures<const K: usize>(
    python: &str,
    script: &Path,
    args: &[&str],
    env: &[(&str, &str)],
    keys: [&str; K],
) -> Result<[f64; K], String> {
    if !script.exists() {
        return Err(format!("{} not found", script.display()));
    }
    let output = Command::new(python)
        .arg(script)
        .args(args)
        .envs(env.iter().copied())
        .output()
        .map_err(|e| format!("cannot run {python}: {e}"))?;
    if !output.status.success() {
        let stderr = String::from_utf8_lossy(&output.stderr);
        let last = stderr.lines().last().unwrap_or("").to_string();
        return Err(format!("{} failed: {last}", script.display()));
    }
    let stdout = String::from_utf8_lossy(&output.stdout);
    let mut figures = [0.0; K];
    for (figure, key) in figures.iter_mut().zip(keys) {
        let prefix = format!("{key}=");
        *figure = stdout
            .lines()
            .rev()
            .find_map(|line| line.strip_prefix(&prefix))
            .and_then(|value| value.trim().parse::<f64>().ok())
            .ok_or_else(|| format!("{} printed no {key}= line", script.display()))?;
    }
    Ok(figures)
}
