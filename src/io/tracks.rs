//! Tracks tables and recording truth (`docs/tracking.md`).
//!
//! - Tracks: CSV with at least `frame,x,y,particle` (TrackPy's `link`
//!   output; other columns are ignored), optionally `sigma_x,sigma_y`
//!   (px), `gate_x,gate_y` (px: the extent of the linker's gate that
//!   admitted the step to the row from the particle's previous row, as
//!   the `lap` linker writes them) and `time` (s). Rows may come in any order; they are grouped by
//!   particle and sorted by frame. Refused, with one line naming the file,
//!   row and column: a missing column, a value that is not a finite number,
//!   a frame that is not a whole number ≥ 0, a negative `sigma`, a
//!   particle found twice in one frame, and a track with `time` in some of
//!   its rows but not all.
//! - Recording truth: `frame,qd,x,y,z_mean,on_fraction,x_seen,y_seen,t_mid,t_beam,t_seen,diffusion`
//!   ([`RecordingTruthRow`]), as `scanloc simulate-recording --truth`
//!   writes it. Read back with every column required (in any order, other
//!   columns ignored); refused, with one line naming the file, row and
//!   column: a missing column, a value that is not a finite number, a
//!   frame or QD id that is not a whole number ≥ 0, and a QD found twice in
//!   one frame.

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::Path;

use super::csv_tables::quoted;
use super::{PendingFile, open_input};
use crate::error::input_error;
use crate::types::{RecordingTruthRow, Track, TrackPoint};

/// Column names of a recording truth table, in order.
pub const RECORDING_TRUTH_COLUMNS: [&str; 12] = [
    "frame",
    "qd",
    "x",
    "y",
    "z_mean",
    "on_fraction",
    "x_seen",
    "y_seen",
    "t_mid",
    "t_beam",
    "t_seen",
    "diffusion",
];

/// Fills a pending output with recording truth rows.
pub(crate) fn fill_recording_truth(
    pending: &mut PendingFile,
    truth: &[RecordingTruthRow],
) -> anyhow::Result<()> {
    pending.fill(|writer| write_recording_truth_to(writer, truth))
}

/// Writes recording truth rows as CSV to any writer.
pub fn write_recording_truth_to<W: Write>(
    writer: W,
    truth: &[RecordingTruthRow],
) -> anyhow::Result<()> {
    let mut csv = csv::Writer::from_writer(writer);
    if truth.is_empty() {
        csv.write_record(RECORDING_TRUTH_COLUMNS)?;
    }
    for row in truth {
        csv.serialize(row)?;
    }
    csv.flush()?;
    Ok(())
}

/// Reads a recording truth table (see the module's documentation); rows in
/// file order.
pub fn read_recording_truth(path: &Path) -> anyhow::Result<Vec<RecordingTruthRow>> {
    read_recording_truth_from(open_input(path)?, &path.display().to_string())
}

/// [`read_recording_truth`] from any reader; `source` names it in errors.
pub(crate) fn read_recording_truth_from<R: Read>(
    reader: R,
    source: &str,
) -> anyhow::Result<Vec<RecordingTruthRow>> {
    let (mut reader, header) =
        super::csv_tables::open_table(reader, source, &RECORDING_TRUTH_COLUMNS)?;
    let at = RECORDING_TRUTH_COLUMNS
        .map(|name| header.iter().position(|h| h.trim() == name).unwrap_or(0));
    let mut rows = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for (index, record) in reader.records().enumerate() {
        let row = index + 1;
        let record =
            record.map_err(|e| input_error(format!("{source}: row {row}: not a CSV row: {e}")))?;
        let parsed = parse_truth_row(&record, &at)
            .map_err(|e| input_error(format!("{source}: row {row}: {e}")))?;
        if !seen.insert((parsed.frame, parsed.qd)) {
            crate::bail_input!(
                "{source}: row {row}: column qd: QD {} appears twice in frame {}",
                parsed.qd,
                parsed.frame
            );
        }
        rows.push(parsed);
    }
    Ok(rows)
}

