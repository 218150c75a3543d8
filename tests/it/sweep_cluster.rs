//! Sweeps on a cluster (issue 15): `registry export` / `import` of shards,
//! and the Slurm executor against a real Slurm (the test cluster of
//! `ci/slurm/start-test-cluster.sh`). Without Slurm the cluster tests skip
//! with a printed reason, unless SCANLOC_REQUIRE_SLURM=1 (CI), where they
//! fail.

use std::path::Path;

use crate::common::{self, blob_path, flip_a_byte, scanloc, smoke, stderr, stdout, write_manifest};

/// A small trackpy-only experiment: seconds, with every kind of artefact
/// but a model.
const TINY: &str = "name: tiny
seed: 7
microscope: {brightness: 7, margin_px: 4}
datasets:
  test-1.00: {frames: 12, diffusion_um2_s: 1.0}
metrics: {eps_px: [1, 2]}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [test-1.00]}
";

/// Whether the Slurm tests can run here; with SCANLOC_REQUIRE_SLURM=1 a
/// missing Slurm is a failure, not a skip.
fn slurm_here(test: &str) -> bool {
    if scanloc::sweep::slurm::available() {
        return true;
    }
    let required = std::env::var(scanloc::env_vars::SCANLOC_REQUIRE_SLURM).is_ok_and(|v| v == "1");
    assert!(
        !required,
        "{test}: SCANLOC_REQUIRE_SLURM=1 but no Slurm answers here (`sinfo` fails); start one with ci/slurm/start-test-cluster.sh"
    );
    eprintln!(
        "SKIPPED {test}: no Slurm here (`sinfo` fails); ci/slurm/start-test-cluster.sh starts a test cluster"
    );
    false
}

