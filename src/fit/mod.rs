//! The microscope from a recording: background photons per pixel, the
//! detector's variance-to-mean ratio (its excess noise), the lateral PSF
//! width σxy and the QD brightness N_qd, each with a standard error,
//! estimated from the frames of a point-scanning recording whose timing is
//! known (docs/fit-microscope.md).
//!
//! The estimators follow the simulator's forward model (docs/simulator.md):
//! a pixel's count is a draw with mean N_bkg + signal and variance F²·mean
//! (F² = 1: Poisson); a QD at depth z in focus adds the lateral Gaussian
//! `N_qd/(2π σxy²) · g(z)` with `g(z) = exp(−z²/2σz²)/√(2π σz²)`.
//!
//! - **Background and excess noise**: the mean and variance-to-mean ratio
//!   of the pixels away from any spot (pixels whose neighbourhood sum is
//!   not above the background's noise, and their surroundings, are left
//!   out).
//! - **σxy**: the autocorrelation of the background-subtracted frames
//!   along the rows. Along a row the beam crosses a QD in microseconds,
//!   so a row's profile is the PSF's, undistorted by the QD's motion
//!   (which happens between rows, during the retrace); pixel noise is
//!   independent between pixels, so lags ≥ 1 hold the profiles alone.
//!   Over spots at random sub-pixel positions their mean is
//!   `B + S·exp(−k²a²/4σxy²)` at lag k exactly; (B, S, σxy) are fitted by
//!   least squares. The same along the columns gives the spot's height
//!   including its motion blur, which sizes the windows below.
//! - **N_qd**: a spot's photons, `T = N_qd·g(z)/a²` in expectation
//!   whatever the motion (photons are conserved; the blur only moves
//!   them), estimated by a matched filter: the Gaussian of width σxy
//!   along the rows and of the blurred height along the columns,
//!   `T̂ = Σg·d · Σg/Σg²`. QDs are taken to be spread evenly in depth over
//!   more than the focal volume, so the totals of detected spots follow
//!   `T₀·exp(−u²/2)`, u uniform, up to the in-focus total
//!   `T₀ = N_qd/(√(2π) σz a²)`, blurred by the photon noise and a relative
//!   spread κ (the motion's, the frame's sampling); T₀ and κ are fitted
//!   by maximum likelihood, conditioned on detection. The spots are found
//!   on one colour of a checkerboard of pixels and measured on the other,
//!   so the noise that made a pixel a local maximum does not inflate its
//!   total.
//!
//! Standard errors: a jackknife over ten blocks of frames for the
//! background, the excess noise and σxy; the profile likelihood's
//! curvature (Δ ln L = ½) for N_qd. Frames are used evenly spaced, at most
//! [`MAX_FIT_PIXELS`] pixels of them; nothing is random.

use rayon::prelude::*;

use crate::error::input_error;
use crate::types::FrameStack;

/// Most pixels (frames × height × width) the fit reads; a longer recording
/// is subsampled to evenly spaced frames.
pub(crate) const MAX_FIT_PIXELS: usize = 24_000_000;
/// Most spots the brightness likelihood uses (evenly spaced among those
/// detected).
pub(crate) const MAX_FIT_SPOTS: usize = 1_500;
/// Fewest detected spots for a brightness estimate.
pub(crate) const MIN_FIT_SPOTS: usize = 20;
/// Blocks of frames of the jackknife.
const BLOCKS: usize = 10;

/// What the user knows about the microscope: the scan's geometry and the
/// PSF's axial width (which N_qd's normalisation needs and a recording of
/// diffusing QDs cannot tell apart from N_qd).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KnownTiming {
    /// Pixel size `a`, µm.
    pub pixel_size_um: f64,
    /// Pixel dwell, µs.
    pub dwell_us: f64,
    /// Line retrace, ms.
    pub retrace_ms: f64,
    /// Axial PSF standard deviation σz, µm.
    pub sigma_z_um: f64,
}

/// A fitted value and its standard error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub value: f64,
    pub standard_error: f64,
}

/// The microscope a recording shows.
#[derive(Debug, Clone, PartialEq)]
pub struct FittedMicroscope {
    /// N_bkg: expected background photons per pixel.
    pub background: Estimate,
    /// N_qd: the PSF's normalisation, photons (docs/simulator.md).
    pub brightness: Estimate,
    /// The background's variance over its mean: F² of a PMT (1 for a
    /// photon-counting detector; the detector's gain times F² if the counts
    /// are not photons).
    pub excess_noise_factor: Estimate,
    /// The lateral PSF's standard deviation σxy, µm.
    pub sigma_xy_um: Estimate,
    /// The spots' height including their motion blur (the column
    /// autocorrelation's width), µm.
    pub blurred_height_um: f64,
    /// Frames the fit read.
    pub frames_used: usize,
    /// Spots the brightness was fitted on.
    pub spots: usize,
    /// Half-width of the spots' windows, px.
    pub window_half_px: usize,
    /// The relative spread of a spot's total beyond photon noise (κ).
    pub spot_spread: f64,
}

