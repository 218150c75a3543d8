//! Shards as untrusted input (issue 39): `registry import` is a validating
//! copy. One test per way a shard went wrong before: `gc` racing an
//! import, step claims carried over, names that are paths, shard paths
//! read as URI text, blob names and files that are not blobs, a refused
//! shard leaving its transaction open, edited specs and false sizes, and
//! refused copies leaving artefacts behind. The fixtures are shared with
//! the shard fuzzer (`hostile_shard_fuzz`).

use std::ffi::OsStr;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;

use rusqlite::Connection;
use scanloc::registry::Registry;
use scanloc::registry::shard::{self, CopyReport};

use crate::common::{self, flip_a_byte, write_manifest};

/// A manifest that runs in well under a second: one small dataset scored
/// by TrackPy's algorithm (every artefact kind but a model).
const TINY: &str = "\
name: tiny
seed: SEED
datasets:
  a: {frames: 4, emitters: 2}
detectors:
  trackpy:
    crocker_grier: {diameter: 7, minmass: 0}
evaluations:
  - {detector: trackpy, datasets: [a]}
";

/// Two registries' worth of shards, made once per test binary.
pub struct Template {
    /// The registry both runs were made in.
    pub main: PathBuf,
    /// Shards of one run each, and the runs.
    pub shards: [PathBuf; 2],
    pub runs: [String; 2],
}

/// The shared fixture: two runs of [`TINY`] (other seeds) in one registry,
/// each exported to its own shard.
pub fn template() -> &'static Template {
    static TEMPLATE: OnceLock<Template> = OnceLock::new();
    TEMPLATE.get_or_init(|| {
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR"))
            .join(format!("shard-template-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let main = dir.join("main");
        let mut runs = Vec::new();
        let mut shards = Vec::new();
        for seed in [5, 6] {
            let manifest = write_manifest(
                &dir,
                &format!("tiny-{seed}.yaml"),
                &TINY.replace("SEED", &seed.to_string()),
            );
            let run = common::run_json(&manifest, &main, &[])["run"]
                .as_str()
                .unwrap()
                .to_string();
            let out = dir.join(format!("shard-{seed}"));
            shard::export(&main, std::slice::from_ref(&run), &out).unwrap();
            runs.push(run);
            shards.push(out);
        }
        Template {
            main,
            shards: [shards[0].clone(), shards[1].clone()],
            runs: [runs[0].clone(), runs[1].clone()],
        }
    })
}

/// Copies folder `from` to `to` (files and folders). A file that vanishes
/// between the listing and the copy is skipped: other tests read the
/// template's registries in place, and SQLite's journal of such a read
/// comes and goes.
pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        let Ok(kind) = entry.file_type() else {
            continue;
        };
        if kind.is_dir() {
            copy_dir(&entry.path(), &target);
        } else if let Err(e) = std::fs::copy(entry.path(), &target) {
            assert_eq!(e.kind(), std::io::ErrorKind::NotFound, "{e}");
        }
    }
}

/// A copy of template shard `which` at `to`.
pub fn shard_copy(which: usize, to: &Path) -> PathBuf {
    copy_dir(&template().shards[which], to);
    to.to_path_buf()
}

/// Runs SQL on the shard's database as another tool would (foreign keys
/// off, so a shard can be made inconsistent).
pub fn tamper(shard: &Path, statements: &str) {
    let conn = Connection::open(shard.join("registry.sqlite")).unwrap();
    conn.execute_batch("PRAGMA foreign_keys = OFF;").unwrap();
    conn.execute_batch(statements)
        .unwrap_or_else(|e| panic!("{statements}: {e}"));
}

/// A value from the shard (or registry) database.
pub fn query(dir: &Path, sql: &str) -> String {
    let conn = Connection::open(dir.join("registry.sqlite")).unwrap();
    conn.query_row(sql, [], |row| {
        row.get::<_, rusqlite::types::Value>(0).map(|v| match v {
            rusqlite::types::Value::Text(t) => t,
            rusqlite::types::Value::Integer(n) => n.to_string(),
            other => format!("{other:?}"),
        })
    })
    .unwrap_or_else(|e| panic!("{sql}: {e}"))
}

