//! Figures as PNG and SVG, drawn with plotters.
//!
//! Every figure is written twice, `NAME.png` and `NAME.svg`. Text is drawn
//! with the TrueType font embedded in the binary ([`EMBEDDED_FONT`], Roboto
//! Regular, Apache-2.0, see `assets/fonts/`), so figures look the same on
//! every machine. `SCANLOC_FONT=/path/to/font.ttf` uses another font; if
//! that file cannot be read, is not a regular file of at most
//! [`MAX_FONT_BYTES`] (a FIFO or a device is not read from at all) or is
//! not a TrueType font, a one-line warning is logged and the embedded font
//! is used.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::Context;
use plotters::coord::Shift;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;

use crate::error::input_error;

/// Roboto Regular (Google, Apache License 2.0; `assets/fonts/README.md`).
pub(crate) const EMBEDDED_FONT: &[u8] = include_bytes!("../../assets/fonts/Roboto-Regular.ttf");

/// The environment variable naming a TrueType font file to draw text with.
pub(crate) const FONT_VARIABLE: &str = crate::env_vars::SCANLOC_FONT;

/// Registers the font figures are drawn with, as plotters' `sans-serif`:
/// the file `requested` (the value of `SCANLOC_FONT`) if it is a readable
/// TrueType font, else the embedded one. Returns a one-line warning saying
/// why the requested file was not used, if it was not.
fn register_figure_font(requested: Option<&Path>) -> Result<Option<String>, String> {
    let register = |bytes: &'static [u8]| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok()
    };
    let mut warning = None;
    if let Some(path) = requested {
        let problem = match read_font_file(path) {
            Ok(bytes) => {
                // plotters keeps fonts for the life of the process.
                if register(Box::leak(bytes.into_boxed_slice())) {
                    return Ok(None);
                }
                "not a TrueType font".to_string()
            }
            Err(problem) => problem,
        };
        warning = Some(format!(
            "{FONT_VARIABLE}={}: {problem}; figures use the embedded font instead",
            path.display()
        ));
    }
    if register(EMBEDDED_FONT) {
        Ok(warning)
    } else {
        Err("the embedded figure font could not be loaded".to_string())
    }
}

/// Largest font file `SCANLOC_FONT` may name: TrueType fonts with every
/// CJK glyph are about 20 MB.
pub(crate) const MAX_FONT_BYTES: u64 = 64 << 20;

/// The bytes of the font file `path`, if it is a regular file (after
/// symbolic links) of at most [`MAX_FONT_BYTES`]; else why not. A FIFO, a
/// device such as /dev/zero or a folder is refused without reading from
/// it: the file is opened without blocking and checked before any read,
/// and the read stops at the bound whatever the file does meanwhile.
fn read_font_file(path: &Path) -> Result<Vec<u8>, String> {
    use std::io::Read as _;
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        // Opening a FIFO for reading would otherwise wait for a writer.
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options
        .open(path)
        .map_err(|error| format!("cannot read it ({error})"))?;
    let metadata = file
        .metadata()
        .map_err(|error| format!("cannot read it ({error})"))?;
    if !metadata.is_file() {
        return Err("not a regular file".to_string());
    }
    if metadata.len() > MAX_FONT_BYTES {
        return Err(format!(
            "{} bytes, more than the {} MiB a font file may have",
            metadata.len(),
            MAX_FONT_BYTES >> 20
        ));
    }
    let mut bytes = Vec::new();
    file.take(MAX_FONT_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|error| format!("cannot read it ({error})"))?;
    if bytes.len() as u64 > MAX_FONT_BYTES {
        return Err(format!(
            "more than the {} MiB a font file may have",
            MAX_FONT_BYTES >> 20
        ));
    }
    Ok(bytes)
}

/// Registers the figure font once per process, logging the warning of
/// [`register_figure_font`] if there is one.
fn ensure_font() -> anyhow::Result<()> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            let requested = std::env::var_os(FONT_VARIABLE).map(PathBuf::from);
            let warning = register_figure_font(requested.as_deref())?;
            if let Some(warning) = warning {
                tracing::warn!("{warning}");
            }
            Ok(())
        })
        .clone()
        .map_err(input_error)
}

