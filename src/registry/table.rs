//! Rows of a registry query for people (aligned text columns) and programs
//! (a JSON array of objects).

use serde::Serialize;
use serde_json::Value;

/// Rows of a query: column names and JSON values.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Table {
    pub columns: Vec<String>,
    pub rows: Vec<Vec<Value>>,
}

impl Table {
    /// The rows as a JSON array of objects keyed by column.
    pub fn to_json(&self) -> Value {
        Value::Array(
            self.rows
                .iter()
                .map(|row| {
                    Value::Object(
                        self.columns
                            .iter()
                            .cloned()
                            .zip(row.iter().cloned())
                            .collect(),
                    )
                })
                .collect(),
        )
    }

    /// The rows as aligned text columns with a header, each cell (and
    /// column name) cut to [`MAX_CELL_CHARS`](crate::limits::MAX_CELL_CHARS)
    /// characters so that no recorded value can widen a column without
    /// bound.
    pub fn render(&self) -> String {
        let shown = |text: &str| crate::limits::display_cell(text).into_owned();
        let columns: Vec<String> = self.columns.iter().map(|c| shown(c)).collect();
        let cells: Vec<Vec<String>> = self
            .rows
            .iter()
            .map(|row| row.iter().map(|value| shown(&cell_text(value))).collect())
            .collect();
        let mut widths: Vec<usize> = columns.iter().map(|c| c.chars().count()).collect();
        for row in &cells {
            for (width, cell) in widths.iter_mut().zip(row) {
                *width = (*width).max(cell.chars().count());
            }
        }
        let line = |values: &[String]| -> String {
            values
                .iter()
                .zip(&widths)
                .map(|(v, w)| format!("{v:<w$}"))
                .collect::<Vec<_>>()
                .join("  ")
                .trim_end()
                .to_string()
        };
        let mut out = line(&columns);
        out.push('\n');
        for row in &cells {
            out.push_str(&line(row));
            out.push('\n');
        }
        out
    }
}

/// A cell as text: strings bare, `-` for NULL.
pub(crate) fn cell_text(value: &Value) -> String {
    match value {
        Value::Null => "-".to_string(),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}
