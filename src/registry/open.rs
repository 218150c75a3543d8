//! Opening a registry: creating its folder and database, read-only when
//! the folder cannot be written, refusing a damaged or lost database, and
//! the write transaction every change goes through.

use std::path::Path;
use std::time::Duration;

use rusqlite::{Connection, OpenFlags};

use super::claims::STEP_CLAIMS;
use super::write_lock::{Holder, WriteTransaction};
use super::{BlobStore, DATABASE_FILE, Registry, SCHEMA_VERSION};
use crate::error::input_error;

impl Registry {
    /// Opens the registry in `dir`, creating it (and applying migrations)
    /// if needed.
    pub fn open(dir: &Path) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).map_err(|e| {
            input_error(format!(
                "{}: cannot create the registry: {e}",
                dir.display()
            ))
        })?;
        if !writable(dir) {
            return Self::connect_read_only(dir);
        }
        Self::connect(dir, Integrity::CheckBeforeWriting)
    }

    /// Opens the registry in `dir`, which cannot be written, read-only (see
    /// [`open_database_read_only`]); blobs are read, nothing is created.
    fn connect_read_only(dir: &Path) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        let path = dir.join(DATABASE_FILE);
        if !path.is_file() {
            return Err(input_error(format!(
                "{}: cannot create a registry here (the folder is read-only)",
                dir.display()
            )));
        }
        let conn = open_database_read_only(dir)?;
        let schema: i64 = conn.query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if schema != SCHEMA_VERSION {
            return Err(input_error(format!(
                "{}: the registry is read-only and its schema (version {schema}) is not this scanloc's ({SCHEMA_VERSION}); open it once where it can be written",
                dir.display()
            )));
        }
        conn.busy_timeout(BUSY_TIMEOUT)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            conn,
            blobs: BlobStore::read_only(dir),
            read_only: true,
            writer_run: None,
        })
    }

    /// Refuses, as bad input, a `command` that needs to write on a
    /// registry opened read-only.
    pub fn refuse_read_only(&self, command: &str) -> anyhow::Result<()> {
        if self.read_only {
            return Err(input_error(format!(
                "the registry at {} is read-only; {command} needs to write",
                self.dir.display()
            )));
        }
        Ok(())
    }

    /// [`Registry::open`] for a `command` that writes: a registry that
    /// cannot be written is refused (see [`Registry::refuse_read_only`]).
    pub fn open_to_write(dir: &Path, command: &str) -> anyhow::Result<Self> {
        let registry = Self::open(dir)?;
        registry.refuse_read_only(command)?;
        Ok(registry)
    }

    /// Begins a write transaction (`BEGIN IMMEDIATE`), waiting for the
    /// write lock and saying whose it is (see [`write_lock`]).
    pub(super) fn write_transaction(&self) -> anyhow::Result<WriteTransaction<'_>> {
        WriteTransaction::begin(
            &self.conn,
            &self.dir,
            &Holder::this_process(self.writer_run.as_deref()),
            BUSY_TIMEOUT,
        )
    }

    /// Whether this registry was opened read-only (see [`Registry::open`]):
    /// run records are then not kept.
    pub fn is_read_only(&self) -> bool {
        self.read_only
    }

    /// Opens an existing registry; a folder without a database is bad input.
    /// A registry this process cannot write (a read-only mount, no write
    /// permission, or [`SCANLOC_REGISTRY_READ_ONLY`]) is opened read-only,
    /// so every command that only reads works on it (see
    /// [`Registry::refuse_read_only`] for those that write).
    ///
    /// [`SCANLOC_REGISTRY_READ_ONLY`]: crate::env_vars::SCANLOC_REGISTRY_READ_ONLY
    pub fn open_existing(dir: &Path) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        if !dir.join(DATABASE_FILE).is_file() {
            return Err(input_error(format!(
                "{}: no registry here (no {DATABASE_FILE}); `scanloc run` creates one",
                dir.display()
            )));
        }
        if !writable(dir) {
            return Self::connect_read_only(dir);
        }
        Self::connect(dir, Integrity::Unchecked)
    }

    fn connect(dir: &Path, integrity: Integrity) -> anyhow::Result<Self> {
        refuse_lost_database(dir)?;
        let path = dir.join(DATABASE_FILE);
        create_database_file(&path)?;
        let conn = Connection::open(&path).map_err(|e| {
            input_error(format!("{}: cannot open the registry: {e}", path.display()))
        })?;
        conn.busy_timeout(BUSY_TIMEOUT)?;
        // Switching to WAL needs a moment without other connections; retry
        // while a concurrent first open holds the file.
        let mut attempts = 0;
        loop {
            match conn.query_row("PRAGMA journal_mode = WAL", [], |row| {
                row.get::<_, String>(0)
            }) {
                Ok(_) => break,
                Err(e) if attempts < 200 && is_busy(&e) => {
                    attempts += 1;
                    std::thread::sleep(Duration::from_millis(50));
                }
                Err(e) if is_damage(&e) => return Err(damaged(dir, &e.to_string())),
                Err(e) => {
                    return Err(input_error(format!(
                        "{}: cannot open the registry database for shared use: {e}",
                        path.display()
                    )));
                }
            }
        }
        if integrity == Integrity::CheckBeforeWriting {
            // Milliseconds for a registry's database (it holds records, not
            // data); a damaged one would take every later write with it.
            let verdict: String = conn
                .query_row("PRAGMA quick_check(1)", [], |row| row.get(0))
                .or_else(|e| {
                    if is_damage(&e) {
                        Ok(e.to_string())
                    } else {
                        Err(e)
                    }
                })?;
            if verdict != "ok" {
                return Err(damaged(dir, &verdict));
            }
        }
        conn.execute_batch("PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = ON;")?;
        // Who is computing which step now: a table of the moment, not of the
        // record (rows live while a step is computed), so it needs no schema
        // version and older scanloc versions ignore it.
        conn.execute_batch(STEP_CLAIMS)?;
        let mut registry = Self {
            dir: dir.to_path_buf(),
            conn,
            blobs: BlobStore::open(dir)?,
            read_only: false,
            writer_run: None,
        };
        registry.migrate()?;
        Ok(registry)
    }
}

