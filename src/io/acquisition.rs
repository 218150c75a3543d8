//! What a recording's file says about how it was acquired: the ImageJ
//! hyperstack description (channels, slices, frames, frame interval, pixel
//! size) and ScanImage's header (frame rate, line period, lines and pixels
//! per line, fill fraction, zoom, channels saved, slices).
//!
//! Every field is optional: a file says what it says, and the caller
//! (the command line) decides what a missing field means. Parsing is plain
//! text work on `key=value` / `key = value` lines, so it is tested without
//! files; [`super::tiff_stack`] hands it the tags.

/// Where a recording's acquisition metadata came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MetadataSource {
    /// No metadata the readers know (a plain stack or a `.npy`).
    #[default]
    None,
    /// An ImageJ / Fiji hyperstack description.
    ImageJ,
    /// ScanImage's header (`SI.` keys, 2015 and later, or `state.` keys of
    /// ScanImage 3–5).
    ScanImage,
}

impl MetadataSource {
    pub fn as_str(self) -> &'static str {
        match self {
            MetadataSource::None => "none",
            MetadataSource::ImageJ => "imagej",
            MetadataSource::ScanImage => "scanimage",
        }
    }
}

/// The acquisition as a recording's file states it; `None` where it does
/// not. Times are those of the scan model (docs/simulator.md): a line
/// period `L = W·δt + t_retrace`, a frame period `T ≥ H·L`.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AcquisitionMetadata {
    pub source: MetadataSource,
    /// Channels interleaved in the file (1 when it has one or says nothing).
    pub channels: usize,
    /// Slices (z planes) per time point (1 when it has one or says nothing).
    pub slices: usize,
    /// Pixel size, µm (ImageJ's resolution with a micrometre unit).
    pub pixel_size_um: Option<f64>,
    /// Pixel dwell δt, µs (ScanImage: fill fraction × line period / pixels).
    pub dwell_us: Option<f64>,
    /// Line period `L`, ms.
    pub line_period_ms: Option<f64>,
    /// Time of a line without photons, ms (ScanImage: (1 − fill fraction) × L).
    pub retrace_ms: Option<f64>,
    /// Frame period `T`, ms (ScanImage's frame rate or frame time stamps,
    /// ImageJ's `finterval`).
    pub frame_period_ms: Option<f64>,
    /// Lines per frame the acquisition software set.
    pub lines_per_frame: Option<usize>,
    /// Pixels per line the acquisition software set.
    pub pixels_per_line: Option<usize>,
    /// The scan's zoom factor.
    pub zoom: Option<f64>,
    /// Whether lines were scanned in both directions (the scan model
    /// scans every line left to right).
    pub bidirectional: Option<bool>,
}

impl AcquisitionMetadata {
    /// No metadata: one channel, one slice, no timing.
    pub fn none() -> Self {
        Self {
            channels: 1,
            slices: 1,
            ..Self::default()
        }
    }
}

/// The `key=value` (or `key = value`) pairs of a description, keys and
/// values trimmed; later lines win.
fn pairs(text: &str) -> impl Iterator<Item = (&str, &str)> {
    text.lines().filter_map(|line| {
        let (key, value) = line.split_once('=')?;
        Some((
            key.trim(),
            value.trim().trim_matches('\'').trim_matches('"'),
        ))
    })
}

fn value_of<'a>(text: &'a str, key: &str) -> Option<&'a str> {
    pairs(text)
        .filter(|(k, _)| *k == key)
        .map(|(_, v)| v)
        .last()
}

fn number(text: &str, key: &str) -> Option<f64> {
    value_of(text, key)?
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite() && *v > 0.0)
}

fn count(text: &str, key: &str) -> Option<usize> {
    value_of(text, key)?
        .parse::<usize>()
        .ok()
        .filter(|&v| v >= 1)
}

/// Whether a description is an ImageJ hyperstack's.
pub(crate) fn is_imagej(description: &str) -> bool {
    description.starts_with("ImageJ=")
}

