//! The source of a copy, read-only: a shard (input like any other file)
//! or one of this user's registries (exporting, seeding a sweep task).
//!
//! A shard's database is first copied into the copy's staging folder (with
//! its write-ahead log, if one is beside it) and read from there, so SQLite
//! never writes, locks or recovers anything in the shard's folder, and the
//! path is never text in an SQLite URI. A registry this user writes is read
//! in place (other processes may be writing it; SQLite's locks keep the
//! reads consistent). Either way, before any row is read, every durable
//! table must be a real table (not a view or a virtual table) with the
//! columns of this registry's table of the same name, and every row read
//! is checked against [`rules`](super::rules).

use std::path::{Path, PathBuf};
use std::time::Duration;

use rusqlite::types::{Value, ValueRef};
use rusqlite::{Connection, OpenFlags};

use super::rules::{self, DURABLE, Durable, TRANSIENT};
use super::staging::Staging;
use crate::error::input_error;
use crate::registry::{DATABASE_FILE, SCHEMA_VERSION};

/// An open source database.
pub(super) struct Source {
    conn: Connection,
    /// Its schema version, [`rules::OLDEST_SOURCE_SCHEMA`] to this
    /// scanloc's: columns added since are read as NULL.
    version: i64,
    /// The source folder, as messages name it.
    dir: PathBuf,
}

/// Rows of one durable table, in the destination's column order.
pub(super) struct TableRows {
    pub table: &'static Durable,
    pub columns: Vec<String>,
    pub rows: Vec<Vec<Value>>,
}

/// `path` made absolute, so that SQLite (built to accept `file:` URIs as
/// file names) never reads a relative path such as `file:x?…` as a URI.
fn absolute(path: &Path) -> PathBuf {
    std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf())
}

/// Opens the SQLite database `path` read-only, without URI processing;
/// messages name `shown`; returns it with its schema version. A file that
/// is not a registry, one of a schema version this scanloc does not read
/// or one that fails SQLite's quick check is bad input.
pub(super) fn open_database(path: &Path, shown: &Path) -> anyhow::Result<(Connection, i64)> {
    let conn = Connection::open_with_flags(
        absolute(path),
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|e| input_error(format!("{}: damaged registry: {e}", shown.display())))?;
    checked_source(conn, shown)
}

/// `conn`, a source database opened read-only, made query-only and checked,
/// with its schema version: the version is this scanloc's or an older one
/// it reads ([`rules::OLDEST_SOURCE_SCHEMA`]), and SQLite's quick check
/// passes.
fn checked_source(conn: Connection, shown: &Path) -> anyhow::Result<(Connection, i64)> {
    let damaged = |e: &dyn std::fmt::Display| {
        input_error(format!("{}: damaged registry: {e}", shown.display()))
    };
    conn.busy_timeout(Duration::from_secs(60))?;
    // Nothing in the file's schema runs with more than the reader's rights.
    conn.execute_batch("PRAGMA trusted_schema = OFF; PRAGMA query_only = ON;")
        .map_err(|e| damaged(&e))?;
    let version: i64 = conn
        .query_row("PRAGMA user_version", [], |row| row.get(0))
        .map_err(|e| damaged(&e))?;
    if !(rules::OLDEST_SOURCE_SCHEMA..=SCHEMA_VERSION).contains(&version) {
        return Err(input_error(format!(
            "{}: registry schema version {version}, this scanloc reads versions {} to {SCHEMA_VERSION}{}",
            shown.display(),
            rules::OLDEST_SOURCE_SCHEMA,
            if version < SCHEMA_VERSION {
                " (any scanloc registry command on it, e.g. `scanloc registry runs --registry DIR`, upgrades it)"
            } else {
                ""
            }
        )));
    }
    let check: String = conn
        .query_row("PRAGMA quick_check", [], |row| row.get(0))
        .map_err(|e| damaged(&e))?;
    if check != "ok" {
        return Err(damaged(&check));
    }
    Ok((conn, version))
}