/// A marker drawn on a frame panel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MarkerKind {
    /// Start of the trajectory (green circle).
    Start,
    /// End of the trajectory (cyan circle).
    End,
    /// The ground-truth trajectory centroid (green cross).
    Truth,
    /// A CNN prediction (blue cross).
    Cnn,
    /// A Crocker–Grier/TrackPy prediction (purple cross).
    CrockerGrier,
}

impl MarkerKind {
    fn colour(self) -> RGBColor {
        match self {
            MarkerKind::Start => RGBColor(0, 200, 0),
            MarkerKind::End => RGBColor(0, 220, 220),
            MarkerKind::Truth => RGBColor(0, 230, 0),
            MarkerKind::Cnn => RGBColor(40, 110, 255),
            MarkerKind::CrockerGrier => RGBColor(200, 60, 220),
        }
    }

    /// Legend text.
    pub fn label(self) -> &'static str {
        match self {
            MarkerKind::Start => "start",
            MarkerKind::End => "end",
            MarkerKind::Truth => "trajectory centroid",
            MarkerKind::Cnn => "CNN",
            MarkerKind::CrockerGrier => "Crocker–Grier",
        }
    }
}

/// One frame shown as an image, with an optional trajectory and markers,
/// all in TrackPy pixel coordinates.
#[derive(Debug, Clone)]
pub struct FramePanel {
    pub title: String,
    pub height: usize,
    pub width: usize,
    pub counts: Vec<u32>,
    pub trajectory: Vec<(f64, f64)>,
    pub markers: Vec<(MarkerKind, f64, f64)>,
}

/// One named curve of (x, y) points.
#[derive(Debug, Clone)]
pub struct Curve {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// Draws frame panels side by side (grey-scale counts, the trajectory as a
/// green line, markers as circles and crosses), as `base.png`/`base.svg`.
pub fn frame_panels(base: &Path, panels: &[FramePanel]) -> anyhow::Result<()> {
    let columns = panels.len().max(1) as u32;
    let size = (300 * columns, 340);
    write_figure(
        base,
        size,
        |root| draw_frame_panels(root, panels),
        |root| draw_frame_panels(root, panels),
    )
}

/// Writes a figure whose drawing code is generic over the backend: the two
/// closures are the same function instantiated for PNG and SVG.
fn write_figure(
    base: &Path,
    size: (u32, u32),
    draw_svg: impl Fn(&DrawingArea<SVGBackend, Shift>) -> anyhow::Result<()>,
    draw_png: impl Fn(&DrawingArea<BitMapBackend, Shift>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    ensure_font()?;
    if let Some(parent) = base.parent() {
        std::fs::create_dir_all(parent)
            .map_err(|e| input_error(format!("{}: cannot create: {e}", parent.display())))?;
    }
    // Append the extensions: names like `pr_test-0.75_eps1` contain dots.
    let with_suffix = |suffix: &str| {
        let mut name = base.as_os_str().to_owned();
        name.push(suffix);
        PathBuf::from(name)
    };
    let png = with_suffix(".png");
    let svg = with_suffix(".svg");
    // Through the one output writer (see `io::PendingFile`): the backends
    // draw into its temporary file, which is renamed into place when done.
    let png_out = crate::io::PendingFile::create(&png)?;
    let svg_out = crate::io::PendingFile::create(&svg)?;
    {
        let root = BitMapBackend::new(png_out.temporary_path(), size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_error)?;
        draw_png(&root).with_context(|| format!("drawing {}", png.display()))?;
        root.present().map_err(plot_error)?;
    }
    {
        let root = SVGBackend::new(svg_out.temporary_path(), size).into_drawing_area();
        root.fill(&WHITE).map_err(plot_error)?;
        draw_svg(&root).with_context(|| format!("drawing {}", svg.display()))?;
        root.present().map_err(plot_error)?;
    }
    png_out.commit()?;
    svg_out.commit()
}

fn plot_error<E: std::fmt::Debug>(error: E) -> anyhow::Error {
    anyhow::anyhow!("plotting failed: {error:?}")
}

/// The chart of one frame panel: its title, pixel axes (rows growing
/// downwards, as in an image) and the frame's counts in grey scale.
type FrameChart<'a, DB> = ChartContext<'a, DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>;

fn draw_frame<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    title: &str,
    (height, width): (usize, usize),
    counts: &[u32],
) -> anyhow::Result<FrameChart<'a, DB>> {
    let (w, h) = (width as f64, height as f64);
    let mut chart = ChartBuilder::on(area)
        .caption(title, ("sans-serif", 16))
        .margin(8)
        .x_label_area_size(22)
        .y_label_area_size(28)
        // Rows grow downwards, as in an image.
        .build_cartesian_2d(-0.5..w - 0.5, h - 0.5..-0.5)
        .map_err(plot_error)?;
    chart
        .configure_mesh()
        .disable_mesh()
        .x_labels(5)
        .y_labels(5)
        .label_style(("sans-serif", 11))
        .draw()
        .map_err(plot_error)?;
    let max = counts.iter().copied().max().unwrap_or(1).max(1) as f64;
    let min = counts.iter().copied().min().unwrap_or(0) as f64;
    let span = (max - min).max(1.0);
    chart
        .draw_series(counts.iter().enumerate().map(|(i, &count)| {
            let (row, column) = ((i / width) as f64, (i % width) as f64);
            let level = (255.0 * (count as f64 - min) / span) as u8;
            Rectangle::new(
                [(column - 0.5, row - 0.5), (column + 0.5, row + 0.5)],
                RGBColor(level, level, level).filled(),
            )
        }))
        .map_err(plot_error)?;
    Ok(chart)
}