/// Estimates the microscope from `frames` (photon counts) and the known
/// timing. Refuses (input error) a recording the fit cannot read: constant
/// frames, frames without a spot profile, too few spots.
pub fn fit_microscope(
    frames: &FrameStack,
    timing: &KnownTiming,
) -> anyhow::Result<FittedMicroscope> {
    let used = check_fittable(frames, timing)?;
    let blocks: Vec<&[usize]> = used.chunks(used.len().div_ceil(BLOCKS)).collect();
    let background = fit_background(frames, &used, &blocks)?;
    let profile = fit_spot_profile(frames, &blocks, background.level.background)?;
    let brightness = fit_brightness(frames, &used, &background.level, &profile)?;
    let a = timing.pixel_size_um;
    // T₀ = N_qd / (√(2π) σz a²), corrected for the window's cut tails.
    let scale =
        (2.0 * std::f64::consts::PI).sqrt() * timing.sigma_z_um * a * a / brightness.captured;
    Ok(FittedMicroscope {
        background: background.background,
        brightness: Estimate {
            value: brightness.fit.total * scale,
            standard_error: brightness.fit.standard_error * scale,
        },
        excess_noise_factor: background.excess,
        sigma_xy_um: Estimate {
            value: profile.sigma_px * a,
            standard_error: profile.sigma_px_standard_error * a,
        },
        blurred_height_um: profile.blurred_px * a,
        frames_used: used.len(),
        spots: brightness.spots,
        window_half_px: brightness.window_half_px,
        spot_spread: brightness.fit.spread,
    })
}

/// The frames the fit reads (evenly spaced, see [`used_frames`]), after
/// refusing what it cannot read: a non-positive pixel size or σz, frames
/// under 8×8 pixels, a constant recording.
fn check_fittable(frames: &FrameStack, timing: &KnownTiming) -> anyhow::Result<Vec<usize>> {
    let a = timing.pixel_size_um;
    if !(a.is_finite() && a > 0.0 && timing.sigma_z_um.is_finite() && timing.sigma_z_um > 0.0) {
        return Err(input_error(format!(
            "pixel size {a} µm and σz {} µm must be positive",
            timing.sigma_z_um
        )));
    }
    let (height, width) = (frames.height, frames.width);
    if height < 8 || width < 8 {
        return Err(input_error(format!(
            "frames of {height}×{width} pixels are too small to fit a microscope on (at least 8×8)"
        )));
    }
    let used = used_frames(frames.n, height * width);
    let first = frames.frame(used[0])[0];
    if used
        .iter()
        .all(|&f| frames.frame(f).iter().all(|&count| count == first))
    {
        return Err(input_error(
            "the recording is constant (every pixel the same count): no photon statistics to fit"
                .to_string(),
        ));
    }
    Ok(used)
}

/// The background's level and its two estimates with their errors.
struct BackgroundFit {
    level: Level,
    background: Estimate,
    excess: Estimate,
}

/// Background and excess noise from the pixels away from spots. Which
/// pixels are "away" depends on the level itself, so the level is
/// iterated three times from the plain mean; the pixel sums are kept per
/// block of frames for the jackknife.
fn fit_background(
    frames: &FrameStack,
    used: &[usize],
    blocks: &[&[usize]],
) -> anyhow::Result<BackgroundFit> {
    let mut level = Level {
        background: mean_count(frames, used),
        variance_ratio: 1.0,
    };
    let mut level_sums = Vec::new();
    for _ in 0..3 {
        level_sums = blocks
            .par_iter()
            .map(|block| background_sums(frames, block, &level))
            .collect::<Vec<_>>();
        level = Level::from_sums(&sum_all(&level_sums));
        if level.background.is_nan() || level.background <= 0.0 {
            return Err(input_error(
                "the recording's background is zero: no photon statistics to fit".to_string(),
            ));
        }
    }
    Ok(BackgroundFit {
        level,
        background: jackknife(&level_sums, |s| Level::from_sums(s).background),
        excess: jackknife(&level_sums, |s| Level::from_sums(s).variance_ratio),
    })
}

/// The spots' profile, px: σxy along the rows (with its jackknife error)
/// and the height along the columns, motion blur included.
struct SpotProfile {
    sigma_px: f64,
    sigma_px_standard_error: f64,
    /// At least σxy: blur only widens a spot.
    blurred_px: f64,
}

