//! The registry against a hostile user and a hostile environment: SQL that
//! tries to write or to run forever, reproductions of runs that never
//! finished.

use crate::common;

use std::path::Path;
use std::process::Output;
use std::time::{Duration, Instant};

use common::*;

/// A manifest that runs in well under a second: one small dataset scored
/// by TrackPy's algorithm.
const TINY: &str = "\
name: tiny
seed: 11
datasets:
  a: {frames: 6, emitters: 2}
  b: {frames: 6, emitters: 2, diffusion_um2_s: 1.5}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [a, b]}
";

/// A registry holding one finished run of [`TINY`]; returns the run id.
fn registry_with_a_run(dir: &Path) -> String {
    let manifest = write_manifest(dir, "tiny.yaml", TINY);
    let run = run_json(&manifest, &dir.join("registry"), &[]);
    assert_eq!(run["status"], "done");
    run["run"].as_str().unwrap().to_string()
}

fn sql(registry: &Path, statement: &str) -> Output {
    scanloc(&[
        "registry",
        "sql",
        "--registry",
        registry.to_str().unwrap(),
        "--json",
        statement,
    ])
}

/// Edits the registry's database directly (as a crash or another tool
/// would leave it).
fn tamper(registry: &Path, statements: &str) {
    let conn = rusqlite::Connection::open(registry.join("registry.sqlite")).unwrap();
    conn.execute_batch(statements).unwrap();
}

/// The registry's files but SQLite's shared-memory index and an empty
/// write-ahead log, which any reader of a WAL database creates.
fn database_and_blobs(registry: &Path) -> std::collections::BTreeMap<std::path::PathBuf, String> {
    let mut files = snapshot(registry);
    files.remove(Path::new("registry.sqlite-shm"));
    let wal = files.remove(Path::new("registry.sqlite-wal"));
    let empty = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855";
    assert!(
        wal.is_none_or(|hash| hash == empty),
        "the write-ahead log holds writes"
    );
    files
}

/// A process id that is certainly not running: a child that has exited.
fn dead_pid() -> u32 {
    let mut child = std::process::Command::new("true").spawn().unwrap();
    let pid = child.id();
    child.wait().unwrap();
    pid
}

#[test]
fn registry_sql_reads() {
    let dir = tempfile::tempdir().unwrap();
    let id = registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let output = sql(&registry, "SELECT id, status FROM runs");
    assert!(output.status.success(), "{}", stderr(&output));
    let rows: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(rows, serde_json::json!([{"id": id, "status": "done"}]));
    // Introspection still works.
    for statement in [
        "PRAGMA table_info(runs)",
        "PRAGMA user_version",
        "WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c WHERE x < 10) SELECT sum(x) AS s FROM c",
    ] {
        let output = sql(&registry, statement);
        assert!(output.status.success(), "{statement}: {}", stderr(&output));
    }
}

#[test]
fn registry_sql_refuses_everything_that_writes_or_reaches_outside() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let copy = dir.path().join("copy.sqlite");
    let other = dir.path().join("other.sqlite");
    rusqlite::Connection::open(&other)
        .unwrap()
        .execute_batch("CREATE TABLE secret (x); INSERT INTO secret VALUES (42);")
        .unwrap();
    let before = database_and_blobs(&registry);
    let attempts = [
        format!("VACUUM INTO '{}'", copy.display()),
        "VACUUM".to_string(),
        format!("ATTACH DATABASE '{}' AS other", other.display()),
        format!(
            "ATTACH DATABASE '{}' AS fresh",
            dir.path().join("new.sqlite").display()
        ),
        "PRAGMA user_version = 7".to_string(),
        "PRAGMA journal_mode = DELETE".to_string(),
        "PRAGMA query_only = 0".to_string(),
        "PRAGMA writable_schema = ON".to_string(),
        "DELETE FROM runs".to_string(),
        "UPDATE runs SET status = 'done'".to_string(),
        "INSERT INTO blobs (sha256, bytes, created_at) VALUES ('x', 1, 'y')".to_string(),
        "DROP TABLE runs".to_string(),
        "CREATE TABLE t (x)".to_string(),
        "CREATE TEMP TABLE t (x)".to_string(),
        "BEGIN IMMEDIATE".to_string(),
        "REINDEX".to_string(),
        "ANALYZE".to_string(),
        "SELECT 1; DELETE FROM runs".to_string(),
        "SELECT load_extension('/nonexistent')".to_string(),
    ];
    for attempt in &attempts {
        let output = sql(&registry, attempt);
        let error = stderr(&output);
        assert_eq!(output.status.code(), Some(2), "{attempt}: {error}");
        assert!(error.starts_with("error: sql: "), "{attempt}: {error}");
        assert_eq!(error.trim_end().lines().count(), 1, "{attempt}: {error}");
    }
    assert!(!copy.exists(), "VACUUM INTO wrote a copy of the database");
    assert!(!dir.path().join("new.sqlite").exists());
    assert_eq!(
        database_and_blobs(&registry),
        before,
        "the registry changed"
    );
    // Refusals say why.
    let error = stderr(&sql(&registry, &attempts[0]));
    assert!(error.contains("only reads the registry"), "{error}");
    let error = stderr(&sql(&registry, &attempts[2]));
    assert!(error.contains("ATTACH"), "{error}");
}

