//! Multi-page TIFF frame stacks, one greyscale page per frame.
//!
//! Written as 16-bit pages when every count fits, else 32-bit, uncompressed,
//! which Fiji/ImageJ opens as a stack and tifffile as an `(n, H, W)` array.
//! Read from 8/16/32/64-bit unsigned or float greyscale pages of equal size;
//! float values must be whole non-negative numbers (see [`super::npy`]).

use std::io::{BufReader, Seek, Write};
use std::path::Path;

use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{TiffEncoder, colortype};

use super::npy::count_from_f64;
use super::open_input;
use crate::error::input_error;
use crate::types::FrameStack;

/// Writes one page per frame.
pub fn write_frames<W: Write + Seek>(writer: &mut W, frames: &FrameStack) -> anyhow::Result<()> {
    let mut encoder = TiffEncoder::new(writer)?;
    let (width, height) = (frames.width as u32, frames.height as u32);
    let sixteen_bit = frames.max_count() <= u16::MAX as u32;
    for frame in frames.iter() {
        if sixteen_bit {
            let page: Vec<u16> = frame.iter().map(|&count| count as u16).collect();
            encoder.write_image::<colortype::Gray16>(width, height, &page)?;
        } else {
            encoder.write_image::<colortype::Gray32>(width, height, frame)?;
        }
    }
    Ok(())
}

/// Reads every page of a TIFF file as one frame.
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    let name = path.display();
    let bad = |e: tiff::TiffError| input_error(format!("{name}: not a readable TIFF stack: {e}"));
    let mut decoder = Decoder::new(BufReader::new(open_input(path)?)).map_err(bad)?;
    let mut stack = FrameStack::default();
    loop {
        let (width, height) = decoder.dimensions().map_err(bad)?;
        let page = decoder.read_image().map_err(bad)?;
        let counts: Vec<u32> = match page {
            DecodingResult::U8(values) => values.into_iter().map(u32::from).collect(),
            DecodingResult::U16(values) => values.into_iter().map(u32::from).collect(),
            DecodingResult::U32(values) => values,
            DecodingResult::U64(values) => {
                whole_counts(&name, stack.n, values.into_iter().map(|v| v as f64))?
            }
            DecodingResult::F32(values) => {
                whole_counts(&name, stack.n, values.into_iter().map(f64::from))?
            }
            DecodingResult::F64(values) => whole_counts(&name, stack.n, values.into_iter())?,
            _ => {
                return Err(input_error(format!(
                    "{name}: page {} has an unsupported sample type; expected greyscale counts",
                    stack.n
                )));
            }
        };
        if counts.len() != (width as usize) * (height as usize) {
            return Err(input_error(format!(
                "{name}: page {} is not single-channel greyscale ({} samples for {width}×{height} pixels)",
                stack.n,
                counts.len()
            )));
        }
        let page = FrameStack::from_vec(1, height as usize, width as usize, counts)?;
        stack
            .append(page)
            .map_err(|e| input_error(format!("{name}: {e}")))?;
        if !decoder.more_images() {
            break;
        }
        decoder.next_image().map_err(bad)?;
    }
    Ok(stack)
}

fn whole_counts(
    name: &impl std::fmt::Display,
    page: usize,
    values: impl Iterator<Item = f64>,
) -> anyhow::Result<Vec<u32>> {
    values
        .enumerate()
        .map(|(index, value)| {
            count_from_f64(value).ok_or_else(|| {
                input_error(format!(
                    "{name}: page {page}, pixel {index}: {value} is not a photon count (a whole number ≥ 0)"
                ))
            })
        })
        .collect()
}
