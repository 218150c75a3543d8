//! CSV tables with a header: ground truth and localisations.
//!
//! - Truth: `frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion`, one row
//!   per emitter per frame (TrackPy pixel coordinates; `z_mean` in µm;
//!   `diffusion` in µm²/s).
//! - Localisations: at least `frame,x,y,score`; detectors add their own
//!   columns (Crocker–Grier writes TrackPy's `mass,size,ecc,signal,raw_mass,ep`).
//!
//! Floats are written in Rust's shortest round-trip form, so reading gives
//! back the same bits. Each table has one writer and one reader over any
//! `Write`/`Read` (the registry stores the same bytes as blobs); the file
//! functions call them.

use std::io::{Read, Write};
use std::path::Path;

use serde::Deserialize;

use super::{PendingFile, open_input, write_atomically};
use crate::error::input_error;
use crate::types::{Prediction, TruthRow};

/// Column names of a truth file, in order.
pub const TRUTH_COLUMNS: [&str; 9] = [
    "frame",
    "x",
    "y",
    "x_start",
    "y_start",
    "x_end",
    "y_end",
    "z_mean",
    "diffusion",
];

/// Writes truth rows to `path` atomically.
pub fn write_truth(path: &Path, truth: &[TruthRow]) -> anyhow::Result<()> {
    write_atomically(path, |writer| write_truth_to(writer, truth))
}

/// Fills a pending output with truth rows.
pub fn fill_truth(pending: &mut PendingFile, truth: &[TruthRow]) -> anyhow::Result<()> {
    pending.fill(|writer| write_truth_to(writer, truth))
}

/// Writes truth rows as CSV to any writer.
pub fn write_truth_to<W: Write>(writer: W, truth: &[TruthRow]) -> anyhow::Result<()> {
    let mut csv = csv::Writer::from_writer(writer);
    for row in truth {
        csv.serialize(row)?;
    }
    if truth.is_empty() {
        csv.write_record(TRUTH_COLUMNS)?;
    }
    csv.flush()?;
    Ok(())
}

/// Reads a truth file; every column of [`TRUTH_COLUMNS`] but `frame`, `x`
/// and `y` may be absent (then NaN), so truth made by other tools works.
pub fn read_truth(path: &Path) -> anyhow::Result<Vec<TruthRow>> {
    read_truth_from(open_input(path)?, &path.display().to_string())
}

/// Reads truth CSV from any reader, as [`read_truth`]; `source` names it in
/// errors.
pub fn read_truth_from<R: Read>(reader: R, source: &str) -> anyhow::Result<Vec<TruthRow>> {
    #[derive(Deserialize)]
    struct Row {
        frame: usize,
        x: f64,
        y: f64,
        #[serde(default = "nan")]
        x_start: f64,
        #[serde(default = "nan")]
        y_start: f64,
        #[serde(default = "nan")]
        x_end: f64,
        #[serde(default = "nan")]
        y_end: f64,
        #[serde(default = "nan")]
        z_mean: f64,
        #[serde(default = "nan")]
        diffusion: f64,
    }
    let rows: Vec<Row> = read_rows(reader, source, &["frame", "x", "y"])?;
    let truth: Vec<TruthRow> = rows
        .into_iter()
        .map(|r| TruthRow {
            frame: r.frame,
            x: r.x,
            y: r.y,
            x_start: r.x_start,
            y_start: r.y_start,
            x_end: r.x_end,
            y_end: r.y_end,
            z_mean: r.z_mean,
            diffusion: r.diffusion,
        })
        .collect();
    for (line, row) in truth.iter().enumerate() {
        if !row.x.is_finite() || !row.y.is_finite() {
            return Err(input_error(format!(
                "{source}: row {}: x and y must be finite numbers",
                line + 1
            )));
        }
    }
    Ok(truth)
}

/// Column names of a predictions table written by scanloc, in order.
pub const PREDICTION_COLUMNS: [&str; 4] = ["frame", "x", "y", "score"];

/// Reads the `frame,x,y,score` columns of a localisation file (other
/// columns are ignored). Non-finite coordinates or scores are refused.
pub fn read_predictions(path: &Path) -> anyhow::Result<Vec<Prediction>> {
    read_predictions_from(open_input(path)?, &path.display().to_string())
}