#[test]
fn registry_sql_stops_a_query_that_never_ends() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let clock = Instant::now();
    // Runs forever without producing a row.
    let output = sql(
        &registry,
        "WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c) SELECT count(*) FROM c",
    );
    let error = stderr(&output);
    assert_eq!(output.status.code(), Some(2), "{error}");
    assert!(error.contains("stopped after"), "{error}");
    assert!(clock.elapsed() < Duration::from_secs(60));
    // Produces rows forever.
    let output = sql(
        &registry,
        "WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c) SELECT x FROM c",
    );
    let error = stderr(&output);
    assert_eq!(output.status.code(), Some(2), "{error}");
    assert!(
        error.contains("rows") || error.contains("stopped after"),
        "{error}"
    );
    // Grows one value without bound.
    let output = sql(&registry, "SELECT length(zeroblob(2000000000))");
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
}

/// What `reproduce` printed and how it exited.
fn reproduce(registry: &Path, run: &str) -> (Option<i32>, String, String) {
    let output = scanloc(&["reproduce", run, "--registry", registry.to_str().unwrap()]);
    (output.status.code(), stdout(&output), stderr(&output))
}

#[test]
fn reproducing_a_run_killed_mid_way_is_refused_with_what_to_do() {
    let dir = tempfile::tempdir().unwrap();
    let id = registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    // What a SIGKILL after the second step leaves: status running, a pid
    // that is gone, two steps, no end and no AUC table.
    tamper(
        &registry,
        &format!(
            "UPDATE runs SET status = 'running', ended_at = NULL, pid = {}, cached_steps = 0,
                 computed_steps = 0, rebuilt_steps = 0 WHERE id = '{id}';
             DELETE FROM run_steps WHERE run_id = '{id}' AND ordinal >= 2;
             DELETE FROM run_auc WHERE run_id = '{id}';",
            dead_pid()
        ),
    );
    let (code, out, err) = reproduce(&registry, &id);
    assert_eq!(code, Some(2), "stdout {out}\nstderr {err}");
    assert!(!out.contains("IDENTICAL"), "{out}");
    assert!(err.contains("unfinished"), "{err}");
    assert!(err.contains("scanloc run"), "{err}");
    assert_eq!(err.trim_end().lines().count(), 1, "{err}");
}

#[test]
fn a_failed_run_is_compared_on_what_it_recorded_and_the_verdict_matches_the_lines() {
    let dir = tempfile::tempdir().unwrap();
    let id = registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    // A run that failed after its steps (say, the disk filled while the
    // AUC table was written): no AUC rows.
    tamper(
        &registry,
        &format!(
            "UPDATE runs SET status = 'failed', error = 'disk full' WHERE id = '{id}';
             DELETE FROM run_auc WHERE run_id = '{id}';"
        ),
    );
    let (code, out, err) = reproduce(&registry, &id);
    assert_eq!(code, Some(0), "stdout {out}\nstderr {err}");
    assert!(out.contains("IDENTICAL"), "{out}");
    assert!(!out.contains("DIFFERS"), "{out}");
    assert!(
        out.contains("only the steps and AUC values it recorded"),
        "{out}"
    );

    // A recorded step that differs makes the verdict and the exit code
    // say so.
    tamper(
        &registry,
        &format!(
            "UPDATE run_steps SET artefact_key = 'not-the-key' WHERE run_id = '{id}' AND ordinal = 0;"
        ),
    );
    let (code, out, _) = reproduce(&registry, &id);
    assert_eq!(code, Some(1), "{out}");
    assert!(out.contains("DIFFERENT"), "{out}");
    assert!(out.contains("DIFFERS"), "{out}");
}

