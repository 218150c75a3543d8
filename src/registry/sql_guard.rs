//! The fence around `scanloc registry sql`: a user's statement may read the
//! registry and nothing else.
//!
//! Four layers, each enough on its own for what it covers:
//! - the database is opened read-only and with `PRAGMA query_only`;
//! - an authorizer admits only reading (SELECT, reading columns, functions,
//!   recursive CTEs, and introspection PRAGMAs without a value), so ATTACH,
//!   transactions and every setting PRAGMA are refused when the statement
//!   is prepared;
//! - a prepared statement that SQLite says may write (`VACUUM INTO`, which
//!   writes a new file and passes no authorizer check) is refused before it
//!   runs;
//! - a progress handler stops a statement after [`SQL_TIME_LIMIT`], SQLite's
//!   own heap is capped at [`SQL_HEAP_LIMIT_BYTES`], and at most
//!   [`SQL_MAX_ROWS`] rows, [`SQL_MAX_CELL_BYTES`] per cell and
//!   [`SQL_MAX_RESULT_BYTES`] in all are collected, so a runaway recursive
//!   CTE or a huge computed string ends with a clear error instead of
//!   running or growing forever.

use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rusqlite::hooks::{AuthAction, AuthContext, Authorization};
use rusqlite::types::ValueRef;
use serde_json::{Value, json};

use super::DATABASE_FILE;
use super::table::Table;
use crate::error::input_error;

/// Longest a `registry sql` statement may run.
pub(crate) const SQL_TIME_LIMIT: Duration = Duration::from_secs(10);
/// Most rows a `registry sql` statement may return.
pub(crate) const SQL_MAX_ROWS: usize = 1_000_000;
/// Most bytes of text one cell of a `registry sql` result may hold (a
/// blob is shown by its size, whatever it holds).
pub(crate) const SQL_MAX_CELL_BYTES: usize = 1 << 20;
/// Most bytes of text a whole `registry sql` result may hold, counted
/// cell by cell as the rows are collected (numbers count 8).
pub(crate) const SQL_MAX_RESULT_BYTES: usize = 64 << 20;
/// Most memory SQLite may hold while running a `registry sql` statement.
pub(crate) const SQL_HEAP_LIMIT_BYTES: i64 = 512 << 20;

/// PRAGMAs that only describe the database, with or without an argument
/// (a table or index name).
const INTROSPECTION_PRAGMAS: &[&str] = &[
    "table_info",
    "table_xinfo",
    "table_list",
    "index_list",
    "index_info",
    "index_xinfo",
    "foreign_key_list",
    "foreign_key_check",
    "integrity_check",
    "quick_check",
    "database_list",
    "collation_list",
    "function_list",
    "module_list",
    "pragma_list",
    "compile_options",
];

/// PRAGMAs that read a setting when given no value (and change it when
/// given one, which is refused).
const SETTING_PRAGMAS: &[&str] = &[
    "user_version",
    "schema_version",
    "application_id",
    "page_count",
    "page_size",
    "freelist_count",
    "encoding",
    "journal_mode",
    "auto_vacuum",
    "foreign_keys",
];

/// SQLite's value as JSON (blobs as their size: they are not text).
pub(crate) fn json_value(value: ValueRef<'_>) -> Value {
    match value {
        ValueRef::Null => Value::Null,
        ValueRef::Integer(i) => json!(i),
        ValueRef::Real(f) => json!(f),
        ValueRef::Text(t) => Value::String(String::from_utf8_lossy(t).into_owned()),
        ValueRef::Blob(b) => Value::String(format!("<{} bytes>", b.len())),
    }
}

/// The bytes a cell of a result takes once collected: its text, a number's
/// 8, a blob's description (it is shown by its size).
fn cell_bytes(value: ValueRef<'_>) -> usize {
    match value {
        ValueRef::Text(text) => text.len(),
        ValueRef::Null | ValueRef::Integer(_) | ValueRef::Real(_) | ValueRef::Blob(_) => 8,
    }
}

/// Whether the authorizer admits `action`; `None` if so, else what it is,
/// for the error message.
fn refusal(action: &AuthAction<'_>) -> Option<String> {
    match action {
        AuthAction::Select | AuthAction::Read { .. } | AuthAction::Recursive => None,
        AuthAction::Function { .. } => None,
        AuthAction::Pragma {
            pragma_name,
            pragma_value,
        } => {
            let name = pragma_name.to_ascii_lowercase();
            if INTROSPECTION_PRAGMAS.contains(&name.as_str())
                || (pragma_value.is_none() && SETTING_PRAGMAS.contains(&name.as_str()))
            {
                None
            } else if pragma_value.is_some() {
                Some(format!("PRAGMA {pragma_name} = … (changes a setting)"))
            } else {
                Some(format!("PRAGMA {pragma_name}"))
            }
        }
        AuthAction::Attach { .. } => Some("ATTACH (opens another database file)".into()),
        AuthAction::Detach { .. } => Some("DETACH".into()),
        AuthAction::Transaction { .. } | AuthAction::Savepoint { .. } => {
            Some("a transaction statement".into())
        }
        other => Some(format!("{other:?}")),
    }
}

