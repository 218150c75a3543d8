//! `scanloc run` over a registry: caching, recomputation of exactly what
//! changed, `--force`, damaged blobs, `reproduce`, and the audit commands.

use crate::common::*;
use serde_json::Value;

fn steps(run: &Value) -> Vec<(String, String)> {
    run["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            (
                s["step"].as_str().unwrap().to_string(),
                s["outcome"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
fn a_second_run_recomputes_nothing_and_prints_the_same_table() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let first = run_json(&smoke(), &registry, &[]);
    let total = first["steps"].as_array().unwrap().len();
    assert!(total >= 4, "the smoke plan has its datasets at least");
    assert_eq!(first["computed_steps"], total);
    assert_eq!(first["cached_steps"], 0);

    let second = run_json(&smoke(), &registry, &[]);
    assert_eq!(second["cached_steps"], total);
    assert_eq!(second["computed_steps"], 0);
    assert_eq!(second["rebuilt_steps"], 0);
    assert_eq!(second["auc"], first["auc"]);
    assert_ne!(second["run"], first["run"]);
    for (a, b) in first["steps"]
        .as_array()
        .unwrap()
        .iter()
        .zip(second["steps"].as_array().unwrap())
    {
        assert_eq!(a["artefact_key"], b["artefact_key"]);
        assert_eq!(a["blobs"], b["blobs"]);
    }

    // The cache hits are recorded in the registry, not only printed.
    let output = scanloc(&[
        "registry",
        "sql",
        "--registry",
        registry.to_str().unwrap(),
        "--json",
        &format!(
            "SELECT outcome, count(*) AS n FROM run_steps WHERE run_id = '{}' GROUP BY outcome",
            second["run"].as_str().unwrap()
        ),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let rows: Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(rows, serde_json::json!([{"outcome": "cached", "n": total}]));

    // The text table is identical between the two runs, too.
    let text = |out: &std::process::Output| {
        let s = stdout(out);
        s.lines()
            .filter(|l| !l.starts_with("run "))
            .collect::<Vec<_>>()
            .join("\n")
    };
    let a = scanloc(&[
        "run",
        smoke().to_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    let b = scanloc(&[
        "run",
        smoke().to_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(a.status.success() && b.status.success());
    assert_eq!(text(&a), text(&b));
    assert!(stdout(&b).contains("computed"), "{}", stdout(&b));
}

#[test]
fn changing_one_dataset_recomputes_only_what_depends_on_it() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let original = std::fs::read_to_string(smoke()).unwrap();
    let first = run_json(&smoke(), &registry, &[]);

    let changed_text = original.replace(
        "  test-1.75:\n    frames: 120\n",
        "  test-1.75:\n    frames: 121\n",
    );
    assert_ne!(changed_text, original, "the edit must apply");
    let changed = write_manifest(dir.path(), "changed.yaml", &changed_text);
    let second = run_json(&changed, &registry, &[]);
    let outcomes = steps(&second);
    let computed: Vec<&String> = outcomes
        .iter()
        .filter(|(_, o)| o == "computed")
        .map(|(s, _)| s)
        .collect();
    assert!(!computed.is_empty());
    for step in &computed {
        assert!(
            step.ends_with("test-1.75"),
            "{step} should not be recomputed"
        );
    }
    for (step, outcome) in &outcomes {
        if !step.ends_with("test-1.75") {
            assert_eq!(outcome, "cached", "{step}");
        }
    }
    // The unchanged steps keep their keys; the changed one has a new key.
    for (a, b) in first["steps"]
        .as_array()
        .unwrap()
        .iter()
        .zip(second["steps"].as_array().unwrap())
    {
        let step = a["step"].as_str().unwrap();
        assert_eq!(
            a["artefact_key"] == b["artefact_key"],
            !step.ends_with("test-1.75"),
            "{step}"
        );
    }

    // A change outside datasets (the name, a comment) recomputes nothing.
    let renamed = write_manifest(
        dir.path(),
        "renamed.yaml",
        &format!(
            "# a comment\n{}",
            original.replace("name: smoke", "name: smoke-renamed")
        ),
    );
    let third = run_json(&renamed, &registry, &[]);
    assert_eq!(third["computed_steps"], 0);
}

#[test]
fn force_recomputes_and_checks_identity() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let first = run_json(&smoke(), &registry, &[]);
    let forced = run_json(&smoke(), &registry, &["--force"]);
    assert_eq!(forced["cached_steps"], 0);
    assert_eq!(forced["computed_steps"], first["computed_steps"]);
    let steps = forced["steps"].as_array().unwrap();
    assert_eq!(steps.len(), first["steps"].as_array().unwrap().len());
    assert!(!steps.is_empty());
    for step in steps {
        assert_eq!(
            step["detail"], "recomputed: identical to the stored artefact",
            "{step}"
        );
    }
    assert_eq!(forced["auc"], first["auc"]);
}

#[test]
fn a_flipped_byte_is_named_by_verify_and_rebuilt_by_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let first = run_json(&smoke(), &registry, &[]);
    let step = &first["steps"][1];
    let sha = step["blobs"][0]["sha256"].as_str().unwrap().to_string();
    let path = blob_path(&registry, &sha);
    let good = std::fs::read(&path).unwrap();
    flip_a_byte(&path);

    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert_eq!(verify.status.code(), Some(1), "{}", stdout(&verify));
    let report = stdout(&verify);
    assert!(report.contains(&format!("BAD damaged {sha}")), "{report}");
    assert!(
        report.contains(step["artefact_key"].as_str().unwrap()),
        "verify names the artefact: {report}"
    );
    let json = scanloc(&["registry", "verify", "--registry", reg, "--json"]);
    assert_eq!(json.status.code(), Some(1));
    let value: Value = serde_json::from_str(&stdout(&json)).unwrap();
    assert_eq!(value["bad"][0]["sha256"], sha.as_str());
    assert_eq!(value["bad"][0]["problem"], "damaged");

    let second = run_json(&smoke(), &registry, &[]);
    assert_eq!(second["rebuilt_steps"], 1);
    let rebuilt = &second["steps"][1];
    assert_eq!(rebuilt["outcome"], "rebuilt");
    assert_eq!(
        rebuilt["blobs"], step["blobs"],
        "the rebuild is bit-identical"
    );
    assert!(
        second["damaged_blobs"][0].as_str().unwrap().contains(&sha),
        "{second}"
    );
    assert_eq!(std::fs::read(&path).unwrap(), good);
    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert!(verify.status.success(), "{}", stdout(&verify));

    // A deleted blob is rebuilt as well.
    std::fs::remove_file(&path).unwrap();
    let third = run_json(&smoke(), &registry, &[]);
    assert_eq!(third["rebuilt_steps"], 1);
    assert_eq!(std::fs::read(&path).unwrap(), good);
}

#[test]
fn reproduce_passes_on_a_fresh_run_and_fails_loudly_on_an_altered_blob() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let first = run_json(&smoke(), &registry, &[]);
    let run = first["run"].as_str().unwrap();

    let output = scanloc(&["reproduce", run, "--registry", reg, "--json"]);
    assert!(
        output.status.success(),
        "{}{}",
        stdout(&output),
        stderr(&output)
    );
    let report: Value = serde_json::from_str(&stdout(&output)).unwrap();
    assert_eq!(report["identical"], true);
    assert_eq!(
        report["artefacts"].as_array().unwrap().len(),
        first["steps"].as_array().unwrap().len()
    );
    assert!(!report["artefacts"].as_array().unwrap().is_empty());
    for artefact in report["artefacts"].as_array().unwrap() {
        assert_eq!(artefact["identical"], true, "{artefact}");
    }
    // A prefix of the id works too, and the text report says IDENTICAL.
    let output = scanloc(&["reproduce", &run[..run.len() - 2], "--registry", reg]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(stdout(&output).contains("IDENTICAL"));

    let sha = first["steps"][0]["blobs"][1]["sha256"].as_str().unwrap();
    flip_a_byte(&blob_path(&registry, sha));
    let output = scanloc(&["reproduce", run, "--registry", reg]);
    assert_eq!(output.status.code(), Some(1));
    let text = stdout(&output);
    assert!(text.contains("DIFFERENT"), "{text}");
    assert!(text.contains("DIFFERS   dataset/train"), "{text}");
    assert!(text.contains("damaged (hashes to"), "{text}");
    assert!(stderr(&output).contains("differs"), "{}", stderr(&output));

    // Both reproductions are recorded.
    let runs = scanloc(&["registry", "runs", "--registry", reg, "--json"]);
    let runs: Value = serde_json::from_str(&stdout(&runs)).unwrap();
    let kinds: Vec<(&str, &str)> = runs
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["kind"].as_str().unwrap(), r["status"].as_str().unwrap()))
        .collect();
    assert!(kinds.contains(&("reproduce", "done")), "{kinds:?}");
    assert!(kinds.contains(&("reproduce", "failed")), "{kinds:?}");
}

#[test]
fn audit_commands_list_show_diff_and_query() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let first = run_json(&smoke(), &registry, &[]);
    let original = std::fs::read_to_string(smoke()).unwrap();
    let changed = write_manifest(
        dir.path(),
        "changed.yaml",
        &original.replace("seed: 20240613", "seed: 7"),
    );
    let second = run_json(&changed, &registry, &[]);
    let (a, b) = (
        first["run"].as_str().unwrap(),
        second["run"].as_str().unwrap(),
    );

    let json = |args: &[&str]| -> Value {
        let mut all = args.to_vec();
        all.extend(["--registry", reg, "--json"]);
        let output = scanloc(&all);
        assert!(output.status.success(), "{all:?}: {}", stderr(&output));
        serde_json::from_str(&stdout(&output)).unwrap()
    };
    let runs = json(&["registry", "runs"]);
    assert_eq!(runs.as_array().unwrap().len(), 2);
    assert_eq!(runs[0]["id"], b, "newest first");
    assert_eq!(runs[0]["status"], "done");
    let datasets = json(&["registry", "datasets"]);
    assert_eq!(datasets.as_array().unwrap().len(), 8, "4 per seed");
    // One CNN per run (the seed changes its training set), each listed
    // with the training set its run used.
    let models = json(&["registry", "models"]);
    let model_step = |run: &Value, id: &str| -> String {
        run["steps"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["step"] == id)
            .unwrap_or_else(|| panic!("no step {id}: {run}"))["artefact_key"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let listed: Vec<(&str, &str, &str)> = models
        .as_array()
        .unwrap()
        .iter()
        .map(|m| {
            (
                m["key"].as_str().unwrap(),
                m["detector"].as_str().unwrap(),
                m["training_dataset_key"].as_str().unwrap(),
            )
        })
        .collect();
    let (first_model, second_model) = (
        model_step(&first, "model/cnn"),
        model_step(&second, "model/cnn"),
    );
    let (first_train, second_train) = (
        model_step(&first, "dataset/train"),
        model_step(&second, "dataset/train"),
    );
    assert_eq!(
        listed,
        [
            (first_model.as_str(), "cnn", first_train.as_str()),
            (second_model.as_str(), "cnn", second_train.as_str()),
        ],
        "{models}"
    );

    let shown = json(&["registry", "show", a]);
    assert_eq!(shown["id"], a);
    assert_eq!(shown["status"], "done");
    assert_eq!(shown["manifest_text"], original.as_str());
    // The recorded seeds are the ones `check` resolves for the manifest.
    let seeds = shown["seeds"].as_object().unwrap();
    let check = scanloc(&["check", smoke().to_str().unwrap()]);
    assert!(check.status.success(), "{}", stderr(&check));
    let resolved: serde_yaml::Value = serde_yaml::from_str(&stdout(&check)).unwrap();
    let datasets = resolved["datasets"].as_sequence().unwrap();
    assert_eq!(datasets.len(), 4);
    for dataset in datasets {
        let name = dataset["name"].as_str().unwrap();
        let seed = dataset["seed"].as_u64().unwrap();
        assert_eq!(
            seeds[&format!("dataset/{name}")].as_str(),
            Some(seed.to_string().as_str()),
            "{name}"
        );
    }
    assert!(shown["git_commit"].as_str().is_some_and(|c| !c.is_empty()));
    assert!(shown["rustc"].as_str().unwrap().contains("rustc"));
    assert!(shown["threads"].as_i64().unwrap() >= 1);
    // ISO 8601 UTC times: ordered as text.
    let (started, ended) = (
        shown["started_at"].as_str().unwrap(),
        shown["ended_at"].as_str().unwrap(),
    );
    assert!(
        !started.is_empty() && ended >= started,
        "{started} .. {ended}"
    );
    let key = first["steps"][0]["artefact_key"].as_str().unwrap();
    let artefact = json(&["registry", "show", &key[..10]]);
    assert_eq!(artefact["key"], key);
    assert_eq!(artefact["kind"], "dataset");
    assert_eq!(artefact["details"]["frames"], 300);
    assert_eq!(artefact["used_by_runs"][0]["run_id"], a);

    let diff = json(&["registry", "diff", a, b]);
    let differences = diff["differences"].as_array().unwrap();
    let sections: Vec<&str> = differences
        .iter()
        .map(|d| d["section"].as_str().unwrap())
        .collect();
    assert!(sections.contains(&"seeds"), "{sections:?}");
    assert!(sections.contains(&"parameters"), "{sections:?}");
    assert!(sections.contains(&"steps"), "{sections:?}");
    assert!(!sections.contains(&"code"), "same binary: {sections:?}");
    let same = json(&["registry", "diff", a, a]);
    assert!(same["differences"].as_array().unwrap().is_empty());

    // Read-only SQL: queries work, writes are refused as bad input.
    let rows = json(&["registry", "sql", "SELECT count(*) AS n FROM runs"]);
    assert_eq!(rows, serde_json::json!([{"n": 2}]));
    let before = snapshot(&registry);
    let output = scanloc(&["registry", "sql", "DELETE FROM runs", "--registry", reg]);
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    let output = scanloc(&["registry", "sql", "SELEC nonsense", "--registry", reg]);
    assert_eq!(output.status.code(), Some(2));
    assert_eq!(snapshot(&registry), before);

    // gc: nothing unreferenced after clean runs; an orphan blob is removed.
    let gc = json(&["registry", "gc", "--dry-run"]);
    assert!(gc["blobs"].as_array().unwrap().is_empty(), "{gc}");
    let orphan = "ab".repeat(32);
    std::fs::create_dir_all(registry.join("blobs/ab")).unwrap();
    std::fs::write(blob_path(&registry, &orphan), b"orphan").unwrap();
    let old = std::time::SystemTime::now() - std::time::Duration::from_secs(3600);
    std::fs::File::options()
        .write(true)
        .open(blob_path(&registry, &orphan))
        .unwrap()
        .set_modified(old)
        .unwrap();
    let gc = json(&["registry", "gc", "--dry-run"]);
    assert_eq!(gc["blobs"], serde_json::json!([orphan]));
    assert!(blob_path(&registry, &orphan).exists(), "dry run keeps it");
    let gc = json(&["registry", "gc"]);
    assert_eq!(gc["blobs"], serde_json::json!([orphan]));
    assert!(!blob_path(&registry, &orphan).exists());
    let verify = scanloc(&["registry", "verify", "--registry", reg]);
    assert!(verify.status.success());

    // For people, `show` is a summary read top-down that ends with the
    // AUC grid exactly as `run` prints it.
    let shown = scanloc(&["registry", "show", a, "--registry", reg]);
    assert!(shown.status.success(), "{}", stderr(&shown));
    let shown = stdout(&shown);
    assert!(shown.starts_with(&format!("run {a}: done\n")), "{shown}");
    let headings: Vec<&str> = shown
        .lines()
        .filter(|line| !line.starts_with(' '))
        .take(6)
        .collect();
    let counts = format!(
        "steps: 0 cached, {} computed, 0 rebuilt",
        steps(&first).len()
    );
    assert_eq!(
        headings[1..5],
        ["manifest", "code", "seeds", counts.as_str()],
        "{shown}"
    );
    assert!(headings[5].starts_with("AUC "), "{shown}");
    for (step, _) in steps(&first) {
        assert!(
            shown
                .lines()
                .any(|line| line.trim_start().starts_with("computed")
                    && line.contains(&format!(" {step} "))),
            "{step}: {shown}"
        );
    }
    let rerun = scanloc(&["run", smoke().to_str().unwrap(), "--registry", reg]);
    let rerun = stdout(&rerun);
    let grid = &rerun[..rerun.trim_end().rfind('\n').unwrap() + 1];
    assert!(
        !grid.is_empty() && shown.ends_with(grid),
        "{grid}\n---\n{shown}"
    );

    // Unknown ids and missing registries are bad input.
    let output = scanloc(&["registry", "show", "zzzzzzzz", "--registry", reg]);
    assert_eq!(output.status.code(), Some(2));
    let missing = dir.path().join("nowhere");
    let output = scanloc(&["registry", "runs", "--registry", missing.to_str().unwrap()]);
    assert_eq!(output.status.code(), Some(2));
    assert!(!missing.exists());
}

#[test]
fn the_registry_can_come_from_the_environment() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("from-env");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(["run", smoke().to_str().unwrap(), "--json"])
        .env(scanloc::env_vars::SCANLOC_REGISTRY, &registry)
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(registry.join("registry.sqlite").is_file());
}

#[test]
fn force_fails_as_a_check_when_a_recomputation_differs() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let first = run_json(&smoke(), &registry, &[]);
    // Make the registry claim a different (intact) truth.csv for the first
    // dataset, as if the code had changed without a version bump.
    let key = first["steps"][0]["artefact_key"].as_str().unwrap();
    let fake = b"frame,x,y\n";
    let fake_sha = {
        use sha2::Digest;
        hex::encode(sha2::Sha256::digest(fake))
    };
    std::fs::create_dir_all(registry.join("blobs").join(&fake_sha[..2])).unwrap();
    std::fs::write(blob_path(&registry, &fake_sha), fake).unwrap();
    let conn = rusqlite::Connection::open(registry.join("registry.sqlite")).unwrap();
    conn.execute(
        "INSERT INTO blobs (sha256, bytes, created_at) VALUES (?1, 10, 'now')",
        [&fake_sha],
    )
    .unwrap();
    conn.execute(
        "UPDATE artefact_blobs SET sha256 = ?1 WHERE artefact_key = ?2 AND role = 'truth.csv'",
        [&fake_sha, key],
    )
    .unwrap();
    drop(conn);

    let output = scanloc(&[
        "run",
        smoke().to_str().unwrap(),
        "--force",
        "--registry",
        reg,
    ]);
    assert_eq!(output.status.code(), Some(1), "{}", stderr(&output));
    assert!(stderr(&output).contains("differ"), "{}", stderr(&output));
    let runs = scanloc(&["registry", "runs", "--registry", reg, "--json"]);
    let runs: Value = serde_json::from_str(&stdout(&runs)).unwrap();
    assert_eq!(runs[0]["status"], "failed");
    // The stored artefact was not overwritten by the disagreeing result.
    let conn = rusqlite::Connection::open(registry.join("registry.sqlite")).unwrap();
    let stored: String = conn
        .query_row(
            "SELECT sha256 FROM artefact_blobs WHERE artefact_key = ?1 AND role = 'truth.csv'",
            [key],
            |r| r.get(0),
        )
        .unwrap();
    assert_eq!(stored, fake_sha);
}

#[test]
fn the_auc_table_is_printed_as_json_and_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let run = run_json(&smoke(), &registry, &[]);
    let auc = run["auc"].as_array().unwrap();
    // trackpy on three test sets at three radii, at least.
    let trackpy: Vec<&Value> = auc.iter().filter(|r| r["detector"] == "trackpy").collect();
    assert_eq!(trackpy.len(), 9);
    for (row, (dataset, diffusion)) in
        trackpy
            .chunks(3)
            .zip([("test-0.75", 0.75), ("test-1.00", 1.0), ("test-1.75", 1.75)])
    {
        for (cell, eps) in row.iter().zip([1.0, 2.0, 3.0]) {
            assert_eq!(cell["dataset"], dataset);
            assert_eq!(cell["diffusion"], diffusion);
            assert_eq!(cell["eps_px"], eps);
            let value = cell["auc"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&value), "{cell}");
        }
        // A larger radius never lowers the AUC.
        assert!(row[0]["auc"].as_f64() <= row[1]["auc"].as_f64());
        assert!(row[1]["auc"].as_f64() <= row[2]["auc"].as_f64());
    }
    // The recorded table is the printed one.
    let output = scanloc(&[
        "registry",
        "sql",
        "--registry",
        reg,
        "--json",
        &format!(
            "SELECT detector, dataset, diffusion, eps_px, auc FROM run_auc WHERE run_id = '{}' ORDER BY rowid",
            run["run"].as_str().unwrap()
        ),
    ]);
    let recorded: Value = serde_json::from_str(&stdout(&output)).unwrap();
    let printed: Vec<Value> = auc
        .iter()
        .map(|r| {
            serde_json::json!({"detector": r["detector"], "dataset": r["dataset"],
                "diffusion": r["diffusion"], "eps_px": r["eps_px"], "auc": r["auc"]})
        })
        .collect();
    assert_eq!(recorded, Value::Array(printed));
    // The text table has one row per detector, the paper's layout.
    let text = stdout(&scanloc(&[
        "run",
        smoke().to_str().unwrap(),
        "--registry",
        reg,
    ]));
    assert!(text.contains("D = 0.75 µm²/s"), "{text}");
    assert!(text.contains("D = 1.00 µm²/s"), "{text}");
    assert!(text.lines().any(|l| l.starts_with("trackpy")), "{text}");
}