/// Reads a localisation table from any reader, as [`read_predictions`];
/// `source` names it in errors.
pub fn read_predictions_from<R: Read>(reader: R, source: &str) -> anyhow::Result<Vec<Prediction>> {
    #[derive(Deserialize)]
    struct Row {
        frame: usize,
        x: f64,
        y: f64,
        score: f64,
    }
    let rows: Vec<Row> = read_rows(reader, source, &PREDICTION_COLUMNS)?;
    rows.into_iter()
        .enumerate()
        .map(|(line, r)| {
            if !(r.x.is_finite() && r.y.is_finite() && r.score.is_finite()) {
                return Err(input_error(format!(
                    "{source}: row {}: x, y and score must be finite numbers",
                    line + 1
                )));
            }
            Ok(Prediction {
                frame: r.frame,
                x: r.x,
                y: r.y,
                score: r.score,
            })
        })
        .collect()
}

/// Writes predictions as `frame,x,y,score` to `path` atomically.
pub fn write_predictions(path: &Path, predictions: &[Prediction]) -> anyhow::Result<()> {
    write_atomically(path, |writer| write_predictions_to(writer, predictions))
}

/// Writes predictions as `frame,x,y,score` CSV (header first, `\n` line
/// ends) to any writer. The registry's `predictions.csv` blobs are these
/// bytes: change them only with the blob format's version.
pub fn write_predictions_to<W: Write>(writer: W, predictions: &[Prediction]) -> anyhow::Result<()> {
    write_localisations_to(writer, [], predictions.iter().map(|&p| (p, [])))
}

/// Writes a detector's localisations to `path` atomically, with its own
/// columns: `frame,x,y`, then `extra_columns`, then `score` (Crocker–Grier
/// passes TrackPy's `mass,size,ecc,signal,raw_mass,ep`). Each row is a
/// prediction and its values of the extra columns, in order.
pub fn write_localisations<const N: usize>(
    path: &Path,
    extra_columns: [&str; N],
    rows: impl IntoIterator<Item = (Prediction, [f64; N])>,
) -> anyhow::Result<()> {
    write_atomically(path, |writer| {
        write_localisations_to(writer, extra_columns, rows)
    })
}

/// The one writer of localisation tables, behind [`write_predictions_to`]
/// and [`write_localisations`].
fn write_localisations_to<W: Write, const N: usize>(
    writer: W,
    extra_columns: [&str; N],
    rows: impl IntoIterator<Item = (Prediction, [f64; N])>,
) -> anyhow::Result<()> {
    let mut csv = csv::Writer::from_writer(writer);
    let header = ["frame", "x", "y"]
        .into_iter()
        .chain(extra_columns)
        .chain(["score"]);
    csv.write_record(header)?;
    for (p, extra) in rows {
        let fields = [p.frame.to_string(), p.x.to_string(), p.y.to_string()]
            .into_iter()
            .chain(extra.iter().map(f64::to_string))
            .chain([p.score.to_string()]);
        csv.write_record(fields)?;
    }
    csv.flush()?;
    Ok(())
}

fn nan() -> f64 {
    f64::NAN
}

/// Reads every row of CSV from `reader` into `T`, first checking that the
/// header has the `required` columns; errors name `source`, the row and the
/// column.
fn read_rows<T: for<'de> Deserialize<'de>>(
    reader: impl Read,
    source: &str,
    required: &[&str],
) -> anyhow::Result<Vec<T>> {
    let mut reader = csv::Reader::from_reader(reader);
    let headers = reader
        .headers()
        .map_err(|e| input_error(format!("{source}: cannot read the CSV header: {e}")))?
        .clone();
    let missing: Vec<&str> = required
        .iter()
        .copied()
        .filter(|column| !headers.iter().any(|h| h.trim() == *column))
        .collect();
    if !missing.is_empty() {
        return Err(input_error(format!(
            "{source}: missing column(s) {} (header: {})",
            missing.join(", "),
            headers.iter().collect::<Vec<_>>().join(",")
        )));
    }
    reader
        .deserialize()
        .enumerate()
        .map(|(index, row)| {
            row.map_err(|e| input_error(format!("{source}: row {}: {e}", index + 1)))
        })
        .collect()
}
