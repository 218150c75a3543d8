//! Output folders and registries under hostile conditions (issue 39, items
//! 3, 9, 16, 17 and 18): recorded names that are paths, special files in an
//! output folder, the umask, a registry that cannot be written, stray
//! folders among the blobs, ids of absurd length.

use std::collections::BTreeMap;
use std::os::unix::fs::{FileTypeExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::OnceLock;

use crate::common::{scanloc, stderr, stdout, write_manifest};

/// A tiny experiment with a CNN (trained for one epoch on 12×12 frames), so
/// that every read command has a run, a model and figures to work on.
const TINY: &str = "name: tiny-outputs
seed: 7
microscope: {height: 12, width: 12, brightness: 30, margin_px: 2}
datasets:
  train: {frames: 32, emitters: {choice: [0, 1]}}
  test: {frames: 6}
detectors:
  trackpy:
    crocker_grier: {diameter: 5, minmass: 0}
  cnn:
    cnn:
      training_set: train
      architecture: {channels: 4, dilations: [1]}
      training: {epochs: 1, batch_size: 16, score_floor: 0.0}
evaluations:
  - {detector: trackpy, datasets: [test]}
  - {detector: cnn, datasets: [test]}
";

/// A registry holding one run of [`TINY`], made once for the module; each
/// test copies it ([`fresh_registry`]).
struct Fixture {
    _dir: tempfile::TempDir,
    registry: PathBuf,
    manifest: PathBuf,
    run: String,
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let manifest = write_manifest(dir.path(), "tiny.yaml", TINY);
        let registry = dir.path().join("registry");
        let run = crate::common::run_json(&manifest, &registry, &[])["run"]
            .as_str()
            .unwrap()
            .to_string();
        Fixture {
            _dir: dir,
            registry,
            manifest,
            run,
        }
    })
}

/// A copy of the fixture's registry at `dir/registry`.
fn fresh_registry(dir: &Path) -> PathBuf {
    let copy = dir.join("registry");
    let status = Command::new("cp")
        .arg("-a")
        .arg(&fixture().registry)
        .arg(&copy)
        .status()
        .unwrap();
    assert!(status.success());
    copy
}

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

fn on(registry: &Path, args: &[&str]) -> Output {
    let mut all = args.to_vec();
    all.extend(["--registry", text(registry)]);
    scanloc(&all)
}

/// Asserts exit code 2 with a one-line error containing every `expected`.
fn assert_refused(output: &Output, expected: &[&str]) {
    let error = stderr(output);
    assert_eq!(output.status.code(), Some(2), "{error}{}", stdout(output));
    assert_eq!(error.trim().lines().count(), 1, "one line: {error}");
    for wanted in expected {
        assert!(error.contains(wanted), "{wanted:?} not in: {error}");
    }
}

/// Every entry under `dir` (not following links): a regular file's sha256
/// prefix and mode, or what else it is. Never opens a FIFO or a device.
fn listing(dir: &Path) -> BTreeMap<PathBuf, String> {
    let mut entries = BTreeMap::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(folder) = stack.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            let metadata = std::fs::symlink_metadata(&path).unwrap();
            let file_type = metadata.file_type();
            let what = if file_type.is_dir() {
                stack.push(path.clone());
                "folder".to_string()
            } else if file_type.is_symlink() {
                format!("link to {}", std::fs::read_link(&path).unwrap().display())
            } else if file_type.is_fifo() {
                "fifo".to_string()
            } else if file_type.is_char_device() {
                "device".to_string()
            } else {
                let bytes = std::fs::read(&path).unwrap();
                use sha2::Digest;
                format!(
                    "{} {:o}",
                    hex::encode(sha2::Sha256::digest(&bytes)),
                    metadata.permissions().mode() & 0o777
                )
            };
            entries.insert(path.strip_prefix(dir).unwrap().to_path_buf(), what);
        }
    }
    entries
}

fn mkfifo(path: &Path) {
    assert!(Command::new("mkfifo").arg(path).status().unwrap().success());
}

/// A character device node at `path` (`None` where this process may not
/// make one: only root may).
fn mknod(path: &Path) -> Option<()> {
    Command::new("mknod")
        .args([text(path), "c", "1", "3"])
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success())
        .then_some(())
}

