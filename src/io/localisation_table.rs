//! The localisation tables `scanloc link` reads and the track tables it
//! writes.
//!
//! Input: CSV with a header that has at least `frame,x,y` (TrackPy pixel
//! coordinates), optionally `sigma_x,sigma_y` (pixels, as
//! [`csv_tables`](super::csv_tables) writes them), and any other columns,
//! which are carried through untouched (their text, not a re-formatted
//! number). Frames are whole numbers ≥ 0 (`3` or pandas' `3.0`); `x`, `y`
//! finite numbers.
//!
//! Output: the input's columns plus `particle` (last; a `particle` column
//! already in the input is overwritten in place, as TrackPy does) and,
//! from the `lap` linker, `gate_x,gate_y` before it (likewise), one row
//! per input row, rows in the order the linker saw them (sorted by frame,
//! ties in input order).

use std::io::{Read, Write};
use std::path::Path;

use crate::error::input_error;
use crate::io::{PendingFile, open_input};
use crate::types::LocalisationSigma;

/// The name of the column of trajectory labels.
pub(crate) const PARTICLE_COLUMN: &str = "particle";

/// The columns of the extent along x and y (px) of the gate that
/// admitted a row's link from its predecessor (the `lap` linker).
pub(crate) const GATE_X_COLUMN: &str = "gate_x";
pub(crate) const GATE_Y_COLUMN: &str = "gate_y";

/// A localisation table: its header and rows as text, and the columns the
/// linkers use, parsed (one entry per row).
#[derive(Debug, Clone)]
pub struct LocalisationTable {
    /// The header, as read.
    pub header: csv::StringRecord,
    /// Every row, as read.
    pub records: Vec<csv::StringRecord>,
    /// `frame` of each row.
    pub frames: Vec<usize>,
    /// `x` (column) of each row, pixels.
    pub xs: Vec<f64>,
    /// `y` (row) of each row, pixels.
    pub ys: Vec<f64>,
    /// `sigma_x,sigma_y` of each row when the table has both columns and the
    /// row fills them (an empty pair is `None`).
    pub sigmas: Vec<Option<LocalisationSigma>>,
}

impl LocalisationTable {
    /// The whole numbers ≥ 0 of column `column` (e.g. `particle` of a track
    /// table); `name` names the table in errors.
    pub fn whole_numbers(&self, column: &str, name: &str) -> anyhow::Result<Vec<usize>> {
        let Some(at) = self.column(column) else {
            crate::bail_input!("{name}: missing column {column}");
        };
        self.records
            .iter()
            .enumerate()
            .map(|(index, record)| {
                let text = record.get(at).unwrap_or("").trim();
                super::csv_tables::parse_frame_number(text)
                    .map_err(|e| input_error(format!("{name}: row {}: {column}: {e}", index + 1)))
            })
            .collect()
    }

    /// Keeps the rows whose `score` column is at least `least` (as
    /// `scanloc locate` writes it) and returns how many were left out;
    /// `name` names the table in errors: a table without a `score` column,
    /// or a score that is not a number (NaN included), is refused.
    pub fn retain_scoring_at_least(&mut self, least: f64, name: &str) -> anyhow::Result<usize> {
        let Some(at) = self.column("score") else {
            crate::bail_input!("{name}: no score column");
        };
        let mut keep = Vec::with_capacity(self.records.len());
        for (index, record) in self.records.iter().enumerate() {
            let text = record.get(at).unwrap_or("").trim();
            match text.parse::<f64>() {
                Ok(score) if !score.is_nan() => keep.push(score >= least),
                _ => crate::bail_input!(
                    "{name}: row {}: score: expected a number, got {}",
                    index + 1,
                    super::csv_tables::quoted(text)
                ),
            }
        }
        keep_rows(&mut self.records, &keep);
        keep_rows(&mut self.frames, &keep);
        keep_rows(&mut self.xs, &keep);
        keep_rows(&mut self.ys, &keep);
        keep_rows(&mut self.sigmas, &keep);
        Ok(keep.iter().filter(|&&k| !k).count())
    }

