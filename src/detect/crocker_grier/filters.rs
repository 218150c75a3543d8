//! The image operations of TrackPy's `locate`, reproducing the arithmetic
//! of the scipy.ndimage and numpy routines it calls, so that integer
//! truncations and threshold comparisons land exactly where TrackPy's do.

/// Reusable per-thread buffers of the image operations.
#[derive(Default)]
pub(super) struct Buffers {
    background: Vec<f64>,
    lowpass: Vec<f64>,
    scratch: Vec<f64>,
    padded: Vec<f64>,
    not_black: Vec<u64>,
    nonzero_prefix: Vec<u32>,
    background_values: Vec<f64>,
}

/// TrackPy's `bandpass(image, noise_size, smoothing_size, threshold)`: a
/// Gaussian low pass (σ = `noise_size`, kernel truncated at 4σ, zero
/// outside the frame) minus a boxcar average over `smoothing_size` (edge
/// pixels repeated outside the frame; for an integer image each axis pass
/// truncated to integers as scipy does for integer arrays, for real values
/// none), with values below `threshold` set to 0. Returns the row-major
/// result.
///
/// Every pixel sees the same floating-point operations in the same order as
/// in scipy; the column passes are written as operations on whole rows so
/// they vectorise.
pub(super) fn bandpass<'a, P: super::Pixel>(
    raw: &[P],
    height: usize,
    width: usize,
    noise_size: f64,
    smoothing_size: usize,
    threshold: f64,
    buffers: &'a mut Buffers,
) -> &'a [f64] {
    let Buffers {
        background,
        lowpass,
        scratch,
        padded,
        ..
    } = buffers;
    background.clear();
    background.extend(raw.iter().map(|&v| v.value()));
    if smoothing_size > 1 {
        boxcar_columns(background, height, width, smoothing_size, scratch);
        if P::INTEGER {
            truncate_to_integers(background);
        }
        for row in background.chunks_exact_mut(width) {
            boxcar_line(row, smoothing_size, padded);
        }
        if P::INTEGER {
            truncate_to_integers(background);
        }
    }
    lowpass.clear();
    lowpass.extend(raw.iter().map(|&v| v.value()));
    if noise_size > 0.0 {
        let kernel = gaussian_kernel(noise_size);
        correlate_columns(lowpass, height, width, &kernel, scratch);
        for row in lowpass.chunks_exact_mut(width) {
            correlate_line(row, &kernel, padded);
        }
    }
    for (value, &back) in lowpass.iter_mut().zip(background.iter()) {
        let difference = *value - back;
        *value = if difference >= threshold {
            difference
        } else {
            0.0
        };
    }
    lowpass
}

/// Integer arrays keep each filter pass as integers (C truncation towards
/// zero; the averages are never negative).
fn truncate_to_integers(values: &mut [f64]) {
    for value in values {
        *value = (*value as u64) as f64;
    }
}

/// scipy's `uniform_filter1d(mode='nearest')` along one row, in place: a
/// running sum updated by `incoming − outgoing` and divided by `size` at
/// each position, as scipy (≥ 1.x) computes it. For integer inputs the sums
/// are exact, so the truncation that follows lands where scipy's does.
fn boxcar_line(line: &mut [f64], size: usize, padded: &mut Vec<f64>) {
    let length = line.len();
    let before = size / 2;
    let after = size - before - 1;
    padded.clear();
    padded.extend(std::iter::repeat_n(line[0], before));
    padded.extend_from_slice(line);
    padded.extend(std::iter::repeat_n(line[length - 1], after));
    let mut sum: f64 = padded[..size].iter().sum();
    line[0] = sum / size as f64;
    for l in 1..length {
        sum += padded[l + size - 1] - padded[l - 1];
        line[l] = sum / size as f64;
    }
}

/// [`boxcar_line`] down every column at once (numpy axis 0).
fn boxcar_columns(
    image: &mut [f64],
    height: usize,
    width: usize,
    size: usize,
    scratch: &mut Vec<f64>,
) {
    let before = size / 2;
    // Row `i` of the edge-extended image.
    let extended = |i: usize| (i.saturating_sub(before)).min(height - 1);
    scratch.clear();
    scratch.extend_from_slice(image);
    let source = &scratch[..];
    let mut sum = vec![0.0; width];
    for i in 0..size {
        let row = &source[extended(i) * width..][..width];
        for (s, &v) in sum.iter_mut().zip(row) {
            *s += v;
        }
    }
    for (out, &s) in image[..width].iter_mut().zip(&sum) {
        *out = s / size as f64;
    }
    for l in 1..height {
        let incoming = &source[extended(l + size - 1) * width..][..width];
        let outgoing = &source[extended(l - 1) * width..][..width];
        let out = &mut image[l * width..(l + 1) * width];
        for c in 0..width {
            sum[c] += incoming[c] - outgoing[c];
            out[c] = sum[c] / size as f64;
        }
    }
}

