//! The image operations of TrackPy's `locate`, reproducing the arithmetic
//! of the scipy.ndimage and numpy routines it calls, so that integer
//! truncations and threshold comparisons land exactly where TrackPy's do.

/// Reusable per-thread buffers of the image operations.
#[derive(Default)]
pub(super) struct Buffers {
    values: Vec<f64>,
    background: Vec<f64>,
    lowpass: Vec<f64>,
    padded: Vec<f64>,
    sums: Vec<f64>,
    not_black: Vec<u32>,
    dilation: Vec<u32>,
    line: Vec<u32>,
    line_next: Vec<u32>,
    padded_rows: Vec<u32>,
    reach: Vec<u8>,
    covered: Vec<u8>,
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
/// in scipy; the passes are written as operations on whole rows (or, for
/// the running sums along rows, on all rows at each column) so they
/// vectorise.
#[inline(always)]
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
        values,
        background,
        lowpass,
        padded,
        sums,
        ..
    } = buffers;
    values.clear();
    values.extend(raw.iter().map(|&v| v.value()));
    background.clear();
    if smoothing_size > 1 {
        boxcar_columns(values, height, width, smoothing_size, background, sums);
        if P::INTEGER {
            truncate_to_integers(background);
        }
        boxcar_rows(background, width, smoothing_size, padded);
        if P::INTEGER {
            truncate_to_integers(background);
        }
    } else {
        background.extend_from_slice(values);
    }
    lowpass.clear();
    if noise_size > 0.0 {
        let kernel = gaussian_kernel(noise_size);
        correlate_columns(values, height, width, &kernel, lowpass);
        for row in lowpass.chunks_exact_mut(width) {
            correlate_line(row, &kernel, padded);
        }
    } else {
        lowpass.extend_from_slice(values);
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

/// 2⁵²: from here up every float is a whole number.
const TWO_52: f64 = 4_503_599_627_370_496.0;

/// `x` truncated towards zero, for `0 ≤ x < 2⁵²`: `x + 2⁵² − 2⁵²` rounds
/// to a whole number (exactly), one less when that rounded up. Float
/// arithmetic only, so it vectorises (no libm call, no integer cast).
#[inline(always)]
fn truncate_small(x: f64) -> f64 {
    let rounded = (x + TWO_52) - TWO_52;
    if rounded > x { rounded - 1.0 } else { rounded }
}

/// `x as u32` for `0 ≤ x ≤ u32::MAX`: the whole number `t` below `x`
/// is the low bits of `t + 2⁵²`.
#[inline(always)]
pub(super) fn small_to_u32(x: f64) -> u32 {
    (truncate_small(x) + TWO_52).to_bits() as u32
}

/// Integer arrays keep each filter pass as integers (C truncation towards
/// zero; the averages are never negative and below 2³², and 2⁵² and up
/// are whole already).
#[inline(always)]
fn truncate_to_integers(values: &mut [f64]) {
    for value in values {
        let v = *value;
        // Both computed, then one picked: a select, which vectorises.
        let truncated = truncate_small(v);
        *value = if v < TWO_52 { truncated } else { v };
    }
}

/// scipy's `uniform_filter1d(mode='nearest')` along every row, in place:
/// per row a running sum updated by `incoming − outgoing` and divided by
/// `size` at each position, as scipy (≥ 1.x) computes it. For integer
/// inputs the sums are exact, so the truncation that follows lands where
/// scipy's does. Rows go [`ROWS_AT_ONCE`] at a time, their (independent)
/// running sums advanced together so the additions overlap.
#[inline(always)]
fn boxcar_rows(image: &mut [f64], width: usize, size: usize, padded: &mut Vec<f64>) {
    let before = size / 2;
    let after = size - before - 1;
    // Each row edge-extended, `stride` values apart.
    let stride = width + size - 1;
    let divisor = size as f64;
    for rows in image.chunks_mut(ROWS_AT_ONCE * width) {
        padded.clear();
        for row in rows.chunks_exact(width) {
            padded.extend(std::iter::repeat_n(row[0], before));
            padded.extend_from_slice(row);
            padded.extend(std::iter::repeat_n(row[width - 1], after));
        }
        let count = rows.len() / width;
        let mut sums = [0.0; ROWS_AT_ONCE];
        let mut lines: [&[f64]; ROWS_AT_ONCE] = [&[]; ROWS_AT_ONCE];
        for (k, line) in padded.chunks_exact(stride).enumerate() {
            lines[k] = line;
            sums[k] = line[..size].iter().sum();
            rows[k * width] = sums[k] / divisor;
        }
        for l in 1..width {
            for k in 0..count {
                sums[k] += lines[k][l + size - 1] - lines[k][l - 1];
                rows[k * width + l] = sums[k] / divisor;
            }
        }
    }
}

/// Rows whose running sums [`boxcar_rows`] advances together.
const ROWS_AT_ONCE: usize = 4;

/// [`boxcar_rows`] down every column at once (numpy axis 0), from
/// `source` into `out`.
#[inline(always)]
fn boxcar_columns(
    source: &[f64],
    height: usize,
    width: usize,
    size: usize,
    out: &mut Vec<f64>,
    sum: &mut Vec<f64>,
) {
    let before = size / 2;
    let divisor = size as f64;
    // Row `i` of the edge-extended image.
    let extended = |i: usize| (i.saturating_sub(before)).min(height - 1);
    sum.clear();
    sum.resize(width, 0.0);
    for i in 0..size {
        let row = &source[extended(i) * width..][..width];
        for (s, &v) in sum.iter_mut().zip(row) {
            *s += v;
        }
    }
    out.clear();
    out.extend(sum.iter().map(|&s| s / divisor));
    for l in 1..height {
        let incoming = &source[extended(l + size - 1) * width..][..width];
        let outgoing = &source[extended(l - 1) * width..][..width];
        for ((s, &i), &o) in sum.iter_mut().zip(incoming).zip(outgoing) {
            *s += i - o;
        }
        out.extend(sum.iter().map(|&s| s / divisor));
    }
}

/// scipy's `correlate1d(mode='constant', cval=0)` with a symmetric odd
/// kernel along one row, in place: `x·w₀ + Σ_(outermost first) (x₋ⱼ + x₊ⱼ)·wⱼ`,
/// each term added to the whole row in turn.
#[inline(always)]
fn correlate_line(line: &mut [f64], kernel: &[f64], padded: &mut Vec<f64>) {
    let half = kernel.len() / 2;
    let length = line.len();
    padded.clear();
    padded.resize(half, 0.0);
    padded.extend_from_slice(line);
    padded.resize(length + 2 * half, 0.0);
    for (out, &v) in line.iter_mut().zip(&padded[half..]) {
        *out = v * kernel[half];
    }
    for j in (1..=half).rev() {
        let weight = kernel[half - j];
        let left = &padded[half - j..][..length];
        let right = &padded[half + j..][..length];
        for ((out, &a), &b) in line.iter_mut().zip(left).zip(right) {
            *out += (a + b) * weight;
        }
    }
}

/// [`correlate_line`] down every column at once (numpy axis 0), from
/// `source` into `out`.
#[inline(always)]
fn correlate_columns(
    source: &[f64],
    height: usize,
    width: usize,
    kernel: &[f64],
    out: &mut Vec<f64>,
) {
    let half = kernel.len() / 2;
    out.clear();
    out.extend(source.iter().map(|&v| v * kernel[half]));
    for l in 0..height {
        let out = &mut out[l * width..(l + 1) * width];
        for j in (1..=half).rev() {
            let weight = kernel[half - j];
            let row = |i: usize| &source[i * width..(i + 1) * width];
            // Rows outside the frame are 0; `0 + x` is `x` exactly, so
            // a missing row only drops its term's zero.
            match (l.checked_sub(j), (l + j < height).then_some(l + j)) {
                (Some(a), Some(b)) => {
                    for ((o, &x), &y) in out.iter_mut().zip(row(a)).zip(row(b)) {
                        *o += (x + y) * weight;
                    }
                }
                (Some(i), None) | (None, Some(i)) => {
                    for (o, &x) in out.iter_mut().zip(row(i)) {
                        *o += (x + 0.0) * weight;
                    }
                }
                (None, None) => {
                    for o in out.iter_mut() {
                        *o += 0.0 * weight;
                    }
                }
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
#[inline(always)]
fn percentile(values: &mut [u32], q: f64) -> f64 {
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
#[inline(always)]
pub(super) fn local_maxima(
    image: &[u32],
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
    // Written at a cursor that advances past non-zero values (no branch
    // per pixel).
    not_black.clear();
    not_black.resize(image.len(), 0);
    let mut count = 0;
    for &v in image {
        not_black[count] = v;
        count += usize::from(v != 0);
    }
    not_black.truncate(count);
    if not_black.is_empty() {
        return;
    }
    let threshold = percentile(not_black, percentile_q);
    let size = ((2.0 * separation / 2f64.sqrt()) as usize).max(1);
    // A pixel is a peak when it equals the grey dilation (nothing in its
    // window is brighter), computed as a maximum along rows then along
    // columns.
    let dilation = dilate(image, height, width, size, buffers);
    let near_edge = |position: usize, extent: usize| {
        (position as f64) < margin || position as f64 > extent as f64 - margin - 1.0
    };
    for row in 0..height {
        if near_edge(row, height) {
            continue;
        }
        let values = &image[row * width..(row + 1) * width];
        let maxima = &dilation[row * width..(row + 1) * width];
        for (column, (&value, &maximum)) in values.iter().zip(maxima).enumerate() {
            if value == maximum && value as f64 > threshold && !near_edge(column, width) {
                peaks.push((row, column));
            }
        }
    }
}

/// scipy's `grey_dilation(image, size)` (mode 'constant', cval 0): the
/// maximum over a `size × size` window, into `buffers.dilation`.
/// grey_dilation reflects its footprint: for an even `size` the window of
/// output p covers inputs p − (size − ⌊size/2⌋ − 1) … p + ⌊size/2⌋.
/// Outside the frame counts as 0, which never raises a maximum.
///
/// Separable: a maximum along each row, then down each column. Along a
/// line padded with zeros, a window of `size` is the union of two windows
/// of the largest power of two `p ≤ size`, and windows of `p` come from
/// `log₂ p` doublings (`m₂ₛ[i] = max(mₛ[i], mₛ[i + s])`): a few
/// operations per pixel whatever the size, each a whole row at a time.
#[inline(always)]
fn dilate<'a>(
    image: &[u32],
    height: usize,
    width: usize,
    size: usize,
    buffers: &'a mut Buffers,
) -> &'a [u32] {
    let before = size - size / 2 - 1;
    let power = 1usize << size.ilog2();
    let shift = size - power;
    let Buffers {
        dilation,
        line,
        line_next,
        padded_rows,
        ..
    } = buffers;
    // Along rows: each row padded to `width + size − 1` in `line`.
    let length = width + size - 1;
    dilation.clear();
    dilation.resize(height * width, 0);
    for (row, out) in image
        .chunks_exact(width)
        .zip(dilation.chunks_exact_mut(width))
    {
        line.clear();
        line.resize(before, 0);
        line.extend_from_slice(row);
        line.resize(length, 0);
        let mut step = 1;
        while step < power {
            line_next.clear();
            line_next.extend(line.iter().zip(&line[step..]).map(|(&a, &b)| a.max(b)));
            line_next.extend_from_slice(&line[length - step..]);
            std::mem::swap(line, line_next);
            step *= 2;
        }
        for ((o, &a), &b) in out.iter_mut().zip(&line[..width]).zip(&line[shift..]) {
            *o = a.max(b);
        }
    }
    // Down columns: the row maxima padded with `size − 1` rows of zeros.
    padded_rows.clear();
    padded_rows.resize(before * width, 0);
    padded_rows.extend_from_slice(dilation);
    padded_rows.resize((height + size - 1) * width, 0);
    let rows = height + size - 1;
    let mut step = 1;
    while step < power {
        for r in 0..rows - step {
            let (head, tail) = padded_rows.split_at_mut((r + step) * width);
            let target = &mut head[r * width..(r + 1) * width];
            for (t, &v) in target.iter_mut().zip(&tail[..width]) {
                *t = (*t).max(v);
            }
        }
        step *= 2;
    }
    for (r, out) in dilation.chunks_exact_mut(width).enumerate() {
        let a = &padded_rows[r * width..(r + 1) * width];
        let b = &padded_rows[(r + shift) * width..(r + shift + 1) * width];
        for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
            *o = a.max(b);
        }
    }
    dilation
}

/// TrackPy's `measure_noise`: the mean and (population) standard deviation
/// of the raw pixels farther than the mask radius from every non-zero pixel
/// of the band-passed image. NaN where too few such pixels exist.
#[inline(always)]
pub(super) fn measure_noise<P: super::Pixel>(
    image: &[u32],
    raw: &[P],
    height: usize,
    width: usize,
    mask: &super::Mask,
    buffers: &mut Buffers,
) -> (f64, f64) {
    // A pixel is in the dilation of the non-zero pixels by the mask if,
    // on some mask row, a non-zero pixel is within that row's half width
    // `h`: a window of `2h + 1` along that row, the union of two windows
    // of the largest power of two `p ≤ 2h + 1`. Windows of `p` come from
    // doublings of the non-zero flags, each row padded by the widest `h`.
    let spans = &mask.row_half_widths;
    let radius = mask.radius;
    let widest = spans.iter().copied().max().unwrap_or(0);
    let stride = width + 2 * widest;
    let levels = (2 * widest + 1).ilog2() as usize + 1;
    let plane = height * stride;
    let reach = &mut buffers.reach;
    reach.clear();
    reach.resize(levels * plane, 0);
    for (values, flags) in image
        .chunks_exact(width)
        .zip(reach[..plane].chunks_exact_mut(stride))
    {
        for (flag, &v) in flags[widest..].iter_mut().zip(values) {
            *flag = u8::from(v != 0);
        }
    }
    for level in 1..levels {
        let step = 1 << (level - 1);
        let (lower, upper) = reach.split_at_mut(level * plane);
        let previous = &lower[(level - 1) * plane..];
        for (next, line) in upper[..plane]
            .chunks_exact_mut(stride)
            .zip(previous.chunks_exact(stride))
        {
            for ((n, &a), &b) in next.iter_mut().zip(line).zip(&line[step..]) {
                *n = a | b;
            }
            next[stride - step..].copy_from_slice(&line[stride - step..]);
        }
    }
    let covered = &mut buffers.covered;
    let values = &mut buffers.background_values;
    values.clear();
    for r in 0..height {
        covered.clear();
        covered.resize(width, 0);
        for (dy, &half_width) in spans.iter().enumerate() {
            let Some(y) = (r + dy).checked_sub(radius).filter(|&y| y < height) else {
                continue;
            };
            let level = (2 * half_width + 1).ilog2() as usize;
            let p = 1 << level;
            let line = &reach[level * plane + y * stride..][..stride];
            let left = &line[widest - half_width..][..width];
            let right = &line[widest + half_width + 1 - p..][..width];
            for ((c, &a), &b) in covered.iter_mut().zip(left).zip(right) {
                *c |= a | b;
            }
        }
        let row = &raw[r * width..(r + 1) * width];
        values.extend(
            covered
                .iter()
                .zip(row)
                .filter(|&(&c, _)| c == 0)
                .map(|(_, v)| v.value()),
        );
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
