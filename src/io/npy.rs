//! NumPy `.npy` frame stacks.
//!
//! Written as `uint16` when every count fits, else `uint32`, shape
//! `(n, H, W)`, C order. Read from any unsigned or signed integer dtype, or
//! from a float dtype whose values are all whole non-negative numbers; a
//! 2-D array is read as one frame. Values that are negative, NaN, infinite,
//! fractional or above `u32::MAX` are refused with the index of the first
//! offender, never rounded or clipped. One writer and one reader, over any
//! `Write`/`Read` (the registry stores the same bytes as `frames.npy`
//! blobs); the file reader calls it.

use std::io::{BufReader, Read, Write};
use std::path::Path;

use npyz::{NpyFile, Order, TypeChar, WriterBuilder};

use super::open_input;
use crate::error::input_error;
use crate::types::FrameStack;

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

/// Reads a frame stack from a `.npy` file.
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    let file = open_input(path)?;
    let file_len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
    read_frames_from(BufReader::new(file), file_len, &path.display().to_string())
}

/// Reads a frame stack from `.npy` data of `len` bytes (header included)
/// from any reader, as [`read_frames`]; the header's shape is checked
/// against `len` before anything is allocated. `name` (a path, or a blob's
/// role) names the data in errors.
pub fn read_frames_from<R: Read>(reader: R, len: u64, name: &str) -> anyhow::Result<FrameStack> {
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
    let data: Vec<u32> = match (dtype.type_char(), dtype.size_field()) {
        (TypeChar::Uint, 1) => read_counts(npy, values, name, |v: u8| Some(v.into()))?,
        (TypeChar::Uint, 2) => read_counts(npy, values, name, |v: u16| Some(v.into()))?,
        (TypeChar::Uint, 4) => read_counts(npy, values, name, |v: u32| Some(v))?,
        (TypeChar::Uint, 8) => read_counts(npy, values, name, |v: u64| u32::try_from(v).ok())?,
        (TypeChar::Int, 1) => read_counts(npy, values, name, |v: i8| u32::try_from(v).ok())?,
        (TypeChar::Int, 2) => read_counts(npy, values, name, |v: i16| u32::try_from(v).ok())?,
        (TypeChar::Int, 4) => read_counts(npy, values, name, |v: i32| u32::try_from(v).ok())?,
        (TypeChar::Int, 8) => read_counts(npy, values, name, |v: i64| u32::try_from(v).ok())?,
        (TypeChar::Float, 4) => read_counts(npy, values, name, |v: f32| count_from_f64(v.into()))?,
        (TypeChar::Float, 8) => read_counts(npy, values, name, count_from_f64)?,
        _ => {
            return Err(input_error(format!(
                "{name}: unsupported dtype {dtype}; expected integer or float counts"
            )));
        }
    };
    FrameStack::from_vec(n, height, width, data).map_err(|e| input_error(format!("{name}: {e}")))
}

/// Reads the `len` values of `npy` as counts, converting each as it is
/// read (no intermediate array: a recording's memory is its counts alone),
/// refusing any value `to_count` rejects, naming the first such one.
fn read_counts<T: npyz::Deserialize, R: std::io::Read>(
    npy: NpyFile<R>,
    len: usize,
    name: &str,
    to_count: impl Fn(T) -> Option<u32>,
) -> anyhow::Result<Vec<u32>> {
    let values = npy
        .data::<T>()
        .map_err(|e| input_error(format!("{name}: unreadable data: {e}")))?;
    let mut counts = Vec::with_capacity(len);
    for (index, value) in values.enumerate() {
        let value =
            value.map_err(|e| input_error(format!("{name}: truncated or unreadable data: {e}")))?;
        let count = to_count(value).ok_or_else(|| {
            input_error(format!(
                "{name}: value at flat index {index} is not a photon count (a whole number from 0 to {}); NaN, negative and fractional values are refused",
                u32::MAX
            ))
        })?;
        counts.push(count);
    }
    Ok(counts)
}

/// `Some(count)` if `value` is a whole number representable as `u32`.
pub fn count_from_f64(value: f64) -> Option<u32> {
    if value.is_finite() && value >= 0.0 && value <= u32::MAX as f64 && value.fract() == 0.0 {
        Some(value as u32)
    } else {
        None
    }
}