/// scipy's `correlate1d(mode='constant', cval=0)` with a symmetric odd
/// kernel along one row, in place: `x·w₀ + Σ_(outermost first) (x₋ⱼ + x₊ⱼ)·wⱼ`.
fn correlate_line(line: &mut [f64], kernel: &[f64], padded: &mut Vec<f64>) {
    let half = kernel.len() / 2;
    padded.clear();
    padded.resize(half, 0.0);
    padded.extend_from_slice(line);
    padded.resize(line.len() + 2 * half, 0.0);
    for (l, out) in line.iter_mut().enumerate() {
        let centre = l + half;
        let mut sum = padded[centre] * kernel[half];
        for j in (1..=half).rev() {
            sum += (padded[centre - j] + padded[centre + j]) * kernel[half - j];
        }
        *out = sum;
    }
}

/// [`correlate_line`] down every column at once (numpy axis 0).
fn correlate_columns(
    image: &mut [f64],
    height: usize,
    width: usize,
    kernel: &[f64],
    scratch: &mut Vec<f64>,
) {
    let half = kernel.len() / 2;
    scratch.clear();
    scratch.extend_from_slice(image);
    let zeros = vec![0.0; width];
    let row = |i: isize| -> &[f64] {
        if (0..height as isize).contains(&i) {
            &scratch[i as usize * width..][..width]
        } else {
            &zeros
        }
    };
    for l in 0..height {
        let out = &mut image[l * width..(l + 1) * width];
        let centre = row(l as isize);
        for c in 0..width {
            out[c] = centre[c] * kernel[half];
        }
        for j in (1..=half).rev() {
            let (above, below) = (row(l as isize - j as isize), row(l as isize + j as isize));
            let weight = kernel[half - j];
            for c in 0..width {
                out[c] += (above[c] + below[c]) * weight;
            }
        }
    }
}

/// TrackPy's `gaussian_kernel(sigma, truncate=4)`: `exp(−x²/2σ²)` for
/// `|x| ≤ ⌊4σ + 0.5⌋`, normalised by numpy's sum.
fn gaussian_kernel(sigma: f64) -> Vec<f64> {
    let half = (4.0 * sigma + 0.5) as i64;
    let values: Vec<f64> = (-half..=half)
        .map(|x| ((x * x) as f64 / (-2.0 * sigma * sigma)).exp())
        .collect();
    let total = numpy_sum(&values);
    values.into_iter().map(|v| v / total).collect()
}

/// numpy's pairwise summation of a contiguous float array, so sums agree
/// with numpy to the last bit.
pub(super) fn numpy_sum(values: &[f64]) -> f64 {
    let n = values.len();
    if n < 8 {
        return values.iter().fold(0.0, |sum, &v| sum + v);
    }
    if n <= 128 {
        let mut r = [0.0; 8];
        r.copy_from_slice(&values[..8]);
        let whole = n - n % 8;
        let mut i = 8;
        while i < whole {
            for (k, slot) in r.iter_mut().enumerate() {
                *slot += values[i + k];
            }
            i += 8;
        }
        let mut sum = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for &v in &values[whole..] {
            sum += v;
        }
        return sum;
    }
    let half = (n / 2) - (n / 2) % 8;
    numpy_sum(&values[..half]) + numpy_sum(&values[half..])
}

/// numpy's `percentile(values, q)` with linear interpolation.
fn percentile(values: &mut [u64], q: f64) -> f64 {
    let position = (q / 100.0) * (values.len() - 1) as f64;
    let below = position.floor();
    let t = position - below;
    let index = below as usize;
    let (_, &mut low, rest) = values.select_nth_unstable(index);
    let low = low as f64;
    // The next order statistic is the smallest of the values above.
    let high = rest.iter().copied().min().map_or(low, |v| v as f64);
    let difference = high - low;
    // numpy's `_lerp` interpolates from the nearer end.
    if t >= 0.5 {
        high - difference * (1.0 - t)
    } else {
        low + difference * t
    }
}