impl Source {
    /// Opens the shard in folder `dir` through a private copy of its
    /// database in `staging`.
    pub(super) fn open_shard(dir: &Path, staging: &Staging) -> anyhow::Result<Self> {
        let database = dir.join(DATABASE_FILE);
        if std::fs::symlink_metadata(&database).is_err() {
            return Err(input_error(format!(
                "{}: no registry here (no {DATABASE_FILE})",
                dir.display()
            )));
        }
        let refuse = |file: &Path, problem: String| {
            input_error(format!("{}: damaged shard: {problem}", file.display()))
        };
        let copy = staging
            .copy_file(&database, DATABASE_FILE)
            .map_err(|p| refuse(&database, p))?;
        let wal = dir.join(format!("{DATABASE_FILE}-wal"));
        if std::fs::symlink_metadata(&wal).is_ok() {
            staging
                .copy_file(&wal, &format!("{DATABASE_FILE}-wal"))
                .map_err(|p| refuse(&wal, p))?;
        }
        let (conn, version) = open_database(&copy, &database)?;
        let source = Self {
            conn,
            version,
            dir: dir.to_path_buf(),
        };
        source.begin()?;
        Ok(source)
    }

    /// Opens the registry in folder `dir` (this user's) read-only in place.
    pub(super) fn open_registry(dir: &Path) -> anyhow::Result<Self> {
        let database = dir.join(DATABASE_FILE);
        if !database.is_file() {
            return Err(input_error(format!(
                "{}: no registry here (no {DATABASE_FILE})",
                dir.display()
            )));
        }
        // The registry's own read-only open: on a read-only mount it falls
        // back to an immutable read, so a registry that cannot be written
        // still exports.
        let conn = crate::registry::open_database_read_only(dir)?;
        let (conn, version) = checked_source(conn, &database)?;
        let source = Self {
            conn,
            version,
            dir: dir.to_path_buf(),
        };
        source.begin()?;
        Ok(source)
    }

    /// One read transaction for the whole copy: every table is read as of
    /// one moment, whatever other processes commit meanwhile.
    fn begin(&self) -> anyhow::Result<()> {
        self.conn
            .execute_batch("BEGIN")
            .map_err(|e| self.damaged(None, &e.to_string()))
    }

    /// The source folder.
    pub(super) fn dir(&self) -> &Path {
        &self.dir
    }

    /// The refusal of this source because of `problem`, in `table`.
    pub(super) fn damaged(&self, table: Option<&str>, problem: &str) -> anyhow::Error {
        let place = table.map(|t| format!(" table {t}:")).unwrap_or_default();
        input_error(format!(
            "{}: damaged shard:{place} {problem}",
            self.dir.display()
        ))
    }

    /// The refusal of row `label` of `table` because of `problem`.
    pub(super) fn refuse_row(&self, table: &str, label: &str, problem: &str) -> anyhow::Error {
        input_error(format!(
            "{}: damaged shard: table {table}, row {label}: {problem}",
            self.dir.display()
        ))
    }