    /// The index of the header's column `name` (surrounding spaces ignored).
    fn column(&self, name: &str) -> Option<usize> {
        self.header.iter().position(|h| h.trim() == name)
    }
}

/// Keeps the `values` whose entry in `keep` (one per value, in order) is
/// true: `Vec::retain` visits each value once, in order.
fn keep_rows<T>(values: &mut Vec<T>, keep: &[bool]) {
    let mut keep = keep.iter();
    values.retain(|_| keep.next().copied().unwrap_or(false));
}

/// Reads a localisation table from `path` (see the module's conventions);
/// a problem is one [`InputError`](crate::error::InputError) naming the
/// file, the row and the column.
pub fn read_localisation_table(path: &Path) -> anyhow::Result<LocalisationTable> {
    read_localisation_table_from(open_input(path)?, &path.display().to_string())
}

/// [`read_localisation_table`] from any reader; `name` names it in errors.
pub(crate) fn read_localisation_table_from<R: Read>(
    reader: R,
    name: &str,
) -> anyhow::Result<LocalisationTable> {
    let (mut reader, header) = super::csv_tables::open_table(reader, name, &["frame", "x", "y"])?;
    let column = |wanted: &str| header.iter().position(|h| h.trim() == wanted);
    let [frame_at, x_at, y_at] = ["frame", "x", "y"].map(|c| column(c).unwrap_or_default());
    let sigma_at = match (column("sigma_x"), column("sigma_y")) {
        (Some(x), Some(y)) => Some((x, y)),
        (None, None) => None,
        (Some(_), None) => crate::bail_input!("{name}: column sigma_x needs a sigma_y column"),
        (None, Some(_)) => crate::bail_input!("{name}: column sigma_y needs a sigma_x column"),
    };
    let mut table = LocalisationTable {
        header: header.clone(),
        records: Vec::new(),
        frames: Vec::new(),
        xs: Vec::new(),
        ys: Vec::new(),
        sigmas: Vec::new(),
    };
    for (index, record) in reader.records().enumerate() {
        let row = index + 1;
        let record = record.map_err(|e| input_error(format!("{name}: row {row}: {e}")))?;
        let cell = |at: usize| record.get(at).unwrap_or("").trim();
        let finite = |at: usize, column: &str| -> anyhow::Result<f64> {
            match cell(at).parse::<f64>() {
                Ok(value) if value.is_finite() => Ok(value),
                _ => Err(input_error(format!(
                    "{name}: row {row}: {column}: expected a finite number, got {}",
                    super::csv_tables::quoted(cell(at))
                ))),
            }
        };
        let frame = super::csv_tables::parse_frame_number(cell(frame_at))
            .map_err(|e| input_error(format!("{name}: row {row}: frame: {e}")))?;
        let sigma = match sigma_at {
            Some((sx, sy)) if !(cell(sx).is_empty() && cell(sy).is_empty()) => {
                let positive = |at: usize, column: &str| -> anyhow::Result<f64> {
                    match finite(at, column)? {
                        value if value > 0.0 => Ok(value),
                        value => Err(input_error(format!(
                            "{name}: row {row}: {column}: expected a number > 0, got {value}"
                        ))),
                    }
                };
                Some(LocalisationSigma {
                    x: positive(sx, "sigma_x")?,
                    y: positive(sy, "sigma_y")?,
                })
            }
            _ => None,
        };
        table.xs.push(finite(x_at, "x")?);
        table.ys.push(finite(y_at, "y")?);
        table.frames.push(frame);
        table.sigmas.push(sigma);
        table.records.push(record);
    }
    Ok(table)
}

/// Fills `pending` with the track table of `table`: the rows `order`
/// (indices into the table) with their trajectory labels `particles`
/// (indexed like the table's rows) and, when the linker gives them,
/// `gates`: the extent along x and y (px) of the gate that admitted
/// each row's link from its predecessor, as `gate_x,gate_y` (empty for a
/// trajectory's first row).
pub(crate) fn fill_track_table(
    pending: &mut PendingFile,
    table: &LocalisationTable,
    order: &[usize],
    particles: &[usize],
    gates: Option<&[Option<[f64; 2]>]>,
) -> anyhow::Result<()> {
    pending.fill(|writer| write_track_table_to(writer, table, order, particles, gates))
}

