//! Multi-page TIFF frame stacks, one greyscale page per frame.
//!
//! Written as 16-bit pages when every count fits, else 32-bit, uncompressed,
//! which Fiji/ImageJ opens as a stack and tifffile as an `(n, H, W)` array.
//! Read from 8/16/32/64-bit unsigned, signed or float greyscale pages of
//! equal size: integer pages as photon counts (signed values must be ≥ 0),
//! float pages as real values (finite; a stack with any float page is read
//! as real-valued frames), see [`super::npy`]. ImageJ hyperstacks are read
//! one channel at a time ([`read_channel`]).

use std::io::{BufReader, Seek, Write};
use std::path::Path;

use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

use super::open_input;
use crate::error::input_error;
use crate::types::frames::whole_count;
use crate::types::{FrameStack, RealFrameStack, Recording};

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

/// Reads every page of a TIFF file as one frame of photon counts; see
/// [`read_channel`].
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    read_channel(path, None)?
        .into_counts()
        .map_err(|e| input_error(format!("{}: {e:#}", path.display())))
}

/// Reads the frames of a TIFF stack, one greyscale page per frame.
///
/// An ImageJ hyperstack (an `ImageDescription` starting `ImageJ=` with
/// `channels=C`) stores its pages channel by channel within each slice and
/// time point; with `C > 1` the frames of channel `channel` (0-based) are
/// read, in slice-then-time order, and without a channel the stack is
/// refused rather than read with channels interleaved as time. Pages with
/// more than one sample per pixel (colour, or channels stored as
/// contiguous samples or separate planes) are refused: no channel is ever
/// dropped silently.
pub fn read_channel(path: &Path, channel: Option<usize>) -> anyhow::Result<Recording> {
    let name = path.display();
    let bad = |e: tiff::TiffError| input_error(format!("{name}: not a readable TIFF stack: {e}"));
    let mut decoder = Decoder::new(BufReader::new(open_input(path)?)).map_err(bad)?;
    let channels = imagej_channels(&mut decoder);
    let selected = match (channels, channel) {
        (1, None) => 0,
        (channels, None) => {
            return Err(input_error(format!(
                "{name}: an ImageJ hyperstack with {channels} channels; choose one with --channel (0 to {})",
                channels - 1
            )));
        }
        (channels, Some(channel)) if channel >= channels => {
            return Err(input_error(format!(
                "{name}: --channel {channel} does not exist; the stack has {channels} channel{} (0 to {})",
                if channels == 1 { "" } else { "s" },
                channels - 1
            )));
        }
        (_, Some(channel)) => channel,
    };
    let mut stack = Recording::Counts(FrameStack::default());
    let mut page_index = 0usize;
    loop {
        if page_index % channels == selected {
            let page = read_page(&mut decoder, &name, page_index)?;
            stack
                .append(page)
                .map_err(|e| input_error(format!("{name}: {e}")))?;
        }
        page_index += 1;
        if !decoder.more_images() {
            break;
        }
        decoder.next_image().map_err(bad)?;
    }
    if !page_index.is_multiple_of(channels) {
        return Err(input_error(format!(
            "{name}: {page_index} pages do not divide into the {channels} channels its ImageJ description declares"
        )));
    }
    Ok(stack)
}

/// The `channels=` of an ImageJ description on the first page (1 if the
/// file is not an ImageJ hyperstack).
fn imagej_channels<R: std::io::Read + Seek>(decoder: &mut Decoder<R>) -> usize {
    let description = match decoder.find_tag(Tag::ImageDescription) {
        Ok(Some(value)) => value.into_string().unwrap_or_default(),
        _ => return 1,
    };
    if !description.starts_with("ImageJ=") {
        return 1;
    }
    description
        .lines()
        .find_map(|line| line.trim().strip_prefix("channels="))
        .and_then(|value| value.trim().parse::<usize>().ok())
        .filter(|&channels| channels >= 1)
        .unwrap_or(1)
}