/// The ImageJ description's channels, slices, frame interval and unit;
/// `x_resolution` is the XResolution tag (pixels per unit), if any.
pub(crate) fn parse_imagej(description: &str, x_resolution: Option<f64>) -> AcquisitionMetadata {
    let unit = value_of(description, "unit").unwrap_or("");
    let micrometres = matches!(unit, "micron" | "um" | "µm" | "\\u00B5m" | "microns");
    let pixel_size_um = match (x_resolution, micrometres) {
        (Some(per_unit), true) if per_unit.is_finite() && per_unit > 0.0 => Some(1.0 / per_unit),
        _ => None,
    };
    AcquisitionMetadata {
        source: MetadataSource::ImageJ,
        channels: count(description, "channels").unwrap_or(1),
        slices: count(description, "slices").unwrap_or(1),
        pixel_size_um,
        frame_period_ms: number(description, "finterval").map(|s| s * 1e3),
        ..AcquisitionMetadata::none()
    }
}

/// Whether a text (the Software tag or the first page's description) holds
/// ScanImage's header.
pub(crate) fn is_scanimage(text: &str) -> bool {
    text.lines().any(|line| {
        let line = line.trim_start();
        line.starts_with("SI.") || line.starts_with("state.acq.") || line.starts_with("SI4.")
    })
}

/// The number of channels a MATLAB-style list (`[1;2]`, `[1 2]`, `1`) names.
fn list_len(value: &str) -> Option<usize> {
    let inner = value.trim().trim_start_matches('[').trim_end_matches(']');
    let n = inner
        .split([';', ',', ' '])
        .filter(|item| !item.trim().is_empty())
        .count();
    (n >= 1).then_some(n)
}

/// ScanImage's header: `SI.hRoiManager.*`/`SI.hScan2D.*` keys (2015 and
/// later) or `state.acq.*` keys (ScanImage 3–5). `header` holds them (the
/// Software tag or a description); `timestamps_s`, the first pages'
/// `frameTimestamps_sec`, if any (their median step is the frame period
/// when no frame rate is given).
pub(crate) fn parse_scanimage(header: &str, timestamps_s: &[f64]) -> AcquisitionMetadata {
    let modern = header.contains("SI.");
    let key = |modern_key: &str, legacy_key: &str| {
        if modern {
            number(header, modern_key)
        } else {
            number(header, legacy_key)
        }
    };
    let pixels_per_line = if modern {
        count(header, "SI.hRoiManager.pixelsPerLine")
    } else {
        count(header, "state.acq.pixelsPerLine")
    };
    let lines_per_frame = if modern {
        count(header, "SI.hRoiManager.linesPerFrame")
    } else {
        count(header, "state.acq.linesPerFrame")
    };
    let line_period_ms = if modern {
        number(header, "SI.hRoiManager.linePeriod").map(|s| s * 1e3)
    } else {
        number(header, "state.acq.msPerLine")
    };
    let fill = if modern {
        number(header, "SI.hScan2D.fillFractionTemporal")
    } else {
        number(header, "state.acq.fillFraction")
    }
    .filter(|&f| f <= 1.0);
    let frame_rate = key("SI.hRoiManager.scanFrameRate", "state.acq.frameRate");
    let stamped = {
        let mut steps: Vec<f64> = timestamps_s
            .windows(2)
            .map(|w| w[1] - w[0])
            .filter(|d| d.is_finite() && *d > 0.0)
            .collect();
        steps.sort_by(f64::total_cmp);
        steps.get(steps.len() / 2).copied()
    };
    let frame_period_ms = frame_rate
        .map(|rate| 1e3 / rate)
        .or(stamped.map(|s| s * 1e3));
    let dwell_us = match (line_period_ms, fill, pixels_per_line) {
        (Some(line), Some(fill), Some(pixels)) => Some(line * 1e3 * fill / pixels as f64),
        _ => None,
    };
    let retrace_ms = match (line_period_ms, fill) {
        (Some(line), Some(fill)) => Some(line * (1.0 - fill)),
        _ => None,
    };
    let channels = if modern {
        value_of(header, "SI.hChannels.channelSave").and_then(list_len)
    } else {
        count(header, "state.acq.numberOfChannelsSave")
    }
    .unwrap_or(1);
    let slices = if modern {
        // Only a stack that was acquired as one has slices in its pages.
        let enabled = value_of(header, "SI.hStackManager.enable")
            .map(|v| v == "true" || v == "1")
            .unwrap_or(true);
        count(header, "SI.hStackManager.numSlices")
            .filter(|_| enabled)
            .unwrap_or(1)
    } else {
        count(header, "state.acq.numberOfZSlices").unwrap_or(1)
    };
    let bidirectional = if modern {
        value_of(header, "SI.hScan2D.bidirectional").map(|v| v == "true" || v == "1")
    } else {
        value_of(header, "state.acq.bidirectionalScan").map(|v| v == "1")
    };
    AcquisitionMetadata {
        source: MetadataSource::ScanImage,
        channels,
        slices,
        pixel_size_um: None,
        dwell_us,
        line_period_ms,
        retrace_ms,
        frame_period_ms,
        lines_per_frame,
        pixels_per_line,
        zoom: key("SI.hRoiManager.scanZoomFactor", "state.acq.zoomFactor"),
        bidirectional,
    }
}