/// One recording truth row (`at`: the column of each of
/// [`RECORDING_TRUTH_COLUMNS`]), or what is wrong with it.
fn parse_truth_row(
    record: &csv::StringRecord,
    at: &[usize; 12],
) -> Result<RecordingTruthRow, String> {
    let cell = |column: usize| record.get(at[column]).unwrap_or("").trim();
    let number = |column: usize| -> Result<f64, String> {
        let text = cell(column);
        match text.parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(value),
            _ => Err(format!(
                "column {}: expected a finite number, got {}",
                RECORDING_TRUTH_COLUMNS[column],
                quoted(text)
            )),
        }
    };
    let frame =
        super::csv_tables::parse_frame_number(cell(0)).map_err(|e| format!("column frame: {e}"))?;
    // A whole number written as a float (`3.0`) is read as `frame` is.
    let whole = |text: &str| -> Option<u64> {
        text.parse::<u64>().ok().or_else(|| {
            let value = text.parse::<f64>().ok()?;
            (value.is_finite() && value >= 0.0 && value.fract() == 0.0 && value < 9.2e18)
                .then_some(value as u64)
        })
    };
    let qd = match whole(cell(1)) {
        Some(value) if value <= i64::MAX as u64 => value,
        _ => {
            return Err(format!(
                "column qd: expected a whole number from 0 to 2^63 − 1, got {}",
                quoted(cell(1))
            ));
        }
    };
    let on_fraction = number(5)?;
    if !(0.0..=1.0).contains(&on_fraction) {
        return Err(format!(
            "column on_fraction: must be a share from 0 to 1, got {}",
            crate::error::readable(on_fraction)
        ));
    }
    Ok(RecordingTruthRow {
        frame,
        qd,
        x: number(2)?,
        y: number(3)?,
        z_mean: number(4)?,
        on_fraction,
        x_seen: number(6)?,
        y_seen: number(7)?,
        t_mid: number(8)?,
        t_beam: number(9)?,
        t_seen: number(10)?,
        diffusion: number(11)?,
    })
}

/// Writes `tracks` as a tracks table: `frame,x,y,particle`, with
/// `sigma_x,sigma_y` before `particle` when any point has an uncertainty
/// (empty cells where one has none); rows by frame, then particle. Floats
/// in Rust's shortest round-trip form, so [`read_tracks_from`] gives back
/// the same bits.
pub(crate) fn write_tracks_to<W: Write>(writer: W, tracks: &[Track]) -> anyhow::Result<()> {
    let with_sigma = tracks
        .iter()
        .any(|t| t.points.iter().any(|p| p.sigma.is_some()));
    let with_gate = tracks
        .iter()
        .any(|t| t.points.iter().any(|p| p.gate.is_some()));
    let mut rows: Vec<(usize, i64, &TrackPoint)> = tracks
        .iter()
        .flat_map(|t| t.points.iter().map(move |p| (p.frame, t.particle, p)))
        .collect();
    rows.sort_by_key(|&(frame, particle, _)| (frame, particle));
    let mut csv = csv::Writer::from_writer(writer);
    let mut header = vec!["frame", "x", "y"];
    if with_sigma {
        header.extend(["sigma_x", "sigma_y"]);
    }
    if with_gate {
        header.extend(["gate_x", "gate_y"]);
    }
    header.push("particle");
    csv.write_record(&header)?;
    let pair = |value: Option<(f64, f64)>| {
        value.map_or([String::new(), String::new()], |(a, b)| {
            [a.to_string(), b.to_string()]
        })
    };
    for (frame, particle, point) in rows {
        let mut record = vec![frame.to_string(), point.x.to_string(), point.y.to_string()];
        if with_sigma {
            record.extend(pair(point.sigma));
        }
        if with_gate {
            record.extend(pair(point.gate));
        }
        record.push(particle.to_string());
        csv.write_record(&record)?;
    }
    csv.flush()?;
    Ok(())
}

/// Reads a tracks table (see the module's documentation).
pub fn read_tracks(path: &Path) -> anyhow::Result<Vec<Track>> {
    read_tracks_from(open_input(path)?, &path.display().to_string())
}

