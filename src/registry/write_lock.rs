//! The registry's write lock, and who holds it.
//!
//! Every write is a `BEGIN IMMEDIATE` transaction: SQLite lets one
//! connection write at a time and the others wait. SQLite does not say who
//! is writing, so a writer records itself (run, pid, host) in
//! `registry.sqlite-writer` beside the database once it holds the lock,
//! and removes the file when its transaction ends. A writer that has to
//! wait reads that file and says once, on standard error, whose lock it is
//! waiting for. The file is only a hint: one left behind by a killed
//! process names a process that is gone, and then the lock is reported as
//! held by another program (the `sqlite3` shell, an older scanloc).
//!
//! A second lock, [`BlobLock`], keeps `registry gc` and imports apart: an
//! import writes blob files before the rows that record them, and `gc`
//! deletes blob files no row records. Imports (and exports, and a sweep
//! task seeding its shard) hold it shared for their whole copy, `gc`
//! holds it exclusively; it is an advisory lock on the file
//! `registry.sqlite-blob-lock`, released by the kernel when its process
//! ends, however it ends.

use std::ops::Deref;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use rusqlite::Connection;
use serde::{Deserialize, Serialize};

use super::{host_name, is_busy, process_alive};

/// The file naming the current writer, beside the database.
pub(crate) const HOLDER_FILE: &str = "registry.sqlite-writer";

/// The file [`BlobLock`] locks, beside the database.
pub(crate) const BLOB_LOCK_FILE: &str = "registry.sqlite-blob-lock";

/// How often a waiting writer tries for the lock again.
const POLL: Duration = Duration::from_millis(100);

/// Who holds (or wants) the write lock.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Holder {
    /// The run this process is executing, if any.
    pub run: Option<String>,
    pub pid: u32,
    pub host: String,
}

impl Holder {
    /// This process, executing `run` (if any).
    pub fn this_process(run: Option<&str>) -> Self {
        Self {
            run: run.map(str::to_string),
            pid: std::process::id(),
            host: host_name(),
        }
    }
}

/// The holder recorded in registry folder `dir`, if its file is there and
/// readable.
pub(crate) fn recorded_holder(dir: &Path) -> Option<Holder> {
    let text = std::fs::read_to_string(dir.join(HOLDER_FILE)).ok()?;
    serde_json::from_str(&text).ok()
}

/// The line a writer prints when it has to wait for `holder`'s lock
/// (`None`: no live scanloc process is recorded).
pub(crate) fn waiting_message(holder: Option<&Holder>) -> String {
    match holder {
        Some(Holder {
            run: Some(run),
            pid,
            host,
        }) => format!("waiting for the registry's write lock held by run {run} (pid {pid} on {host})"),
        Some(Holder {
            run: None,
            pid,
            host,
        }) => format!(
            "waiting for the registry's write lock held by scanloc outside a run (pid {pid} on {host})"
        ),
        None => "waiting for the registry's write lock held by another program (no scanloc process records it; e.g. the sqlite3 shell)".to_string(),
    }
}

/// The recorded holder, unless it is certainly not holding the lock: a
/// process on this host that is gone.
fn live_holder(dir: &Path) -> Option<Holder> {
    recorded_holder(dir).filter(|h| h.host != host_name() || process_alive(h.pid))
}

/// A `BEGIN IMMEDIATE` transaction on the registry database: commit it
/// with [`WriteTransaction::commit`]; dropped uncommitted, it rolls back.
/// Dereferences to the connection for the statements in between.
pub struct WriteTransaction<'c> {
    conn: &'c Connection,
    holder_file: PathBuf,
    /// The holder file's text as this transaction wrote it.
    written: String,
    open: bool,
}

impl<'c> WriteTransaction<'c> {
    /// Waits for the write lock (at most `timeout`) and begins the
    /// transaction, recording `me` as its holder in registry folder `dir`.
    /// When the lock is taken, says once on standard error whose it is.
    pub fn begin(
        conn: &'c Connection,
        dir: &Path,
        me: &Holder,
        timeout: Duration,
    ) -> anyhow::Result<Self> {
        let started = Instant::now();
        let mut said = false;
        // Short waits inside SQLite, so the first busy answer comes soon
        // enough to say whose lock this is.
        conn.busy_timeout(POLL)?;
        let began = loop {
            match conn.execute_batch("BEGIN IMMEDIATE") {
                Ok(()) => break Ok(()),
                Err(e) if is_busy(&e) && started.elapsed() < timeout => {
                    if !said {
                        crate::progress::note(waiting_message(live_holder(dir).as_ref()));
                        said = true;
                    }
                }
                Err(e) if is_busy(&e) => {
                    break Err(anyhow::anyhow!(
                        "{}: gave up after {} s: {}",
                        dir.display(),
                        timeout.as_secs(),
                        waiting_message(live_holder(dir).as_ref()).replacen(
                            "waiting for",
                            "could not get",
                            1
                        )
                    ));
                }
                Err(e) => break Err(e.into()),
            }
        };
        // Statements inside the transaction, and autocommit writes, keep
        // SQLite's own long wait.
        conn.busy_timeout(timeout)?;
        began?;
        let holder_file = dir.join(HOLDER_FILE);
        let written = serde_json::to_string(me)?;
        // A hint only: a registry folder that cannot take the file still
        // takes the transaction.
        let _ = write_replacing(&holder_file, &written);
        Ok(Self {
            conn,
            holder_file,
            written,
            open: true,
        })
    }

    /// Commits the transaction.
    pub fn commit(mut self) -> rusqlite::Result<()> {
        self.conn.execute_batch("COMMIT")?;
        self.open = false;
        self.forget_holder();
        Ok(())
    }

