//! NumPy `.npy` frame stacks.
//!
//! Written as `uint16` when every count fits, else `uint32`, shape
//! `(n, H, W)`, C order. Read ([`read_recording_from`]) from any unsigned
//! or signed integer dtype as photon counts (negative values or values
//! above `u32::MAX` refused), or from `float32`/`float64` as real-valued
//! frames (any finite value; NaN and infinities refused); a 2-D array is
//! read as one frame. A refused value is named with the flat index of the
//! first offender, never rounded or clipped. Readers of counts
//! ([`read_frames_from`]) also take float arrays whose values are all
//! whole and ≥ 0. One writer and one reader, over any `Write`/`Read` (the
//! registry stores the same bytes as `frames.npy` blobs); the file reader
//! calls it.

use std::io::{BufReader, Read, Write};
use std::path::Path;

use npyz::{NpyFile, Order, TypeChar, WriterBuilder};

use super::open_input;
use crate::error::input_error;
use crate::types::{FrameStack, RealFrameStack, Recording};

/// Writes `frames` as a C-order `(n, H, W)` array.
pub fn write_frames<W: Write>(writer: &mut W, frames: &FrameStack) -> anyhow::Result<()> {
    let shape = [frames.n as u64, frames.height as u64, frames.width as u64];
    if frames.max_count() <= u16::MAX as u32 {
        let mut npy = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&shape)
            .writer(writer)
            .begin_nd()?;
        npy.extend(frames.data.iter().map(|&count| count as u16))?;
        npy.finish()?;
    } else {
        let mut npy = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&shape)
            .writer(writer)
            .begin_nd()?;
        npy.extend(frames.data.iter().copied())?;
        npy.finish()?;
    }
    Ok(())
}

/// Reads a frame stack of photon counts from a `.npy` file.
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    counts_of(read_recording(path)?, &path.display().to_string())
}

/// Reads the frames of a `.npy` file: counts from an integer array, real
/// values from a float array.
pub fn read_recording(path: &Path) -> anyhow::Result<Recording> {
    let file = open_input(path)?;
    let file_len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
    read_recording_from(BufReader::new(file), file_len, &path.display().to_string())
}

/// Reads a frame stack of photon counts from `.npy` data of `len` bytes
/// (header included) from any reader, as [`read_frames`]. `name` (a path,
/// or a blob's role) names the data in errors.
pub(crate) fn read_frames_from<R: Read>(
    reader: R,
    len: u64,
    name: &str,
) -> anyhow::Result<FrameStack> {
    counts_of(read_recording_from(reader, len, name)?, name)
}

/// `recording` as photon counts, the error naming `name`.
fn counts_of(recording: Recording, name: &str) -> anyhow::Result<FrameStack> {
    recording
        .into_counts()
        .map_err(|e| input_error(format!("{name}: {e:#}")))
}