#[test]
fn reproduce_compares_the_numbers_inside_an_altered_evaluation() {
    let dir = tempfile::tempdir().unwrap();
    let registry = dir.path().join("registry");
    let reg = registry.to_str().unwrap();
    let run = run_json(&smoke(), &registry, &[]);
    let step = run["steps"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["step"] == "evaluation/trackpy@test-1.00")
        .unwrap();
    let sha = step["blobs"][0]["sha256"].as_str().unwrap();
    let path = blob_path(&registry, sha);
    let text = std::fs::read_to_string(&path).unwrap();
    let score: Value = serde_json::from_str(&text).unwrap();
    let auc = score["per_eps"][1]["auc"].as_f64().unwrap();
    let altered = text.replacen(&format!("\"auc\":{auc}"), "\"auc\":0.999", 1);
    assert_ne!(altered, text);
    let mut permissions = std::fs::metadata(&path).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    permissions.set_readonly(false);
    std::fs::set_permissions(&path, permissions).unwrap();
    std::fs::write(&path, altered).unwrap();

    let output = scanloc(&["reproduce", run["run"].as_str().unwrap(), "--registry", reg]);
    assert_eq!(output.status.code(), Some(1));
    let report = stdout(&output);
    assert!(
        report.contains("DIFFERS   evaluation/trackpy@test-1.00"),
        "{report}"
    );
    assert!(
        report.contains(&format!("per_eps[1].auc: recorded 0.999 reproduced {auc}")),
        "{report}"
    );
    // The recorded AUC cell itself still matches the reproduction.
    assert!(
        report.contains("identical AUC trackpy@test-1.00 ε=2"),
        "{report}"
    );
}