fn draw_frame_panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    panels: &[FramePanel],
) -> anyhow::Result<()> {
    let areas = root.split_evenly((1, panels.len().max(1)));
    for (area, panel) in areas.iter().zip(panels) {
        let mut chart = draw_frame(
            area,
            &panel.title,
            (panel.height, panel.width),
            &panel.counts,
        )?;
        if !panel.trajectory.is_empty() {
            chart
                .draw_series(LineSeries::new(
                    panel.trajectory.iter().copied(),
                    RGBColor(0, 200, 0).stroke_width(1),
                ))
                .map_err(plot_error)?;
        }
        for &(kind, x, y) in &panel.markers {
            let style = kind.colour().stroke_width(2);
            match kind {
                MarkerKind::Start | MarkerKind::End => {
                    chart
                        .draw_series(std::iter::once(Circle::new((x, y), 6, style)))
                        .map_err(plot_error)?;
                }
                _ => {
                    chart
                        .draw_series(std::iter::once(Cross::new((x, y), 6, style)))
                        .map_err(plot_error)?;
                }
            }
        }
    }
    Ok(())
}

/// One frame of a recording with tracks over a window of frames around
/// it, in TrackPy pixel coordinates: the truth's tracks as thick green
/// lines, the estimated tracks as thin lines, one colour per track; where
/// a track is in the shown frame, a circle (truth) or a cross (estimate).
#[derive(Debug, Clone)]
pub(crate) struct TrackPanel {
    pub title: String,
    pub height: usize,
    pub width: usize,
    pub counts: Vec<u32>,
    /// Each truth track's points over the window, in frame order.
    pub truth: Vec<Vec<(f64, f64)>>,
    pub tracks: Vec<Vec<(f64, f64)>>,
    /// The truth's and the tracks' points in the shown frame.
    pub truth_now: Vec<(f64, f64)>,
    pub tracks_now: Vec<(f64, f64)>,
}

/// Draws track panels side by side, as `base.png`/`base.svg`.
pub(crate) fn track_panels(base: &Path, panels: &[TrackPanel]) -> anyhow::Result<()> {
    let columns = panels.len().max(1) as u32;
    write_figure(
        base,
        (360 * columns, 400),
        |root| draw_track_panels(root, panels),
        |root| draw_track_panels(root, panels),
    )
}

/// The colour of estimated tracks (the palette without its green, the
/// truth's colour).
fn track_colour(index: usize) -> RGBColor {
    const COLOURS: [RGBColor; 5] = [PALETTE[0], PALETTE[1], PALETTE[3], PALETTE[4], PALETTE[5]];
    COLOURS[index % COLOURS.len()]
}