/// Imports `shards` into registry `dest` in this process, failing the test
/// if the import takes over a minute (a hang).
pub fn import(dest: &Path, shards: &[&Path]) -> Vec<anyhow::Result<CopyReport>> {
    let dest = dest.to_path_buf();
    let shards: Vec<PathBuf> = shards.iter().map(|s| s.to_path_buf()).collect();
    let (send, receive) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut registry = Registry::open(&dest).unwrap();
        let paths: Vec<&Path> = shards.iter().map(PathBuf::as_path).collect();
        let results = shard::import_all(&mut registry, &paths);
        let _ = send.send(results.into_iter().map(|(_, r)| r).collect::<Vec<_>>());
    });
    receive
        .recv_timeout(Duration::from_secs(60))
        .expect("the import ended within a minute")
}

/// The refusal of a one-shard import: exit code 2 and its message.
fn refused(dest: &Path, shard: &Path) -> String {
    let mut results = import(dest, &[shard]);
    let error = results.pop().unwrap().expect_err("the shard is refused");
    assert_eq!(scanloc::error::exit_code(&error), 2, "{error:#}");
    format!("{error:#}")
}

/// The run ids in registry `dir`.
pub fn runs(dir: &Path) -> Vec<String> {
    let registry = Registry::open_existing(dir).unwrap();
    let mut statement = registry
        .connection()
        .prepare("SELECT id FROM runs ORDER BY id")
        .unwrap();
    statement
        .query_map([], |row| row.get(0))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap()
}

/// `registry verify` finds nothing wrong and nothing left over.
pub fn assert_verify_clean(dir: &Path) {
    let report = Registry::open_existing(dir).unwrap().verify().unwrap();
    assert!(report.ok(), "{report:?}");
    assert!(report.unrecorded_files.is_empty(), "{report:?}");
    assert!(report.leftover_temporaries.is_empty(), "{report:?}");
}

#[test]
fn gc_never_deletes_what_an_import_is_writing() {
    let template = template();
    for round in 0..4 {
        let dir = tempfile::tempdir().unwrap();
        let dest = dir.path().join("registry");
        drop(Registry::open(&dest).unwrap());
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let collector = {
            let (dest, stop) = (dest.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut collections = 0;
                while !stop.load(std::sync::atomic::Ordering::Relaxed) || collections == 0 {
                    Registry::open_existing(&dest).unwrap().gc(false).unwrap();
                    collections += 1;
                }
            })
        };
        for result in import(&dest, &[&template.shards[0], &template.shards[1]]) {
            result.unwrap();
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        collector.join().unwrap();
        assert_eq!(runs(&dest).len(), 2, "round {round}");
        assert_verify_clean(&dest);
        assert_eq!(
            query(&dest, "SELECT count(*) FROM artefacts"),
            query(&template.main, "SELECT count(*) FROM artefacts"),
            "round {round}: gc removed imported artefacts"
        );
    }
}

#[test]
fn step_claims_in_a_shard_are_not_imported() {
    let dir = tempfile::tempdir().unwrap();
    let shard = shard_copy(0, &dir.path().join("shard"));
    tamper(
        &shard,
        "INSERT INTO step_claims (key, run_id, host, pid, claimed_at)
         SELECT key, 'someone', 'here', 1, 'now' FROM artefacts",
    );
    let dest = dir.path().join("registry");
    import(&dest, &[&shard]).pop().unwrap().unwrap();
    assert_eq!(query(&dest, "SELECT count(*) FROM step_claims"), "0");
    assert_eq!(runs(&dest), [template().runs[0].clone()]);
}

#[test]
fn a_name_that_would_be_a_path_refuses_the_shard() {
    let hostile = "/../../../../elsewhere/X";
    for (table, column) in [
        ("datasets", "name"),
        ("artefacts", "name"),
        ("evaluations", "dataset"),
        ("predictions", "detector"),
        ("run_auc", "dataset"),
        ("artefact_blobs", "role"),
        ("run_steps", "step"),
        ("runs", "id"),
    ] {
        let dir = tempfile::tempdir().unwrap();
        let shard = shard_copy(0, &dir.path().join("shard"));
        tamper(
            &shard,
            &format!("UPDATE {table} SET {column} = '{hostile}' || rowid"),
        );
        let dest = dir.path().join("registry");
        let error = refused(&dest, &shard);
        for part in [
            shard.display().to_string(),
            format!("table {table}, row"),
            hostile.to_string(),
        ] {
            assert!(error.contains(&part), "{table}.{column}: {error}");
        }
        assert!(runs(&dest).is_empty(), "{table}.{column}");
        assert_eq!(query(&dest, "SELECT count(*) FROM artefacts"), "0");
        assert_verify_clean(&dest);
    }
}