    /// Removes the holder file if it still names this transaction (the
    /// next writer may already have replaced it).
    fn forget_holder(&self) {
        if std::fs::read_to_string(&self.holder_file).is_ok_and(|text| text == self.written) {
            let _ = std::fs::remove_file(&self.holder_file);
        }
    }
}

impl Deref for WriteTransaction<'_> {
    type Target = Connection;

    fn deref(&self) -> &Connection {
        self.conn
    }
}

impl Drop for WriteTransaction<'_> {
    fn drop(&mut self) {
        if self.open {
            let _ = self.conn.execute_batch("ROLLBACK");
            self.forget_holder();
        }
    }
}

/// Who holds a [`BlobLock`]: copies into the registry share it, `gc`
/// holds it alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum BlobLockUse {
    /// An import, export or seeding copy: writes blobs before recording them.
    Copy,
    /// `registry gc`: deletes blobs no row records.
    Gc,
}

/// The lock that keeps `registry gc` from deleting the blobs a copy into
/// the registry is writing (see the module docs); released when dropped.
#[derive(Debug)]
pub(crate) struct BlobLock {
    _file: std::fs::File,
}

impl BlobLock {
    /// Takes the lock of registry folder `dir` for `purpose`, waiting at
    /// most `timeout` and saying once on standard error what it waits for.
    pub(crate) fn take(
        dir: &Path,
        purpose: BlobLockUse,
        timeout: Duration,
    ) -> anyhow::Result<Self> {
        let path = dir.join(BLOB_LOCK_FILE);
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(|e| anyhow::anyhow!("{}: cannot open the lock file: {e}", path.display()))?;
        let (waiting_for, try_lock): (&str, fn(&std::fs::File) -> _) = match purpose {
            BlobLockUse::Copy => ("`registry gc`", std::fs::File::try_lock_shared),
            BlobLockUse::Gc => (
                "a copy into the registry (an import)",
                std::fs::File::try_lock,
            ),
        };
        let started = Instant::now();
        let mut said = false;
        loop {
            match try_lock(&file) {
                Ok(()) => return Ok(Self { _file: file }),
                Err(std::fs::TryLockError::WouldBlock) if started.elapsed() < timeout => {
                    if !said {
                        crate::progress::note(format_args!(
                            "{}: waiting for {waiting_for} to finish",
                            dir.display()
                        ));
                        said = true;
                    }
                    std::thread::sleep(POLL);
                }
                Err(std::fs::TryLockError::WouldBlock) => anyhow::bail!(
                    "{}: gave up after {} s waiting for {waiting_for} to finish",
                    dir.display(),
                    timeout.as_secs()
                ),
                Err(std::fs::TryLockError::Error(e)) => {
                    anyhow::bail!("{}: cannot lock: {e}", path.display())
                }
            }
        }
    }
}

/// Writes `text` to `path` through a temporary file and a rename, so a
/// reader never sees half of it.
fn write_replacing(path: &Path, text: &str) -> std::io::Result<()> {
    let folder = path.parent().unwrap_or(Path::new("."));
    let mut temporary = tempfile::Builder::new()
        .prefix(".scanloc-writer-")
        .tempfile_in(folder)?;
    std::io::Write::write_all(&mut temporary, text.as_bytes())?;
    temporary.persist(path).map_err(|e| e.error)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_message_names_the_run_pid_and_host() {
        let holder = Holder {
            run: Some("20261129-abc".into()),
            pid: 42,
            host: "node7".into(),
        };
        assert_eq!(
            waiting_message(Some(&holder)),
            "waiting for the registry's write lock held by run 20261129-abc (pid 42 on node7)"
        );
    }

    #[test]
    fn gc_waits_for_copies_and_copies_share() {
        let dir = tempfile::tempdir().unwrap();
        let short = Duration::from_millis(300);
        let first = BlobLock::take(dir.path(), BlobLockUse::Copy, short).unwrap();
        let second = BlobLock::take(dir.path(), BlobLockUse::Copy, short).unwrap();
        let error = BlobLock::take(dir.path(), BlobLockUse::Gc, short).unwrap_err();
        assert!(error.to_string().contains("gave up"), "{error}");
        drop((first, second));
        let gc = BlobLock::take(dir.path(), BlobLockUse::Gc, short).unwrap();
        assert!(BlobLock::take(dir.path(), BlobLockUse::Copy, short).is_err());
        drop(gc);
        BlobLock::take(dir.path(), BlobLockUse::Copy, short).unwrap();
    }

    #[test]
    fn the_holder_file_lives_while_the_transaction_does() {
        let dir = tempfile::tempdir().unwrap();
        let conn = Connection::open(dir.path().join("registry.sqlite")).unwrap();
        conn.execute_batch("PRAGMA journal_mode = WAL; CREATE TABLE t (x)")
            .unwrap();
        let me = Holder::this_process(Some("run-1"));
        let tx = WriteTransaction::begin(&conn, dir.path(), &me, Duration::from_secs(5)).unwrap();
        tx.execute("INSERT INTO t VALUES (1)", []).unwrap();
        assert_eq!(recorded_holder(dir.path()), Some(me.clone()));
        tx.commit().unwrap();
        assert_eq!(recorded_holder(dir.path()), None);
        let tx = WriteTransaction::begin(&conn, dir.path(), &me, Duration::from_secs(5)).unwrap();
        tx.execute("INSERT INTO t VALUES (2)", []).unwrap();
        drop(tx);
        assert_eq!(recorded_holder(dir.path()), None);
        let count: i64 = conn
            .query_row("SELECT count(*) FROM t", [], |row| row.get(0))
            .unwrap();
        assert_eq!(count, 1, "the dropped transaction rolled back");
    }
}