/// σxy from the rows' autocorrelation, the blurred height from the
/// columns' (see the module's documentation); refuses frames whose pixels
/// are uncorrelated (no spots).
fn fit_spot_profile(
    frames: &FrameStack,
    blocks: &[&[usize]],
    background: f64,
) -> anyhow::Result<SpotProfile> {
    let lags_x = (frames.width - 2).min(60);
    let lags_y = (frames.height - 2).min(60);
    // Per block: the row lags 0..=lags_x, then the column lags.
    let correlations = blocks
        .par_iter()
        .map(|block| autocorrelation_sums(frames, block, background, lags_x, lags_y))
        .collect::<Vec<_>>();
    let fit_x = |sums: &[Vec<f64>]| {
        let total = sum_all_vec(sums.iter().map(|s| &s[..=lags_x]));
        fit_gaussian_lags(&total).map(|f| f.width_px)
    };
    let profile_x = fit_gaussian_lags(&sum_all_vec(correlations.iter().map(|s| &s[..=lags_x])));
    let profile_y = fit_gaussian_lags(&sum_all_vec(correlations.iter().map(|s| &s[lags_x + 1..])));
    let (Some(profile_x), Some(profile_y)) = (profile_x, profile_y) else {
        return Err(input_error(
            "the recording shows no spots: its pixels are uncorrelated along the rows, as noise alone would be"
                .to_string(),
        ));
    };
    let sigma_px = jackknife_vec(&correlations, |s| fit_x(s).unwrap_or(f64::NAN));
    Ok(SpotProfile {
        sigma_px: profile_x.width_px,
        sigma_px_standard_error: sigma_px.standard_error,
        blurred_px: profile_y.width_px.max(profile_x.width_px),
    })
}

/// The in-focus total and what it was measured with.
struct BrightnessFit {
    fit: TotalFit,
    /// The share of a spot's photons inside the matched filter's window.
    captured: f64,
    spots: usize,
    window_half_px: usize,
}

/// The in-focus total T₀ from the spots' matched-filter totals; refuses a
/// recording whose spots do not fit in its frames or with fewer than
/// [`MIN_FIT_SPOTS`] spots above the cut, and keeps at most
/// [`MAX_FIT_SPOTS`] (evenly spaced: the likelihood's cost grows with
/// them).
fn fit_brightness(
    frames: &FrameStack,
    used: &[usize],
    level: &Level,
    profile: &SpotProfile,
) -> anyhow::Result<BrightnessFit> {
    let (height, width) = (frames.height, frames.width);
    let kernel = Kernel::new(profile.sigma_px, profile.blurred_px);
    if 2 * kernel.half_y + 1 > height || 2 * kernel.half_x + 1 > width {
        return Err(input_error(format!(
            "the spots ({:.1} × {:.1} px, blur included) do not fit in {height}×{width} frames: no brightness can be fitted",
            2.0 * profile.sigma_px,
            2.0 * profile.blurred_px
        )));
    }
    let captured = captured_fraction(kernel.half_x, profile.sigma_px)
        * captured_fraction(kernel.half_y, profile.blurred_px);
    let noise = kernel.noise(level.background, level.variance_ratio.max(0.5));
    let cuts = Cuts {
        selection: SELECTION_SD * noise.sd(0.0, 0.0),
        total: THRESHOLD_SD * noise.sd(0.0, 0.0),
    };
    // Each total labelled with its block of frames, for the jackknife.
    let block_len = used.len().div_ceil(BLOCKS);
    let mut totals: Vec<(usize, f64)> = used
        .par_iter()
        .enumerate()
        .flat_map_iter(|(i, &f)| {
            spot_totals(frames, f, level.background, &kernel, cuts.selection)
                .into_iter()
                .map(move |t| (i / block_len, t))
        })
        .collect();
    totals.retain(|&(_, t)| t > cuts.total);
    if totals.len() < MIN_FIT_SPOTS {
        return Err(input_error(format!(
            "only {} spots stand out of the background in {} frames (at least {MIN_FIT_SPOTS} are needed to fit the brightness)",
            totals.len(),
            used.len()
        )));
    }
    if totals.len() > MAX_FIT_SPOTS {
        let step = totals.len() as f64 / MAX_FIT_SPOTS as f64;
        totals = (0..MAX_FIT_SPOTS)
            .map(|i| totals[(i as f64 * step) as usize])
            .collect();
    }
    Ok(BrightnessFit {
        fit: fit_in_focus_total(&totals, &cuts, &noise),
        captured,
        spots: totals.len(),
        window_half_px: kernel.half_x.max(kernel.half_y),
    })
}

/// Evenly spaced frames, at most [`MAX_FIT_PIXELS`] pixels of them.
fn used_frames(n: usize, frame_len: usize) -> Vec<usize> {
    let most = (MAX_FIT_PIXELS / frame_len.max(1)).max(1);
    if n <= most {
        return (0..n).collect();
    }
    let step = n as f64 / most as f64;
    (0..most).map(|i| (i as f64 * step) as usize).collect()
}

fn mean_count(frames: &FrameStack, used: &[usize]) -> f64 {
    let sum: f64 = used
        .iter()
        .map(|&f| frames.frame(f).iter().map(|&c| c as f64).sum::<f64>())
        .sum();
    sum / (used.len() * frames.frame_len()) as f64
}