/// TrackPy's `grey_dilation(image, separation, percentile, margin,
/// precise=False)`: pixels equal to the maximum over a square of side
/// `⌊2·separation/√2⌋` (zero outside the frame), above the percentile of
/// the non-zero pixels, and not within `margin` of an edge. Row-major order.
#[allow(clippy::too_many_arguments)]
pub(super) fn local_maxima(
    image: &[u64],
    height: usize,
    width: usize,
    separation: f64,
    percentile_q: f64,
    margin: f64,
    buffers: &mut Buffers,
    peaks: &mut Vec<(usize, usize)>,
) {
    peaks.clear();
    let not_black = &mut buffers.not_black;
    not_black.clear();
    not_black.extend(image.iter().copied().filter(|&v| v != 0));
    if not_black.is_empty() {
        return;
    }
    let threshold = percentile(not_black, percentile_q);
    let size = ((2.0 * separation / 2f64.sqrt()) as usize).max(1);
    // grey_dilation reflects its footprint: for an even `size` the window
    // of output p covers inputs p − (size − ⌊size/2⌋ − 1) … p + ⌊size/2⌋.
    // Outside the frame counts as 0 (mode 'constant'), which never raises
    // a maximum of counts.
    let before = size - size / 2 - 1;
    let after = size / 2;
    let near_edge = |position: usize, extent: usize| {
        (position as f64) < margin || position as f64 > extent as f64 - margin - 1.0
    };
    // A pixel equals its dilation when nothing in its window is brighter;
    // only pixels above the threshold and away from the edges can qualify,
    // and most candidates meet a brighter neighbour within a few looks.
    for row in 0..height {
        if near_edge(row, height) {
            continue;
        }
        let rows = row.saturating_sub(before)..(row + after + 1).min(height);
        'candidate: for column in 0..width {
            let value = image[row * width + column];
            if value as f64 <= threshold || near_edge(column, width) {
                continue;
            }
            let columns = column.saturating_sub(before)..(column + after + 1).min(width);
            for r in rows.clone() {
                if image[r * width + columns.start..r * width + columns.end]
                    .iter()
                    .any(|&other| other > value)
                {
                    continue 'candidate;
                }
            }
            peaks.push((row, column));
        }
    }
}

/// TrackPy's `measure_noise`: the mean and (population) standard deviation
/// of the raw pixels farther than the mask radius from every non-zero pixel
/// of the band-passed image. NaN where too few such pixels exist.
pub(super) fn measure_noise<P: super::Pixel>(
    image: &[u64],
    raw: &[P],
    height: usize,
    width: usize,
    mask: &super::Mask,
    buffers: &mut Buffers,
) -> (f64, f64) {
    // Per row, a prefix count of non-zero pixels: a pixel is in the
    // dilation if some mask row's span around it holds a non-zero pixel.
    let stride = width + 1;
    let prefix = &mut buffers.nonzero_prefix;
    prefix.clear();
    prefix.resize(height * stride, 0);
    for r in 0..height {
        for c in 0..width {
            prefix[r * stride + c + 1] =
                prefix[r * stride + c] + u32::from(image[r * width + c] != 0);
        }
    }
    let spans = &mask.row_half_widths;
    let radius = mask.radius as isize;
    let values = &mut buffers.background_values;
    values.clear();
    for r in 0..height as isize {
        'pixel: for c in 0..width as isize {
            for (dy, &half_width) in spans.iter().enumerate() {
                let y = r + dy as isize - radius;
                if !(0..height as isize).contains(&y) {
                    continue;
                }
                let low = (c - half_width as isize).max(0) as usize;
                let high = ((c + half_width as isize + 1).min(width as isize)) as usize;
                let row = y as usize * stride;
                if prefix[row + high] > prefix[row + low] {
                    continue 'pixel;
                }
            }
            values.push(raw[r as usize * width + c as usize].value());
        }
    }
    match values.len() {
        0 => (f64::NAN, f64::NAN),
        1 => (values[0], f64::NAN),
        n => {
            let mean = numpy_sum(values) / n as f64;
            for value in values.iter_mut() {
                *value = (*value - mean) * (*value - mean);
            }
            (mean, (numpy_sum(values) / n as f64).sqrt())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numpy_pairwise_sum_orders_additions_like_numpy() {
        // 0.1 × 10 summed sequentially is 0.9999999999999999; numpy's
        // pairwise order gives 1.0000000000000002 for this input.
        let values = vec![0.1; 10];
        assert_eq!(
            numpy_sum(&values),
            ((0.1 + 0.1) + (0.1 + 0.1) + ((0.1 + 0.1) + (0.1 + 0.1))) + 0.1 + 0.1
        );
    }

    #[test]
    fn percentile_interpolates_linearly() {
        assert_eq!(percentile(&mut [1, 2, 3, 4, 5], 50.0), 3.0);
        assert_eq!(percentile(&mut [10, 20], 25.0), 12.5);
        assert_eq!(percentile(&mut [7], 64.0), 7.0);
    }
}