fn sql(registry: &Path, query: &str) -> serde_json::Value {
    let out = scanloc(&[
        "registry",
        "sql",
        query,
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    serde_json::from_str(&stdout(&out)).unwrap()
}

/// Every artefact key with its blobs, and every AUC: what must agree
/// between registries that ran the same thing.
fn contents(registry: &Path) -> (serde_json::Value, serde_json::Value) {
    (
        sql(
            registry,
            "SELECT a.key, a.kind, a.name, b.role, b.sha256 FROM artefacts a \
             JOIN artefact_blobs b ON b.artefact_key = a.key ORDER BY a.key, b.role",
        ),
        sql(
            registry,
            "SELECT evaluation_key, eps_px, auc, true_positives, false_positives FROM auc \
             ORDER BY evaluation_key, eps_px",
        ),
    )
}

fn run_tiny(dir: &Path, registry: &Path, seed: u64) -> String {
    let text = TINY.replace("seed: 7", &format!("seed: {seed}"));
    let manifest = write_manifest(dir, &format!("tiny-{seed}.yaml"), &text);
    common::run_json(&manifest, registry, &[])["run"]
        .as_str()
        .unwrap()
        .to_string()
}

fn import(registry: &Path, shards: &[&Path]) -> std::process::Output {
    let mut args = vec!["registry", "import"];
    args.extend(shards.iter().map(|s| s.to_str().unwrap()));
    args.extend(["--registry", registry.to_str().unwrap()]);
    scanloc(&args)
}

#[test]
fn export_then_import_into_an_empty_registry_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let main = dir.path().join("main");
    let run = run_tiny(dir.path(), &main, 7);
    let shard = dir.path().join("shard");
    let out = scanloc(&[
        "registry",
        "export",
        &run[..12],
        "--out",
        shard.to_str().unwrap(),
        "--registry",
        main.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));

    let other = dir.path().join("other");
    let out = import(&other, &[&shard]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(contents(&other), contents(&main));
    let runs = |registry: &Path| {
        sql(
            registry,
            "SELECT r.id, r.kind, r.status, r.manifest_text, r.resolved, a.detector, a.dataset, a.eps_px, a.auc \
             FROM runs r JOIN run_auc a ON a.run_id = r.id ORDER BY r.id, a.dataset, a.eps_px",
        )
    };
    assert_eq!(runs(&other), runs(&main));
    assert_eq!(
        sql(&other, "SELECT count(*) AS n FROM run_steps")[0]["n"],
        sql(&main, "SELECT count(*) AS n FROM run_steps")[0]["n"]
    );
    let out = scanloc(&["registry", "verify", "--registry", other.to_str().unwrap()]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));

    // Importing again changes nothing.
    let before = (contents(&other), runs(&other));
    let out = import(&other, &[&shard]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("(0 new)"), "{}", stdout(&out));
    assert_eq!((contents(&other), runs(&other)), before);

    // The imported run is cached in its new registry and reproducible there.
    let out = scanloc(&["reproduce", &run, "--registry", other.to_str().unwrap()]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));

    // A key stored with other blobs is refused (exit 1), the rest imported.
    let conflicting = dir.path().join("conflicting");
    let out = scanloc(&[
        "registry",
        "export",
        &run,
        "--out",
        conflicting.to_str().unwrap(),
        "--registry",
        main.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    {
        let registry = scanloc::registry::Registry::open_existing(&conflicting).unwrap();
        let other_bytes = registry.blobs().put(b"not the same predictions").unwrap();
        registry
            .connection()
            .execute(
                "INSERT INTO blobs (sha256, bytes, created_at) VALUES (?1, 25, 'now')",
                [&other_bytes],
            )
            .unwrap();
        registry
            .connection()
            .execute(
                "UPDATE artefact_blobs SET sha256 = ?1 WHERE artefact_key IN \
                 (SELECT key FROM artefacts WHERE kind = 'predictions')",
                [&other_bytes],
            )
            .unwrap();
    }
    let out = import(&main, &[&conflicting]);
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(stdout(&out).contains("REFUSED"), "{}", stdout(&out));
    assert!(stderr(&out).contains("refused"), "{}", stderr(&out));
    assert_eq!(contents(&main).0, contents(&other).0, "main is unchanged");
}

#[test]
fn a_damaged_or_missing_shard_is_reported_and_the_others_imported() {
    let dir = tempfile::tempdir().unwrap();
    let main = dir.path().join("main");
    let first = run_tiny(dir.path(), &main, 11);
    let second = run_tiny(dir.path(), &main, 12);
    let export = |run: &str, name: &str| {
        let out_dir = dir.path().join(name);
        let out = scanloc(&[
            "registry",
            "export",
            run,
            "--out",
            out_dir.to_str().unwrap(),
            "--registry",
            main.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        out_dir
    };
    let (damaged, intact) = (export(&first, "a"), export(&second, "b"));
    let dataset_blob = sql(
        &damaged,
        "SELECT b.sha256 FROM artefact_blobs b JOIN artefacts a ON a.key = b.artefact_key \
         WHERE a.kind = 'dataset' AND b.role = 'frames.npy'",
    )[0]["sha256"]
        .as_str()
        .unwrap()
        .to_string();
    flip_a_byte(&blob_path(&damaged, &dataset_blob));
    let missing = dir.path().join("never-written");

    let fresh = dir.path().join("fresh");
    let out = import(&fresh, &[&damaged, &missing, &intact]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let errors = stderr(&out);
    assert!(errors.contains("damaged shard"), "{errors}");
    assert!(errors.contains(&dataset_blob), "{errors}");
    assert!(errors.contains("never-written"), "{errors}");
    let runs = sql(&fresh, "SELECT id FROM runs ORDER BY id");
    assert_eq!(
        runs,
        serde_json::json!([{"id": second}]),
        "only the intact shard"
    );
    let out = scanloc(&["registry", "verify", "--registry", fresh.to_str().unwrap()]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));

    // A database that is not one.
    std::fs::write(damaged.join("registry.sqlite"), b"not a database at all").unwrap();
    let out = import(&fresh, &[&damaged]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("damaged registry"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn smoke_cv_through_slurm_equals_local_bit_for_bit() {
    if !slurm_here("smoke_cv_through_slurm_equals_local_bit_for_bit") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let cv = |registry: &Path, executor: &[&str]| {
        let mut args: Vec<String> = vec![
            "cv".into(),
            smoke().to_str().unwrap().to_string(),
            "--detector".into(),
            "cnn".into(),
            "--folds".into(),
            "2".into(),
            "--json".into(),
            "--registry".into(),
            registry.to_str().unwrap().to_string(),
        ];
        args.extend(executor.iter().map(|s| s.to_string()));
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let clock = std::time::Instant::now();
        let out = scanloc(&args);
        assert!(out.status.success(), "{args:?}: {}", stderr(&out));
        eprintln!("{executor:?}: {:.1} s", clock.elapsed().as_secs_f64());
        let result: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
        (result, stderr(&out))
    };
    let local = dir.path().join("local");
    let cluster = dir.path().join("cluster");
    let (on_this_machine, _) = cv(&local, &[]);
    let (on_slurm, log) = cv(
        &cluster,
        &["--executor", "slurm", "--wait", "--max-parallel", "2"],
    );
    assert!(log.contains("submitted array job"), "{log}");
    assert_eq!(on_slurm["cells"], on_this_machine["cells"]);
    assert_eq!(contents(&cluster), contents(&local));
    // Each fold ran as an array task into its own shard, imported since.
    let folds = sql(
        &cluster,
        "SELECT count(*) AS n FROM runs WHERE kind = 'cv' AND status = 'done'",
    );
    assert_eq!(folds[0]["n"], 3, "two fold runs and the table's run");
    let sweep = on_slurm["sweep"].as_str().unwrap();
    let folder = cluster.join("sweeps").join(sweep);
    for script in [
        "task.sh",
        "aggregate.sh",
        "logs/task-0.out",
        "logs/task-1.out",
    ] {
        assert!(folder.join(script).is_file(), "{script}");
    }
    assert!(
        !folder.join("shards/0").exists(),
        "imported shards are removed"
    );
    let aggregate = std::fs::read_to_string(folder.join("aggregate.sh")).unwrap();
    assert!(
        aggregate.contains("--kill-on-invalid-dep=yes"),
        "{aggregate}"
    );

    // The table's run, made of cluster tasks, re-executes here bit for bit.
    let out = scanloc(&[
        "reproduce",
        on_slurm["run"].as_str().unwrap(),
        "--registry",
        cluster.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    assert!(
        stdout(&out).contains("model/cnn-cv2of2"),
        "{}",
        stdout(&out)
    );

    // Submitting the finished sweep again submits nothing.
    let (again, log) = cv(&cluster, &["--executor", "slurm", "--wait"]);
    assert!(!log.contains("submitted"), "{log}");
    assert_eq!(again["cells"], on_this_machine["cells"]);
}

#[test]
fn a_sweep_with_a_failing_point_reports_it_and_reruns_only_it() {
    if !slurm_here("a_sweep_with_a_failing_point_reports_it_and_reruns_only_it") {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let text = format!(
        "{TINY}sweep:\n  diameter:\n    path: detectors.trackpy.crocker_grier.diameter\n    values: [5, 7, 9]\n"
    );
    let manifest = write_manifest(dir.path(), "grid.yaml", &text);
    let registry = dir.path().join("registry");
    let spec = scanloc::sweep::SweepSpec {
        kind: scanloc::sweep::SweepKind::Grid,
        manifest_path: manifest.display().to_string(),
        manifest_text: text.clone(),
    };
    let folder = registry.join("sweeps").join(spec.id().unwrap());
    // Point 1's task cannot create its shard: a file is in the way.
    std::fs::create_dir_all(folder.join("shards")).unwrap();
    std::fs::write(folder.join("shards/1"), "in the way").unwrap();
    let sweep = |extra: &[&str]| {
        let mut args = vec![
            "sweep",
            "run",
            manifest.to_str().unwrap(),
            "--executor",
            "slurm",
            "--registry",
            registry.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        scanloc(&args)
    };
    let out = sweep(&["--wait"]);
    assert_eq!(
        out.status.code(),
        Some(1),
        "{}{}",
        stdout(&out),
        stderr(&out)
    );
    let printed = stdout(&out);
    assert!(printed.contains("diameter=5"), "{printed}");
    assert!(printed.contains("diameter=9"), "{printed}");
    let log = folder.join("logs/task-1.out");
    assert!(
        printed.contains("FAILED diameter=7") && printed.contains(log.to_str().unwrap()),
        "{printed}"
    );
    assert!(stderr(&out).contains("did not finish"), "{}", stderr(&out));
    assert!(
        std::fs::read_to_string(&log).unwrap().contains("shards/1"),
        "the log says why"
    );
    let out = scanloc(&[
        "sweep",
        "status",
        &spec.id().unwrap()[..10],
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let status: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let states: Vec<&str> = status["points"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["status"].as_str().unwrap())
        .collect();
    assert_eq!(states, ["done", "failed", "done"], "{status}");

    // Out of the way, the same command runs only the missing point.
    std::fs::remove_file(folder.join("shards/1")).unwrap();
    let out = sweep(&["--wait", "--json"]);
    assert!(out.status.success(), "{}{}", stdout(&out), stderr(&out));
    let file: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(folder.join("sweep.json")).unwrap()).unwrap();
    assert_eq!(file["submissions"][1]["points"], serde_json::json!([1]));
    let result: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(result["grid"].as_array().unwrap().len(), 3);

    // The same grid locally, two processes at once: the same numbers.
    let local = dir.path().join("local");
    let out = scanloc(&[
        "sweep",
        "run",
        manifest.to_str().unwrap(),
        "--jobs",
        "2",
        "--json",
        "--registry",
        local.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let here: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    let auc = |r: &serde_json::Value| -> Vec<serde_json::Value> {
        r["grid"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["auc"].clone())
            .collect()
    };
    assert_eq!(auc(&here), auc(&result));
    assert_eq!(contents(&local), contents(&registry));
}
