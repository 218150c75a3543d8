//! Tracks tables and recording truth (`docs/tracking.md`).
//!
//! - Tracks: CSV with at least `frame,x,y,particle` (TrackPy's `link`
//!   output; other columns are ignored), optionally `sigma_x,sigma_y`
//!   (px) and `time` (s). Rows may come in any order; they are grouped by
//!   particle and sorted by frame. Refused, with one line naming the file,
//!   row and column: a missing column, a value that is not a finite number,
//!   a frame that is not a whole number ≥ 0, a negative `sigma`, and a
//!   particle found twice in one frame.
//! - Recording truth: `frame,qd,x,y,z_mean,on_fraction,x_seen,y_seen,t_mid,t_beam,t_seen,diffusion`
//!   ([`RecordingTruthRow`]).

use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::path::Path;

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
pub fn fill_recording_truth(
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
        let sigma = match (at("sigma_x"), at("sigma_y")) {
            (Some(sx), Some(sy)) => Some((sx, sy)),
            (None, None) => None,
            _ => {
                return Err(input_error(format!(
                    "{source}: sigma_x and sigma_y come together; only one is present"
                )));
            }
        };
        Ok(Self {
            frame: at("frame").unwrap_or(0),
            x: at("x").unwrap_or(0),
            y: at("y").unwrap_or(0),
            particle: at("particle").unwrap_or(0),
            sigma,
            time: at("time"),
        })
    }
}

/// Reads a tracks table from any reader; `source` names it in errors.
pub fn read_tracks_from<R: Read>(reader: R, source: &str) -> anyhow::Result<Vec<Track>> {
    let mut reader = csv::Reader::from_reader(reader);
    let headers = reader
        .headers()
        .map_err(|e| input_error(format!("{source}: not a CSV table: {e}")))?
        .clone();
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
                "column {name}: expected a finite number, got {text:?}"
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
                    "column particle: expected a whole number, got {particle_text:?}"
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
        },
    ))
}