fn draw_track_panels<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    panels: &[TrackPanel],
) -> anyhow::Result<()> {
    let areas = root.split_evenly((1, panels.len().max(1)));
    let green = MarkerKind::Truth.colour();
    for (area, panel) in areas.iter().zip(panels) {
        let mut chart = draw_frame(
            area,
            &panel.title,
            (panel.height, panel.width),
            &panel.counts,
        )?;
        for path in &panel.truth {
            chart
                .draw_series(LineSeries::new(
                    path.iter().copied(),
                    green.mix(0.8).stroke_width(3),
                ))
                .map_err(plot_error)?;
        }
        for (index, path) in panel.tracks.iter().enumerate() {
            chart
                .draw_series(LineSeries::new(
                    path.iter().copied(),
                    track_colour(index).stroke_width(2),
                ))
                .map_err(plot_error)?;
        }
        chart
            .draw_series(
                panel
                    .truth_now
                    .iter()
                    .map(|&p| Circle::new(p, 6, green.stroke_width(2))),
            )
            .map_err(plot_error)?;
        chart
            .draw_series(
                panel
                    .tracks_now
                    .iter()
                    .map(|&p| Cross::new(p, 5, PALETTE[1].stroke_width(2))),
            )
            .map_err(plot_error)?;
    }
    Ok(())
}

/// Estimates with intervals against the true value, one series per
/// estimator: each point a filled circle with its interval as a vertical
/// bar, a series' `scatter` as light dots in its colour, and the identity
/// line. Series are set slightly apart along x so that estimates of the
/// same true value do not hide each other; what lies above the y range is
/// left out (intervals are cut at its top).
#[derive(Debug, Clone)]
pub(crate) struct EstimateChart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// Both axes run from 0 to this.
    pub x_max: f64,
    pub y_max: f64,
    pub series: Vec<EstimateSeries>,
}

/// One estimator's estimates: (true value, estimate, low, high) and,
/// lighter, single estimates as (true value, estimate).
#[derive(Debug, Clone)]
pub(crate) struct EstimateSeries {
    pub label: String,
    pub points: Vec<(f64, f64, f64, f64)>,
    pub scatter: Vec<(f64, f64)>,
}

/// Draws `chart` as `base.png`/`base.svg`.
pub(crate) fn estimate_chart(base: &Path, chart: &EstimateChart) -> anyhow::Result<()> {
    write_figure(
        base,
        (640, 520),
        |root| draw_estimate_chart(root, chart),
        |root| draw_estimate_chart(root, chart),
    )
}

fn draw_estimate_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &EstimateChart,
) -> anyhow::Result<()> {
    let valid = |v: f64, max: f64| v.is_finite() && (0.0..=max).contains(&v);
    let (x_max, y_max) = (chart.x_max.max(1e-9), chart.y_max.max(1e-9));
    let mut plot = ChartBuilder::on(root)
        .caption(&chart.title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(52)
        .build_cartesian_2d(0.0..x_max, 0.0..y_max)
        .map_err(plot_error)?;
    plot.configure_mesh()
        .x_desc(chart.x_label.as_str())
        .y_desc(chart.y_label.as_str())
        .x_label_formatter(&compact_number)
        .y_label_formatter(&compact_number)
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    let grey = RGBColor(120, 120, 120);
    let top = x_max.min(y_max);
    plot.draw_series(LineSeries::new(
        [(0.0, 0.0), (top, top)],
        grey.stroke_width(1),
    ))
    .map_err(plot_error)?
    .label("estimate = truth")
    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], grey.stroke_width(1)));
    let count = chart.series.len();
    for (index, series) in chart.series.iter().enumerate() {
        let colour = PALETTE[index % PALETTE.len()];
        let shift = (index as f64 - (count as f64 - 1.0) / 2.0) * 0.012 * x_max;
        plot.draw_series(
            series
                .scatter
                .iter()
                .filter(|&&(x, y)| valid(x + shift, x_max) && valid(y, y_max))
                .map(|&(x, y)| Circle::new((x + shift, y), 2, colour.mix(0.3).filled())),
        )
        .map_err(plot_error)?;
        let points: Vec<(f64, f64, f64, f64)> = series
            .points
            .iter()
            .filter(|&&(x, y, _, _)| valid(x + shift, x_max) && valid(y, y_max))
            .map(|&(x, y, low, high)| {
                let cut = |v: f64| {
                    if v.is_finite() {
                        v.clamp(0.0, y_max)
                    } else {
                        y_max
                    }
                };
                (x + shift, y, cut(low), cut(high))
            })
            .collect();
        let cap = 0.008 * x_max;
        for &(x, _, low, high) in &points {
            plot.draw_series(std::iter::once(PathElement::new(
                vec![(x, low), (x, high)],
                colour.stroke_width(2),
            )))
            .map_err(plot_error)?;
            plot.draw_series([low, high].map(|v| {
                PathElement::new(vec![(x - cap, v), (x + cap, v)], colour.stroke_width(2))
            }))
            .map_err(plot_error)?;
        }
        plot.draw_series(
            points
                .iter()
                .map(|&(x, y, _, _)| Circle::new((x, y), 5, colour.filled())),
        )
        .map_err(plot_error)?
        .label(series.label.clone())
        .legend(move |(x, y)| Circle::new((x + 9, y), 5, colour.filled()));
    }
    plot.configure_series_labels()
        .position(SeriesLabelPosition::UpperLeft)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

