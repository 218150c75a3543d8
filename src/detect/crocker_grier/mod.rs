//! The Crocker–Grier locator, step for step as TrackPy 0.7's `locate`
//! (Crocker & Grier, J. Colloid Interface Sci. 179:298, 1996).
//!
//! 1. Band pass (`filters::bandpass`): a Gaussian low pass of width
//!    `noise_size` minus a boxcar background of side `smoothing_size`, values
//!    below `threshold` set to 0.
//! 2. Integer rescaling: the band-passed image is scaled so its maximum is
//!    the largest value of the input's integer type and truncated to
//!    integers (TrackPy's `convert_to_int`); masses are divided by the same
//!    factor at the end.
//! 3. Local maxima: pixels equal to the grey dilation of the image over a
//!    square of side `⌊2·separation/√2⌋`, brighter than the `percentile`-th
//!    percentile of the non-zero pixels, and at least `margin` from the edge.
//! 4. Refinement: the centroid in a circular mask of radius `diameter/2`,
//!    moving the mask by a pixel while the centroid is more than 0.6 px off
//!    centre, up to `max_iterations` times.
//! 5. Characterisation: mass, radius of gyration (`size`), eccentricity,
//!    peak (`signal`), mass in the raw image (`raw_mass`) and the static
//!    error `ep` from the background noise.
//! 6. Of features closer than `separation`, the dimmer is dropped; then
//!    `minmass`, `maxsize` and `topn` filter.
//!
//! Input frames are integer counts ([`crate::types::FrameStack`]): like TrackPy on a
//! `uint16` array (or `uint32` when a count exceeds 65,535), which sets the
//! rescaling range; or real values ([`crate::types::RealFrameStack`]: fractional,
//! negative), like TrackPy on a `float64` array, which differs in three
//! places: the default `threshold` is 1/255 instead of 1, the boxcar
//! background is not truncated to integers, and the image the peaks are
//! found in is rescaled to `0..=255` (TrackPy assumes 8 bits for float
//! images), with or without preprocessing. `raw_mass` and `ep` are
//! measured in the real values. The element type decides, as in TrackPy:
//! whole numbers in a float array take the float path.
//! Coordinates: `x` column, `y` row, pixel centres at integers.

mod filters;

use indicatif::ProgressBar;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, input_error, require_finite};
use crate::limits::check_feature_px;
use crate::types::{Frames, Prediction, Recording};

/// A raw pixel value the locator takes: a photon count (`u32`, TrackPy's
/// integer-image path) or a real value (`f64`, its float-image path).
pub trait Pixel: Copy + Send + Sync + 'static {
    /// Whether this is an integer image to TrackPy.
    const INTEGER: bool;
    /// The value as a float.
    fn value(self) -> f64;
}

impl Pixel for u32 {
    const INTEGER: bool = true;
    fn value(self) -> f64 {
        f64::from(self)
    }
}

impl Pixel for f64 {
    const INTEGER: bool = false;
    fn value(self) -> f64 {
        self
    }
}

// The other element types a caller's array may hold (the Python bindings
// borrow numpy's uint8, uint16 and float32 stacks without converting them).
impl Pixel for u8 {
    const INTEGER: bool = true;
    fn value(self) -> f64 {
        f64::from(self)
    }
}

impl Pixel for u16 {
    const INTEGER: bool = true;
    fn value(self) -> f64 {
        f64::from(self)
    }
}

impl Pixel for f32 {
    const INTEGER: bool = false;
    fn value(self) -> f64 {
        f64::from(self)
    }
}

/// TrackPy's default `threshold`: 1 for integer images, 1/255 for float
/// images.
fn default_threshold<P: Pixel>() -> f64 {
    if P::INTEGER { 1.0 } else { 1.0 / 255.0 }
}

/// Most centroid refinement steps: each moves the mask by at most a pixel,
/// so more than a feature's width of steps only repeats an oscillation.
pub(crate) const MAX_ITERATIONS: usize = crate::limits::MAX_FEATURE_PX;

/// Version of the locator's output, part of the content key of every
/// prediction it makes in the registry: bump it whenever a change alters any
/// feature (a position, mass or any other column), so cached predictions
/// made by the old code are not reused.
pub const CODE_VERSION: &str = "scanloc-crocker-grier/1";