/// How long a writer waits for another's transaction before giving up.
pub(super) const BUSY_TIMEOUT: Duration = Duration::from_secs(300);

/// Creates the (empty) database file if missing, with mode 0666 minus the
/// umask like any other file a user makes (SQLite's own default is 0644
/// whatever the umask; its `-wal` and `-shm` files copy the database's
/// mode), so that a group sharing a registry can share its database.
fn create_database_file(path: &Path) -> anyhow::Result<()> {
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.mode(0o666);
    }
    match options.open(path) {
        Ok(_) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
        Err(e) => Err(input_error(format!(
            "{}: cannot create the registry database: {e}",
            path.display()
        ))),
    }
}

/// Whether every registry is to be opened read-only
/// ([`SCANLOC_REGISTRY_READ_ONLY`](crate::env_vars::SCANLOC_REGISTRY_READ_ONLY)
/// is true; a value that is not a boolean, which the CLI refuses, counts as
/// true).
fn read_only_forced() -> bool {
    crate::env_vars::flag(crate::env_vars::SCANLOC_REGISTRY_READ_ONLY).unwrap_or(true)
}

/// Whether this process can create files in `dir` and write its database
/// (tried, not inferred from permission bits, which do not apply to root
/// or to a read-only mount); never for an existing registry when read-only
/// is forced (a new one, such as `reproduce`'s scratch registry, is made).
fn writable(dir: &Path) -> bool {
    if read_only_forced() && dir.join(DATABASE_FILE).is_file() {
        return false;
    }
    let refused = |e: &std::io::Error| {
        matches!(
            e.kind(),
            std::io::ErrorKind::ReadOnlyFilesystem | std::io::ErrorKind::PermissionDenied
        )
    };
    let database = dir.join(DATABASE_FILE);
    if database.is_file()
        && let Err(e) = std::fs::OpenOptions::new().write(true).open(&database)
        && refused(&e)
    {
        return false;
    }
    match tempfile::Builder::new()
        .prefix(".scanloc-write-probe-")
        .tempfile_in(dir)
    {
        Ok(_) => true,
        Err(e) => !refused(&e),
    }
}