/// Line chart of named curves (e.g. precision against recall), as
/// `base.png`/`base.svg`.
pub fn line_chart(
    base: &Path,
    title: &str,
    axes: (&str, &str),
    range: ((f64, f64), (f64, f64)),
    curves: &[Curve],
) -> anyhow::Result<()> {
    write_figure(
        base,
        (640, 480),
        |root| draw_line_chart(root, title, axes, range, curves),
        |root| draw_line_chart(root, title, axes, range, curves),
    )
}

fn draw_line_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    axes: (&str, &str),
    ((x0, x1), (y0, y1)): ((f64, f64), (f64, f64)),
    curves: &[Curve],
) -> anyhow::Result<()> {
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(36)
        .y_label_area_size(48)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(plot_error)?;
    chart
        .configure_mesh()
        .x_desc(axes.0)
        .y_desc(axes.1)
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    for (index, curve) in curves.iter().enumerate() {
        let colour = PALETTE[index % PALETTE.len()];
        chart
            .draw_series(LineSeries::new(
                curve.points.iter().copied(),
                colour.stroke_width(2),
            ))
            .map_err(plot_error)?
            .label(curve.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

/// A run-time-against-error chart: every setting as a circle, the Pareto
/// front as a line through its settings, an optional floor (e.g. the
/// Cramér–Rao bound) as a horizontal line. Both axes are logarithmic, since
/// settings differ by orders of magnitude in speed and in error; values
/// must be positive (others are left out).
#[derive(Debug, Clone)]
pub(crate) struct TradeoffChart {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    /// Every setting, (cost or speed, error).
    pub points: Vec<(f64, f64)>,
    /// The Pareto front, in the order to join it.
    pub front: Vec<(f64, f64)>,
    /// The same settings' error on a static QD (D = 0), drawn as triangles
    /// to compare with the floor (empty: none drawn).
    pub static_points: Vec<(f64, f64)>,
    /// A labelled horizontal line.
    pub floor: Option<(String, f64)>,
}

/// Draws `chart` as `base.png`/`base.svg`.
pub(crate) fn tradeoff_chart(base: &Path, chart: &TradeoffChart) -> anyhow::Result<()> {
    write_figure(
        base,
        (720, 520),
        |root| draw_tradeoff_chart(root, chart),
        |root| draw_tradeoff_chart(root, chart),
    )
}

/// A positive axis range holding `values` (finite, > 0) with some room
/// either side: at least a factor 10 wide, so a logarithmic axis has labels.
fn log_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (low, high) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
            (lo.min(v), hi.max(v))
        });
    if !low.is_finite() {
        return (0.1, 10.0);
    }
    let (low, high) = if high / low < 10.0 {
        let middle = (low * high).sqrt();
        (middle / 3.2, middle * 3.2)
    } else {
        (low, high)
    };
    (low / 1.3, high * 1.3)
}

/// A tick label with at most three significant digits and no trailing
/// zeros (`0.0025`, `1.5`, `12000`).
fn compact_number(value: &f64) -> String {
    if *value == 0.0 || !value.is_finite() {
        return format!("{value}");
    }
    let digits = (2 - value.abs().log10().floor() as i32).max(0) as usize;
    let text = format!("{value:.digits$}");
    if text.contains('.') {
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        text
    }
}

/// Speeds and costs that span more than this factor get a logarithmic axis.
const LOG_AXIS_SPAN: f64 = 20.0;

fn draw_tradeoff_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &TradeoffChart,
) -> anyhow::Result<()> {
    let (low, high) = log_range(chart.points.iter().map(|p| p.0));
    if high / low > LOG_AXIS_SPAN * 1.69 {
        draw_tradeoff_chart_on(root, chart, (low..high).log_scale())
    } else {
        let top = chart
            .points
            .iter()
            .map(|p| p.0)
            .filter(|x| x.is_finite())
            .fold(0.0f64, f64::max);
        draw_tradeoff_chart_on(root, chart, 0.0..(top * 1.1).max(1e-9))
    }
}