/// TrackPy's `locate` parameters, with its names and defaults
/// (`diameter` 7 here; TrackPy has no default).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CrockerGrierParams {
    /// Feature diameter in pixels: a positive odd integer.
    pub diameter: usize,
    /// Minimum integrated brightness (features need mass > minmass).
    pub minmass: Option<f64>,
    /// Maximum radius of gyration.
    pub maxsize: Option<f64>,
    /// Minimum separation between features; default `diameter + 1`.
    pub separation: Option<f64>,
    /// Width of the Gaussian low pass, pixels.
    pub noise_size: f64,
    /// Side of the boxcar background, pixels (odd); default `diameter`.
    pub smoothing_size: Option<usize>,
    /// Band-pass values below this are set to 0; default 1 for counts,
    /// 1/255 for real-valued frames (TrackPy's defaults).
    pub threshold: Option<f64>,
    /// Peaks must be brighter than this percentile of non-zero pixels.
    pub percentile: f64,
    /// Keep only the `topn` brightest features.
    pub topn: Option<usize>,
    /// Band-pass the image before finding peaks.
    pub preprocess: bool,
    /// Maximum centroid refinement steps.
    pub max_iterations: usize,
}

impl Default for CrockerGrierParams {
    fn default() -> Self {
        Self {
            diameter: 7,
            minmass: None,
            maxsize: None,
            separation: None,
            noise_size: 1.0,
            smoothing_size: None,
            threshold: None,
            percentile: 64.0,
            topn: None,
            preprocess: true,
            max_iterations: 10,
        }
    }
}

impl CrockerGrierParams {
    /// Checks every parameter, naming the one at fault.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.diameter < 3 || self.diameter.is_multiple_of(2) {
            return Err(FieldError::new(
                "diameter",
                format!("must be an odd integer ≥ 3, got {}", self.diameter),
            ));
        }
        // Every size in pixels is bounded (the mask, the filters' kernels
        // and the dilation window grow with them), the same bound wherever
        // the parameters come from.
        check_feature_px("diameter", self.diameter as f64)?;
        if let Some(smoothing_size) = self.smoothing_size {
            check_feature_px("smoothing_size", smoothing_size as f64)?;
        }
        if let Some(minmass) = self.minmass {
            // Negative values would let empty (mass 0, size NaN) features through.
            crate::error::require_non_negative("minmass", minmass)?;
        }
        if let Some(maxsize) = self.maxsize {
            require_finite("maxsize", maxsize)?;
        }
        if let Some(separation) = self.separation {
            require_finite("separation", separation)?;
            if separation < 0.0 {
                return Err(FieldError::new(
                    "separation",
                    format!("must be ≥ 0, got {separation}"),
                ));
            }
            check_feature_px("separation", separation)?;
        }
        require_finite("noise_size", self.noise_size)?;
        if self.noise_size < 0.0 {
            return Err(FieldError::new(
                "noise_size",
                format!("must be ≥ 0, got {}", self.noise_size),
            ));
        }
        check_feature_px("noise_size", self.noise_size)?;
        let smoothing = self.smoothing_size();
        if smoothing == 0 || smoothing.is_multiple_of(2) {
            return Err(FieldError::new(
                "smoothing_size",
                format!("must be a positive odd integer, got {smoothing}"),
            ));
        }
        if self.preprocess && self.noise_size >= smoothing as f64 {
            return Err(FieldError::new(
                "noise_size",
                format!(
                    "must be smaller than smoothing_size ({smoothing}), got {}",
                    self.noise_size
                ),
            ));
        }
        if let Some(threshold) = self.threshold {
            require_finite("threshold", threshold)?;
        }
        require_finite("percentile", self.percentile)?;
        if !(0.0..=100.0).contains(&self.percentile) {
            return Err(FieldError::new(
                "percentile",
                format!("must be between 0 and 100, got {}", self.percentile),
            ));
        }
        if self.topn == Some(0) {
            return Err(FieldError::new("topn", "must be at least 1"));
        }
        if self.max_iterations == 0 || self.max_iterations > MAX_ITERATIONS {
            return Err(FieldError::new(
                "max_iterations",
                format!(
                    "must be between 1 and {MAX_ITERATIONS}, got {}",
                    self.max_iterations
                ),
            ));
        }
        Ok(())
    }

    fn radius(&self) -> usize {
        self.diameter / 2
    }

    fn separation(&self) -> f64 {
        self.separation.unwrap_or((self.diameter + 1) as f64)
    }

    fn smoothing_size(&self) -> usize {
        self.smoothing_size.unwrap_or(self.diameter)
    }
}

