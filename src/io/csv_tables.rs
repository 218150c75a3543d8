//! CSV tables with a header: ground truth and localisations.
//!
//! - Truth: `frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion`, one row
//!   per emitter per frame (TrackPy pixel coordinates; `z_mean` in µm;
//!   `diffusion` in µm²/s).
//! - Localisations: at least `frame,x,y,score`; detectors add their own
//!   columns (Crocker–Grier writes TrackPy's `mass,size,ecc,signal,raw_mass,ep`),
//!   and predictions that carry an uncertainty add `sigma_x,sigma_y` (pixels)
//!   before `score`. Tables without those columns read as predictions
//!   without an uncertainty. A detector giving a ranked list of guesses
//!   per frame adds `candidate` (the rank, 1 = the frame's best) after
//!   `score`; tables without it (every table with one guess per frame, and
//!   every one written before it existed) keep their bytes and read as
//!   unranked predictions.
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
use crate::types::{LocalisationSigma, Prediction, TruthRow};

/// Column names of a truth file, in order.
pub(crate) const TRUTH_COLUMNS: [&str; 9] = [
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
pub(crate) fn fill_truth(pending: &mut PendingFile, truth: &[TruthRow]) -> anyhow::Result<()> {
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
        #[serde(deserialize_with = "frame_number")]
        frame: usize,
        x: f64,
        y: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
        x_start: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
        y_start: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
        x_end: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
        y_end: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
        z_mean: f64,
        #[serde(default = "nan", deserialize_with = "optional_number")]
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

/// The optional columns of a localisation's uncertainty
/// ([`LocalisationSigma`]), written before `score` when any prediction of
/// the table has one.
pub(crate) const SIGMA_COLUMNS: [&str; 2] = ["sigma_x", "sigma_y"];

/// The optional column of a guess's rank in a ranked list
/// ([`Prediction::candidate`]), written after `score` when any prediction
/// of the table has one.
pub(crate) const CANDIDATE_COLUMN: &str = "candidate";

/// Reads the `frame,x,y,score` columns of a localisation file, and
/// `sigma_x,sigma_y` and `candidate` when present (other columns are ignored). Non-finite
/// coordinates or scores are refused.
pub fn read_predictions(path: &Path) -> anyhow::Result<Vec<Prediction>> {
    read_predictions_from(open_input(path)?, &path.display().to_string())
}

/// Reads a localisation table from any reader, as [`read_predictions`];
/// `source` names it in errors.
pub fn read_predictions_from<R: Read>(reader: R, source: &str) -> anyhow::Result<Vec<Prediction>> {
    read_predictions_scored_by_from(reader, source, "score")
}

/// Reads a localisation file whose score is column `score_column` (e.g.
/// `mass` in TrackPy's own output): columns `frame`, `x`, `y` and
/// `score_column`, and the uncertainty `sigma_x,sigma_y` if the table has
/// both (a row with both cells empty has none; otherwise each must be a
/// finite number > 0), and the rank `candidate` if the table has it (an
/// empty cell: unranked; otherwise a whole number ≥ 1); others ignored.
/// Frame numbers may be written as whole
/// floats (`3.0`, as pandas writes them); non-finite coordinates or scores
/// are refused, naming the row.
pub(crate) fn read_predictions_scored_by(
    path: &Path,
    score_column: &str,
) -> anyhow::Result<Vec<Prediction>> {
    read_predictions_scored_by_from(open_input(path)?, &path.display().to_string(), score_column)
}

/// [`read_predictions_scored_by`] from any reader; `name` names it in
/// errors.
pub(crate) fn read_predictions_scored_by_from<R: Read>(
    reader: R,
    name: &str,
    score_column: &str,
) -> anyhow::Result<Vec<Prediction>> {
    let required = ["frame", "x", "y", score_column];
    let (mut reader, headers) = open_table(reader, name, &required)?;
    let column = |wanted: &str| headers.iter().position(|h| h.trim() == wanted);
    let [frame_at, x_at, y_at, score_at] = required.map(|c| column(c).unwrap_or_default());
    let sigma_at = match SIGMA_COLUMNS.map(column) {
        [Some(x), Some(y)] => Some((x, y)),
        [None, None] => None,
        [Some(_), None] => crate::bail_input!("{name}: column sigma_x needs a sigma_y column"),
        [None, Some(_)] => crate::bail_input!("{name}: column sigma_y needs a sigma_x column"),
    };
    let candidate_at = column(CANDIDATE_COLUMN);
    let mut predictions = Vec::new();
    for (index, record) in reader.records().enumerate() {
        let row = index + 1;
        let record = record.map_err(|e| input_error(format!("{name}: row {row}: {e}")))?;
        let cell = |at: usize| record.get(at).unwrap_or("").trim();
        let number = |at: usize, column: &str| -> anyhow::Result<f64> {
            let text = cell(at);
            match text.parse::<f64>() {
                Ok(value) if value.is_finite() => Ok(value),
                _ => Err(input_error(format!(
                    "{name}: row {row}: {column}: expected a finite number, got {}",
                    quoted(text)
                ))),
            }
        };
        let frame = parse_frame_number(cell(frame_at))
            .map_err(|e| input_error(format!("{name}: row {row}: frame: {e}")))?;
        let sigma = match sigma_at {
            Some((sx_at, sy_at)) if !(cell(sx_at).is_empty() && cell(sy_at).is_empty()) => {
                let positive = |at: usize, column: &str| -> anyhow::Result<f64> {
                    match number(at, column)? {
                        value if value > 0.0 => Ok(value),
                        value => Err(input_error(format!(
                            "{name}: row {row}: {column}: expected a number > 0, got {value}"
                        ))),
                    }
                };
                Some(LocalisationSigma {
                    x: positive(sx_at, "sigma_x")?,
                    y: positive(sy_at, "sigma_y")?,
                })
            }
            _ => None,
        };
        let candidate = match candidate_at.map(cell) {
            None | Some("") => None,
            Some(text) => match text.parse::<u32>() {
                Ok(rank) if rank >= 1 => Some(rank),
                _ => crate::bail_input!(
                    "{name}: row {row}: candidate: expected a whole number ≥ 1, got {}",
                    quoted(text)
                ),
            },
        };
        predictions.push(Prediction {
            frame,
            x: number(x_at, "x")?,
            y: number(y_at, "y")?,
            score: number(score_at, score_column)?,
            sigma,
            candidate,
        });
    }
    Ok(predictions)
}

/// A frame number as written by scanloc (`3`) or pandas (`3.0`): a whole
/// number from 0 to below [`MAX_FRAMES`](crate::limits::MAX_FRAMES), the
/// limit every frame count has.
pub(crate) fn parse_frame_number(text: &str) -> Result<usize, String> {
    let text = text.trim();
    let value = match text.parse::<u64>() {
        Ok(value) => value,
        Err(_) => match text.parse::<f64>() {
            Ok(value) if value.is_finite() && value >= 0.0 && value.fract() == 0.0 => {
                // Saturates for huge values, which the bound below refuses.
                value as u64
            }
            _ => return Err(format!("expected a whole number ≥ 0, got {}", quoted(text))),
        },
    };
    let limit = crate::limits::MAX_FRAMES;
    if value >= limit as u64 {
        return Err(format!("{value} is beyond the limit of {limit} frames"));
    }
    Ok(value as usize)
}

/// serde adapter for [`parse_frame_number`].
fn frame_number<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<usize, D::Error> {
    let text = String::deserialize(deserializer)?;
    parse_frame_number(&text).map_err(serde::de::Error::custom)
}

/// serde adapter for an optional number column: an empty cell (as pandas
/// writes a missing value) is NaN, like an absent column.
fn optional_number<'de, D: serde::Deserializer<'de>>(deserializer: D) -> Result<f64, D::Error> {
    let text = String::deserialize(deserializer)?;
    let text = text.trim();
    if text.is_empty() {
        return Ok(f64::NAN);
    }
    text.parse::<f64>()
        .map_err(|_| serde::de::Error::custom(format!("expected a number, got {}", quoted(text))))
}

/// Writes a table of text cells to `path` as CSV, atomically: `header`,
/// then each of `rows` (as many cells as the header has). For tables whose
/// columns the caller decides (a precision–recall curve, a bench's sweep);
/// the fixed formats have writers of their own above and below.
pub(crate) fn write_table<H: AsRef<str>>(
    path: &Path,
    header: &[H],
    rows: impl IntoIterator<Item = Vec<String>>,
) -> anyhow::Result<()> {
    write_atomically(path, |writer| {
        let mut csv = csv::Writer::from_writer(writer);
        csv.write_record(header.iter().map(AsRef::as_ref))?;
        for row in rows {
            csv.write_record(&row)?;
        }
        csv.flush()?;
        Ok(())
    })
}

/// Writes predictions as `frame,x,y,score` (with `sigma_x,sigma_y` before
/// `score` if any has an uncertainty) to `path` atomically.
pub fn write_predictions(path: &Path, predictions: &[Prediction]) -> anyhow::Result<()> {
    write_atomically(path, |writer| write_predictions_to(writer, predictions))
}

/// Writes predictions as `frame,x,y,score` CSV (header first, `\n` line
/// ends) to any writer; if any prediction has an uncertainty, the columns
/// are `frame,x,y,sigma_x,sigma_y,score` (empty cells for predictions
/// without one), and `candidate` after `score` if any prediction is ranked
/// (empty cells for unranked ones). The registry's `predictions.csv` blobs are these bytes:
/// change them only with the blob format's version.
pub(crate) fn write_predictions_to<W: Write>(
    writer: W,
    predictions: &[Prediction],
) -> anyhow::Result<()> {
    write_localisations_to(writer, [], predictions.iter().map(|&p| (p, [])))
}

/// Writes a detector's localisations to `path` atomically, with its own
/// columns: `frame,x,y`, then `extra_columns`, then `sigma_x,sigma_y` if
/// any prediction has an uncertainty, then `score`, then `candidate` if
/// any prediction is ranked (Crocker–Grier passes
/// TrackPy's `mass,size,ecc,signal,raw_mass,ep`). Each row is a prediction
/// and its values of the extra columns, in order.
pub(crate) fn write_localisations<const N: usize>(
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
    let rows: Vec<(Prediction, [f64; N])> = rows.into_iter().collect();
    // The columns only when there is something to put in them, so tables
    // of detectors without an uncertainty keep their bytes.
    let with_sigma = rows.iter().any(|(p, _)| p.sigma.is_some());
    let sigma_columns: &[&str] = if with_sigma { &SIGMA_COLUMNS } else { &[] };
    // Likewise the rank: tables of one guess per frame keep their bytes.
    let ranked = rows.iter().any(|(p, _)| p.candidate.is_some());
    let candidate_columns: &[&str] = if ranked { &[CANDIDATE_COLUMN] } else { &[] };
    let mut csv = csv::Writer::from_writer(writer);
    let header = ["frame", "x", "y"]
        .into_iter()
        .chain(extra_columns)
        .chain(sigma_columns.iter().copied())
        .chain(["score"])
        .chain(candidate_columns.iter().copied());
    csv.write_record(header)?;
    for (p, extra) in rows {
        let sigma_fields = match (with_sigma, p.sigma) {
            (false, _) => Vec::new(),
            (true, Some(sigma)) => vec![sigma.x.to_string(), sigma.y.to_string()],
            (true, None) => vec![String::new(), String::new()],
        };
        let fields = [p.frame.to_string(), p.x.to_string(), p.y.to_string()]
            .into_iter()
            .chain(extra.iter().map(f64::to_string))
            .chain(sigma_fields)
            .chain([p.score.to_string()])
            .chain(ranked.then(|| p.candidate.map_or(String::new(), |r| r.to_string())));
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
    let (mut reader, _) = open_table(reader, source, required)?;
    reader
        .deserialize()
        .enumerate()
        .map(|(index, row)| {
            row.map_err(|e| input_error(format!("{source}: row {}: {e}", index + 1)))
        })
        .collect()
}

/// Starts reading CSV from `reader`: its header, checked to have every
/// `required` column (an error names `source` and the missing columns) and
/// no column named twice (which of the two a reader took would be a guess;
/// unnamed columns, as pandas writes an index, are left alone), with each
/// record bounded by [`BoundedRecords`].
pub(crate) fn open_table<R: Read>(
    reader: R,
    source: &str,
    required: &[&str],
) -> anyhow::Result<(csv::Reader<BoundedRecords<R>>, csv::StringRecord)> {
    let mut reader = csv::Reader::from_reader(BoundedRecords::new(reader));
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
    let named: Vec<&str> = headers.iter().map(str::trim).collect();
    if let Some((later, name)) = named
        .iter()
        .enumerate()
        .find(|(at, name)| !name.is_empty() && named[..*at].contains(name))
    {
        return Err(input_error(format!(
            "{source}: column {} appears twice in the header (columns {} and {})",
            quoted(name),
            named.iter().position(|n| n == name).unwrap_or(0) + 1,
            later + 1
        )));
    }
    Ok((reader, headers))
}

/// The longest a cell is quoted in an error, in characters.
const QUOTED_CELL_CHARS: usize = 40;

/// A cell's text as an error quotes it: in quotes, cut to its first
/// [`QUOTED_CELL_CHARS`] characters and marked `…` where longer, so that a
/// runaway cell (a row may hold a MiB) keeps the error one short line.
pub(crate) fn quoted(text: &str) -> String {
    match text.char_indices().nth(QUOTED_CELL_CHARS) {
        Some((cut, _)) => format!("{:?}…", &text[..cut]),
        None => format!("{text:?}"),
    }
}

/// Where a [`BoundedRecords`] is within the CSV it reads, as far as
/// record boundaries go (the `csv` crate's defaults: `,` between fields,
/// `"` quotes a field that starts with it, `""` is a quote inside one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum CsvPosition {
    FieldStart,
    Unquoted,
    Quoted,
    /// A `"` inside a quoted field: its end, or the first of `""`.
    QuoteInQuoted,
}

/// A reader that refuses a CSV record (a row, which a quoted field may
/// spread over several lines) longer than
/// [`MAX_CSV_RECORD_BYTES`](crate::limits::MAX_CSV_RECORD_BYTES): the `csv`
/// crate holds a whole record in memory, so a file of one endless line
/// would otherwise be read whole before any check. The error names the
/// line at which the record passed the bound.
pub(crate) struct BoundedRecords<R> {
    inner: R,
    position: CsvPosition,
    record_bytes: usize,
    line: u64,
}

impl<R> BoundedRecords<R> {
    fn new(inner: R) -> Self {
        Self {
            inner,
            position: CsvPosition::FieldStart,
            record_bytes: 0,
            line: 1,
        }
    }

    /// Follows `bytes` through the record structure; an error if a record
    /// grows past the bound.
    fn follow(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        use CsvPosition::*;
        let limit = crate::limits::MAX_CSV_RECORD_BYTES;
        for &byte in bytes {
            self.record_bytes += 1;
            let ends_record = byte == b'\n' && self.position != Quoted;
            if byte == b'\n' {
                self.line += 1;
            }
            self.position = match (self.position, byte) {
                (_, b'\n') if ends_record => FieldStart,
                (FieldStart, b'"') | (QuoteInQuoted, b'"') => Quoted,
                (Quoted, b'"') => QuoteInQuoted,
                (Quoted, _) => Quoted,
                (_, b',') => FieldStart,
                _ => Unquoted,
            };
            if ends_record {
                self.record_bytes = 0;
            } else if self.record_bytes > limit {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!(
                        "line {}: a row longer than {} MiB (the limit of one row; is this a CSV table?)",
                        self.line,
                        limit >> 20
                    ),
                ));
            }
        }
        Ok(())
    }
}