/// The background's level: mean and variance-to-mean ratio.
#[derive(Debug, Clone, Copy)]
struct Level {
    background: f64,
    variance_ratio: f64,
}

impl Level {
    /// From `[pixels, Σ count, Σ count²]`.
    fn from_sums(sums: &[f64]) -> Self {
        let n = sums[0].max(1.0);
        let mean = sums[1] / n;
        let variance = (sums[2] / n - mean * mean).max(0.0) * n / (n - 1.0).max(1.0);
        Level {
            background: mean,
            variance_ratio: if mean > 0.0 {
                variance / mean
            } else {
                f64::NAN
            },
        }
    }
}

fn sum_all(parts: &[Vec<f64>]) -> Vec<f64> {
    sum_all_vec(parts.iter().map(|p| &p[..]))
}

fn sum_all_vec<'a>(mut parts: impl Iterator<Item = &'a [f64]>) -> Vec<f64> {
    let mut total = parts.next().map(|p| p.to_vec()).unwrap_or_default();
    for part in parts {
        for (t, v) in total.iter_mut().zip(part) {
            *t += v;
        }
    }
    total
}

/// A statistic's value on all blocks and its jackknife standard error.
fn jackknife(parts: &[Vec<f64>], statistic: impl Fn(&[f64]) -> f64) -> Estimate {
    jackknife_vec(parts, |sums| statistic(&sum_all(sums)))
}

fn jackknife_vec(parts: &[Vec<f64>], statistic: impl Fn(&[Vec<f64>]) -> f64) -> Estimate {
    let value = statistic(parts);
    let k = parts.len();
    if k < 2 {
        return Estimate {
            value,
            standard_error: f64::NAN,
        };
    }
    let leave_out: Vec<f64> = (0..k)
        .map(|i| {
            let rest: Vec<Vec<f64>> = parts
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, p)| p.clone())
                .collect();
            statistic(&rest)
        })
        .collect();
    let mean = leave_out.iter().sum::<f64>() / k as f64;
    let spread = leave_out.iter().map(|v| (v - mean).powi(2)).sum::<f64>();
    Estimate {
        value,
        standard_error: ((k - 1) as f64 / k as f64 * spread).sqrt(),
    }
}

/// Summed-area table of `values` (`(h+1)×(w+1)`).
fn integral(values: &[f64], height: usize, width: usize) -> Vec<f64> {
    let mut table = vec![0.0; (height + 1) * (width + 1)];
    for r in 0..height {
        let mut row = 0.0;
        for c in 0..width {
            row += values[r * width + c];
            table[(r + 1) * (width + 1) + c + 1] = table[r * (width + 1) + c + 1] + row;
        }
    }
    table
}

/// Sum of the box rows `r0..r1`, columns `c0..c1` (exclusive ends).
fn box_sum(table: &[f64], width: usize, r0: usize, r1: usize, c0: usize, c1: usize) -> f64 {
    let w = width + 1;
    table[r1 * w + c1] - table[r0 * w + c1] - table[r1 * w + c0] + table[r0 * w + c0]
}

/// `[pixels, Σ count, Σ count²]` of the pixels of `block` away from spots:
/// a pixel is left out when a 5 × 5 box within 3 px of it sums to more
/// than 4 standard deviations above `level`'s background.
fn background_sums(frames: &FrameStack, block: &[usize], level: &Level) -> Vec<f64> {
    let (height, width) = (frames.height, frames.width);
    let radius = 2usize;
    let grow = 3usize;
    let box_pixels = ((2 * radius + 1) * (2 * radius + 1)) as f64;
    let limit = level.background * box_pixels
        + 4.0 * (level.variance_ratio.max(0.5) * level.background * box_pixels).sqrt();
    let mut sums = vec![0.0; 3];
    let mut bright = vec![0.0; height * width];
    for &f in block {
        let frame = frames.frame(f);
        let values: Vec<f64> = frame.iter().map(|&c| c as f64).collect();
        let table = integral(&values, height, width);
        for r in 0..height {
            for c in 0..width {
                let (r0, r1) = (r.saturating_sub(radius), (r + radius + 1).min(height));
                let (c0, c1) = (c.saturating_sub(radius), (c + radius + 1).min(width));
                let area = ((r1 - r0) * (c1 - c0)) as f64;
                let sum = box_sum(&table, width, r0, r1, c0, c1) * box_pixels / area;
                bright[r * width + c] = if sum > limit { 1.0 } else { 0.0 };
            }
        }
        let near = integral(&bright, height, width);
        for r in 0..height {
            for c in 0..width {
                let (r0, r1) = (r.saturating_sub(grow), (r + grow + 1).min(height));
                let (c0, c1) = (c.saturating_sub(grow), (c + grow + 1).min(width));
                if box_sum(&near, width, r0, r1, c0, c1) == 0.0 {
                    let v = values[r * width + c];
                    sums[0] += 1.0;
                    sums[1] += v;
                    sums[2] += v * v;
                }
            }
        }
    }
    sums
}

