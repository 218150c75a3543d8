//! Fuzzing `registry import` with damaged and crafted shards: a good
//! shard (`hostile_shards::template`) with random damage of every kind
//! issue 39 found — views for tables, wrong or generated columns, names
//! that are paths or not text, edited specs, false sizes, step claims,
//! rows whose foreign keys fail, blobs that are symlinks, FIFOs, folders,
//! truncated or longer, a truncated or garbled database or write-ahead
//! log — imported in process (`cli::main_with`) together with a good
//! shard into a scratch registry. The property: exit 0 or 2, no panic,
//! nothing written outside the registry, no hang past the fuzz guard's
//! watchdog, `registry verify` clean afterwards, and the good shard
//! imported. `make fuzz` runs it with `SCANLOC_FUZZ_CASES` cases.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use proptest::prelude::*;
use rusqlite::types::Value;
use sha2::{Digest, Sha256};

use crate::hostile_shards::{assert_verify_clean, runs, shard_copy, template};
use scanloc::cli;

use crate::{common, hostile_fuzz_guard};

/// The durable tables and the columns damage is aimed at.
const TABLES: &[&str] = &[
    "blobs",
    "artefacts",
    "artefact_blobs",
    "datasets",
    "predictions",
    "evaluations",
    "auc",
    "runs",
    "run_steps",
    "run_auc",
];
const COLUMNS: &[(&str, &str)] = &[
    ("blobs", "sha256"),
    ("blobs", "bytes"),
    ("artefacts", "key"),
    ("artefacts", "kind"),
    ("artefacts", "name"),
    ("artefacts", "spec"),
    ("artefacts", "created_by_run"),
    ("artefact_blobs", "role"),
    ("artefact_blobs", "sha256"),
    ("datasets", "name"),
    ("predictions", "detector"),
    ("evaluations", "dataset"),
    ("auc", "evaluation_key"),
    ("runs", "id"),
    ("runs", "status"),
    ("runs", "parent_run"),
    ("runs", "cv_detector"),
    ("run_steps", "step"),
    ("run_steps", "artefact_key"),
    ("run_auc", "detector"),
    ("run_auc", "dataset"),
];

/// One piece of damage to a shard.
#[derive(Debug, Clone)]
enum Damage {
    /// SQL run on the shard's database (foreign keys off; an error, e.g.
    /// a uniqueness conflict, leaves the shard as it was).
    Sql(String),
    /// One row's column set to a value.
    Set {
        table: &'static str,
        column: &'static str,
        value: Value,
    },
    /// Blob file number `n` (of the shard's, in order) replaced.
    Blob(usize, BlobDamage),
    /// The database file truncated to this fraction (per mille).
    TruncateDatabase(u16),
    /// Bytes written over the database at this fraction (per mille).
    GarbleDatabase(u16, Vec<u8>),
    /// A write-ahead log of these bytes beside the database.
    Wal(Vec<u8>),
    /// The database replaced by a symbolic link to a good shard's.
    DatabaseSymlink,
}

#[derive(Debug, Clone)]
enum BlobDamage {
    SymlinkToDevZero,
    SymlinkOutside,
    Fifo,
    Folder,
    Removed,
    Truncated(usize),
    Appended(Vec<u8>),
}

fn hostile_text() -> BoxedStrategy<String> {
    prop_oneof![
        Just("/../../../../elsewhere/X".to_string()),
        Just("../elsewhere".to_string()),
        Just("..".to_string()),
        Just(String::new()),
        Just("a/b".to_string()),
        Just("ok-name".to_string()),
        Just("dataset/ok".to_string()),
        Just("x".repeat(300)),
        Just("a\u{0}b".to_string()),
        Just("é@b+c".to_string()),
        Just("0".repeat(64)),
        Just("A".repeat(64)),
        "[a-z0-9/.@+-]{0,12}",
        any::<String>(),
    ]
    .boxed()
}