/// What a trade-off chart draws on its log axes: its points, its front and
/// its static-QD points (those with both coordinates finite and > 0), and
/// the range of the y axis.
struct TradeoffSeries {
    points: Vec<(f64, f64)>,
    front: Vec<(f64, f64)>,
    static_points: Vec<(f64, f64)>,
    y_range: (f64, f64),
}

impl TradeoffSeries {
    fn of(chart: &TradeoffChart) -> Self {
        let positive = |&(x, y): &(f64, f64)| x.is_finite() && y.is_finite() && x > 0.0 && y > 0.0;
        let kept = |series: &[(f64, f64)]| series.iter().copied().filter(positive).collect();
        let points: Vec<(f64, f64)> = kept(&chart.points);
        let static_points: Vec<(f64, f64)> = kept(&chart.static_points);
        let (y0, y1) = log_range(
            points
                .iter()
                .chain(&static_points)
                .map(|p| p.1)
                .chain(chart.floor.as_ref().map(|f| f.1)),
        );
        Self {
            front: kept(&chart.front),
            points,
            static_points,
            // Headroom above the data for the legend.
            y_range: (y0, y1 * (y1 / y0).powf(0.35)),
        }
    }
}

fn draw_tradeoff_chart_on<DB, X>(
    root: &DrawingArea<DB, Shift>,
    chart: &TradeoffChart,
    x_range: X,
) -> anyhow::Result<()>
where
    DB: DrawingBackend,
    X: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
{
    let TradeoffSeries {
        points,
        front,
        static_points,
        y_range: (y0, y1),
    } = TradeoffSeries::of(chart);
    let mut plot = ChartBuilder::on(root)
        .caption(&chart.title, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(x_range, (y0..y1).log_scale())
        .map_err(plot_error)?;
    let (x0, x1) = {
        let range = plot.x_range();
        (range.start, range.end)
    };
    plot.configure_mesh()
        .x_desc(chart.x_label.as_str())
        .y_desc(chart.y_label.as_str())
        .x_labels(8)
        .y_labels(12)
        .x_label_formatter(&compact_number)
        .y_label_formatter(&compact_number)
        .label_style(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    let grey = RGBColor(120, 120, 120);
    plot.draw_series(
        points
            .iter()
            .map(|&p| Circle::new(p, 4, grey.stroke_width(1))),
    )
    .map_err(plot_error)?
    .label("setting")
    .legend(move |(x, y)| Circle::new((x + 9, y), 4, grey.stroke_width(1)));
    let front_colour = PALETTE[3];
    plot.draw_series(LineSeries::new(
        front.iter().copied(),
        front_colour.stroke_width(2),
    ))
    .map_err(plot_error)?
    .label("Pareto front")
    .legend(move |(x, y)| {
        PathElement::new(vec![(x, y), (x + 18, y)], front_colour.stroke_width(2))
    });
    plot.draw_series(
        front
            .iter()
            .map(|&p| Circle::new(p, 4, front_colour.filled())),
    )
    .map_err(plot_error)?;
    if !static_points.is_empty() {
        let static_colour = PALETTE[0];
        plot.draw_series(
            static_points
                .iter()
                .map(|&p| TriangleMarker::new(p, 5, static_colour.stroke_width(1))),
        )
        .map_err(plot_error)?
        .label("setting, precision on a static QD (D = 0)")
        .legend(move |(x, y)| TriangleMarker::new((x + 9, y), 5, static_colour.stroke_width(1)));
    }
    if let Some((label, floor)) = &chart.floor
        && *floor > 0.0
        && floor.is_finite()
    {
        let floor_colour = PALETTE[2];
        plot.draw_series(LineSeries::new(
            [(x0.max(f64::MIN_POSITIVE), *floor), (x1, *floor)],
            floor_colour.stroke_width(2),
        ))
        .map_err(plot_error)?
        .label(label.clone())
        .legend(move |(x, y)| {
            PathElement::new(vec![(x, y), (x + 18, y)], floor_colour.stroke_width(2))
        });
    }
    plot.configure_series_labels()
        .position(SeriesLabelPosition::UpperRight)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 12))
        .draw()
        .map_err(plot_error)?;
    Ok(())
}