/// Runs one user-supplied SQL statement on a read-only connection to the
/// registry in `dir`. Bad SQL, any attempt to write or to reach beyond the
/// registry, and a statement over the time, memory or row limits are bad
/// input (exit code 2) with a one-line message.
pub(crate) fn read_only_sql(dir: &Path, sql: &str) -> anyhow::Result<Table> {
    let path = dir.join(DATABASE_FILE);
    if !path.is_file() {
        return Err(input_error(format!(
            "{}: no registry here (no {DATABASE_FILE})",
            dir.display()
        )));
    }
    // Read-only, and on a registry that cannot be written as well.
    let conn = super::open_database_read_only(dir)?;
    conn.busy_timeout(Duration::from_secs(30))?;
    conn.execute_batch(&format!(
        "PRAGMA query_only = ON; PRAGMA hard_heap_limit = {SQL_HEAP_LIMIT_BYTES};"
    ))?;
    let refused: Arc<Mutex<Option<String>>> = Arc::default();
    let seen = Arc::clone(&refused);
    conn.authorizer(Some(move |context: AuthContext<'_>| {
        match refusal(&context.action) {
            None => Authorization::Allow,
            Some(what) => {
                let mut seen = seen.lock().unwrap_or_else(|e| e.into_inner());
                seen.get_or_insert(what);
                Authorization::Deny
            }
        }
    }));
    let read_only = |what: &str| {
        input_error(format!(
            "sql: refused: {what}; `registry sql` only reads the registry"
        ))
    };
    let mut statement = conn.prepare(sql).map_err(|e| {
        match refused.lock().unwrap_or_else(|e| e.into_inner()).take() {
            Some(what) => read_only(&what),
            None => input_error(format!("sql: {e}")),
        }
    })?;
    if !statement.readonly() {
        return Err(read_only("a statement that writes"));
    }
    let deadline = Instant::now() + SQL_TIME_LIMIT;
    conn.progress_handler(10_000, Some(move || Instant::now() > deadline));
    let columns: Vec<String> = statement
        .column_names()
        .iter()
        .map(|c| c.to_string())
        .collect();
    let mut rows = Vec::new();
    let limited = |e: rusqlite::Error| {
        if Instant::now() > deadline {
            input_error(format!(
                "sql: stopped after {} s, the limit for one statement (a recursive query without an end?)",
                SQL_TIME_LIMIT.as_secs()
            ))
        } else if e.sqlite_error_code() == Some(rusqlite::ErrorCode::OutOfMemory) {
            input_error(format!(
                "sql: stopped at the memory limit of {} MiB for one statement",
                SQL_HEAP_LIMIT_BYTES >> 20
            ))
        } else {
            input_error(format!("sql: {e}"))
        }
    };
    let mut cursor = statement.query([]).map_err(limited)?;
    let mut result_bytes = 0usize;
    while let Some(row) = cursor.next().map_err(limited)? {
        if rows.len() == SQL_MAX_ROWS {
            return Err(input_error(format!(
                "sql: more than {SQL_MAX_ROWS} rows; narrow the query or add a LIMIT"
            )));
        }
        let mut values = Vec::with_capacity(columns.len());
        for (index, column) in columns.iter().enumerate() {
            let value = row.get_ref(index)?;
            // Measured before it is copied out of SQLite.
            let bytes = cell_bytes(value);
            if bytes > SQL_MAX_CELL_BYTES {
                return Err(input_error(format!(
                    "sql: row {} column {}: {bytes} bytes, more than the limit of {} MiB per cell; select a substr() of it",
                    rows.len() + 1,
                    crate::limits::display_cell(column),
                    SQL_MAX_CELL_BYTES >> 20
                )));
            }
            result_bytes += bytes;
            if result_bytes > SQL_MAX_RESULT_BYTES {
                return Err(input_error(format!(
                    "sql: the result passes the limit of {} MiB at row {}; narrow the query or add a LIMIT",
                    SQL_MAX_RESULT_BYTES >> 20,
                    rows.len() + 1
                )));
            }
            values.push(json_value(value));
        }
        rows.push(values);
    }
    Ok(Table { columns, rows })
}
