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
    let read_error =
        |e: std::io::Error| input_error(format!("{name}: truncated or unreadable data: {e}"));
    let data: Vec<u32> = match (dtype.type_char(), dtype.size_field()) {
        (TypeChar::Uint, 1) => widen(npy.into_vec::<u8>().map_err(read_error)?),
        (TypeChar::Uint, 2) => widen(npy.into_vec::<u16>().map_err(read_error)?),
        (TypeChar::Uint, 4) => npy.into_vec::<u32>().map_err(read_error)?,
        (TypeChar::Uint, 8) => checked(name, npy.into_vec::<u64>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Int, 1) => checked(name, npy.into_vec::<i8>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Int, 2) => checked(name, npy.into_vec::<i16>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Int, 4) => checked(name, npy.into_vec::<i32>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Int, 8) => checked(name, npy.into_vec::<i64>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Float, 4) => checked(name, npy.into_vec::<f32>().map_err(read_error)?, |v| {
            v as f64
        })?,
        (TypeChar::Float, 8) => checked(name, npy.into_vec::<f64>().map_err(read_error)?, |v| v)?,
        _ => {
            return Err(input_error(format!(
                "{name}: unsupported dtype {dtype}; expected integer or float counts"
            )));
        }
    };
    FrameStack::from_vec(n, height, width, data).map_err(|e| input_error(format!("{name}: {e}")))
}

fn widen<T: Into<u32>>(values: Vec<T>) -> Vec<u32> {
    values.into_iter().map(Into::into).collect()
}

/// Converts values to counts, refusing any that is not a whole number in
/// `0..=u32::MAX` and naming the first such one.
fn checked<T: Copy>(
    name: &str,
    values: Vec<T>,
    to_f64: impl Fn(T) -> f64,
) -> anyhow::Result<Vec<u32>> {
    values
        .into_iter()
        .enumerate()
        .map(|(index, value)| count_from_f64(to_f64(value)).ok_or(index))
        .collect::<Result<Vec<u32>, usize>>()
        .map_err(|index| {
            input_error(format!(
                "{name}: value at flat index {index} is not a photon count (a whole number from 0 to {}); NaN, negative and fractional values are refused",
                u32::MAX
            ))
        })
}

/// `Some(count)` if `value` is a whole number representable as `u32`.
pub fn count_from_f64(value: f64) -> Option<u32> {
    if value.is_finite() && value >= 0.0 && value <= u32::MAX as f64 && value.fract() == 0.0 {
        Some(value as u32)
    } else {
        None
    }
}