/// Overlaid histograms (as step lines of frequencies per bin) of named
/// samples, as `base.png`/`base.svg`. Values above `max` fall in the last bin.
pub fn histograms(
    base: &Path,
    title: &str,
    x_label: &str,
    max: f64,
    bins: usize,
    series: &[(String, Vec<f64>)],
) -> anyhow::Result<()> {
    let bins = bins.max(1);
    let width = max / bins as f64;
    let curves: Vec<Curve> = series
        .iter()
        .map(|(label, values)| {
            let mut counts = vec![0usize; bins];
            for &value in values.iter().filter(|v| v.is_finite()) {
                let bin = ((value / width).floor().max(0.0) as usize).min(bins - 1);
                counts[bin] += 1;
            }
            let total = values.len().max(1) as f64;
            let mut points = Vec::with_capacity(2 * bins);
            for (bin, &count) in counts.iter().enumerate() {
                let frequency = count as f64 / total;
                points.push((bin as f64 * width, frequency));
                points.push(((bin + 1) as f64 * width, frequency));
            }
            Curve {
                label: label.clone(),
                points,
            }
        })
        .collect();
    let top = curves
        .iter()
        .flat_map(|c| c.points.iter().map(|p| p.1))
        .fold(0.0f64, f64::max)
        .max(1e-3)
        * 1.1;
    line_chart(
        base,
        title,
        (x_label, "fraction of frames"),
        ((0.0, max), (0.0, top)),
        &curves,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_embedded_font_is_used_without_scanloc_font() {
        assert_eq!(register_figure_font(None), Ok(None));
    }

    #[test]
    fn a_missing_or_broken_scanloc_font_falls_back_with_one_warning_line() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("no-such-font.ttf");
        let warning = register_figure_font(Some(&missing)).unwrap().unwrap();
        assert!(warning.starts_with("SCANLOC_FONT="), "{warning}");
        assert!(warning.contains("cannot read it"), "{warning}");
        assert!(!warning.contains('\n'), "{warning}");

        let broken = dir.path().join("broken.ttf");
        std::fs::write(&broken, b"not a font").unwrap();
        let warning = register_figure_font(Some(&broken)).unwrap().unwrap();
        assert!(warning.contains("not a TrueType font"), "{warning}");
    }

    #[cfg(unix)]
    #[test]
    fn a_scanloc_font_that_is_no_regular_file_or_too_large_falls_back_without_hanging() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("font.fifo");
        let name = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path; mkfifo only creates a file.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
        let link = dir.path().join("zero.ttf");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let large = dir.path().join("large.ttf");
        std::fs::File::create(&large)
            .unwrap()
            .set_len(MAX_FONT_BYTES + 1)
            .unwrap();
        for (path, problem) in [
            (Path::new("/dev/zero"), "not a regular file"),
            (link.as_path(), "not a regular file"),
            (fifo.as_path(), "not a regular file"),
            (dir.path(), "not a regular file"),
            (large.as_path(), "more than the 64 MiB"),
        ] {
            let warning = register_figure_font(Some(path)).unwrap().unwrap();
            assert!(warning.contains(problem), "{warning}");
            assert!(!warning.contains('\n'), "{warning}");
        }
    }

    #[test]
    fn a_readable_scanloc_font_is_used_without_warning() {
        let dir = tempfile::tempdir().unwrap();
        let font = dir.path().join("font.ttf");
        std::fs::write(&font, EMBEDDED_FONT).unwrap();
        assert_eq!(register_figure_font(Some(&font)), Ok(None));
    }

    #[test]
    fn figures_are_written_after_a_font_fallback() {
        let dir = tempfile::tempdir().unwrap();
        register_figure_font(Some(&dir.path().join("missing.ttf"))).unwrap();
        let base = dir.path().join("chart");
        let curves = [Curve {
            label: "ε = 1 px".into(),
            points: vec![(0.0, 1.0), (1.0, 0.5)],
        }];
        line_chart(
            &base,
            "PR",
            ("recall", "precision"),
            ((0.0, 1.0), (0.0, 1.0)),
            &curves,
        )
        .unwrap();
        let png = std::fs::read(dir.path().join("chart.png")).unwrap();
        assert_eq!(&png[1..4], b"PNG");
        let svg = std::fs::read_to_string(dir.path().join("chart.svg")).unwrap();
        assert!(svg.contains("ε = 1 px"));
    }
}