/// The content keys of the paper manifest's 44 steps, as the run of
/// 2026-12-02 recorded them (the bound's since `scanloc-likelihood/2`, the CNN's
/// since its recipe of 2026-12-02: the categorical head with 6 guesses per
/// frame; every evaluation's since `scanloc-metric/5`, whose `score.json`
/// holds a reliability diagram per candidate rank). A
/// change that alters any of them makes every user's cached paper run
/// recompute (tens of minutes), and a change to what an artefact holds that leaves its key
/// alone would serve stale results: so a key may only change together with a
/// deliberate version bump (`GENERATOR_VERSION`, a detector's
/// `CODE_VERSION`, `FORMAT_VERSION`, …) or a manifest edit, and then this
/// list is updated with it.
#[test]
fn the_paper_manifests_content_keys_are_stable() {
    let manifest = scanloc::manifest::load(std::path::Path::new("experiments/paper.yaml")).unwrap();
    let plan = scanloc::run::Plan::from_manifest(&manifest).unwrap();
    let planned: Vec<(String, &str)> = plan
        .steps
        .iter()
        .map(|step| (step.id.to_string(), step.key.as_str()))
        .collect();
    let recorded = [
        (
            "dataset/train",
            "e22b5ad1e85c493f4eb599145c56c5b09e1e3b65738b0d3da01d45a38f241b29",
        ),
        (
            "dataset/test-0.75",
            "2ebe6cf2fe29e8681ca4cfed7d82bd22f3792318bf8eaa352c0c5bb9cf101780",
        ),
        (
            "dataset/test-1.00",
            "dc163b5bcb4dbeed8fdab36151d5ccadaf24f77e50016c6f58f183a7385a1aae",
        ),
        (
            "dataset/test-1.75",
            "a37883d89501d8f8e318bd821b97f967430bef4e18e7514e45517601f201d90e",
        ),
        (
            "predictions/trackpy@test-0.75",
            "92399a461264e27b73acef50736a6f06ef9ac7529dcb9279cd412d27524baa7d",
        ),
        (
            "evaluation/trackpy@test-0.75",
            "f37cab693a5c1a75be336fc6031be13e347716d2819daaebe14017e48e6d6dc8",
        ),
        (
            "predictions/trackpy@test-1.00",
            "00325b8eb1b2c2a893bc59d7720f25b3540b966647a611f6a9ffe6eea522a6db",
        ),
        (
            "evaluation/trackpy@test-1.00",
            "fbd997659781e8bf2c99075032e7f02875d838276d79b4b51a9cd9ba7a469735",
        ),
        (
            "predictions/trackpy@test-1.75",
            "3b93dd673047df9a06978ed83388c7362042617026e020f54f5e73f3b5c94c10",
        ),
        (
            "evaluation/trackpy@test-1.75",
            "f3bcb109c28acc58a73438f23e3d7c557b4d31da2513e0f731f518ebb664320e",
        ),
        (
            "model/cnn",
            "39b2934c0a6c6ac6ed3f818a92cf8d582e6c23bdb2ff7731d6fbffbd3ac79555",
        ),
        (
            "predictions/cnn@test-0.75",
            "c2a30bffaedd3b78e2f221f77a4b2c6640d07cd7369b0eb38454ae67d5e6f2e8",
        ),
        (
            "evaluation/cnn@test-0.75",
            "11de1eef66e21ed459d9947bf575bcc925688fa294c9bb780c276307aea28345",
        ),
        (
            "predictions/cnn@test-1.00",
            "812fd0df66a20e937ea3b24580e78be9a18c75ef2e58e8ce184f90df00e8a0f4",
        ),
        (
            "evaluation/cnn@test-1.00",
            "3b707f696b283f7cca3293d8d15c080e91c0e81689428e6d57636d42d0c34bf6",
        ),
        (
            "predictions/cnn@test-1.75",
            "c759d39e0c05a9de7f3aa8ddc4c2d1c2617fa7222ccbdc53dbc28bfe21353381",
        ),
        (
            "evaluation/cnn@test-1.75",
            "16a7522155f2d8be6db462d1de59baea1e70c5cc1343c8710cc152536eb7c8ed",
        ),
        (
            "dataset/test-0.75+first300",
            "704e1f544a434ee5faeae462db5a744a70219f0289baaecdaab3f3985fdbe4e4",
        ),
        (
            "predictions/bound-known-d@test-0.75+first300",
            "f592a77ab1ed03534976ca6e28a43e1d97ce63d10fe29707fe9a8f51828e804d",
        ),
        (
            "evaluation/bound-known-d@test-0.75+first300",
            "6a20bbd8f0b2c9cd7db450a9b49734f32f5a8e0ca1fde75b746cbc5ec4196cdb",
        ),
        (
            "dataset/test-1.00+first300",
            "c8766373d3fc60e4393303e1cd6ec8343782364a2a9f77006e0fd338a984663b",
        ),
        (
            "predictions/bound-known-d@test-1.00+first300",
            "dce308c2fc2543333223e9862a99f3b0c10a10754da0b1131768a3c0f7e793a5",
        ),
        (
            "evaluation/bound-known-d@test-1.00+first300",
            "eee7dde81be55cb1367559601ca4c279fd3db668088147aa1cb4bb5a6eed835a",
        ),
        (
            "dataset/test-1.75+first300",
            "5452a48b8650c5d4caeab452e5e1aed9fc5d08114b4f966ffa2a141b24db42d6",
        ),
        (
            "predictions/bound-known-d@test-1.75+first300",
            "dd128ee243a810bfaed861185df802d3e0177b427a380f86dd8b3ba42d895a40",
        ),
        (
            "evaluation/bound-known-d@test-1.75+first300",
            "83843bcf52b67bab39cec9c92e93c4a2ee4c90719b06359f07db63083c4f776f",
        ),
        (
            "predictions/bound-marginal-d@test-0.75+first300",
            "35ba141891418e759828f9451430f9ccbef76910c093cefdf478e0d2af1baa35",
        ),
        (
            "evaluation/bound-marginal-d@test-0.75+first300",
            "9abfa5cc571a1bbe2606ed8b1652baf60acfe9bea50ad0d9c586057fbc74ae65",
        ),
        (
            "predictions/bound-marginal-d@test-1.00+first300",
            "d021cc626455150f9cc1ae739c61c9dc16da4392411e37e10e31d83c0f01975d",
        ),
        (
            "evaluation/bound-marginal-d@test-1.00+first300",
            "2788e9464f523999f65336710c0dbcb4dcf595466ff705ea03d4712bacf01762",
        ),
        (
            "predictions/bound-marginal-d@test-1.75+first300",
            "2317a14ae1e798c724afcbc1f0a140d47509e50efa09b8f1adc4ea831906d16b",
        ),
        (
            "evaluation/bound-marginal-d@test-1.75+first300",
            "5275339bc82dc51ddc3881cf273529cdaa7b0573311af9f7338c28e79ae5c4f9",
        ),
        (
            "predictions/cnn@test-0.75+first300",
            "e4c4546d5772d206b51fc14fa615d33c06b99b3c30b712475578de7ca6341747",
        ),
        (
            "evaluation/cnn@test-0.75+first300",
            "b091dc52310a085af17fb4ae1c5284d068b341978a243d00a564a0ea93029f39",
        ),
        (
            "predictions/cnn@test-1.00+first300",
            "db7685028e68005aaa4aca598ff5be9def69bd12f9eec655f40decd2cfce6572",
        ),
        (
            "evaluation/cnn@test-1.00+first300",
            "958ae3d68253d056b5400005a2e22ecfc56e9334f5fe69c0a7aca9f730f82a2d",
        ),
        (
            "predictions/cnn@test-1.75+first300",
            "fa3e6a5b7b2c969497d7bf6450d3e76acbe7a9a5fbdae84332978a0b2b9f014a",
        ),
        (
            "evaluation/cnn@test-1.75+first300",
            "8809f043741d9f2e353b236b409f1baf249075c491354aa06beb519a14d82e9b",
        ),
        (
            "dataset/test-0.75+first1000",
            "bde9b4bd52b692840162952130d16263796697afc0a395b5f0fa476b74673da3",
        ),
        (
            "predictions/bound-list-marginal-d@test-0.75+first1000",
            "d7b0ce52f3da73b13aaedb85601a8f1d5f6ab12149dd205b9d561cd1363a3569",
        ),
        (
            "evaluation/bound-list-marginal-d@test-0.75+first1000",
            "1d32e806a91d666c32c701340c2557e53f9104fc8fb2ed717a778cc53b01c7dd",
        ),
        (
            "dataset/test-1.00+first1000",
            "824b22fdc724355e60bc9e6e948ef7cf64847da6df1cc98f801649b8c880803e",
        ),
        (
            "predictions/bound-list-marginal-d@test-1.00+first1000",
            "b7a15dae334e3b2286b4fa9b83d7665a8522993183feb55d00dbfcccc24ca4f5",
        ),
        (
            "evaluation/bound-list-marginal-d@test-1.00+first1000",
            "925045cadab27fac400b7afce8029069890504cd10011ea81acf7cfa5af68f59",
        ),
        (
            "dataset/test-1.75+first1000",
            "aa23f991c23be38c1865b863eb833f0cbddb48fe751896ae84c015a86a6d851d",
        ),
        (
            "predictions/bound-list-marginal-d@test-1.75+first1000",
            "5e50b11aa3cba2b465e4fabe29132d17a693fa454f9031691420401b795e0d77",
        ),
        (
            "evaluation/bound-list-marginal-d@test-1.75+first1000",
            "4263dbbc0993a8d0a110a1f631f04ed49348598ff71ae724b3410762eb7c6411",
        ),
        (
            "predictions/cnn@test-0.75+first1000",
            "7d8dbff1e83979bc2c7c0fe5c939a04bec8de6e64031b4a8e191fdabbee96648",
        ),
        (
            "evaluation/cnn@test-0.75+first1000",
            "c0e9703d794970850483e3b75296442634d86c1078594e8f1d5dcee1ca93fcc7",
        ),
        (
            "predictions/cnn@test-1.00+first1000",
            "51357fdec4feda69ffefa9988bca05fb088161dc91aca4e12f9914280fce9bc5",
        ),
        (
            "evaluation/cnn@test-1.00+first1000",
            "05b31c4f3f7608dff5a649bee6b236545292b742af689d59acd3710e3b0bf03a",
        ),
        (
            "predictions/cnn@test-1.75+first1000",
            "6dceb905af1009ec8f9c8cefa049de84c0264dd5e0947b40c73e47641ec9f512",
        ),
        (
            "evaluation/cnn@test-1.75+first1000",
            "9cd5e3cce9b0ad0f726a8379082edb8a005e1300bdab935667a8d86fb0a34112",
        ),
    ];
    assert_eq!(planned, recorded.map(|(id, key)| (id.to_string(), key)));
}