/// Reads the frames of `.npy` data of `len` bytes (header included) from
/// any reader, as [`read_recording`]; the header's shape is checked against
/// `len` before anything is allocated. `name` (a path, or a blob's role)
/// names the data in errors.
pub(crate) fn read_recording_from<R: Read>(
    reader: R,
    len: u64,
    name: &str,
) -> anyhow::Result<Recording> {
    let npy = NpyFile::new(reader)
        .map_err(|e| input_error(format!("{name}: not a readable .npy file: {e}")))?;
    if npy.order() != Order::C {
        return Err(input_error(format!(
            "{name}: Fortran-ordered arrays are not supported; save with numpy.ascontiguousarray"
        )));
    }
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let (n, height, width) = match shape[..] {
        [height, width] => (1, height, width),
        [n, height, width] => (n, height, width),
        _ => {
            return Err(input_error(format!(
                "{name}: expected shape (n, H, W) or (H, W), got {shape:?}"
            )));
        }
    };
    let dtype = match npy.dtype() {
        npyz::DType::Plain(type_str) => type_str,
        other => {
            return Err(input_error(format!(
                "{name}: unsupported dtype {}; expected an integer or float array",
                other.descr()
            )));
        }
    };
    // A damaged header can claim any shape: check it against the data's
    // size before allocating anything for it.
    let claimed_bytes = shape.iter().try_fold(dtype.size_field().max(1), |acc, &d| {
        acc.checked_mul(d as u64)
    });
    if claimed_bytes.is_none_or(|bytes| bytes > len) {
        return Err(input_error(format!(
            "{name}: header claims shape {shape:?} of {dtype}, more data than its {len} bytes"
        )));
    }
    // Exact: the shape's product was checked against the data's size above.
    let values = n * height * width;
    let counts = |data: Vec<u32>| {
        FrameStack::from_vec(n, height, width, data)
            .map(Recording::Counts)
            .map_err(|e| input_error(format!("{name}: {e}")))
    };
    let real = |data: Vec<f64>| {
        RealFrameStack::from_vec(n, height, width, data)
            .map(Recording::Real)
            .map_err(|e| input_error(format!("{name}: {e}")))
    };
    match (dtype.type_char(), dtype.size_field()) {
        (TypeChar::Uint, 1) => counts(read_counts(npy, values, name, |v: u8| Some(v.into()))?),
        (TypeChar::Uint, 2) => counts(read_counts(npy, values, name, |v: u16| Some(v.into()))?),
        (TypeChar::Uint, 4) => counts(read_counts(npy, values, name, |v: u32| Some(v))?),
        (TypeChar::Uint, 8) => counts(read_counts(npy, values, name, |v: u64| {
            u32::try_from(v).ok()
        })?),
        (TypeChar::Int, 1) => counts(read_counts(npy, values, name, |v: i8| {
            u32::try_from(v).ok()
        })?),
        (TypeChar::Int, 2) => counts(read_counts(npy, values, name, |v: i16| {
            u32::try_from(v).ok()
        })?),
        (TypeChar::Int, 4) => counts(read_counts(npy, values, name, |v: i32| {
            u32::try_from(v).ok()
        })?),
        (TypeChar::Int, 8) => counts(read_counts(npy, values, name, |v: i64| {
            u32::try_from(v).ok()
        })?),
        (TypeChar::Float, 4) => real(read_reals(npy, values, name, |v: f32| f64::from(v))?),
        (TypeChar::Float, 8) => real(read_reals(npy, values, name, |v: f64| v)?),
        _ => Err(input_error(format!(
            "{name}: unsupported dtype {dtype}; expected integer counts or float32/float64 values"
        ))),
    }
}

/// Reads the `len` values of `npy` as counts, converting each as it is
/// read (no intermediate array: a recording's memory is its counts alone),
/// refusing any value `to_count` rejects, naming the first such one.
fn read_counts<T: npyz::Deserialize + std::fmt::Display + Copy, R: std::io::Read>(
    npy: NpyFile<R>,
    len: usize,
    name: &str,
    to_count: impl Fn(T) -> Option<u32>,
) -> anyhow::Result<Vec<u32>> {
    read_values(npy, len, name, |index, value: T| {
        to_count(value).ok_or_else(|| {
            format!(
                "value at flat index {index} ({value}) is not a photon count (0 to {}) in an integer array; save background-subtracted or scaled frames as float32/float64 (docs/detectors.md, \"Input frames\")",
                u32::MAX
            )
        })
    })
}

/// Reads the `len` values of `npy` as real values, converting each as it
/// is read, refusing NaN and infinities and naming the first.
fn read_reals<T: npyz::Deserialize, R: std::io::Read>(
    npy: NpyFile<R>,
    len: usize,
    name: &str,
    to_f64: impl Fn(T) -> f64,
) -> anyhow::Result<Vec<f64>> {
    read_values(npy, len, name, |index, value: T| {
        let value = to_f64(value);
        if value.is_finite() {
            Ok(value)
        } else {
            Err(format!(
                "value at flat index {index} is {value}; frames must hold finite numbers"
            ))
        }
    })
}

/// Reads the `len` values of `npy`, converting each with `convert` (given
/// its flat index) as it is read; the first refusal is the error.
fn read_values<T: npyz::Deserialize, V, R: std::io::Read>(
    npy: NpyFile<R>,
    len: usize,
    name: &str,
    convert: impl Fn(usize, T) -> Result<V, String>,
) -> anyhow::Result<Vec<V>> {
    let values = npy
        .data::<T>()
        .map_err(|e| input_error(format!("{name}: unreadable data: {e}")))?;
    let mut converted = Vec::with_capacity(len);
    for (index, value) in values.enumerate() {
        let value =
            value.map_err(|e| input_error(format!("{name}: truncated or unreadable data: {e}")))?;
        converted.push(convert(index, value).map_err(|e| input_error(format!("{name}: {e}")))?);
    }
    Ok(converted)
}