/// Runs `scanloc ARGS --registry DIR`.
fn on_registry(registry: &Path, args: &[&str]) -> Output {
    let mut all = args.to_vec();
    all.extend(["--registry", registry.to_str().unwrap()]);
    scanloc(&all)
}

#[test]
fn a_database_with_garbage_pages_is_not_written_into() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let database = registry.join("registry.sqlite");
    // Garbage over every page but the first (the header and schema stay
    // readable, the tables' b-trees do not).
    let mut bytes = std::fs::read(&database).unwrap();
    assert!(bytes.len() > 3 * 4096, "{} bytes", bytes.len());
    for (i, byte) in bytes.iter_mut().enumerate().skip(4096) {
        *byte = (i * 7919 % 251) as u8;
    }
    std::fs::write(&database, &bytes).unwrap();
    let before = snapshot(&registry);

    let manifest = dir.path().join("tiny.yaml");
    let run = on_registry(&registry, &["run", manifest.to_str().unwrap()]);
    let error = stderr(&run);
    assert_eq!(run.status.code(), Some(2), "{error}");
    assert!(error.contains("damaged"), "{error}");
    assert!(error.contains("registry verify"), "{error}");
    assert_eq!(error.trim_end().lines().count(), 1, "{error}");
    assert!(!error.contains("WAL"), "{error}");
    assert_eq!(
        snapshot(&registry),
        before,
        "the damaged registry was written"
    );
    let verify = on_registry(&registry, &["registry", "verify"]);
    assert_ne!(verify.status.code(), Some(0), "{}", stdout(&verify));
}

#[test]
fn a_lost_database_beside_stored_blobs_is_not_silently_recreated() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let database = registry.join("registry.sqlite");
    let manifest = dir.path().join("tiny.yaml");
    for lose in ["truncate", "delete"] {
        match lose {
            "truncate" => std::fs::write(&database, b"").unwrap(),
            _ => std::fs::remove_file(&database).unwrap(),
        }
        for name in ["registry.sqlite-wal", "registry.sqlite-shm"] {
            std::fs::remove_file(registry.join(name)).ok();
        }
        let before = snapshot(&registry);
        for args in [
            vec!["run", manifest.to_str().unwrap()],
            vec!["registry", "runs"],
        ] {
            let output = on_registry(&registry, &args);
            let error = stderr(&output);
            assert_eq!(output.status.code(), Some(2), "{lose} {args:?}: {error}");
            assert!(error.contains("restore registry.sqlite"), "{error}");
            assert_eq!(error.trim_end().lines().count(), 1, "{error}");
        }
        assert_eq!(snapshot(&registry), before, "{lose}: the registry changed");
    }
    // A folder with no blobs is a new registry, as before.
    let fresh = dir.path().join("fresh");
    std::fs::create_dir_all(fresh.join("blobs")).unwrap();
    run_json(&manifest, &fresh, &[]);
}

#[test]
fn an_artefact_whose_spec_no_longer_hashes_to_its_key_fails_verify() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let verify = on_registry(&registry, &["registry", "verify"]);
    assert!(verify.status.success(), "{}", stdout(&verify));
    tamper(
        &registry,
        "UPDATE artefacts SET spec = replace(spec, '\"frames\":6', '\"frames\":7')
         WHERE kind = 'dataset' AND name = 'a';",
    );
    let verify = on_registry(&registry, &["registry", "verify"]);
    assert_eq!(verify.status.code(), Some(1), "{}", stdout(&verify));
    let out = stdout(&verify);
    assert!(out.contains("BAD spec of dataset a"), "{out}");
}

/// `dir` bound read-only at `at` for as long as it lives (a real read-only
/// mount: writes fail with EROFS whoever the user is, root included).
pub(crate) struct ReadOnlyMount {
    pub(crate) at: std::path::PathBuf,
}