fn value() -> BoxedStrategy<Value> {
    prop_oneof![
        4 => hostile_text().prop_map(Value::Text),
        1 => Just(Value::Null),
        1 => prop_oneof![Just(-5i64), Just(i64::MAX), Just(0), any::<i64>()].prop_map(Value::Integer),
        1 => any::<f64>().prop_map(Value::Real),
        1 => proptest::collection::vec(any::<u8>(), 0..70).prop_map(Value::Blob),
    ]
    .boxed()
}

fn table() -> impl Strategy<Value = &'static str> {
    proptest::sample::select(TABLES)
}

fn sql() -> BoxedStrategy<String> {
    prop_oneof![
        table().prop_map(|t| format!(
            "ALTER TABLE {t} RENAME TO {t}_old; CREATE VIEW {t} AS SELECT * FROM {t}_old;"
        )),
        table().prop_map(|t| format!(
            "DROP TABLE {t}; CREATE VIEW {t} AS WITH RECURSIVE c(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM c) SELECT x AS id FROM c;"
        )),
        table().prop_map(|t| format!("ALTER TABLE {t} ADD COLUMN extra TEXT;")),
        table().prop_map(|t| format!("ALTER TABLE {t} ADD COLUMN g BLOB AS (zeroblob(100000));")),
        proptest::sample::select(COLUMNS)
            .prop_map(|(t, c)| format!("ALTER TABLE {t} RENAME COLUMN {c} TO {c}_renamed;")),
        proptest::sample::select(COLUMNS).prop_map(|(t, c)| format!("ALTER TABLE {t} DROP COLUMN {c};")),
        table().prop_map(|t| format!("DELETE FROM {t};")),
        table().prop_map(|t| format!("DROP TABLE {t};")),
        Just("INSERT INTO step_claims (key, run_id, host, pid, claimed_at) SELECT key, 'ghost', 'here', 1, 'now' FROM artefacts;".to_string()),
        Just("UPDATE artefacts SET spec = spec || ' ' WHERE rowid = (SELECT min(rowid) FROM artefacts);".to_string()),
        Just("UPDATE blobs SET bytes = bytes + 1;".to_string()),
        Just("UPDATE runs SET status = 'running';".to_string()),
        Just("CREATE TABLE evil (x); INSERT INTO evil VALUES (1);".to_string()),
        Just("CREATE TRIGGER t AFTER INSERT ON runs BEGIN DELETE FROM runs; END;".to_string()),
        Just("CREATE INDEX i ON runs (length(zeroblob(100000)));".to_string()),
        Just("PRAGMA user_version = 1;".to_string()),
        Just("INSERT INTO blobs SELECT '../../../../dev/zero', 5, 'now';
              INSERT INTO artefact_blobs SELECT key, 'extra.bin', '../../../../dev/zero' FROM artefacts;".to_string()),
    ]
    .boxed()
}

fn blob_damage() -> BoxedStrategy<BlobDamage> {
    prop_oneof![
        Just(BlobDamage::SymlinkToDevZero),
        Just(BlobDamage::SymlinkOutside),
        Just(BlobDamage::Fifo),
        Just(BlobDamage::Folder),
        Just(BlobDamage::Removed),
        (0usize..64).prop_map(BlobDamage::Truncated),
        proptest::collection::vec(any::<u8>(), 1..16).prop_map(BlobDamage::Appended),
    ]
    .boxed()
}

fn damage() -> BoxedStrategy<Damage> {
    prop_oneof![
        6 => sql().prop_map(Damage::Sql),
        6 => (proptest::sample::select(COLUMNS), value())
            .prop_map(|((table, column), value)| Damage::Set { table, column, value }),
        4 => (0usize..32, blob_damage()).prop_map(|(n, d)| Damage::Blob(n, d)),
        1 => (0u16..1000).prop_map(Damage::TruncateDatabase),
        1 => (0u16..1000, proptest::collection::vec(any::<u8>(), 1..64))
            .prop_map(|(at, bytes)| Damage::GarbleDatabase(at, bytes)),
        1 => proptest::collection::vec(any::<u8>(), 0..200).prop_map(Damage::Wal),
        1 => Just(Damage::DatabaseSymlink),
    ]
    .boxed()
}

/// The shard's blob files, in order.
fn blob_files(shard: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = walk(&shard.join("blobs"))
        .into_iter()
        .filter(|(_, kind)| kind != "folder")
        .map(|(path, _)| path)
        .collect();
    files.sort();
    files
}

fn make_fifo(path: &Path) {
    use std::os::unix::ffi::OsStrExt;
    let name = std::ffi::CString::new(path.as_os_str().as_bytes()).unwrap();
    // SAFETY: a valid NUL-terminated path.
    unsafe { libc::mkfifo(name.as_ptr(), 0o600) };
}

fn apply(shard: &Path, elsewhere: &Path, damage: &Damage) {
    let database = shard.join("registry.sqlite");
    let sql = |run: &dyn Fn(&rusqlite::Connection) -> rusqlite::Result<()>| {
        if let Ok(conn) = rusqlite::Connection::open(&database) {
            let _ = conn.execute_batch("PRAGMA foreign_keys = OFF;");
            let _ = run(&conn);
        }
    };
    match damage {
        Damage::Sql(statements) => sql(&|conn| conn.execute_batch(statements)),
        Damage::Set {
            table,
            column,
            value,
        } => sql(&|conn| {
            conn.execute(
                &format!(
                    "UPDATE {table} SET {column} = ?1 WHERE rowid = (SELECT min(rowid) FROM {table})"
                ),
                [value],
            )
            .map(|_| ())
        }),
        Damage::Blob(n, damage) => {
            let files = blob_files(shard);
            if files.is_empty() {
                return;
            }
            let path = &files[n % files.len()];
            // Never opened unless a regular file: an earlier damage may
            // have left a FIFO here, which would block the reader.
            let regular = std::fs::symlink_metadata(path).is_ok_and(|m| m.is_file());
            let bytes = if regular {
                std::fs::read(path).unwrap_or_default()
            } else {
                Vec::new()
            };
            let _ = std::fs::remove_file(path);
            match damage {
                BlobDamage::SymlinkToDevZero => {
                    std::os::unix::fs::symlink("/dev/zero", path).unwrap()
                }
                BlobDamage::SymlinkOutside => {
                    std::os::unix::fs::symlink(elsewhere.join("file"), path).unwrap()
                }
                BlobDamage::Fifo => make_fifo(path),
                BlobDamage::Folder => std::fs::create_dir(path).unwrap(),
                BlobDamage::Removed => {}
                BlobDamage::Truncated(keep) => {
                    std::fs::write(path, &bytes[..(*keep).min(bytes.len())]).unwrap()
                }
                BlobDamage::Appended(more) => {
                    std::fs::write(path, [bytes.as_slice(), more].concat()).unwrap()
                }
            }
        }
        Damage::TruncateDatabase(permille) => {
            let bytes = std::fs::read(&database).unwrap_or_default();
            let keep = bytes.len() * usize::from(*permille) / 1000;
            let _ = std::fs::write(&database, &bytes[..keep]);
        }
        Damage::GarbleDatabase(permille, garbage) => {
            let mut bytes = std::fs::read(&database).unwrap_or_default();
            let at = bytes.len() * usize::from(*permille) / 1000;
            for (i, byte) in garbage.iter().enumerate() {
                if let Some(slot) = bytes.get_mut(at + i) {
                    *slot = *byte;
                }
            }
            let _ = std::fs::write(&database, bytes);
        }
        Damage::Wal(bytes) => {
            let _ = std::fs::write(shard.join("registry.sqlite-wal"), bytes);
        }
        Damage::DatabaseSymlink => {
            // To a copy of a good database outside the shard (later damage
            // goes through the link, never into the template).
            let target = elsewhere.join("registry.sqlite");
            std::fs::copy(template().shards[1].join("registry.sqlite"), &target).unwrap();
            let _ = std::fs::remove_file(&database);
            std::os::unix::fs::symlink(&target, &database).unwrap();
        }
    }
}

/// Every entry under `dir`, symbolic links not followed: a file by the
/// sha256 of its bytes, anything else by its kind (a FIFO is never read).
fn walk(dir: &Path) -> Vec<(PathBuf, String)> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return out;
    };
    for entry in entries.flatten() {
        let path = entry.path();
        let Ok(metadata) = std::fs::symlink_metadata(&path) else {
            continue;
        };
        let kind = metadata.file_type();
        if kind.is_dir() {
            out.push((path.clone(), "folder".to_string()));
            out.extend(walk(&path));
        } else if kind.is_file() {
            let bytes = std::fs::read(&path).unwrap_or_default();
            out.push((path, hex::encode(Sha256::digest(&bytes))));
        } else if kind.is_symlink() {
            let target = std::fs::read_link(&path).unwrap_or_default();
            out.push((path, format!("link to {}", target.display())));
        } else {
            out.push((path, "special".to_string()));
        }
    }
    out
}