/// Sums of `d(r, c)·d(r, c + k)` for k = 0..=lags_x, then of
/// `d(r, c)·d(r + k, c)` for k = 0..=lags_y, with their pair counts
/// folded in as means per lag at the end of the block (d = count −
/// background). Returned as sums so blocks add.
fn autocorrelation_sums(
    frames: &FrameStack,
    block: &[usize],
    background: f64,
    lags_x: usize,
    lags_y: usize,
) -> Vec<f64> {
    let (height, width) = (frames.height, frames.width);
    let mut sums = vec![0.0; lags_x + 1 + lags_y + 1];
    let mut d = vec![0.0; height * width];
    for &f in block {
        for (v, &c) in d.iter_mut().zip(frames.frame(f)) {
            *v = c as f64 - background;
        }
        for r in 0..height {
            let row = &d[r * width..(r + 1) * width];
            for k in 0..=lags_x {
                let s: f64 = row[..width - k]
                    .iter()
                    .zip(&row[k..])
                    .map(|(a, b)| a * b)
                    .sum();
                sums[k] += s / (width - k) as f64;
            }
        }
        for k in 0..=lags_y {
            let mut s = 0.0;
            for r in 0..height - k {
                let (top, below) = (
                    &d[r * width..(r + 1) * width],
                    &d[(r + k) * width..(r + k + 1) * width],
                );
                s += top.iter().zip(below).map(|(a, b)| a * b).sum::<f64>();
            }
            sums[lags_x + 1 + k] += s / ((height - k) * width) as f64;
        }
    }
    sums
}

/// A fitted Gaussian autocorrelation `B + S·exp(−k²/4s²)`.
#[derive(Debug, Clone, Copy)]
struct LagFit {
    /// s: the profile's standard deviation, px.
    width_px: f64,
}