/// The column indices of a tracks table.
struct Columns {
    frame: usize,
    x: usize,
    y: usize,
    particle: usize,
    sigma: Option<(usize, usize)>,
    gate: Option<(usize, usize)>,
    time: Option<usize>,
}

impl Columns {
    fn find(headers: &csv::StringRecord, source: &str) -> anyhow::Result<Self> {
        let at = |name: &str| headers.iter().position(|h| h.trim() == name);
        let required = ["frame", "x", "y", "particle"];
        let missing: Vec<&str> = required.into_iter().filter(|c| at(c).is_none()).collect();
        if !missing.is_empty() {
            return Err(input_error(format!(
                "{source}: not a tracks table: missing column(s) {} (it needs frame,x,y,particle)",
                missing.join(", ")
            )));
        }
        let together = |x: &str, y: &str| match (at(x), at(y)) {
            (Some(a), Some(b)) => Ok(Some((a, b))),
            (None, None) => Ok(None),
            _ => Err(input_error(format!(
                "{source}: {x} and {y} come together; only one is present"
            ))),
        };
        let sigma = together("sigma_x", "sigma_y")?;
        let gate = together("gate_x", "gate_y")?;
        Ok(Self {
            frame: at("frame").unwrap_or(0),
            x: at("x").unwrap_or(0),
            y: at("y").unwrap_or(0),
            particle: at("particle").unwrap_or(0),
            sigma,
            gate,
            time: at("time"),
        })
    }
}

/// Reads a tracks table from any reader; `source` names it in errors.
pub fn read_tracks_from<R: Read>(reader: R, source: &str) -> anyhow::Result<Vec<Track>> {
    let (mut reader, headers) = super::csv_tables::open_table(reader, source, &[])?;
    let columns = Columns::find(&headers, source)?;
    let mut tracks: BTreeMap<i64, Vec<TrackPoint>> = BTreeMap::new();
    for (index, record) in reader.records().enumerate() {
        let row = index + 1;
        let record =
            record.map_err(|e| input_error(format!("{source}: row {row}: not a CSV row: {e}")))?;
        let (particle, point) = parse_row(&record, &columns)
            .map_err(|e| input_error(format!("{source}: row {row}: {e}")))?;
        tracks.entry(particle).or_default().push(point);
    }
    tracks
        .into_iter()
        .map(|(particle, mut points)| {
            points.sort_by_key(|p| p.frame);
            if let Some(pair) = points.windows(2).find(|w| w[0].frame == w[1].frame) {
                return Err(input_error(format!(
                    "{source}: particle {particle} appears twice in frame {}",
                    pair[0].frame
                )));
            }
            // A time stamp replaces the scan's: a track timed in part would
            // mix two clocks.
            if let Some(untimed) = points.iter().find(|p| p.time_s.is_none())
                && points.iter().any(|p| p.time_s.is_some())
            {
                return Err(input_error(format!(
                    "{source}: particle {particle}: column time: empty in frame {} but given in others of the track (give every row of a track its time, or none)",
                    untimed.frame
                )));
            }
            Ok(Track { particle, points })
        })
        .collect()
}