/// Everything in the case folder but the registry.
fn outside(case: &Path, registry: &Path) -> BTreeMap<PathBuf, String> {
    walk(case)
        .into_iter()
        .filter(|(path, _)| !path.starts_with(registry))
        .collect()
}

/// `scanloc registry import SHARDS --registry REGISTRY` in process, under
/// the fuzz guards: (exit code, standard error) or the panic's message.
fn import_in_process(
    registry: &Path,
    shards: &[&Path],
    description: String,
) -> Result<(u8, String), String> {
    let _case = hostile_fuzz_guard::Case::enter(description);
    let mut args = vec!["scanloc".to_string(), "registry".into(), "import".into()];
    args.extend(shards.iter().map(|s| s.display().to_string()));
    args.extend(["--registry".into(), registry.display().to_string()]);
    let (mut stdout, mut stderr) = (Vec::new(), Vec::new());
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        cli::main_with(args, &mut stdout, &mut stderr, false)
    }));
    let stderr = String::from_utf8_lossy(&stderr).into_owned();
    match outcome {
        Ok(code) => (0..=255u8)
            .find(|&n| std::process::ExitCode::from(n) == code)
            .map(|n| (n, stderr))
            .ok_or_else(|| "an exit code above 255".to_string()),
        Err(payload) => Err(payload
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "a panic without a message".into())),
    }
}