/// Writes the track table (see [`fill_track_table`]) to any writer, `\n`
/// line ends. Columns the linker writes replace the table's own of the
/// same name.
pub(crate) fn write_track_table_to<W: Write>(
    writer: W,
    table: &LocalisationTable,
    order: &[usize],
    particles: &[usize],
    gates: Option<&[Option<[f64; 2]>]>,
) -> anyhow::Result<()> {
    let mut csv = csv::WriterBuilder::new().from_writer(writer);
    let mut written: Vec<&str> = Vec::new();
    if gates.is_some() {
        written.extend([GATE_X_COLUMN, GATE_Y_COLUMN]);
    }
    written.push(PARTICLE_COLUMN);
    // Each written column in the table's own place, else appended.
    let mut header: Vec<&str> = table.header.iter().collect();
    for name in &written {
        if !header.iter().any(|h| h.trim() == *name) {
            header.push(name);
        }
    }
    csv.write_record(&header)?;
    for &row in order {
        let record = &table.records[row];
        let gate = gates.and_then(|g| g[row]);
        let fields: Vec<String> = header
            .iter()
            .enumerate()
            .map(|(at, name)| match name.trim() {
                PARTICLE_COLUMN => particles[row].to_string(),
                GATE_X_COLUMN if gates.is_some() => {
                    gate.map_or(String::new(), |g| g[0].to_string())
                }
                GATE_Y_COLUMN if gates.is_some() => {
                    gate.map_or(String::new(), |g| g[1].to_string())
                }
                _ => record.get(at).unwrap_or("").to_string(),
            })
            .collect();
        csv.write_record(&fields)?;
    }
    csv.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_below_the_least_score_are_left_out_of_every_column() {
        let text = "frame,x,y,sigma_x,sigma_y,score\n0,1,2,0.5,0.5,0.9\n0,3,4,1,1,0.1\n1,5,6,,,0.3\n2,7,8,2,2,-1e9\n";
        let mut table = read_localisation_table_from(text.as_bytes(), "t").unwrap();
        assert_eq!(table.retain_scoring_at_least(0.3, "t").unwrap(), 2);
        assert_eq!(table.frames, [0, 1]);
        assert_eq!(table.xs, [1.0, 5.0]);
        assert_eq!(table.ys, [2.0, 6.0]);
        assert_eq!(
            table.sigmas,
            [Some(LocalisationSigma { x: 0.5, y: 0.5 }), None]
        );
        let kept: Vec<&str> = table.records.iter().map(|r| r.get(5).unwrap()).collect();
        assert_eq!(kept, ["0.9", "0.3"]);
    }

    #[test]
    fn other_columns_pass_through_and_particle_is_appended() {
        let text = "x,y,frame,mass\n1.50,2,1,10\n3,4,0.0,20\n";
        let table = read_localisation_table_from(text.as_bytes(), "t.csv").unwrap();
        assert_eq!(table.frames, [1, 0]);
        let mut bytes = Vec::new();
        // Labels are indexed by table row; rows are written in `order`.
        write_track_table_to(&mut bytes, &table, &[1, 0], &[7, 3], None).unwrap();
        assert_eq!(
            String::from_utf8(bytes).unwrap(),
            "x,y,frame,mass,particle\n3,4,0.0,20,3\n1.50,2,1,10,7\n"
        );
    }

    #[test]
    fn an_existing_particle_column_is_overwritten_in_place() {
        let text = "frame,particle,x,y\n0,9,1,1\n";
        let table = read_localisation_table_from(text.as_bytes(), "t.csv").unwrap();
        let mut bytes = Vec::new();
        write_track_table_to(&mut bytes, &table, &[0], &[0], None).unwrap();
        assert_eq!(
            String::from_utf8(bytes).unwrap(),
            "frame,particle,x,y\n0,0,1,1\n"
        );
    }
}