/// The companion manifests say they reuse the paper run's artefacts (the
/// bound's and the scenes' comparison with the paper's CNN is served from
/// the registry after `make reproduce-paper`): every step they share with
/// the paper manifest by name must have the paper's key, the trained CNN's
/// among them. A detector edited in one manifest and not the other would
/// silently train a second, different "paper CNN".
#[test]
fn the_companion_manifests_reuse_the_paper_runs_artefacts() {
    let plan_of = |path: &str| {
        let manifest = scanloc::manifest::load(std::path::Path::new(path)).unwrap();
        scanloc::run::Plan::from_manifest(&manifest)
            .unwrap()
            .steps
            .into_iter()
            .map(|step| (step.id.to_string(), step.key))
            .collect::<std::collections::BTreeMap<String, String>>()
    };
    let paper = plan_of("experiments/paper.yaml");
    for (companion, must_share) in [
        (
            "experiments/bound.yaml",
            &[
                "model/cnn",
                "predictions/cnn@test-1.75",
                "dataset/test-0.75",
                "predictions/trackpy@test-1.00",
            ][..],
        ),
        (
            "experiments/scenes.yaml",
            &["model/cnn", "dataset/train"][..],
        ),
    ] {
        let plan = plan_of(companion);
        for step in must_share {
            assert!(plan.contains_key(*step), "{companion} has no step {step}");
        }
        for (step, key) in &plan {
            if let Some(paper_key) = paper.get(step) {
                assert_eq!(key, paper_key, "{companion}: {step}");
            }
        }
    }
}