/// One located feature, with TrackPy's columns.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Feature {
    /// Column of the centroid, pixels.
    pub x: f64,
    /// Row of the centroid, pixels.
    pub y: f64,
    /// Integrated brightness of the band-passed image in the mask.
    pub mass: f64,
    /// Radius of gyration, pixels.
    pub size: f64,
    /// Eccentricity (0 is circular).
    pub ecc: f64,
    /// Peak of the band-passed image in the mask.
    pub signal: f64,
    /// Integrated brightness of the raw image in the mask.
    pub raw_mass: f64,
    /// Static localisation error estimate, pixels; NaN when the frame has
    /// too little background to measure its noise (as TrackPy).
    pub ep: f64,
}

/// The columns a localisation file gets for each [`Feature`] beside
/// `frame,x,y,score` (score = mass): TrackPy's, in the order of
/// [`Feature::column_values`]. `ep` is `NaN` where TrackPy's would be (no
/// background to measure the noise on).
pub(crate) const FEATURE_COLUMNS: [&str; 6] = ["mass", "size", "ecc", "signal", "raw_mass", "ep"];

impl Feature {
    /// The prediction this feature makes on `frame`: its centroid, scored
    /// by its mass.
    pub fn prediction(&self, frame: usize) -> Prediction {
        Prediction::new(frame, self.x, self.y, self.mass)
    }

    /// The feature's values of [`FEATURE_COLUMNS`], in order.
    pub fn column_values(&self) -> [f64; 6] {
        [
            self.mass,
            self.size,
            self.ecc,
            self.signal,
            self.raw_mass,
            self.ep,
        ]
    }
}

/// The circular mask of radius `r` and its moments, shared by all features.
struct Mask {
    radius: usize,
    /// Offsets (row, column) within the square, and per point r², cos 2θ,
    /// sin 2θ, in row-major order.
    points: Vec<MaskPoint>,
    /// √(Σ x²) over the mask (TrackPy's `_root_sum_x_squared`).
    root_sum_x2: f64,
    /// For each mask row (top to bottom), how far the mask reaches left
    /// and right of its centre column.
    row_half_widths: Vec<usize>,
}

#[derive(Clone, Copy)]
struct MaskPoint {
    row: usize,
    column: usize,
    r2: f64,
    cos2: f64,
    sin2: f64,
}

impl Mask {
    fn new(radius: usize) -> Self {
        let side = 2 * radius + 1;
        let mut points = Vec::new();
        let mut sum_x2 = 0.0;
        let r = radius as f64;
        for row in 0..side {
            for column in 0..side {
                let dy = row as f64 - r;
                let dx = column as f64 - r;
                // TrackPy's elliptical mask: Σ (coord / radius)² ≤ 1.
                let inside = (dy / r).powi(2) + (dx / r).powi(2) <= 1.0;
                if inside {
                    let theta = dy.atan2(dx);
                    points.push(MaskPoint {
                        row,
                        column,
                        r2: dy * dy + dx * dx,
                        cos2: (2.0 * theta).cos(),
                        sin2: (2.0 * theta).sin(),
                    });
                    sum_x2 += dy * dy;
                }
            }
        }
        let mut row_half_widths = vec![0usize; side];
        for p in &points {
            row_half_widths[p.row] = row_half_widths[p.row].max(p.column.abs_diff(radius));
        }
        Self {
            radius,
            points,
            root_sum_x2: sum_x2.sqrt(),
            row_half_widths,
        }
    }
}

/// Reusable per-thread buffers.
#[derive(Default)]
struct Buffers {
    filters: filters::Buffers,
    scaled: Vec<u32>,
    peaks: Vec<(usize, usize)>,
}

/// Locates features in one frame (row-major `height × width` counts or
/// real values, see [`Pixel`]). Features come in TrackPy's order: by peak
/// position, row-major.
pub fn locate_frame<P: Pixel>(
    frame: &[P],
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
) -> anyhow::Result<Vec<Feature>> {
    params.validate()?;
    crate::limits::check_frame_not_empty(height, width)?;
    if frame.len() != height * width {
        return Err(input_error(format!(
            "frame has {} pixels, expected {height} × {width}",
            frame.len()
        )));
    }
    let integer_max = integer_range(frame);
    let mask = Mask::new(params.radius());
    Ok(locate_with(
        frame,
        height,
        width,
        params,
        &mask,
        integer_max,
        &mut Buffers::default(),
    ))
}