#[test]
fn shard_paths_are_file_names_never_uri_text() {
    let template = template();
    let dir = tempfile::tempdir().unwrap();
    // `pc%41` is not `pcA`, whatever a URI would decode it to.
    shard_copy(1, &dir.path().join("pcA"));
    let names: [&[u8]; 3] = [b"pc%41", b"a b?c=d#e%20&mode=rw", b"bytes-\xff\xfe"];
    for name in names {
        let shard = shard_copy(0, &dir.path().join(OsStr::from_bytes(name)));
        let dest = dir
            .path()
            .join(OsStr::from_bytes(&[name, b"-registry"].concat()));
        import(&dest, &[&shard]).pop().unwrap().unwrap();
        assert_eq!(runs(&dest), [template.runs[0].clone()], "{name:?}");
    }
    // Exporting from, and into, such folders.
    let main = dir.path().join(OsStr::from_bytes(b"main%20 ?#\xff"));
    copy_dir(&template.main, &main);
    let out = dir.path().join(OsStr::from_bytes(b"out%41\xfe"));
    shard::export(&main, &template.runs[..1], &out).unwrap();
    assert_eq!(runs(&out), [template.runs[0].clone()]);
}

#[test]
fn blob_names_and_files_that_are_not_blobs_are_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let blob = query(
        &template().shards[0],
        "SELECT sha256 FROM artefact_blobs WHERE role = 'frames.npy'",
    );
    let traversal = "../../../../../../../../dev/zero".to_string();
    type Damage = Box<dyn Fn(&Path)>;
    let blob_file = move |shard: &Path| common::blob_path(shard, &blob);
    let cases: Vec<(&str, Damage, &str)> = vec![
        (
            "a blob name that is a path",
            Box::new(move |shard: &Path| {
                tamper(
                    shard,
                    &format!(
                        "UPDATE blobs SET sha256 = '{traversal}' WHERE sha256 IN (SELECT sha256 FROM artefact_blobs WHERE role = 'frames.npy');
                         UPDATE artefact_blobs SET sha256 = '{traversal}' WHERE role = 'frames.npy';"
                    ),
                )
            }),
            "64 lower-case hex digits",
        ),
        (
            "a symlink to /dev/zero",
            Box::new({
                let blob_file = blob_file.clone();
                move |shard: &Path| {
                    std::fs::remove_file(blob_file(shard)).unwrap();
                    std::os::unix::fs::symlink("/dev/zero", blob_file(shard)).unwrap();
                }
            }),
            "symbolic link",
        ),
        (
            "a FIFO",
            Box::new({
                let blob_file = blob_file.clone();
                move |shard: &Path| {
                    let path = blob_file(shard);
                    std::fs::remove_file(&path).unwrap();
                    let name = std::ffi::CString::new(path.as_os_str().as_bytes()).unwrap();
                    // SAFETY: a valid NUL-terminated path.
                    assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
                }
            }),
            "FIFO",
        ),
        (
            "a view with an endless recursive CTE for a table",
            Box::new(|shard: &Path| {
                tamper(
                    shard,
                    "DROP TABLE run_auc; DROP TABLE run_steps; DROP TABLE runs;
                     CREATE VIEW runs AS WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c)
                     SELECT x AS id FROM c;",
                )
            }),
            "not a table",
        ),
    ];
    for (index, (what, damage, said)) in cases.into_iter().enumerate() {
        let shard = shard_copy(0, &dir.path().join(format!("shard-{index}")));
        damage(&shard);
        let dest = dir.path().join(format!("registry-{index}"));
        let error = refused(&dest, &shard);
        assert!(error.contains(said), "{what}: {error}");
        assert!(runs(&dest).is_empty(), "{what}");
        assert_verify_clean(&dest);
    }
}