/// The manifest of a YAML text (a variant of the paper manifest's).
fn manifest_of_text(text: &str) -> scanloc::manifest::Manifest {
    let dir = tempfile::tempdir().unwrap();
    let path = write_manifest(dir.path(), "paper.yaml", text);
    scanloc::manifest::load(&path).unwrap()
}

/// A teacher (`training.teacher_particles`) is part of what a model is: the
/// same manifest with one gives the CNN a model key of its own (and so new
/// predictions and evaluations), and leaves every other step's key alone.
#[test]
fn a_teacher_gives_the_model_a_key_of_its_own() {
    let keys = |text: &str| {
        let manifest = manifest_of_text(text);
        let plan = scanloc::run::Plan::from_manifest(&manifest).unwrap();
        plan.steps
            .iter()
            .map(|step| (step.id.to_string(), step.key.clone()))
            .collect::<Vec<_>>()
    };
    let text = std::fs::read_to_string("experiments/paper.yaml").unwrap();
    // The CNN is the manifest's one detector with a `training` block.
    let taught = text.replacen(
        "      training:\n",
        "      training:\n        teacher_particles: 2000\n",
        1,
    );
    assert_ne!(taught, text);
    let (before, after) = (keys(&text), keys(&taught));
    assert_eq!(before.len(), after.len());
    for ((id, old), (same_id, new)) in before.iter().zip(&after) {
        assert_eq!(id, same_id);
        let renewed = id.contains("cnn");
        assert_eq!(old != new, renewed, "{id}: {old} → {new}");
    }
}