/// The largest value of the integer type TrackPy would rescale `values`
/// to: for counts, `uint16` unless a count needs `uint32` (what scanloc
/// writes); for real values `uint8` (TrackPy assumes 8 bits for float
/// images).
fn integer_range<P: Pixel>(values: &[P]) -> u64 {
    if !P::INTEGER {
        return u8::MAX as u64;
    }
    if largest(values) <= u16::MAX as f64 {
        u16::MAX as u64
    } else {
        u32::MAX as u64
    }
}

/// The largest of `values` and 0, a NaN passed over (as a fold of
/// `f64::max` from 0): the maximum does not depend on the order, so it is
/// taken in eight lanes, which vectorises.
#[inline(always)]
fn largest<P: Pixel>(values: &[P]) -> f64 {
    const LANES: usize = 8;
    let mut lanes = [0.0f64; LANES];
    let chunks = values.chunks_exact(LANES);
    let rest = chunks.remainder();
    for chunk in chunks {
        for (lane, v) in lanes.iter_mut().zip(chunk) {
            let v = v.value();
            *lane = if v > *lane { v } else { *lane };
        }
    }
    for (lane, v) in lanes.iter_mut().zip(rest) {
        let v = v.value();
        *lane = if v > *lane { v } else { *lane };
    }
    lanes
        .into_iter()
        .fold(0.0, |max, v| if v > max { v } else { max })
}

/// TrackPy's `convert_to_int`: `values` (negatives as 0) scaled so their
/// maximum is `integer_max` and truncated to integers, into `scaled`;
/// returns the scale factor (1 when the maximum is not positive).
#[inline(always)]
fn rescale_to_integers<P: Pixel>(values: &[P], integer_max: u64, scaled: &mut Vec<u32>) -> f64 {
    let max = largest(values);
    let scale = if max == 0.0 {
        1.0
    } else {
        integer_max as f64 / max
    };
    scaled.clear();
    // A NaN is taken as 0, as `f64::max(v, 0)` does.
    let positive = |v: P| {
        let v = v.value();
        if v > 0.0 { v } else { 0.0 }
    };
    if max.is_finite() {
        // Every scaled value is then in `0..=integer_max` (`scale · max`
        // rounds to it), below 2⁵²: truncated and converted by float
        // arithmetic, which vectorises (a cast saturates, which does not).
        scaled.extend(
            values
                .iter()
                .map(|&v| filters::small_to_u32(scale * positive(v))),
        );
    } else {
        scaled.extend(values.iter().map(|&v| (scale * positive(v)) as u32));
    }
    scale
}