#[test]
fn a_refused_shard_is_rolled_back_and_the_next_one_imports() {
    let template = template();
    let dir = tempfile::tempdir().unwrap();
    // Scores without their evaluation: a foreign key to a row that is in
    // neither the shard nor the registry.
    let bad = shard_copy(0, &dir.path().join("bad"));
    tamper(&bad, "DELETE FROM evaluations");
    let dest = dir.path().join("registry");
    let mut results = import(&dest, &[&bad, &template.shards[1]]).into_iter();
    let error = format!("{:#}", results.next().unwrap().unwrap_err());
    assert!(error.contains("table auc, row (evaluation_key="), "{error}");
    assert!(error.contains("FOREIGN KEY"), "{error}");
    results.next().unwrap().unwrap();
    assert_eq!(runs(&dest), [template.runs[1].clone()]);
    assert_eq!(
        query(&dest, "SELECT count(*) FROM artefacts"),
        query(&template.shards[1], "SELECT count(*) FROM artefacts"),
        "nothing of the refused shard"
    );
    assert_verify_clean(&dest);
    // And once more on its own, in a later import.
    refused(&dest, &bad);
    import(&dest, &[&template.shards[0]])
        .pop()
        .unwrap()
        .unwrap();
    assert_eq!(runs(&dest).len(), 2);
    assert_verify_clean(&dest);
}

#[test]
fn a_shard_of_schema_2_imports_with_no_best_guess_and_one_of_schema_1_is_refused() {
    let template = template();
    let dir = tempfile::tempdir().unwrap();
    let best = "SELECT count(*) FROM auc WHERE auc_best_per_frame IS NOT NULL";
    // A shard of this version carries each evaluation's best-guess AUC.
    let dest = dir.path().join("registry");
    import(&dest, &[&template.shards[1]])
        .pop()
        .unwrap()
        .unwrap();
    assert_ne!(query(&dest, best), "0");
    assert_eq!(query(&dest, best), query(&template.shards[1], best));

    // Schema 2 had no best-guess columns: read as NULL.
    let old = shard_copy(0, &dir.path().join("old"));
    tamper(
        &old,
        "ALTER TABLE auc DROP COLUMN auc_best_per_frame;
         ALTER TABLE run_auc DROP COLUMN auc_best_per_frame;
         PRAGMA user_version = 2;",
    );
    let dest = dir.path().join("from-old");
    import(&dest, &[&old]).pop().unwrap().unwrap();
    assert_eq!(runs(&dest), [template.runs[0].clone()]);
    assert_eq!(
        query(&dest, "SELECT count(*) FROM auc"),
        query(&old, "SELECT count(*) FROM auc")
    );
    assert_eq!(query(&dest, best), "0");
    assert_eq!(
        query(
            &dest,
            "SELECT count(*) FROM run_auc WHERE auc_best_per_frame IS NULL"
        ),
        query(&old, "SELECT count(*) FROM run_auc")
    );
    assert_verify_clean(&dest);

    // A schema-2 shard that has the new column anyway does not match.
    let odd = shard_copy(0, &dir.path().join("odd"));
    tamper(&odd, "PRAGMA user_version = 2;");
    let error = refused(&dir.path().join("odd-dest"), &odd);
    assert!(error.contains("table auc: columns"), "{error}");

    // Schema 1 is older than a copy reads.
    let older = shard_copy(0, &dir.path().join("older"));
    tamper(&older, "PRAGMA user_version = 1;");
    let error = refused(&dir.path().join("older-dest"), &older);
    assert!(
        error.contains("registry schema version 1, this scanloc reads versions 2 to 3"),
        "{error}"
    );
}