impl ReadOnlyMount {
    /// `None` where this process may not mount (not root, no mount
    /// namespace rights): the caller then says so and skips.
    pub(crate) fn bind(dir: &Path, at: &Path) -> Option<Self> {
        std::fs::create_dir_all(at).unwrap();
        let mount = |args: &[&str]| {
            std::process::Command::new("mount")
                .args(args)
                .stderr(std::process::Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        };
        let (dir, at_text) = (dir.to_str().unwrap(), at.to_str().unwrap());
        if !mount(&["--bind", dir, at_text]) {
            return None;
        }
        let mounted = Self {
            at: at.to_path_buf(),
        };
        assert!(
            mount(&["-o", "remount,ro,bind", at_text]),
            "bound {dir} but could not make it read-only"
        );
        Some(mounted)
    }
}

impl Drop for ReadOnlyMount {
    fn drop(&mut self) {
        std::process::Command::new("umount")
            .arg(&self.at)
            .status()
            .ok();
    }
}

#[test]
fn a_fully_cached_run_on_a_read_only_registry_is_served_and_says_it_was_not_recorded() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let manifest = dir.path().join("tiny.yaml");
    let recorded = run_json(&manifest, &registry, &[]);
    let Some(mount) = ReadOnlyMount::bind(&registry, &dir.path().join("ro")) else {
        eprintln!("skipped: cannot mount here (needs root and mount rights)");
        return;
    };
    assert!(
        std::fs::write(mount.at.join("probe"), b"x").is_err(),
        "the mount is writable"
    );
    let before = snapshot(&registry);
    let output = on_registry(&mount.at, &["run", manifest.to_str().unwrap(), "--json"]);
    let error = stderr(&output);
    assert!(output.status.success(), "{error}");
    let served: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(served["auc"], recorded["auc"]);
    assert_eq!(served["cached_steps"], recorded["cached_steps"]);
    assert!(error.contains("read-only"), "{error}");
    assert!(error.contains("could not be recorded"), "{error}");
    // What is not stored cannot be served: refused before any work.
    let more = write_manifest(
        dir.path(),
        "more.yaml",
        &TINY.replace("b: {frames: 6,", "b: {frames: 7,"),
    );
    let output = on_registry(&mount.at, &["run", more.to_str().unwrap()]);
    let error = stderr(&output);
    assert_eq!(output.status.code(), Some(2), "{error}");
    assert!(error.contains("not stored intact"), "{error}");
    drop(mount);
    assert_eq!(
        snapshot(&registry),
        before,
        "the read-only registry changed"
    );
}

/// A run whose first step takes a few seconds (the others are quick).
const SHARED: &str = "\
name: shared
seed: 3
datasets:
  a: {frames: 40000}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [a]}
";

fn spawn_run(manifest: &Path, registry: &Path) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(["run", manifest.to_str().unwrap(), "--json", "--registry"])
        .arg(registry)
        .env_remove("SCANLOC_REGISTRY")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

