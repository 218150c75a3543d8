//! Multi-page TIFF frame stacks, one greyscale page per frame.
//!
//! Written as 16-bit pages when every count fits, else 32-bit, uncompressed,
//! which Fiji/ImageJ opens as a stack and tifffile as an `(n, H, W)` array.
//! Read from 8/16/32/64-bit unsigned, signed or float greyscale pages of
//! equal size: integer pages as photon counts (signed values must be ≥ 0),
//! float pages as real values (finite; a stack with any float page is read
//! as real-valued frames), see [`super::npy`]. ImageJ hyperstacks are read
//! one channel and one slice at a time, BigTIFF as classic TIFF, and the
//! acquisition metadata of ImageJ and ScanImage files with the frames
//! ([`read_selected`]).

use std::io::{BufReader, Seek, Write};
use std::path::Path;

use tiff::decoder::{Decoder, DecodingResult};
use tiff::encoder::{TiffEncoder, colortype};
use tiff::tags::Tag;

use super::acquisition::{self, AcquisitionMetadata, MetadataSource};
use super::open_input;
use crate::error::input_error;
use crate::types::frames::whole_count;
use crate::types::{FrameStack, RealFrameStack, Recording};

/// Writes one page per frame.
pub(crate) fn write_frames<W: Write + Seek>(
    writer: &mut W,
    frames: &FrameStack,
) -> anyhow::Result<()> {
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

/// Reads the frames of a TIFF stack, one greyscale page per frame; see
/// [`read_selected`] (this is its channel selection alone, without the
/// metadata).
pub(crate) fn read_channel(path: &Path, channel: Option<usize>) -> anyhow::Result<Recording> {
    let selection = StackSelection {
        channel,
        slice: None,
    };
    Ok(read_selected(path, &selection)?.0)
}

/// Which plane of a hyperstack to read: a channel and a z slice (0-based),
/// `None` where the stack has one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StackSelection {
    pub channel: Option<usize>,
    pub slice: Option<usize>,
}

/// Reads the frames of a TIFF stack (classic or BigTIFF), one greyscale
/// page per frame, and the acquisition metadata the file states
/// ([`AcquisitionMetadata`]: an ImageJ description or ScanImage's header).
///
/// An ImageJ hyperstack (an `ImageDescription` starting `ImageJ=` with
/// `channels=C`, `slices=Z`) stores its pages channel by channel within
/// each slice, slice by slice within each time point; a ScanImage file
/// interleaves the channels it saved. With `C > 1` (or `Z > 1`) the frames
/// of the selected channel (slice) are read in time order, and without a
/// selection the stack is refused rather than read with channels or planes
/// interleaved as time. Pages with more than one sample per pixel (colour,
/// or channels stored as contiguous samples or separate planes) are
/// refused: no channel is ever dropped silently. The frames read so far
/// are checked against the size limits page by page, so a file cannot make
/// the reader hold more than [`MAX_DATASET_PIXELS`](crate::limits::MAX_DATASET_PIXELS).
pub(crate) fn read_selected(
    path: &Path,
    selection: &StackSelection,
) -> anyhow::Result<(Recording, AcquisitionMetadata)> {
    let name = path.display();
    let bad = |e: tiff::TiffError| input_error(format!("{name}: not a readable TIFF stack: {e}"));
    let mut decoder = Decoder::new(BufReader::new(open_input(path)?)).map_err(bad)?;
    let metadata = read_metadata(&mut decoder);
    let channels = metadata.channels;
    let slices = metadata.slices;
    if slices > 1 && metadata.source == MetadataSource::ScanImage {
        return Err(input_error(format!(
            "{name}: a ScanImage z-stack ({slices} slices); a recording is one plane over time: save one plane per file"
        )));
    }
    let choose = |what: &str, flag: &str, count: usize, chosen: Option<usize>| match (count, chosen)
    {
        (1, None | Some(0)) => Ok(0),
        (count, None) => Err(input_error(format!(
            "{name}: a {} with {count} {what}s; choose one with {flag} (0 to {})",
            if what == "slice" {
                "3-D (z) stack"
            } else {
                "hyperstack"
            },
            count - 1
        ))),
        (count, Some(chosen)) if chosen >= count => Err(input_error(format!(
            "{name}: {flag} {chosen} does not exist; the stack has {count} {what}{} (0 to {})",
            if count == 1 { "" } else { "s" },
            count - 1
        ))),
        (_, Some(chosen)) => Ok(chosen),
    };
    let channel = choose("channel", "--channel", channels, selection.channel)?;
    let slice = choose("slice", "--slice", slices, selection.slice)?;
    let mut stack = Recording::Counts(FrameStack::default());
    let mut page_index = 0usize;
    loop {
        if page_index % channels == channel && (page_index / channels) % slices == slice {
            let page = read_page(&mut decoder, &name, page_index)?;
            let (n, height, width) = page.shape();
            crate::limits::check_dataset_size("frame count", stack.shape().0 + n, height, width)
                .map_err(|e| input_error(format!("{name}: {e}")))?;
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
    if !page_index.is_multiple_of(channels * slices) {
        return Err(input_error(format!(
            "{name}: {page_index} pages do not divide into the {channels} channel(s) × {slices} slice(s) its {} metadata declares",
            metadata.source.as_str()
        )));
    }
    Ok((stack, metadata))
}

/// The acquisition metadata of the first page: an ImageJ description, or
/// ScanImage's header in the Software tag or the description (with the
/// frame time stamps of the first two time points' descriptions; the
/// decoder is rewound to the first page).
fn read_metadata<R: std::io::Read + Seek>(decoder: &mut Decoder<R>) -> AcquisitionMetadata {
    let text = |decoder: &mut Decoder<R>, tag: Tag| match decoder.find_tag(tag) {
        Ok(Some(value)) => value.into_string().unwrap_or_default(),
        _ => String::new(),
    };
    let description = text(decoder, Tag::ImageDescription);
    if acquisition::is_imagej(&description) {
        let resolution = match decoder.find_tag(Tag::XResolution) {
            Ok(Some(value)) => value
                .into_u32_vec()
                .ok()
                .filter(|v| v.len() == 2 && v[1] > 0)
                .map(|v| f64::from(v[0]) / f64::from(v[1])),
            _ => None,
        };
        return acquisition::parse_imagej(&description, resolution);
    }
    let software = text(decoder, Tag::Software);
    let header = if acquisition::is_scanimage(&software) {
        software
    } else if acquisition::is_scanimage(&description) {
        description.clone()
    } else {
        return AcquisitionMetadata::none();
    };
    let mut stamps = Vec::new();
    stamps.extend(acquisition::scanimage_timestamp(&description));
    let channels = acquisition::parse_scanimage(&header, &[]).channels;
    if stamps.len() == 1 && decoder.seek_to_image(channels).is_ok() {
        let next = text(decoder, Tag::ImageDescription);
        stamps.extend(acquisition::scanimage_timestamp(&next));
    }
    let metadata = acquisition::parse_scanimage(&header, &stamps);
    if decoder.seek_to_image(0).is_err() {
        return AcquisitionMetadata::none();
    }
    metadata
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