/// Names of the hidden partial or replaced folders scanloc left in `dir`.
fn leftovers(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| name.starts_with(".scanloc-"))
        .collect()
}

// ---- 3. names are data, never paths ---------------------------------------

#[test]
fn a_dataset_name_that_is_a_path_stays_a_file_name_inside_the_report_folder() {
    let dir = tempfile::tempdir().unwrap();
    let registry = fresh_registry(dir.path());
    // As a crafted shard would carry it.
    let hostile = "/../../../../elsewhere/X";
    let conn = rusqlite::Connection::open(registry.join("registry.sqlite")).unwrap();
    conn.execute("UPDATE evaluations SET dataset = ?1", [hostile])
        .unwrap();
    drop(conn);
    let deep = dir.path().join("a/b/c");
    std::fs::create_dir_all(&deep).unwrap();
    let out = deep.join("rep");
    let output = on(&registry, &["report", &fixture().run, "--out", text(&out)]);
    assert!(output.status.success(), "{}", stderr(&output));
    let written: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    let named: Vec<&String> = written.iter().filter(|n| n.contains("elsewhere")).collect();
    assert!(!named.is_empty(), "no figure of the dataset: {written:?}");
    for name in &named {
        assert!(
            name.bytes()
                .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b)),
            "{name}"
        );
    }
    let markdown = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(markdown.contains(named[0].trim_end_matches(".svg").trim_end_matches(".png")));
    // Nothing anywhere else in the temporary folder.
    let everything = listing(dir.path());
    let outside: Vec<&PathBuf> = everything
        .keys()
        .filter(|p| p.to_string_lossy().contains("elsewhere") && !p.starts_with("a/b/c/rep"))
        .collect();
    assert!(outside.is_empty(), "written outside --out: {outside:?}");
    assert!(leftovers(&deep).is_empty(), "{:?}", leftovers(&deep));
}

// ---- 9. all-or-nothing output folders -------------------------------------

fn model_args<'a>(registry: &'a Path, model: &'a str, out: &'a Path) -> Vec<&'a str> {
    vec![
        "registry",
        "--registry",
        text(registry),
        "model",
        model,
        "--out",
        text(out),
    ]
}

#[test]
fn a_model_folder_with_a_link_fifo_device_subfolder_or_foreign_file_is_refused_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let registry = &fixture().registry;
    let model = format!("{}:cnn", fixture().run);
    let precious = dir.path().join("precious.txt");
    std::fs::write(&precious, "keep me").unwrap();
    let good = dir.path().join("good");
    let output = scanloc(&model_args(registry, &model, &good));
    assert!(output.status.success(), "{}", stderr(&output));

    type Plant = fn(&Path, &Path) -> Option<()>;
    let cases: [(&str, &str, Plant); 5] = [
        ("training.json", "a symbolic link", |at, precious| {
            std::fs::remove_file(at).ok();
            std::os::unix::fs::symlink(precious, at).ok()
        }),
        ("model-2.bpk", "a FIFO", |at, _| {
            mkfifo(at);
            Some(())
        }),
        ("model-3.bpk", "a device node", |at, _| mknod(at)),
        ("training-2.json", "a folder", |at, _| {
            std::fs::create_dir(at).ok()
        }),
        ("notes.txt", "not a file this command writes", |at, _| {
            std::fs::write(at, "mine").ok()
        }),
    ];
    for (name, kind, plant) in cases {
        let folder = dir.path().join(format!("case-{}", name.replace('.', "-")));
        assert!(
            Command::new("cp")
                .arg("-a")
                .arg(&good)
                .arg(&folder)
                .status()
                .unwrap()
                .success()
        );
        let at = folder.join(name);
        if plant(&at, &precious).is_none() {
            eprintln!("skipped {kind}: cannot make one here");
            continue;
        }
        let before = listing(&folder);
        let output = scanloc(&model_args(registry, &model, &folder));
        assert_refused(&output, &[kind, text(&at)]);
        assert_eq!(listing(&folder), before, "{kind}: the folder changed");
        assert!(
            leftovers(dir.path()).is_empty(),
            "{:?}",
            leftovers(dir.path())
        );
    }
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "keep me");
    // The destination itself a link or a FIFO: refused, left as it is.
    let link = dir.path().join("link");
    std::os::unix::fs::symlink(&good, &link).unwrap();
    assert_refused(
        &scanloc(&model_args(registry, &model, &link)),
        &["a symbolic link"],
    );
    assert!(
        std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink()
    );
    let fifo = dir.path().join("fifo");
    mkfifo(&fifo);
    assert_refused(&scanloc(&model_args(registry, &model, &fifo)), &["a FIFO"]);
    assert!(
        std::fs::symlink_metadata(&fifo)
            .unwrap()
            .file_type()
            .is_fifo()
    );
}