fn shard_case(damages: &[Damage]) -> Result<(), TestCaseError> {
    let template = template();
    let dir = common::fuzz_case_dir();
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    std::fs::write(elsewhere.join("file"), b"not a blob").unwrap();
    let shard = shard_copy(0, &dir.path().join("shard"));
    for damage in damages {
        apply(&shard, &elsewhere, damage);
    }
    let registry = dir.path().join("registry");
    let before = outside(dir.path(), &registry);
    let good = &template.shards[1];
    let ended = import_in_process(
        &registry,
        &[&shard, good],
        format!(
            "registry import of a shard damaged by {damages:?} (in {})",
            dir.path().display()
        ),
    );
    let (code, stderr) = match ended {
        Ok(ended) => ended,
        Err(panic) => {
            return Err(TestCaseError::fail(format!(
                "panicked: {panic}: {damages:?}"
            )));
        }
    };
    prop_assert!(
        code == 0 || code == 2,
        "exit {}: {}: {:?}",
        code,
        stderr,
        damages
    );
    prop_assert_eq!(
        outside(dir.path(), &registry),
        before,
        "wrote outside the registry: {:?}",
        damages
    );
    assert_verify_clean(&registry);
    prop_assert!(
        runs(&registry).contains(&template.runs[1]),
        "the good shard did not land: {}: {:?}",
        stderr,
        damages
    );
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: common::fuzz_cases(24),
        max_shrink_iters: 64,
        max_shrink_time: 60_000,
        ..ProptestConfig::default()
    })]

    #[test]
    fn crafted_shards_are_imported_or_refused_cleanly(
        damages in proptest::collection::vec(damage(), 0..4),
    ) {
        shard_case(&damages)?;
    }
}