/// Locates features in one frame: with AVX2 where the CPU has it (wider
/// vectors for the same operations: the same bits), else the baseline
/// build.
fn locate_with<P: Pixel>(
    raw: &[P],
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    mask: &Mask,
    integer_max: u64,
    buffers: &mut Buffers,
) -> Vec<Feature> {
    #[cfg(target_arch = "x86_64")]
    if crate::detect::cpu::has_avx2() {
        // SAFETY: the CPU has AVX2 (checked at run time).
        return unsafe { locate_with_avx2(raw, height, width, params, mask, integer_max, buffers) };
    }
    locate_portable(raw, height, width, params, mask, integer_max, buffers)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn locate_with_avx2<P: Pixel>(
    raw: &[P],
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    mask: &Mask,
    integer_max: u64,
    buffers: &mut Buffers,
) -> Vec<Feature> {
    locate_portable(raw, height, width, params, mask, integer_max, buffers)
}

/// [`locate_with`]'s work, inlined into each build (as are the filters
/// it calls), so that each is compiled for its instruction set.
#[inline(always)]
fn locate_portable<P: Pixel>(
    raw: &[P],
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    mask: &Mask,
    integer_max: u64,
    buffers: &mut Buffers,
) -> Vec<Feature> {
    // Steps 1–2: the integer image the peaks are found in.
    let scale = integer_image(raw, height, width, params, integer_max, buffers);
    let image = &buffers.scaled;
    let peaks = &mut buffers.peaks;

    // Step 3: local maxima away from the edges.
    let separation = params.separation();
    let radius = params.radius();
    let margin = (radius as f64)
        .max((separation / 2.0).floor() - 1.0)
        .max((params.smoothing_size() / 2) as f64);
    filters::local_maxima(
        image,
        height,
        width,
        separation,
        params.percentile,
        margin,
        &mut buffers.filters,
        peaks,
    );

    // Step 4–5: refine and characterise.
    let features: Vec<Feature> = peaks
        .iter()
        .map(|&(row, column)| {
            refine(
                raw,
                image,
                height,
                width,
                mask,
                row,
                column,
                params.max_iterations,
            )
        })
        .collect();

    // Step 6: filter, then the static error, which needs the frame's
    // background noise.
    let mut features = filter_features(features, params, scale);
    let (black_level, noise) =
        filters::measure_noise(image, raw, height, width, mask, &mut buffers.filters);
    let pixels_in_mask = mask.points.len() as f64;
    for feature in &mut features {
        let mass = feature.raw_mass - pixels_in_mask * black_level;
        feature.ep = noise / mass * params.noise_size * mask.root_sum_x2;
    }
    features
}

/// Steps 1–2: the band-passed (or raw) image as integers in
/// `buffers.scaled`; returns the factor it was scaled by.
#[inline(always)]
fn integer_image<P: Pixel>(
    raw: &[P],
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    integer_max: u64,
    buffers: &mut Buffers,
) -> f64 {
    if params.preprocess {
        let threshold = params.threshold.unwrap_or_else(default_threshold::<P>);
        let band = filters::bandpass(
            raw,
            height,
            width,
            params.noise_size,
            params.smoothing_size(),
            threshold,
            &mut buffers.filters,
        );
        rescale_to_integers(band, integer_max, &mut buffers.scaled)
    } else if P::INTEGER {
        // An integer image is used as it is.
        buffers.scaled.clear();
        buffers.scaled.extend(raw.iter().map(|&v| v.value() as u32));
        1.0
    } else {
        rescale_to_integers(raw, integer_max, &mut buffers.scaled)
    }
}

/// Step 6: drops the dimmer of close pairs (TrackPy's `where_close`, on
/// unscaled masses), then rescales masses and signals by `scale` and keeps
/// the features `minmass`, `maxsize` and `topn` allow, in their order.
#[inline(always)]
fn filter_features(
    mut features: Vec<Feature>,
    params: &CrockerGrierParams,
    scale: f64,
) -> Vec<Feature> {
    let separation = params.separation();
    if separation > 0.0 {
        let dropped = close_pairs_to_drop(&features, separation);
        let mut index = 0;
        features.retain(|_| {
            let keep = dropped.binary_search(&index).is_err();
            index += 1;
            keep
        });
    }
    for feature in &mut features {
        feature.mass /= scale;
        feature.signal /= scale;
    }
    let minmass = params.minmass.unwrap_or(0.0);
    features.retain(|f| f.mass > minmass && params.maxsize.is_none_or(|maxsize| f.size < maxsize));
    if let Some(topn) = params.topn
        && features.len() > topn
    {
        // The `topn` largest masses; equal masses keep their earlier order.
        let mut order: Vec<usize> = (0..features.len()).collect();
        order.sort_by(|&a, &b| {
            features[b]
                .mass
                .total_cmp(&features[a].mass)
                .then(a.cmp(&b))
        });
        let mut keep: Vec<usize> = order[..topn].to_vec();
        keep.sort_unstable();
        features = keep.into_iter().map(|i| features[i]).collect();
    }
    features
}

/// Centroid refinement and characterisation of one peak (TrackPy's
/// `_refine`, Python engine).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn refine<P: Pixel>(
    raw: &[P],
    image: &[u32],
    height: usize,
    width: usize,
    mask: &Mask,
    row: usize,
    column: usize,
    max_iterations: usize,
) -> Feature {
    const SHIFT_THRESHOLD: f64 = 0.6;
    let r = mask.radius;
    let (mut row, mut column) = (row, column);
    let mut centroid = (row as f64, column as f64);
    let mut mass = 0u64;
    let mut top = (row - r, column - r);
    for _ in 0..max_iterations {
        top = (row - r, column - r);
        mass = 0;
        let (mut sum_row, mut sum_column) = (0.0, 0.0);
        for p in &mask.points {
            let value = image[(top.0 + p.row) * width + top.1 + p.column];
            mass += u64::from(value);
            sum_row += value as f64 * p.row as f64;
            sum_column += value as f64 * p.column as f64;
        }
        // An all-zero neighbourhood has its centroid at the centre.
        let offset = if mass == 0 {
            (0.0, 0.0)
        } else {
            (
                sum_row / mass as f64 - r as f64,
                sum_column / mass as f64 - r as f64,
            )
        };
        centroid = (row as f64 + offset.0, column as f64 + offset.1);
        if offset.0.abs() < SHIFT_THRESHOLD && offset.1.abs() < SHIFT_THRESHOLD {
            break;
        }
        let step = |position: usize, offset: f64, upper: usize| -> usize {
            let moved = if offset > SHIFT_THRESHOLD {
                position + 1
            } else if offset < -SHIFT_THRESHOLD {
                position - 1
            } else {
                position
            };
            moved.clamp(r, upper)
        };
        row = step(row, offset.0, height - 1 - r);
        column = step(column, offset.1, width - 1 - r);
    }
    // Characterise the last neighbourhood evaluated.
    let (mut r2_sum, mut cos_sum, mut sin_sum, mut signal) = (0.0, 0.0, 0.0, 0u64);
    for p in &mask.points {
        let value = image[(top.0 + p.row) * width + top.1 + p.column];
        r2_sum += p.r2 * value as f64;
        cos_sum += p.cos2 * value as f64;
        sin_sum += p.sin2 * value as f64;
        signal = signal.max(u64::from(value));
    }
    let raw_mass = raw_mass(raw, width, mask, top);
    let mass = mass as f64;
    let centre = image[(top.0 + r) * width + top.1 + r] as f64;
    Feature {
        x: centroid.1,
        y: centroid.0,
        mass,
        size: (r2_sum / mass).sqrt(),
        ecc: (cos_sum * cos_sum + sin_sum * sin_sum).sqrt() / (mass - centre + 1e-6),
        signal: signal as f64,
        raw_mass,
        ep: f64::NAN,
    }
}