#[test]
fn an_existing_model_folder_is_replaced_whole() {
    let dir = tempfile::tempdir().unwrap();
    let registry = &fixture().registry;
    let model = format!("{}:cnn", fixture().run);
    let folder = dir.path().join("model");
    std::fs::create_dir(&folder).unwrap();
    // An older model's files: a second member, stale weights.
    for name in ["model.bpk", "config.json", "model-2.bpk", "training-2.json"] {
        std::fs::write(folder.join(name), "old").unwrap();
    }
    let output = scanloc(&model_args(registry, &model, &folder));
    assert!(output.status.success(), "{}", stderr(&output));
    let names: Vec<String> = listing(&folder)
        .keys()
        .map(|p| p.display().to_string())
        .collect();
    assert_eq!(names, ["config.json", "model.bpk", "training.json"]);
    assert_ne!(std::fs::read(folder.join("model.bpk")).unwrap(), b"old");
    assert!(
        leftovers(dir.path()).is_empty(),
        "{:?}",
        leftovers(dir.path())
    );
}

#[test]
fn a_report_folder_with_a_linked_report_md_is_refused_before_any_figure() {
    let dir = tempfile::tempdir().unwrap();
    let registry = &fixture().registry;
    let precious = dir.path().join("precious.md");
    std::fs::write(&precious, "keep me").unwrap();
    let out = dir.path().join("rep");
    std::fs::create_dir(&out).unwrap();
    std::os::unix::fs::symlink(&precious, out.join("report.md")).unwrap();
    let before = listing(&out);
    let output = on(registry, &["report", &fixture().run, "--out", text(&out)]);
    assert_refused(&output, &["a symbolic link", "report.md"]);
    assert_eq!(listing(&out), before, "something was written");
    assert_eq!(std::fs::read_to_string(&precious).unwrap(), "keep me");
    assert!(
        leftovers(dir.path()).is_empty(),
        "{:?}",
        leftovers(dir.path())
    );

    // A report folder written before is replaced whole.
    std::fs::remove_file(out.join("report.md")).unwrap();
    std::fs::write(out.join("pr_gone_eps1.png"), "stale").unwrap();
    let output = on(registry, &["report", &fixture().run, "--out", text(&out)]);
    assert!(output.status.success(), "{}", stderr(&output));
    assert!(out.join("report.md").is_file());
    assert!(
        !out.join("pr_gone_eps1.png").exists(),
        "a stale figure stayed"
    );
    assert!(
        leftovers(dir.path()).is_empty(),
        "{:?}",
        leftovers(dir.path())
    );
}

// ---- 16. blobs and the database follow the umask --------------------------

#[test]
fn blobs_and_the_database_follow_the_umask() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = write_manifest(
        dir.path(),
        "small.yaml",
        "name: small
seed: 1
microscope: {height: 10, width: 10}
datasets:
  a: {frames: 3}
detectors:
  trackpy:
    crocker_grier: {diameter: 5, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [a]}
",
    );
    for (umask, blob_mode, database_mode) in [
        ("002", 0o444, 0o664),
        ("027", 0o440, 0o640),
        ("077", 0o400, 0o600),
    ] {
        let registry = dir.path().join(format!("registry-{umask}"));
        // The shell sets the umask, then becomes scanloc.
        let output = Command::new("sh")
            .arg("-c")
            .arg(format!("umask {umask}; exec \"$0\" \"$@\""))
            .arg(env!("CARGO_BIN_EXE_scanloc"))
            .args(["run", text(&manifest), "--registry", text(&registry)])
            .current_dir(crate::common::root())
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", stderr(&output));
        let mode = |path: &Path| std::fs::metadata(path).unwrap().permissions().mode() & 0o777;
        assert_eq!(
            mode(&registry.join("registry.sqlite")),
            database_mode,
            "umask {umask}: the database"
        );
        let mut blobs = 0;
        for prefix in std::fs::read_dir(registry.join("blobs")).unwrap() {
            for blob in std::fs::read_dir(prefix.unwrap().path()).unwrap() {
                assert_eq!(
                    mode(&blob.unwrap().path()),
                    blob_mode,
                    "umask {umask}: a blob"
                );
                blobs += 1;
            }
        }
        assert!(blobs > 0);
    }
}