/// Least squares of `B + S·exp(−k²/(4s²))` to lags 1.. of `sums` (lag 0
/// holds the noise's variance and is left out): a grid over s, then a
/// golden-section refinement; `None` without a positive S.
fn fit_gaussian_lags(sums: &[f64]) -> Option<LagFit> {
    let values = &sums[1..];
    let lags: Vec<f64> = (1..sums.len()).map(|k| k as f64).collect();
    let residual = |s: f64| -> (f64, f64) {
        // Linear least squares in (B, S) for this s.
        let g: Vec<f64> = lags
            .iter()
            .map(|k| (-k * k / (4.0 * s * s)).exp())
            .collect();
        let n = g.len() as f64;
        let (sg, sy) = (g.iter().sum::<f64>(), values.iter().sum::<f64>());
        let sgg = g.iter().map(|v| v * v).sum::<f64>();
        let sgy = g.iter().zip(values).map(|(a, b)| a * b).sum::<f64>();
        let det = n * sgg - sg * sg;
        if det.abs() < 1e-300 {
            return (f64::INFINITY, 0.0);
        }
        let amplitude = (n * sgy - sg * sy) / det;
        let base = (sy - amplitude * sg) / n;
        let rss = g
            .iter()
            .zip(values)
            .map(|(gv, y)| (y - base - amplitude * gv).powi(2))
            .sum::<f64>();
        (rss, amplitude)
    };
    let top = (lags.len() as f64).max(2.0);
    let grid: Vec<f64> = (0..400)
        .map(|i| 0.2 * (top / 0.2).powf(i as f64 / 399.0))
        .collect();
    let best = grid
        .iter()
        .enumerate()
        .filter(|(_, s)| residual(**s).1 > 0.0)
        .min_by(|a, b| residual(*a.1).0.total_cmp(&residual(*b.1).0))?
        .0;
    let (mut lo, mut hi) = (
        grid[best.saturating_sub(1)],
        grid[(best + 1).min(grid.len() - 1)],
    );
    let ratio = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..60 {
        let m1 = hi - ratio * (hi - lo);
        let m2 = lo + ratio * (hi - lo);
        if residual(m1).0 < residual(m2).0 {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let width_px = 0.5 * (lo + hi);
    (residual(width_px).1 > 0.0).then_some(LagFit { width_px })
}

/// The fraction of a Gaussian of standard deviation `s` px inside a window
/// of `2·half + 1` pixels centred on it.
fn captured_fraction(half: usize, s: f64) -> f64 {
    if s <= 0.0 {
        return 1.0;
    }
    let z = (half as f64 + 0.5) / s;
    2.0 * normal_cdf(z) - 1.0
}

/// The noise of a spot's matched-filter total (see [`spot_totals`]):
/// background photon noise, the spot's own photon noise and the relative
/// spread κ.
#[derive(Debug, Clone, Copy)]
struct Noise {
    /// Variance of a total without a spot.
    background: f64,
    /// Variance per photon of the spot.
    per_photon: f64,
}

impl Noise {
    /// Standard deviation of a total with mean `signal` and spread κ.
    fn sd(&self, signal: f64, spread: f64) -> f64 {
        (self.background + self.per_photon * signal.max(0.0) + (spread * signal).powi(2)).sqrt()
    }
}

/// The separable Gaussian kernel of the spots: `exp(−k²/2s²)` for
/// `|k| ≤ half` along each axis.
#[derive(Debug, Clone)]
struct Kernel {
    x: Vec<f64>,
    y: Vec<f64>,
    half_x: usize,
    half_y: usize,
    /// Σg / Σg² over the 2-D kernel: a spot `T·g/Σg` gives `c·Σ g·d = T`.
    scale: f64,
}

impl Kernel {
    fn new(s_x: f64, s_y: f64) -> Self {
        let axis = |s: f64| {
            let half = (2.5 * s).ceil().max(1.0) as usize;
            let values: Vec<f64> = (0..=2 * half)
                .map(|i| {
                    let k = i as f64 - half as f64;
                    (-k * k / (2.0 * s * s)).exp()
                })
                .collect();
            (values, half)
        };
        let ((x, half_x), (y, half_y)) = (axis(s_x), axis(s_y));
        let sum = |v: &[f64], p: i32| v.iter().map(|g| g.powi(p)).sum::<f64>();
        let scale = sum(&x, 1) * sum(&y, 1) / (sum(&x, 2) * sum(&y, 2));
        Kernel {
            x,
            y,
            half_x,
            half_y,
            scale,
        }
    }

    fn power_sum(&self, p: i32) -> f64 {
        self.x.iter().map(|g| g.powi(p)).sum::<f64>()
            * self.y.iter().map(|g| g.powi(p)).sum::<f64>()
    }

    /// The noise of a total from one colour of the checkerboard, doubled,
    /// with background `b` and variance-to-mean ratio `ratio`.
    fn noise(&self, b: f64, ratio: f64) -> Noise {
        let c = self.scale;
        Noise {
            background: 2.0 * c * c * ratio * b * self.power_sum(2),
            per_photon: 2.0 * c * c * ratio * self.power_sum(3) / self.power_sum(1),
        }
    }

    /// `Σ g·values` around every pixel whose kernel lies inside the frame
    /// (0 elsewhere).
    fn filter(&self, values: &[f64], height: usize, width: usize) -> Vec<f64> {
        let mut rows = vec![0.0; height * width];
        for r in 0..height {
            for c in self.half_x..width.saturating_sub(self.half_x) {
                let start = r * width + c - self.half_x;
                rows[r * width + c] = self
                    .x
                    .iter()
                    .zip(&values[start..])
                    .map(|(g, v)| g * v)
                    .sum();
            }
        }
        let mut out = vec![0.0; height * width];
        for r in self.half_y..height.saturating_sub(self.half_y) {
            for c in self.half_x..width.saturating_sub(self.half_x) {
                out[r * width + c] = self
                    .y
                    .iter()
                    .enumerate()
                    .map(|(i, g)| g * rows[(r + i - self.half_y) * width + c])
                    .sum();
            }
        }
        out
    }
}

/// The matched-filter totals of the spots of frame `f`: pixels where the
/// filter over the black squares of a checkerboard ((r + c) even) is a
/// local maximum whose total exceeds `selection_cut`, the total
/// taken from the white squares and doubled (so the noise that made the
/// maximum is not in the total). Kernels reaching past the frame are
/// skipped.
fn spot_totals(
    frames: &FrameStack,
    f: usize,
    background: f64,
    kernel: &Kernel,
    selection_cut: f64,
) -> Vec<f64> {
    let (height, width) = (frames.height, frames.width);
    if 2 * kernel.half_y + 1 > height || 2 * kernel.half_x + 1 > width {
        return Vec::new();
    }
    let frame = frames.frame(f);
    let mut black = vec![0.0; height * width];
    let mut white = vec![0.0; height * width];
    for r in 0..height {
        for c in 0..width {
            let d = frame[r * width + c] as f64 - background;
            if (r + c) % 2 == 0 {
                black[r * width + c] = d;
            } else {
                white[r * width + c] = d;
            }
        }
    }
    let selection = kernel.filter(&black, height, width);
    let cut = selection_cut / (2.0 * kernel.scale);
    let (hx, hy) = (kernel.half_x, kernel.half_y);
    let mut candidates = Vec::new();
    for r in hy..height - hy {
        for c in hx..width - hx {
            let value = selection[r * width + c];
            if value <= cut {
                continue;
            }
            let (ry, rx) = (hy.div_ceil(2), hx.div_ceil(2));
            let mut is_max = true;
            'scan: for rr in r.saturating_sub(ry).max(hy)..(r + ry + 1).min(height - hy) {
                for cc in c.saturating_sub(rx).max(hx)..(c + rx + 1).min(width - hx) {
                    let other = selection[rr * width + cc];
                    if other > value || (other == value && (rr, cc) < (r, c)) {
                        is_max = false;
                        break 'scan;
                    }
                }
            }
            if is_max {
                candidates.push((r, c));
            }
        }
    }
    if candidates.is_empty() {
        return Vec::new();
    }
    let totals = kernel.filter(&white, height, width);
    candidates
        .into_iter()
        .map(|(r, c)| 2.0 * kernel.scale * totals[r * width + c])
        .collect()
}

/// The in-focus total T₀ with its standard error, and the spread κ.
struct TotalFit {
    total: f64,
    standard_error: f64,
    spread: f64,
}

/// A spot is a candidate where its total measured on the black squares
/// exceeds this many background standard deviations...
const SELECTION_SD: f64 = 2.5;
/// ...and is kept where its total on the white squares exceeds this many.
const THRESHOLD_SD: f64 = 3.0;

/// The detection's cuts on a spot's two totals (black, white squares).
#[derive(Debug, Clone, Copy)]
struct Cuts {
    selection: f64,
    total: f64,
}

/// Maximum likelihood of T₀ and κ: a detected total is `T₀·exp(−u²/2)`
/// (u uniform: depth in units of σz) plus noise of [`Noise::sd`],
/// conditioned on detection (its black-square total above
/// `cuts.selection`, its white-square total above `cuts.total`; the two
/// have independent noise of the same size). `totals` pair a block of
/// frames with a total; the standard error is the larger of the profile
/// likelihood's and a jackknife's over the blocks (spots of the same QD in
/// nearby frames are not independent).
fn fit_in_focus_total(totals: &[(usize, f64)], cuts: &Cuts, noise: &Noise) -> TotalFit {
    let likelihood = TotalLikelihood { cuts, noise };
    let best = likelihood.maximise(totals);
    let jackknife_error = likelihood.jackknife_error(totals, &best);
    TotalFit {
        total: best.total,
        standard_error: best.profile_error.max(jackknife_error),
        spread: best.spread,
    }
}

/// The likelihood of detected totals given T₀ and κ (see
/// [`fit_in_focus_total`]).
struct TotalLikelihood<'a> {
    cuts: &'a Cuts,
    noise: &'a Noise,
}