    /// Checks that every durable table of the source is a real table with
    /// exactly the columns `expected` gives for it (the destination's), and
    /// that the source has no table a registry does not.
    pub(super) fn check_schema(&self, expected: &Connection) -> anyhow::Result<()> {
        let sql_err = |e: rusqlite::Error| self.damaged(None, &e.to_string());
        let mut tables = self
            .conn
            .prepare(
                "SELECT type, name, coalesce(sql, '') FROM sqlite_master
                 WHERE type IN ('table', 'view') AND name NOT LIKE 'sqlite\\_%' ESCAPE '\\'",
            )
            .map_err(sql_err)?;
        let entries: Vec<(String, String, String)> = tables
            .query_map([], |row| Ok((row.get(0)?, row.get(1)?, row.get(2)?)))
            .map_err(sql_err)?
            .collect::<Result<_, _>>()
            .map_err(sql_err)?;
        for (kind, name, sql) in &entries {
            let known = DURABLE.iter().any(|t| t.name.eq_ignore_ascii_case(name))
                || TRANSIENT.iter().any(|t| t.eq_ignore_ascii_case(name));
            if !known {
                return Err(self.damaged(Some(name), &format!("a {kind} no registry has")));
            }
            let is_table = kind == "table"
                && sql
                    .trim_start()
                    .get(..12)
                    .is_some_and(|start| start.eq_ignore_ascii_case("CREATE TABLE"));
            if !is_table {
                return Err(self.damaged(Some(name), "not a table (a view or a virtual table)"));
            }
        }
        for table in DURABLE {
            if !entries.iter().any(|(_, name, _)| name == table.name) {
                return Err(self.damaged(Some(table.name), "missing"));
            }
            // A source of an older schema lacks the columns added since.
            let ours: Vec<(String, i64)> = columns(expected, table.name)?
                .into_iter()
                .filter(|(name, _)| !rules::added_after(self.version, table.name, name))
                .collect();
            let theirs = columns(&self.conn, table.name)
                .map_err(|e| self.damaged(Some(table.name), &e.to_string()))?;
            let sorted = |list: &[(String, i64)]| {
                let mut names: Vec<String> = list.iter().map(|(n, _)| n.clone()).collect();
                names.sort();
                names
            };
            if theirs.iter().any(|(_, hidden)| *hidden != 0) || sorted(&theirs) != sorted(&ours) {
                return Err(self.damaged(
                    Some(table.name),
                    &format!(
                        "columns {:?}, a registry's are {:?}",
                        theirs.iter().map(|(n, _)| n).collect::<Vec<_>>(),
                        ours.iter().map(|(n, _)| n).collect::<Vec<_>>()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Every value of `column` of `table` as text (a planning query over
    /// key columns; a value that is not text is refused).
    pub(super) fn texts(&self, table: &str, column: &str) -> anyhow::Result<Vec<String>> {
        self.rows(table, &[column])?
            .into_iter()
            .map(|mut row| match row.pop() {
                Some(Value::Text(text)) => Ok(text),
                other => Err(self.damaged(
                    Some(table),
                    &format!(
                        "{column}: {} is not text",
                        rules::shown(&other.unwrap_or(Value::Null))
                    ),
                )),
            })
            .collect()
    }

    /// Every row of `table`, the values of `columns` (NULL for a column
    /// added after the source's schema version).
    pub(super) fn rows(&self, table: &str, columns: &[&str]) -> anyhow::Result<Vec<Vec<Value>>> {
        let list: Vec<String> = columns
            .iter()
            .map(|c| {
                if rules::added_after(self.version, table, c) {
                    "NULL".to_string()
                } else {
                    format!("\"{c}\"")
                }
            })
            .collect();
        let sql_err = |e: rusqlite::Error| self.damaged(Some(table), &e.to_string());
        let mut statement = self
            .conn
            .prepare(&format!("SELECT {} FROM \"{table}\"", list.join(", ")))
            .map_err(sql_err)?;
        let mut rows = statement.query([]).map_err(sql_err)?;
        let mut out = Vec::new();
        while let Some(row) = rows.next().map_err(sql_err)? {
            let mut values = Vec::with_capacity(columns.len());
            for (i, column) in columns.iter().enumerate() {
                values.push(match row.get_ref(i).map_err(sql_err)? {
                    // rusqlite's own conversion panics on text that is not
                    // UTF-8.
                    ValueRef::Text(bytes) => match std::str::from_utf8(bytes) {
                        Ok(text) => Value::Text(text.to_string()),
                        Err(e) => {
                            let problem = format!("{column}: text that is not UTF-8 ({e})");
                            return Err(self.damaged(Some(table), &problem));
                        }
                    },
                    other => Value::from(other),
                });
            }
            out.push(values);
        }
        Ok(out)
    }

    /// The rows of durable table `table` that `wanted` selects (by the
    /// table's key column), every one checked against the rules; `columns`
    /// are the destination's.
    pub(super) fn selected_rows(
        &self,
        table: &'static Durable,
        columns: Vec<String>,
        wanted: impl Fn(&str) -> bool,
    ) -> anyhow::Result<TableRows> {
        let key = match table.keyed {
            rules::KeyedBy::Blob => "sha256",
            rules::KeyedBy::Run(column) | rules::KeyedBy::Artefact(column) => column,
        };
        let at = columns
            .iter()
            .position(|c| c == key)
            .expect("a durable table has its key column");
        let names: Vec<&str> = columns.iter().map(String::as_str).collect();
        let mut rows = Vec::new();
        for values in self.rows(table.name, &names)? {
            let Value::Text(value) = &values[at] else {
                continue;
            };
            if !wanted(value) {
                continue;
            }
            if let Some(problem) = rules::row_problem(table, &columns, &values) {
                let label = rules::row_label(table, &columns, &values);
                return Err(self.refuse_row(table.name, &label, &problem));
            }
            rows.push(values);
        }
        Ok(TableRows {
            table,
            columns,
            rows,
        })
    }
}

/// The columns of `table` in database `conn` (`main`), with their
/// `hidden` flag (generated columns are hidden).
pub(super) fn columns(conn: &Connection, table: &str) -> rusqlite::Result<Vec<(String, i64)>> {
    conn.prepare(&format!("PRAGMA main.table_xinfo(\"{table}\")"))?
        .query_map([], |row| Ok((row.get(1)?, row.get(6)?)))?
        .collect()
}