// ---- 17. read-only registries ---------------------------------------------

/// Every command that only reads, on `registry`; each must succeed. The
/// outputs go under `out`.
fn read_commands(registry: &Path, out: &Path, env: &[(&str, &str)]) {
    let f = fixture();
    let run = f.run.as_str();
    let model = format!("{run}:cnn");
    let frames = out.join("frames.npy");
    let simulated = scanloc(&[
        "simulate",
        "--frames",
        "2",
        "--height",
        "12",
        "--width",
        "12",
        "--out",
        text(&frames),
    ]);
    assert!(simulated.status.success(), "{}", stderr(&simulated));
    let report = out.join("report");
    let model_out = out.join("model");
    let locs = out.join("locs.csv");
    let scratch = out.join("scratch");
    let shard = out.join("shard");
    let commands: Vec<Vec<&str>> = vec![
        vec!["registry", "runs"],
        vec!["registry", "datasets"],
        vec!["registry", "models"],
        vec!["registry", "evaluations"],
        vec!["registry", "show", run],
        vec!["registry", "show", &run[..8]],
        vec!["registry", "diff", run, run],
        vec!["registry", "verify"],
        vec!["registry", "gc", "--dry-run"],
        vec!["registry", "sql", "SELECT count(*) FROM runs"],
        vec!["registry", "export", run, "--out", text(&shard)],
        vec!["registry", "model", &model, "--out", text(&model_out)],
        vec!["report", run, "--out", text(&report)],
        vec![
            "locate",
            "--method",
            "cnn",
            "--model",
            &model,
            "--input",
            text(&frames),
            "--out",
            text(&locs),
        ],
        vec!["run", text(&f.manifest)],
        vec!["reproduce", run, "--scratch", text(&scratch)],
    ];
    for args in commands {
        let mut command = Command::new(env!("CARGO_BIN_EXE_scanloc"));
        command
            .args(&args)
            .args(["--registry", text(registry)])
            .current_dir(crate::common::root())
            .env_remove(scanloc::env_vars::SCANLOC_REGISTRY);
        for (name, value) in env {
            command.env(name, value);
        }
        let output = command.output().unwrap();
        assert!(
            output.status.success(),
            "{args:?} on a read-only registry: {}",
            stderr(&output)
        );
    }
    assert!(report.join("report.md").is_file());
    assert!(model_out.join("model.bpk").is_file());
    assert!(locs.is_file());
    assert!(shard.join("registry.sqlite").is_file());
}

/// The commands that write, refused plainly on `registry`.
fn write_commands_refused(registry: &Path, env: &[(&str, &str)]) {
    let shard = fixture().registry.as_path();
    for (args, command) in [
        (vec!["registry", "gc"], "registry gc"),
        (vec!["registry", "import", text(shard)], "registry import"),
    ] {
        let mut process = Command::new(env!("CARGO_BIN_EXE_scanloc"));
        process.args(&args).args(["--registry", text(registry)]);
        for (name, value) in env {
            process.env(name, value);
        }
        let output = process.output().unwrap();
        assert_refused(
            &output,
            &[&format!(
                "the registry at {} is read-only; {command} needs to write",
                registry.display()
            )],
        );
    }
}

#[test]
fn every_read_command_works_on_a_registry_forced_read_only_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let registry = fresh_registry(dir.path());
    let env = [(scanloc::env_vars::SCANLOC_REGISTRY_READ_ONLY, "1")];
    let before = listing(&registry);
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    read_commands(&registry, &out, &env);
    write_commands_refused(&registry, &env);
    assert_eq!(listing(&registry), before, "the read-only registry changed");
}