/// The sum of the raw values in the mask whose square starts at `top`:
/// exact for counts; for real values numpy's pairwise sum over the square
/// with the corners outside the mask as 0 (TrackPy's
/// `(mask * raw_image[rect]).sum()`), so it agrees to the last bit.
fn raw_mass<P: Pixel>(raw: &[P], width: usize, mask: &Mask, top: (usize, usize)) -> f64 {
    let at = |row: usize, column: usize| raw[(top.0 + row) * width + top.1 + column].value();
    if P::INTEGER {
        // Counts: the sum of integers below 2⁵³ is exact in any order.
        return mask.points.iter().map(|p| at(p.row, p.column)).sum();
    }
    let side = 2 * mask.radius + 1;
    let mut square = vec![0.0; side * side];
    for p in &mask.points {
        square[p.row * side + p.column] = at(p.row, p.column);
    }
    filters::numpy_sum(&square)
}

/// Indices of features to drop: for every pair closer than `separation`
/// (strictly, to within 1e−7), the one with the smaller mass, or on equal
/// masses the one whose rescaled `y + x` is not larger (TrackPy's
/// `where_close`). Pairs are judged independently, as TrackPy does.
#[inline(always)]
fn close_pairs_to_drop(features: &[Feature], separation: f64) -> Vec<usize> {
    let mut dropped = Vec::new();
    let limit = (1.0 - 1e-7) * (1.0 - 1e-7);
    // Only pairs less than `separation` apart in y can be close: once
    // `y_b − y_a ≥ separation`, `|y_a − y_b| / separation ≥ 1` (rounding is
    // monotone), above the limit. So the features are swept in order of y.
    let mut by_y: Vec<usize> = (0..features.len()).collect();
    by_y.sort_unstable_by(|&a, &b| features[a].y.total_cmp(&features[b].y).then(a.cmp(&b)));
    for (k, &first) in by_y.iter().enumerate() {
        for &second in &by_y[k + 1..] {
            if features[second].y - features[first].y >= separation {
                break;
            }
            // The pair as TrackPy sees it: the earlier feature first.
            let (i, j) = (first.min(second), first.max(second));
            let (a, b) = (&features[i], &features[j]);
            let dy = (a.y - b.y) / separation;
            let dx = (a.x - b.x) / separation;
            if dy * dy + dx * dx > limit {
                continue;
            }
            let drop = if a.mass > b.mass {
                j
            } else if a.mass < b.mass {
                i
            } else if (a.y + a.x) / separation > (b.y + b.x) / separation {
                j
            } else {
                i
            };
            dropped.push(drop);
        }
    }
    dropped.sort_unstable();
    dropped.dedup();
    dropped
}