#[test]
fn edited_specs_and_false_sizes_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    for (index, (edit, said)) in [
        (
            "UPDATE artefacts SET spec = replace(spec, '\"frames\":4', '\"frames\":5') WHERE kind = 'dataset'",
            "spec: hashes to",
        ),
        ("UPDATE artefacts SET kind = 'model' WHERE kind = 'dataset'", "the spec describes"),
        ("UPDATE blobs SET bytes = -5", "bytes: -5 is not a size"),
        ("UPDATE blobs SET bytes = 9223372036854775807", "the shard records 9223372036854775807"),
        ("UPDATE blobs SET bytes = bytes + 1", "the shard records"),
    ]
    .into_iter()
    .enumerate()
    {
        let shard = shard_copy(0, &dir.path().join(format!("shard-{index}")));
        tamper(&shard, edit);
        let dest = dir.path().join(format!("registry-{index}"));
        let error = refused(&dest, &shard);
        assert!(error.contains(said), "{edit}: {error}");
        assert!(error.contains("row ("), "{edit}: {error}");
        assert!(runs(&dest).is_empty());
        assert_verify_clean(&dest);
    }
}

/// Stores other bytes as the predictions' blob in registry `dir`: the
/// artefact key then names other content than elsewhere.
fn other_predictions(dir: &Path) {
    let registry = Registry::open_existing(dir).unwrap();
    let other = registry.blobs().put(b"not the same predictions").unwrap();
    registry
        .connection()
        .execute(
            "INSERT INTO blobs (sha256, bytes, created_at) VALUES (?1, 24, 'now')",
            [&other],
        )
        .unwrap();
    registry
        .connection()
        .execute(
            "UPDATE artefact_blobs SET sha256 = ?1 WHERE artefact_key IN \
             (SELECT key FROM artefacts WHERE kind = 'predictions')",
            [&other],
        )
        .unwrap();
}

#[test]
fn a_refused_export_or_import_leaves_nothing_behind() {
    let template = template();
    let dir = tempfile::tempdir().unwrap();
    // An export that fails on a damaged blob removes the folder it made.
    let main = dir.path().join("main");
    copy_dir(&template.main, &main);
    let blob = query(
        &main,
        "SELECT sha256 FROM artefact_blobs WHERE role = 'frames.npy' LIMIT 1",
    );
    flip_a_byte(&common::blob_path(&main, &blob));
    let out = dir.path().join("out");
    let error = shard::export(&main, &template.runs, &out).unwrap_err();
    assert_eq!(scanloc::error::exit_code(&error), 2, "{error:#}");
    assert!(!out.exists(), "the refused export left {}", out.display());

    // An export into a shard that stores an artefact with other blobs is
    // refused before anything is written.
    let existing = dir.path().join("existing");
    copy_dir(&template.shards[0], &existing);
    other_predictions(&existing);
    tamper(
        &existing,
        "DELETE FROM run_auc; DELETE FROM run_steps; DELETE FROM runs;",
    );
    let count = |dir: &Path| {
        query(
            dir,
            "SELECT (SELECT count(*) FROM artefacts) || '/' || (SELECT count(*) FROM blobs)",
        )
    };
    let before = count(&existing);
    let error = shard::export(&template.main, &template.runs, &existing).unwrap_err();
    assert_eq!(scanloc::error::exit_code(&error), 1, "{error:#}");
    assert_eq!(count(&existing), before);
    assert!(runs(&existing).is_empty());

    // An import refusing a run for a conflict leaves none of the artefacts
    // only that run used.
    let dest = dir.path().join("registry");
    import(&dest, &[&template.shards[0]])
        .pop()
        .unwrap()
        .unwrap();
    tamper(
        &dest,
        "DELETE FROM run_auc; DELETE FROM run_steps; DELETE FROM runs;
         DELETE FROM auc; DELETE FROM evaluations; DELETE FROM datasets;
         DELETE FROM artefact_blobs WHERE artefact_key NOT IN (SELECT key FROM predictions);
         DELETE FROM artefacts WHERE key NOT IN (SELECT key FROM predictions);",
    );
    let conflicting = dir.path().join("conflicting");
    copy_dir(&template.shards[0], &conflicting);
    other_predictions(&conflicting);
    let before = query(&dest, "SELECT count(*) FROM artefacts");
    let report = import(&dest, &[&conflicting]).pop().unwrap().unwrap();
    assert_eq!(report.conflicts.len(), 1, "{report:?}");
    assert_eq!(
        report.conflicts[0].runs_not_copied,
        [template.runs[0].clone()]
    );
    assert_eq!(
        query(&dest, "SELECT count(*) FROM artefacts"),
        before,
        "orphans were left"
    );
    assert!(runs(&dest).is_empty());
}