/// Opens the database of the registry in `dir` for reading only, creating
/// no file: as a database others may be writing (`mode=ro`) while SQLite
/// can share it so, else (a read-only folder holds no write-ahead-log
/// index for it, and none can be made) as an immutable file. With
/// [`SCANLOC_REGISTRY_READ_ONLY`](crate::env_vars::SCANLOC_REGISTRY_READ_ONLY)
/// it is opened immutable at once (a shared read would create that index).
pub fn open_database_read_only(dir: &Path) -> anyhow::Result<Connection> {
    let path = dir.join(DATABASE_FILE);
    let flags = OpenFlags::SQLITE_OPEN_READ_ONLY
        | OpenFlags::SQLITE_OPEN_URI
        | OpenFlags::SQLITE_OPEN_NO_MUTEX;
    let cannot = |e: rusqlite::Error| {
        input_error(format!("{}: cannot read the registry: {e}", path.display()))
    };
    let readable = |conn: &Connection| {
        conn.query_row("PRAGMA user_version", [], |row| row.get::<_, i64>(0))
            .map(|_| ())
    };
    if !read_only_forced() {
        let conn =
            Connection::open_with_flags(database_uri(&path, "mode=ro"), flags).map_err(cannot)?;
        match readable(&conn) {
            Ok(()) => return Ok(conn),
            // Where the folder can be written, a shared read should work:
            // the error is the database's, not the folder's.
            Err(e) if writable(dir) => return Err(cannot(e)),
            Err(_) => {}
        }
    }
    let conn = Connection::open_with_flags(database_uri(&path, "mode=ro&immutable=1"), flags)
        .map_err(cannot)?;
    readable(&conn).map_err(cannot)?;
    Ok(conn)
}

/// The SQLite URI of the file `path` with `options`: every byte of the
/// path but unreserved ASCII percent-encoded, so no character of a folder
/// name (`%`, `?`, `#`, spaces, bytes that are not UTF-8) is read as URI
/// syntax.
fn database_uri(path: &Path, options: &str) -> String {
    #[cfg(unix)]
    let bytes = {
        use std::os::unix::ffi::OsStrExt;
        path.as_os_str().as_bytes().to_vec()
    };
    #[cfg(not(unix))]
    let bytes = path.to_string_lossy().into_owned().into_bytes();
    // An absolute path after an empty authority (`file:///…`), so that
    // one starting with `//` is not read as a host name.
    let mut uri = String::from(if path.is_absolute() {
        "file://"
    } else {
        "file:"
    });
    for byte in bytes {
        if byte.is_ascii_alphanumeric() || b"/._-~".contains(&byte) {
            uri.push(byte as char);
        } else {
            uri.push_str(&format!("%{byte:02X}"));
        }
    }
    uri.push('?');
    uri.push_str(options);
    uri
}

/// Whether a registry is checked for damage when opened.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Integrity {
    /// Before anything is written (runs): a damaged database is refused.
    CheckBeforeWriting,
    /// For reading and auditing (`registry verify` must open a damaged one).
    Unchecked,
}

/// Whether SQLite says the database file is not a sound database.
fn is_damage(error: &rusqlite::Error) -> bool {
    matches!(
        error.sqlite_error_code(),
        Some(rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase)
    )
}

/// The refusal to write into a damaged registry database.
fn damaged(dir: &Path, problem: &str) -> anyhow::Error {
    let path = dir.join(DATABASE_FILE);
    input_error(format!(
        "{}: the registry database is damaged ({}), so nothing is written to it; \
         `scanloc registry verify --registry {}` shows what is wrong; restore {DATABASE_FILE} \
         from a backup, or save what still reads with `sqlite3 {} .recover`",
        path.display(),
        problem.lines().next().unwrap_or(problem),
        dir.display(),
        path.display()
    ))
}

/// Refuses to start a new database in a registry whose database is gone or
/// empty while its blob store holds artefacts: that database was lost (a
/// truncation, a bad copy), and a new one would silently forget every run.
fn refuse_lost_database(dir: &Path) -> anyhow::Result<()> {
    let path = dir.join(DATABASE_FILE);
    let state = match std::fs::metadata(&path) {
        Ok(metadata) if metadata.len() > 0 => return Ok(()),
        Ok(_) => "is empty (0 bytes)",
        Err(_) => "is missing",
    };
    let blobs = dir.join("blobs");
    let holds_blobs = std::fs::read_dir(&blobs)
        .into_iter()
        .flatten()
        .flatten()
        .any(|prefix| {
            std::fs::read_dir(prefix.path()).is_ok_and(|mut files| files.next().is_some())
        });
    if !holds_blobs {
        return Ok(());
    }
    Err(input_error(format!(
        "{}: {DATABASE_FILE} {state} but {} holds stored artefacts: the record of the runs was \
         lost, and scanloc will not start a new one over it; restore {DATABASE_FILE} from a \
         backup, or move the folder aside to start a new registry",
        dir.display(),
        blobs.display()
    )))
}

pub(super) fn is_busy(error: &rusqlite::Error) -> bool {
    matches!(
        error,
        rusqlite::Error::SqliteFailure(e, _)
            if e.code == rusqlite::ErrorCode::DatabaseBusy || e.code == rusqlite::ErrorCode::DatabaseLocked
    )
}