/// Decodes the current page as one frame: counts from integer samples,
/// real values from float samples.
fn read_page<R: std::io::Read + Seek>(
    decoder: &mut Decoder<R>,
    name: &impl std::fmt::Display,
    page_index: usize,
) -> anyhow::Result<Recording> {
    let bad = |e: tiff::TiffError| input_error(format!("{name}: not a readable TIFF stack: {e}"));
    let (width, height) = decoder.dimensions().map_err(bad)?;
    let samples = decoder
        .find_tag_unsigned::<u16>(Tag::SamplesPerPixel)
        .map_err(bad)?
        .unwrap_or(1);
    if samples != 1 {
        return Err(input_error(format!(
            "{name}: page {page_index} has {samples} samples per pixel (colour or channels in one page); save one channel per page (e.g. an ImageJ hyperstack) or one file per channel"
        )));
    }
    let page = decoder.read_image().map_err(bad)?;
    let pixels = (width as usize) * (height as usize);
    let frame = match page {
        DecodingResult::U8(values) => Page::Counts(values.into_iter().map(u32::from).collect()),
        DecodingResult::U16(values) => Page::Counts(values.into_iter().map(u32::from).collect()),
        DecodingResult::U32(values) => Page::Counts(values),
        DecodingResult::U64(values) => Page::Counts(whole_counts(
            name,
            page_index,
            values.into_iter().map(|v| v as f64),
        )?),
        DecodingResult::I8(values) => Page::Counts(whole_counts(
            name,
            page_index,
            values.into_iter().map(f64::from),
        )?),
        DecodingResult::I16(values) => Page::Counts(whole_counts(
            name,
            page_index,
            values.into_iter().map(f64::from),
        )?),
        DecodingResult::I32(values) => Page::Counts(whole_counts(
            name,
            page_index,
            values.into_iter().map(f64::from),
        )?),
        DecodingResult::I64(values) => Page::Counts(whole_counts(
            name,
            page_index,
            values.into_iter().map(|v| v as f64),
        )?),
        DecodingResult::F32(values) => Page::Real(values.into_iter().map(f64::from).collect()),
        DecodingResult::F64(values) => Page::Real(values),
        _ => {
            return Err(input_error(format!(
                "{name}: page {page_index} has an unsupported sample type; expected greyscale counts or float values"
            )));
        }
    };
    let samples = match &frame {
        Page::Counts(values) => values.len(),
        Page::Real(values) => values.len(),
    };
    if samples != pixels {
        return Err(input_error(format!(
            "{name}: page {page_index} is not single-channel greyscale ({samples} samples for {width}×{height} pixels)"
        )));
    }
    let (height, width) = (height as usize, width as usize);
    match frame {
        Page::Counts(counts) => {
            FrameStack::from_vec(1, height, width, counts).map(Recording::Counts)
        }
        Page::Real(values) => RealFrameStack::from_vec(1, height, width, values)
            .map(Recording::Real)
            .map_err(|e| input_error(format!("{name}: page {page_index}: {e}"))),
    }
}

/// One decoded page's samples.
enum Page {
    Counts(Vec<u32>),
    Real(Vec<f64>),
}

/// Integer samples as photon counts: whole and from 0 to `u32::MAX`.
fn whole_counts(
    name: &impl std::fmt::Display,
    page: usize,
    values: impl Iterator<Item = f64>,
) -> anyhow::Result<Vec<u32>> {
    values
        .enumerate()
        .map(|(index, value)| {
            whole_count(value).ok_or_else(|| {
                input_error(format!(
                    "{name}: page {page}, pixel {index}: {value} is not a photon count (0 to {}) in an integer page; save background-subtracted or scaled frames as float pages (docs/detectors.md, \"Input frames\")",
                    u32::MAX
                ))
            })
        })
        .collect()
}