/// One row's particle and localisation, or what is wrong with it.
fn parse_row(record: &csv::StringRecord, columns: &Columns) -> Result<(i64, TrackPoint), String> {
    let cell = |at: usize, name: &str| {
        record
            .get(at)
            .map(str::trim)
            .ok_or_else(|| format!("column {name}: missing cell"))
    };
    let finite = |at: usize, name: &str| -> Result<f64, String> {
        let text = cell(at, name)?;
        match text.parse::<f64>() {
            Ok(value) if value.is_finite() => Ok(value),
            _ => Err(format!(
                "column {name}: expected a finite number, got {}",
                quoted(text)
            )),
        }
    };
    let frame = super::csv_tables::parse_frame_number(cell(columns.frame, "frame")?)
        .map_err(|e| format!("column frame: {e}"))?;
    let particle_text = cell(columns.particle, "particle")?;
    let particle = match particle_text.parse::<i64>() {
        Ok(value) => value,
        Err(_) => match particle_text.parse::<f64>() {
            Ok(value) if value.fract() == 0.0 && value.abs() < 9e15 => value as i64,
            _ => {
                return Err(format!(
                    "column particle: expected a whole number, got {}",
                    quoted(particle_text)
                ));
            }
        },
    };
    let sigma = match columns.sigma {
        Some((sx, sy)) if !cell(sx, "sigma_x")?.is_empty() || !cell(sy, "sigma_y")?.is_empty() => {
            let (sx, sy) = (finite(sx, "sigma_x")?, finite(sy, "sigma_y")?);
            if sx < 0.0 || sy < 0.0 {
                return Err(format!("sigma_x, sigma_y must be ≥ 0, got {sx}, {sy}"));
            }
            Some((sx, sy))
        }
        _ => None,
    };
    let gate = match columns.gate {
        Some((gx, gy)) if !cell(gx, "gate_x")?.is_empty() || !cell(gy, "gate_y")?.is_empty() => {
            let (gx, gy) = (finite(gx, "gate_x")?, finite(gy, "gate_y")?);
            if gx <= 0.0 || gy <= 0.0 {
                return Err(format!("gate_x, gate_y must be > 0, got {gx}, {gy}"));
            }
            Some((gx, gy))
        }
        _ => None,
    };
    let time_s = match columns.time {
        Some(at) if !cell(at, "time")?.is_empty() => Some(finite(at, "time")?),
        _ => None,
    };
    Ok((
        particle,
        TrackPoint {
            frame,
            x: finite(columns.x, "x")?,
            y: finite(columns.y, "y")?,
            sigma,
            time_s,
            gate,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(frame: usize, qd: u64) -> RecordingTruthRow {
        RecordingTruthRow {
            frame,
            qd,
            x: 1.25,
            y: -0.5,
            z_mean: 0.3,
            on_fraction: 1.0,
            x_seen: 1.5,
            y_seen: -0.25,
            t_mid: 0.01,
            t_beam: 0.02,
            t_seen: 0.015,
            diffusion: 1.0,
        }
    }

    #[test]
    fn recording_truth_reads_back_what_is_written() {
        let rows = vec![row(0, 3), row(1, 3), row(1, 7)];
        let mut bytes = Vec::new();
        write_recording_truth_to(&mut bytes, &rows).unwrap();
        let read = read_recording_truth_from(bytes.as_slice(), "truth.csv").unwrap();
        assert_eq!(read, rows);
    }

    #[test]
    fn bad_recording_truth_is_one_line_naming_file_row_and_column() {
        let mut bytes = Vec::new();
        write_recording_truth_to(&mut bytes, &[row(0, 3), row(0, 3)]).unwrap();
        let good = String::from_utf8(bytes).unwrap();
        let replace_second_row = |from: &str, to: &str| {
            let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
            lines[2] = lines[2].replacen(from, to, 1);
            lines.join("\n")
        };
        let cases = [
            (
                good.clone(),
                "truth.csv: row 2: column qd: QD 3 appears twice in frame 0",
            ),
            (
                replace_second_row("0,3,", "0,-3,"),
                "truth.csv: row 2: column qd: expected a whole number",
            ),
            (
                replace_second_row("0,3,1.25", "0,4,NaN"),
                "truth.csv: row 2: column x: expected a finite number",
            ),
            (
                replace_second_row("0,3,", "-1,4,"),
                "truth.csv: row 2: column frame: expected a whole number ≥ 0",
            ),
            (
                good.replacen("z_mean", "depth", 1),
                "truth.csv: missing column(s) z_mean",
            ),
        ];
        for (text, expected) in cases {
            let error = read_recording_truth_from(text.as_bytes(), "truth.csv").unwrap_err();
            let message = format!("{error:#}");
            assert!(message.starts_with(expected), "{message}");
            assert!(!message.contains('\n'), "{message}");
            assert_eq!(crate::error::exit_code(&error), 2, "{message}");
        }
    }
}