/// SCANLOC_REGISTRY_READ_ONLY takes the usual spellings of true (each
/// guards the registry) and refuses anything else, leaving the registry as
/// it was, rather than leaving it writable without a word.
#[test]
fn the_read_only_flag_takes_every_spelling_of_true_and_refuses_other_values() {
    let dir = tempfile::tempdir().unwrap();
    let registry = fresh_registry(dir.path());
    let before = listing(&registry);
    let name = scanloc::env_vars::SCANLOC_REGISTRY_READ_ONLY;
    for value in ["1", "true", "TRUE", "yes", "On"] {
        write_commands_refused(&registry, &[(name, value)]);
    }
    for value in ["2", "", "enable", "y"] {
        let output = Command::new(env!("CARGO_BIN_EXE_scanloc"))
            .args(["registry", "gc", "--registry", text(&registry)])
            .env(name, value)
            .output()
            .unwrap();
        assert_refused(&output, &[&format!("{name}=\"{value}\": not a boolean")]);
    }
    assert_eq!(listing(&registry), before, "the guarded registry changed");
}

#[test]
fn every_read_command_works_on_a_read_only_mount() {
    let dir = tempfile::tempdir().unwrap();
    let registry = fresh_registry(dir.path());
    let before = listing(&registry);
    let Some(mount) =
        crate::hostile_registry::ReadOnlyMount::bind(&registry, &dir.path().join("ro"))
    else {
        eprintln!("skipped: cannot mount here (needs root and mount rights)");
        return;
    };
    assert!(
        std::fs::write(mount.at.join("probe"), b"x").is_err(),
        "the mount is writable"
    );
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    read_commands(&mount.at, &out, &[]);
    write_commands_refused(&mount.at, &[]);
    drop(mount);
    assert_eq!(listing(&registry), before, "the read-only registry changed");
}

// ---- 18. stray folders among the blobs; absurd ids ------------------------

#[test]
fn gc_and_verify_name_a_stray_folder_among_the_blobs_and_leave_it() {
    let dir = tempfile::tempdir().unwrap();
    let registry = fresh_registry(dir.path());
    let prefix = std::fs::read_dir(registry.join("blobs"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let stray = prefix.join("not-a-blob");
    std::fs::create_dir(&stray).unwrap();
    std::fs::write(stray.join("inside"), "x").unwrap();
    let stray_tmp = registry.join("tmp").join("folder");
    std::fs::create_dir(&stray_tmp).unwrap();
    for args in [vec!["registry", "verify"], vec!["registry", "gc"]] {
        let output = on(&registry, &args);
        let printed = stdout(&output);
        assert!(
            output.status.success(),
            "{args:?}: {}{printed}",
            stderr(&output)
        );
        for path in [&stray, &stray_tmp] {
            assert!(
                printed.contains(&format!("{} (a folder)", path.display())),
                "{args:?}: {printed}"
            );
        }
    }
    assert!(stray.join("inside").is_file());
    assert!(stray_tmp.is_dir());
}

#[test]
fn an_absurdly_long_or_wildcard_id_is_a_short_one_line_refusal() {
    let registry = &fixture().registry;
    let long = "2".repeat(100_000);
    for args in [
        vec!["registry", "show", long.as_str()],
        vec!["registry", "diff", long.as_str(), long.as_str()],
        vec!["report", long.as_str(), "--out", "/nonexistent/never"],
    ] {
        let output = on(registry, &args);
        assert_refused(&output, &["an id of 100000 characters"]);
        assert!(stderr(&output).len() < 200, "{}", stderr(&output));
    }
    let model = format!("{long}:cnn");
    let output = on(
        registry,
        &["registry", "model", &model, "--out", "/nonexistent/never"],
    );
    assert_refused(&output, &["an id of 100004 characters"]);
    // Wildcards are taken literally: `%` and `_` match only themselves.
    let run = &fixture().run;
    for pattern in [
        format!("{}%", &run[..4]),
        format!("{}_", &run[..4]),
        "%%%%".to_string(),
    ] {
        let output = on(registry, &["registry", "show", &pattern]);
        assert_refused(&output, &["no run or artefact"]);
    }
    assert!(
        on(registry, &["registry", "show", &run[..8]])
            .status
            .success()
    );
}
