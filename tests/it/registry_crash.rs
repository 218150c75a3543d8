//! A registry survives what users do to runs: SIGKILL mid-run, and several
//! runs started at once on one registry.

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::*;
use serde_json::Value;

fn json(args: &[&str]) -> Value {
    let output = scanloc(args);
    assert!(output.status.success(), "{args:?}: {}", stderr(&output));
    serde_json::from_str(&stdout(&output)).unwrap()
}

/// A tiny first dataset (so one step is recorded quickly) and a large
/// second one (so the process is still simulating when it is killed).
const SLOW: &str = "\
name: slow
seed: 5
datasets:
  quick:
    frames: 10
  slow:
    frames: 120000
";

#[test]
fn a_run_killed_mid_way_leaves_a_usable_registry() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let manifest = write_manifest(dir.path(), "slow.yaml", SLOW);
    let mut child = Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(["run", manifest.to_str().unwrap(), "--registry", reg])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until the first step is recorded, then kill without warning.
    let database = registry.join("registry.sqlite");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        assert!(Instant::now() < deadline, "the run never recorded a step");
        if database.exists()
            && let Ok(conn) = rusqlite::Connection::open_with_flags(
                &database,
                rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY,
            )
            && conn
                .query_row("SELECT count(*) FROM run_steps", [], |r| r.get::<_, i64>(0))
                .is_ok_and(|n| n >= 1)
        {
            break;
        }
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run finished before it could be killed"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap(); // SIGKILL on Unix
    let status = child.wait().unwrap();
    assert!(!status.success(), "the run was killed, not finished");

    // The registry opens, verifies, and shows the run as unfinished.
    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert!(
        verify.status.success(),
        "{}{}",
        stdout(&verify),
        stderr(&verify)
    );
    let runs = json(&["registry", "runs", "--registry", reg, "--json"]);
    assert_eq!(runs.as_array().unwrap().len(), 1);
    assert_eq!(runs[0]["status"], "unfinished", "{runs}");
    assert!(runs[0]["ended_at"].is_null());

    // A rerun completes, reusing the step that was finished.
    let rerun = run_json(&manifest, &registry, &[]);
    assert_eq!(rerun["status"], "done");
    assert_eq!(rerun["cached_steps"], 1);
    assert_eq!(rerun["computed_steps"], 1);
    let runs = json(&["registry", "runs", "--registry", reg, "--json"]);
    let statuses: Vec<&str> = runs
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["status"].as_str().unwrap())
        .collect();
    assert_eq!(statuses, ["done", "unfinished"]);
    // The killed run is marked in the database itself, not only displayed.
    let rows = json(&[
        "registry",
        "sql",
        "--registry",
        reg,
        "--json",
        "SELECT status FROM runs ORDER BY started_at",
    ]);
    assert_eq!(
        rows,
        serde_json::json!([{"status": "unfinished"}, {"status": "done"}])
    );
    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert!(verify.status.success(), "{}", stdout(&verify));
    // What the killed run left behind (temporaries) is collectable.
    let gc = scanloc(&["registry", "gc", "--registry", reg]);
    assert!(gc.status.success());
}

#[test]
fn four_runs_started_at_once_all_finish_and_are_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let children: Vec<_> = (0..4)
        .map(|_| {
            Command::new(env!("CARGO_BIN_EXE_scanloc"))
                .args([
                    "run",
                    smoke().to_str().unwrap(),
                    "--json",
                    "--registry",
                    reg,
                ])
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut ids = Vec::new();
    let mut tables = Vec::new();
    for child in children {
        let output = child.wait_with_output().unwrap();
        assert!(output.status.success(), "{}", stderr(&output));
        let value: Value = serde_json::from_str(&stdout(&output)).unwrap();
        ids.push(value["run"].as_str().unwrap().to_string());
        tables.push(value["auc"].clone());
    }
    ids.sort();
    ids.dedup();
    assert_eq!(ids.len(), 4, "four distinct runs");
    assert!(tables.windows(2).all(|w| w[0] == w[1]));
    let runs = json(&["registry", "runs", "--registry", reg, "--json"]);
    let mut recorded: Vec<String> = runs
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            assert_eq!(r["status"], "done");
            r["id"].as_str().unwrap().to_string()
        })
        .collect();
    recorded.sort();
    assert_eq!(recorded, ids);
    // Each artefact is stored once, whoever made it.
    let rows = json(&[
        "registry",
        "sql",
        "--registry",
        reg,
        "--json",
        "SELECT count(*) AS n, count(DISTINCT key) AS distinct_keys FROM artefacts",
    ]);
    assert_eq!(rows[0]["n"], rows[0]["distinct_keys"]);
    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert!(verify.status.success(), "{}", stdout(&verify));
}