/// A cross-validation keeps to a recipe in which the training set never
/// trains (`validation_fraction: 1`, the paper manifest's CNN): its fold
/// models train on fresh frames only, so their keys say so and stay apart
/// from the fold models that also trained on their k − 1 folds. Nothing
/// else of the plan (the folds' subsets, the test sets) changes, and a
/// recipe that does train on the training set keeps the keys it had.
#[test]
fn a_cross_validation_of_fresh_frames_only_keys_its_fold_models_apart() {
    let cv_steps = |text: &str| {
        let manifest = manifest_of_text(text);
        let cv = scanloc::registry::CrossValidationPlan {
            detector: "cnn".into(),
            folds: 5,
            fold: None,
        };
        scanloc::run::cross_validation::plan(&manifest, &cv)
            .unwrap()
            .steps
    };
    let fresh_only = std::fs::read_to_string("experiments/paper.yaml").unwrap();
    assert!(fresh_only.contains("        validation_fraction: 1\n"));
    let mixed = fresh_only.replacen(
        "        validation_fraction: 1\n",
        "        validation_fraction: 0.1\n",
        1,
    );
    let (fresh_only, mixed) = (cv_steps(&fresh_only), cv_steps(&mixed));
    assert_eq!(fresh_only.len(), mixed.len());
    let mut fold_models = 0;
    for (a, b) in fresh_only.iter().zip(&mixed) {
        assert_eq!(a.id, b.id);
        let marked = |step: &scanloc::run::Step| step.spec.contains("fresh frames only");
        if a.id.to_string().starts_with("model/") {
            fold_models += 1;
            assert!(marked(a), "{}: {}", a.id, a.spec);
            assert!(!marked(b), "{}: {}", b.id, b.spec);
        } else if a.id.to_string().starts_with("dataset/") {
            assert_eq!(a.key, b.key, "{}", a.id);
        }
    }
    assert_eq!(fold_models, 5);
}