impl<R: Read> Read for BoundedRecords<R> {
    fn read(&mut self, buffer: &mut [u8]) -> std::io::Result<usize> {
        let read = self.inner.read(buffer)?;
        self.follow(&buffer[..read])?;
        Ok(read)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(predictions: &[Prediction]) -> String {
        let mut bytes = Vec::new();
        write_predictions_to(&mut bytes, predictions).unwrap();
        String::from_utf8(bytes).unwrap()
    }

    #[test]
    fn uncertainties_round_trip_bit_for_bit_in_their_own_columns() {
        let predictions = [
            Prediction {
                sigma: Some(LocalisationSigma {
                    x: 0.1 + 0.2,
                    y: 1e-7,
                }),
                ..Prediction::new(0, 1.5, -1.0 / 3.0, 0.25)
            },
            // A row without an uncertainty in a table that has them.
            Prediction::new(2, 3.0, 4.0, 0.5),
        ];
        let text = write(&predictions);
        assert_eq!(
            text,
            "frame,x,y,sigma_x,sigma_y,score\n\
             0,1.5,-0.3333333333333333,0.30000000000000004,0.0000001,0.25\n\
             2,3,4,,,0.5\n"
        );
        let back = read_predictions_from(text.as_bytes(), "t.csv").unwrap();
        assert_eq!(back, predictions);
        let sigma = back[0].sigma.unwrap();
        assert_eq!(sigma.x.to_bits(), (0.1f64 + 0.2).to_bits());
    }

    #[test]
    fn rows_past_the_bound_are_refused_naming_the_line_and_quoted_lines_join() {
        let limit = crate::limits::MAX_CSV_RECORD_BYTES;
        let long = "9".repeat(limit + 1);
        let cases = [
            (format!("frame,x,y,score\n0,1,1,{long}\n"), "line 2"),
            (format!("frame,x,y,score{long}\n0,1,1,1\n"), "line 1"),
            // A quoted field's lines are one row.
            (
                format!(
                    "frame,x,y,score,note\n0,1,1,1,\"{}\"\n",
                    "a\n".repeat(limit / 2 + 1)
                ),
                "line",
            ),
        ];
        for (text, line) in &cases {
            let error = read_predictions_from(text.as_bytes(), "long.csv").unwrap_err();
            let message = format!("{error:#}");
            assert!(message.starts_with("long.csv: "), "{message:.200}");
            assert!(
                message.contains(line) && message.contains("longer than"),
                "{message:.200}"
            );
            assert_eq!(crate::error::exit_code(&error), 2);
        }
        // Rows just within the bound, and many short rows, still read;
        // quotes (`""` inside) do not end a row early or late.
        let note = "x".repeat(limit - 40);
        let text = format!("frame,x,y,score,note\n0,1,1,0.5,\"a\"\"b,\n{note}\"\n");
        assert_eq!(
            read_predictions_from(text.as_bytes(), "ok.csv")
                .unwrap()
                .len(),
            1
        );
        let many = "frame,x,y,score\n".to_string() + &"0,1,1,0.5\n".repeat(200_000);
        assert_eq!(
            read_predictions_from(many.as_bytes(), "many.csv")
                .unwrap()
                .len(),
            200_000
        );
    }

    #[test]
    fn tables_without_uncertainties_keep_their_bytes_and_still_read() {
        let predictions = [Prediction::new(1, 2.5, 3.5, 0.75)];
        assert_eq!(write(&predictions), "frame,x,y,score\n1,2.5,3.5,0.75\n");
        // Column order is free and extra columns are ignored, as before.
        let old = "x,y,frame,mass,score\n2.5,3.5,1,10,0.75\n";
        assert_eq!(
            read_predictions_from(old.as_bytes(), "old.csv").unwrap(),
            predictions
        );
    }

    #[test]
    fn ranks_round_trip_in_their_own_column_after_the_score() {
        let predictions = [
            Prediction {
                candidate: Some(1),
                ..Prediction::new(0, 1.5, 2.0, 0.625)
            },
            Prediction {
                candidate: Some(2),
                ..Prediction::new(0, 4.0, 2.0, 0.25)
            },
            // An unranked row in a ranked table.
            Prediction::new(1, 3.0, 4.0, 0.5),
        ];
        let text = write(&predictions);
        assert_eq!(
            text,
            "frame,x,y,score,candidate\n0,1.5,2,0.625,1\n0,4,2,0.25,2\n1,3,4,0.5,\n"
        );
        assert_eq!(
            read_predictions_from(text.as_bytes(), "t.csv").unwrap(),
            predictions
        );
        for bad in ["0", "-1", "1.5", "x"] {
            let text = format!("frame,x,y,score,candidate\n0,1,1,0.5,{bad}\n");
            let error = read_predictions_from(text.as_bytes(), "bad.csv").unwrap_err();
            assert!(
                format!("{error:#}").contains("bad.csv: row 1: candidate: expected a whole number"),
                "{bad}: {error:#}"
            );
        }
    }

    #[test]
    fn bad_uncertainties_are_refused_naming_row_and_column() {
        let cases = [
            (
                "frame,x,y,sigma_x,score\n0,1,1,0.5,0.9\n",
                "sigma_x needs a sigma_y",
            ),
            (
                "frame,x,y,sigma_y,score\n0,1,1,0.5,0.9\n",
                "sigma_y needs a sigma_x",
            ),
            (
                "frame,x,y,sigma_x,sigma_y,score\n0,1,1,0,0.5,0.9\n",
                "row 1: sigma_x: expected a number > 0",
            ),
            (
                "frame,x,y,sigma_x,sigma_y,score\n0,1,1,0.5,,0.9\n",
                "row 1: sigma_y: expected a finite number",
            ),
            (
                "frame,x,y,sigma_x,sigma_y,score\n0,1,1,0.5,inf,0.9\n",
                "row 1: sigma_y: expected a finite number",
            ),
        ];
        for (text, expected) in cases {
            let error = read_predictions_from(text.as_bytes(), "bad.csv").unwrap_err();
            let message = format!("{error:#}");
            assert!(
                message.starts_with("bad.csv: ") && message.contains(expected),
                "{text:?}: {message}"
            );
            assert!(
                error.chain().any(|c| c.is::<crate::error::InputError>()),
                "{message}"
            );
        }
    }
}