/// The profile likelihood's maximum.
struct ProfileMaximum {
    total: f64,
    /// κ at the maximum.
    spread: f64,
    /// Half the interval where the profile is within ½ of its peak (at
    /// least half the grid's step).
    profile_error: f64,
}

/// The spreads κ the profile likelihood maximises over (a grid: the
/// likelihood is flat in κ, and T₀ is what is reported).
const SPREADS: [f64; 8] = [0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.6];

impl TotalLikelihood<'_> {
    /// The log likelihood of `totals` with in-focus total `t0` and spread
    /// `spread`: the density of each total, integrated over depth u on a
    /// grid and conditioned on detection.
    fn log_likelihood(&self, totals: &[(usize, f64)], t0: f64, spread: f64) -> f64 {
        let (cuts, noise) = (self.cuts, self.noise);
        let threshold = cuts.total;
        // u from 0 to where the mean total is 1 % of the threshold.
        let top = (2.0 * (t0 / (0.01 * threshold)).ln()).max(1e-6).sqrt();
        let steps = 240;
        let du = top / steps as f64;
        let grid: Vec<(f64, f64, f64)> = (0..=steps)
            .map(|j| {
                let u = j as f64 * du;
                let mean = t0 * (-0.5 * u * u).exp();
                let sd = noise.sd(mean, spread);
                (mean, sd, normal_cdf((mean - cuts.selection) / sd))
            })
            .collect();
        // The trapezoid rule's weights.
        let weight = |j: usize| if j == 0 || j == steps { 0.5 } else { 1.0 };
        let detected: f64 = grid
            .iter()
            .enumerate()
            .map(|(j, (mean, sd, selected))| {
                weight(j) * selected * normal_cdf((mean - threshold) / sd)
            })
            .sum::<f64>()
            * du;
        if detected.is_nan() || detected <= 0.0 {
            return f64::NEG_INFINITY;
        }
        let sum: f64 = totals
            .par_iter()
            .map(|&(_, t)| {
                let density: f64 = grid
                    .iter()
                    .enumerate()
                    .map(|(j, (mean, sd, selected))| {
                        let z = (t - mean) / sd;
                        weight(j) * selected * (-0.5 * z * z).exp() / sd
                    })
                    .sum::<f64>()
                    * du;
                density.max(1e-300).ln()
            })
            .sum();
        sum - totals.len() as f64 * detected.ln()
    }

    /// The profile likelihood at `t0`: the best over [`SPREADS`], and that
    /// spread.
    fn profile(&self, totals: &[(usize, f64)], t0: f64) -> (f64, f64) {
        SPREADS
            .iter()
            .map(|&k| (self.log_likelihood(totals, t0, k), k))
            .fold((f64::NEG_INFINITY, 0.0), |best, x| {
                if x.0 > best.0 { x } else { best }
            })
    }

    /// The profile's maximum over T₀ between the threshold and twice the
    /// largest total: a coarse log grid, then a finer one around its best.
    fn maximise(&self, totals: &[(usize, f64)]) -> ProfileMaximum {
        let threshold = self.cuts.total;
        let high = totals.iter().map(|t| t.1).fold(threshold, f64::max) * 2.0;
        let low = threshold;
        let coarse: Vec<f64> = (0..40)
            .map(|i| low * (high / low).powf(i as f64 / 39.0))
            .collect();
        let scores: Vec<(f64, f64)> = coarse.iter().map(|&t| self.profile(totals, t)).collect();
        let best = (0..coarse.len())
            .max_by(|&a, &b| scores[a].0.total_cmp(&scores[b].0))
            .unwrap_or(0);
        let (lo, hi) = (
            coarse[best.saturating_sub(2)],
            coarse[(best + 2).min(coarse.len() - 1)],
        );
        let fine: Vec<f64> = (0..41).map(|i| lo + (hi - lo) * i as f64 / 40.0).collect();
        let fine_scores: Vec<(f64, f64)> = fine.iter().map(|&t| self.profile(totals, t)).collect();
        let top = (0..fine.len())
            .max_by(|&a, &b| fine_scores[a].0.total_cmp(&fine_scores[b].0))
            .unwrap_or(0);
        let peak = fine_scores[top].0;
        // The interval where the profile is within ½ of its peak.
        let inside: Vec<f64> = fine
            .iter()
            .zip(&fine_scores)
            .filter(|(_, s)| s.0 >= peak - 0.5)
            .map(|(t, _)| *t)
            .collect();
        let (min, max) = inside
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &t| {
                (a.min(t), b.max(t))
            });
        let step = (hi - lo) / 40.0;
        ProfileMaximum {
            total: fine[top],
            spread: fine_scores[top].1,
            profile_error: ((max - min) / 2.0).max(step / 2.0),
        }
    }

    /// The jackknife's standard error of T₀ over the blocks of frames
    /// (spots of one QD in nearby frames are not independent, which the
    /// profile's error ignores): each block left out in turn, T₀ refitted
    /// on a grid of ±5 profile errors around `best` (κ kept). NaN with
    /// fewer than two blocks.
    fn jackknife_error(&self, totals: &[(usize, f64)], best: &ProfileMaximum) -> f64 {
        let threshold = self.cuts.total;
        let blocks = totals.iter().map(|t| t.0 + 1).max().unwrap_or(0);
        let refits: Vec<f64> = (0..blocks)
            .map(|left_out| {
                let rest: Vec<(usize, f64)> =
                    totals.iter().copied().filter(|t| t.0 != left_out).collect();
                let grid: Vec<f64> = (0..41)
                    .map(|i| best.total + best.profile_error * (i as f64 - 20.0) / 4.0)
                    .filter(|&t| t > threshold)
                    .collect();
                let scores: Vec<f64> = grid
                    .iter()
                    .map(|&t| self.log_likelihood(&rest, t, best.spread))
                    .collect();
                (0..grid.len())
                    .max_by(|&a, &b| scores[a].total_cmp(&scores[b]))
                    .map(|i| grid[i])
                    .unwrap_or(best.total)
            })
            .collect();
        if refits.len() < 2 {
            return f64::NAN;
        }
        let k = refits.len() as f64;
        let mean = refits.iter().sum::<f64>() / k;
        ((k - 1.0) / k * refits.iter().map(|v| (v - mean).powi(2)).sum::<f64>()).sqrt()
    }
}

/// The standard normal's cumulative distribution function, from the
/// complementary error function of Abramowitz & Stegun 7.1.26 (absolute
/// error below 1.5·10⁻⁷).
fn normal_cdf(x: f64) -> f64 {
    let z = x.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * z);
    let poly = t
        * (0.254_829_592
            + t * (-0.284_496_736
                + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    let erfc = poly * (-z * z).exp();
    if x >= 0.0 {
        1.0 - 0.5 * erfc
    } else {
        0.5 * erfc
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gaussian_lags_recover_their_width() {
        let sums: Vec<f64> = (0..30)
            .map(|k| 0.3 + 2.0 * (-(k as f64).powi(2) / (4.0 * 2.5f64.powi(2))).exp())
            .collect();
        let fit = fit_gaussian_lags(&sums).unwrap();
        assert!((fit.width_px - 2.5).abs() < 1e-3, "{}", fit.width_px);
    }

    #[test]
    fn normal_cdf_matches_known_values() {
        assert!((normal_cdf(0.0) - 0.5).abs() < 1e-7);
        assert!((normal_cdf(1.959_964) - 0.975).abs() < 1e-6);
        assert!((normal_cdf(-1.0) - 0.158_655_25).abs() < 1e-6);
    }
}