/// The `frameTimestamps_sec` of a ScanImage page's description.
pub(crate) fn scanimage_timestamp(description: &str) -> Option<f64> {
    value_of(description, "frameTimestamps_sec")?
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn imagej_hyperstack_description() {
        let text = "ImageJ=1.11a\nimages=12\nchannels=2\nslices=3\nframes=2\nhyperstack=true\nunit=micron\nfinterval=0.05\n";
        let meta = parse_imagej(text, Some(10.0));
        assert_eq!((meta.channels, meta.slices), (2, 3));
        assert_eq!(meta.pixel_size_um, Some(0.1));
        assert!((meta.frame_period_ms.unwrap() - 50.0).abs() < 1e-9);
        // Without a micrometre unit the resolution says nothing.
        assert_eq!(
            parse_imagej("ImageJ=1\nunit=inch\n", Some(10.0)).pixel_size_um,
            None
        );
    }

    #[test]
    fn scanimage_header_maps_to_scan_timing() {
        let text = "SI.hRoiManager.scanFrameRate = 20\nSI.hRoiManager.linePeriod = 0.001\nSI.hRoiManager.pixelsPerLine = 50\nSI.hRoiManager.linesPerFrame = 40\nSI.hScan2D.fillFractionTemporal = 0.2\nSI.hRoiManager.scanZoomFactor = 2\nSI.hChannels.channelSave = [1;2]\nSI.hScan2D.bidirectional = false\n";
        assert!(is_scanimage(text));
        let meta = parse_scanimage(text, &[]);
        assert!((meta.dwell_us.unwrap() - 4.0).abs() < 1e-9);
        assert!((meta.retrace_ms.unwrap() - 0.8).abs() < 1e-9);
        assert!((meta.frame_period_ms.unwrap() - 50.0).abs() < 1e-9);
        assert_eq!(meta.channels, 2);
        assert_eq!(meta.bidirectional, Some(false));
        assert_eq!(
            (meta.lines_per_frame, meta.pixels_per_line),
            (Some(40), Some(50))
        );
        // Time stamps give the frame period when the rate is missing.
        let meta = parse_scanimage("SI.VERSION_MAJOR = 2020\n", &[0.0, 0.05, 0.1]);
        assert!((meta.frame_period_ms.unwrap() - 50.0).abs() < 1e-9);
        assert_eq!(
            scanimage_timestamp("frameNumbers = 3\nframeTimestamps_sec = 0.125\n"),
            Some(0.125)
        );
    }
}