#[test]
fn identical_runs_wait_for_a_step_another_run_computes_and_reuse_it() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let manifest = write_manifest(dir.path(), "shared.yaml", SHARED);
    let first = spawn_run(&manifest, &registry);
    // Once the first run has claimed its first step, start two more.
    let database = registry.join("registry.sqlite");
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        assert!(
            Instant::now() < deadline,
            "the first run never claimed a step"
        );
        let claimed = rusqlite::Connection::open_with_flags(
            &database,
            rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY,
        )
        .and_then(|c| {
            c.query_row("SELECT count(*) FROM step_claims", [], |r| {
                r.get::<_, i64>(0)
            })
        })
        .is_ok_and(|n| n > 0);
        if claimed {
            break;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    let others = [
        spawn_run(&manifest, &registry),
        spawn_run(&manifest, &registry),
    ];
    let mut computed = 0;
    let mut waited = 0;
    let mut tables = Vec::new();
    for child in std::iter::once(first).chain(others) {
        let output = child.wait_with_output().unwrap();
        assert!(output.status.success(), "{}", stderr(&output));
        let run: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
        computed += run["computed_steps"].as_u64().unwrap();
        tables.push(run["auc"].clone());
        let error = stderr(&output);
        if error.contains("waiting for dataset/a: run ") {
            waited += 1;
            assert!(error.contains("is computing it"), "{error}");
        }
    }
    assert_eq!(computed, 3, "each of the 3 steps computed once, by one run");
    assert_eq!(waited, 2, "both later runs waited for the first");
    assert!(tables.windows(2).all(|w| w[0] == w[1]));
    let rows = sql(&registry, "SELECT count(*) AS n FROM step_claims");
    assert_eq!(stdout(&rows).trim(), r#"[{"n":0}]"#, "claims are released");
}

#[test]
fn a_claim_left_by_a_killed_run_is_taken_over() {
    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let manifest = write_manifest(
        dir.path(),
        "more.yaml",
        &TINY.replace("a: {frames: 6,", "a: {frames: 7,"),
    );
    let check = scanloc(&["check", manifest.to_str().unwrap(), "--json"]);
    let plan: serde_json::Value = serde_json::from_str(&stdout(&check)).unwrap();
    let key = plan["plan"][0]["key"].as_str().unwrap().to_string();
    tamper(
        &registry,
        &format!(
            "INSERT INTO step_claims (key, run_id, host, pid, claimed_at)
             VALUES ('{key}', 'killed-run', '{}', {}, '2026-01-01T00:00:00.000Z');",
            scanloc::registry::host_name(),
            dead_pid()
        ),
    );
    let output = on_registry(&registry, &["run", manifest.to_str().unwrap(), "--json"]);
    let error = stderr(&output);
    assert!(output.status.success(), "{error}");
    assert!(!error.contains("waiting"), "{error}");
    let run: serde_json::Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(run["status"], "done");
}

/// Starts `scanloc run` of [`TINY`] on `registry` and returns it with a
/// channel of its stderr lines as they come.
fn spawn_run_reading_stderr(
    manifest: &Path,
    registry: &Path,
) -> (std::process::Child, std::sync::mpsc::Receiver<String>) {
    let mut child = spawn_run(manifest, registry);
    let stderr = child.stderr.take().unwrap();
    let (lines, received) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            if lines.send(line).is_err() {
                break;
            }
        }
    });
    (child, received)
}

/// The stderr lines of a run until one contains `wanted` (all of them, or
/// a failure after a minute).
fn lines_until(received: &std::sync::mpsc::Receiver<String>, wanted: &str) -> Vec<String> {
    let mut seen = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(60);
    while !seen.iter().any(|l: &String| l.contains(wanted)) {
        let left = deadline.saturating_duration_since(Instant::now());
        match received.recv_timeout(left) {
            Ok(line) => seen.push(line),
            Err(_) => panic!("no line with {wanted:?} within a minute; stderr so far: {seen:?}"),
        }
    }
    seen
}

#[test]
fn a_run_waiting_for_the_write_lock_says_whose_lock_it_is() {
    use scanloc::registry::write_lock::{Holder, WriteTransaction};

    let dir = tempfile::tempdir().unwrap();
    registry_with_a_run(dir.path());
    let registry = dir.path().join("registry");
    let manifest = dir.path().join("tiny.yaml");
    let database = registry.join("registry.sqlite");

    // This test process holds the lock as a scanloc writer recording run
    // "holding-run" would: the waiting run names it, once.
    let conn = rusqlite::Connection::open(&database).unwrap();
    let holder = Holder::this_process(Some("holding-run"));
    let tx = WriteTransaction::begin(&conn, &registry, &holder, Duration::from_secs(5)).unwrap();
    let (child, received) = spawn_run_reading_stderr(&manifest, &registry);
    let expected = format!(
        "waiting for the registry's write lock held by run holding-run (pid {} on {})",
        holder.pid, holder.host
    );
    let seen = lines_until(&received, &expected);
    // Still waiting a while later, without saying it again.
    std::thread::sleep(Duration::from_millis(500));
    drop(tx);
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success(), "{seen:?}");
    let rest: Vec<String> = received.iter().collect();
    let said = seen
        .iter()
        .chain(&rest)
        .filter(|l| l.contains("waiting for the registry's write lock"))
        .count();
    assert_eq!(said, 1, "said once: {seen:?} {rest:?}");
    assert!(
        !registry.join("registry.sqlite-writer").exists(),
        "the holder file goes with the transaction"
    );

    // A lock taken by something that records no holder (the sqlite3 shell).
    conn.execute_batch("BEGIN IMMEDIATE").unwrap();
    let (child, received) = spawn_run_reading_stderr(&manifest, &registry);
    lines_until(
        &received,
        "waiting for the registry's write lock held by another program",
    );
    conn.execute_batch("ROLLBACK").unwrap();
    let output = child.wait_with_output().unwrap();
    assert!(output.status.success());
}