/// Locates features in every frame of a stack of counts or real values
/// (see [`Pixel`]), in parallel. Results are ordered by frame, then by
/// descending mass (ties by x, then y), whatever the thread count.
pub fn locate_stack<P: Pixel>(
    frames: &Frames<P>,
    params: &CrockerGrierParams,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<(usize, Feature)>> {
    locate_frames(
        &frames.data,
        frames.n,
        frames.height,
        frames.width,
        params,
        progress,
    )
}

/// [`locate_stack`] of counts or real values, as read from a file.
pub fn locate_recording(
    recording: &Recording,
    params: &CrockerGrierParams,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<(usize, Feature)>> {
    match recording {
        Recording::Counts(frames) => locate_stack(frames, params, progress),
        Recording::Real(frames) => locate_stack(frames, params, progress),
    }
}

/// Locates features in the `n` row-major `height × width` frames of
/// `data`, in parallel.
fn locate_frames<P: Pixel>(
    data: &[P],
    n: usize,
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<(usize, Feature)>> {
    crate::limits::check_frame_not_empty(height, width)?;
    check_frame_data(data.len(), n, height, width)?;
    // One rescaling range for the whole stack, as TrackPy's for one array.
    let integer_max = integer_range(&data[..n * height * width]);
    locate_frames_in_range(data, n, height, width, params, integer_max, progress)
}

/// That `len` values hold `n` frames of `height × width`.
fn check_frame_data(len: usize, n: usize, height: usize, width: usize) -> anyhow::Result<()> {
    match n
        .checked_mul(height)
        .and_then(|rows| rows.checked_mul(width))
    {
        Some(expected) if expected <= len => Ok(()),
        _ => Err(input_error(format!(
            "{len} values cannot hold {n} frames of {height} × {width}"
        ))),
    }
}

/// [`locate_stack`] of the first `n` row-major `height × width` frames of
/// `data`, with peaks found in band-passed frames rescaled to
/// `0..=integer_max` (TrackPy's `convert_to_int`: the largest value of the
/// array's integer type, e.g. 255 for `uint8` and 65,535 for `uint16`;
/// 255 for float arrays). A caller that goes through a long stack in
/// chunks (to stay interruptible) passes every chunk the same
/// `integer_max`, so the features do not depend on the chunking; frame
/// indices are within `data`.
pub fn locate_frames_in_range<P: Pixel>(
    data: &[P],
    n: usize,
    height: usize,
    width: usize,
    params: &CrockerGrierParams,
    integer_max: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<(usize, Feature)>> {
    params.validate()?;
    crate::limits::check_frame_not_empty(height, width)?;
    check_frame_data(data.len(), n, height, width)?;
    // The image the peaks are found in holds `u32`s (the widest dtype
    // the locator takes).
    if integer_max == 0 || integer_max > u64::from(u32::MAX) {
        return Err(input_error(format!(
            "integer_max: must be between 1 and {}, got {integer_max}",
            u32::MAX
        )));
    }
    let frame_len = height * width;
    let frame = |index: usize| &data[index * frame_len..(index + 1) * frame_len];
    let mask = Mask::new(params.radius());
    let per_frame: Vec<Vec<(usize, Feature)>> = (0..n)
        .into_par_iter()
        .map_init(Buffers::default, |buffers, index| {
            let mut features = locate_with(
                frame(index),
                height,
                width,
                params,
                &mask,
                integer_max,
                buffers,
            );
            features.sort_by(|a, b| {
                b.mass
                    .total_cmp(&a.mass)
                    .then(a.x.total_cmp(&b.x))
                    .then(a.y.total_cmp(&b.y))
            });
            progress.inc(1);
            features.into_iter().map(|f| (index, f)).collect()
        })
        .collect();
    Ok(per_frame.into_iter().flatten().collect())
}

/// Predictions for the metric: score = mass.
pub(crate) fn to_predictions(features: &[(usize, Feature)]) -> Vec<Prediction> {
    features
        .iter()
        .map(|(frame, f)| f.prediction(*frame))
        .collect()
}
