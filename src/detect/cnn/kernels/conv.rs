//! Dilated 3×3 convolution (stride 1, "same" zero padding) on the padded
//! channels-last layout: forward (optionally with bias and fused ReLU),
//! and the weight gradient. The gradient with respect to the input is a
//! forward convolution of the output gradient with the taps flipped and
//! the channel axes swapped ([`Conv3x3::transposed_weights`]).
//!
//! Weights are `[tap][in_channel][out_channel]` with taps in raster order
//! (`tap = 3·ky + kx`, tap (ky, kx) reading the input at
//! `(row + (ky − 1)·dilation, col + (kx − 1)·dilation)`), the layout whose
//! innermost axis is the one the vector lanes run along.

use rayon::prelude::*;

use super::Geometry;
use crate::detect::cpu::{has_avx2_fma, has_avx512};

/// One convolution's parameters.
#[derive(Debug, Clone, Copy)]
pub struct Conv3x3<'a> {
    /// `[9][in_channels][out_channels]`.
    pub weights: &'a [f32],
    /// Added before the taps (`out_channels` values), if any.
    pub bias: Option<&'a [f32]>,
    pub in_channels: usize,
    pub out_channels: usize,
    pub dilation: usize,
    /// Clamp the output at 0 (a fused ReLU).
    pub relu: bool,
}

impl Conv3x3<'_> {
    /// The weights of the convolution that maps an output gradient to the
    /// input gradient: tap `8 − t` of the forward weights, in and out
    /// channels swapped (`[9][out_channels][in_channels]`).
    pub fn transposed_weights(&self) -> Vec<f32> {
        let (ci_n, co_n) = (self.in_channels, self.out_channels);
        let mut out = vec![0.0; 9 * ci_n * co_n];
        for tap in 0..9 {
            for ci in 0..ci_n {
                for co in 0..co_n {
                    out[((8 - tap) * co_n + co) * ci_n + ci] =
                        self.weights[(tap * ci_n + ci) * co_n + co];
                }
            }
        }
        out
    }

    /// Pixel offsets of the nine taps in a padded batch of `geometry`.
    fn tap_offsets(&self, geometry: &Geometry) -> [isize; 9] {
        let row = geometry.padded_width() as isize;
        let d = self.dilation as isize;
        let mut offsets = [0isize; 9];
        for (tap, offset) in offsets.iter_mut().enumerate() {
            let (ky, kx) = ((tap / 3) as isize - 1, (tap % 3) as isize - 1);
            *offset = (ky * row + kx) * d;
        }
        offsets
    }

    fn check(&self, geometry: &Geometry) {
        assert!(
            self.dilation <= geometry.pad,
            "dilation exceeds the padding"
        );
        assert_eq!(self.weights.len(), 9 * self.in_channels * self.out_channels);
        if let Some(bias) = self.bias {
            assert_eq!(bias.len(), self.out_channels);
        }
    }
}

/// `output` (padded, `out_channels` per pixel, border zero) ← the
/// convolution of `input` (padded, `in_channels` per pixel, border zero).
/// Rows are computed in parallel; each output value sums the bias, then
/// the taps in raster order, each over the input channels in order.
pub fn conv3x3_forward(input: &[f32], output: &mut [f32], geometry: &Geometry, conv: &Conv3x3) {
    conv3x3_forward_on(input, output, geometry, conv, Isa::Detect)
}

/// Which instruction-set path a kernel takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Isa {
    /// The fastest the CPU has.
    Detect,
    /// Plain Rust (for checking that the paths agree bit for bit).
    #[cfg_attr(not(test), allow(dead_code))]
    Portable,
}

/// [`conv3x3_forward`] on the path `isa`.
pub(super) fn conv3x3_forward_on(
    input: &[f32],
    output: &mut [f32],
    geometry: &Geometry,
    conv: &Conv3x3,
    isa: Isa,
) {
    conv.check(geometry);
    assert_eq!(input.len(), geometry.pixels() * conv.in_channels);
    assert_eq!(output.len(), geometry.pixels() * conv.out_channels);
    let offsets = conv.tap_offsets(geometry);
    let row_floats = geometry.padded_width() * conv.out_channels;
    let padded_height = geometry.padded_height();
    let detect = isa == Isa::Detect;
    let avx512 = detect && has_avx512() && conv.out_channels.is_multiple_of(16);
    let avx2 = detect && has_avx2_fma();
    output
        .par_chunks_mut(row_floats)
        .enumerate()
        .for_each(|(padded_row_index, out_row)| {
            let row = padded_row_index % padded_height;
            if row < geometry.pad || row >= geometry.pad + geometry.height {
                return;
            }
            // Pixel index of this row's first interior pixel.
            let first = padded_row_index * geometry.padded_width() + geometry.pad;
            let out = &mut out_row[geometry.pad * conv.out_channels..];
            #[cfg(target_arch = "x86_64")]
            if avx512 {
                // SAFETY: the CPU has AVX-512F (checked above); every tap of
                // every interior pixel lies inside `input` because the
                // padding is at least the dilation (checked in `check`).
                unsafe { avx512::conv_row(input, out, first, geometry.width, &offsets, conv) };
                return;
            }
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: the CPU has AVX2 and FMA (checked above).
                unsafe { conv_row_avx2(input, out, first, geometry.width, &offsets, conv) };
                return;
            }
            let _ = (avx512, avx2);
            conv_row_portable(input, out, first, geometry.width, &offsets, conv);
        });
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn conv_row_avx2(
    input: &[f32],
    out: &mut [f32],
    first: usize,
    width: usize,
    offsets: &[isize; 9],
    conv: &Conv3x3,
) {
    conv_row_portable(input, out, first, width, offsets, conv)
}

/// One output row (`width` pixels from pixel `first`), any channel counts.
#[inline(always)]
fn conv_row_portable(
    input: &[f32],
    out: &mut [f32],
    first: usize,
    width: usize,
    offsets: &[isize; 9],
    conv: &Conv3x3,
) {
    let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
    for col in 0..width {
        let acc = &mut out[col * co_n..(col + 1) * co_n];
        match conv.bias {
            Some(bias) => acc.copy_from_slice(bias),
            None => acc.fill(0.0),
        }
        for (tap, &offset) in offsets.iter().enumerate() {
            let pixel = (first + col).wrapping_add_signed(offset);
            let x = &input[pixel * ci_n..(pixel + 1) * ci_n];
            let w_tap = &conv.weights[tap * ci_n * co_n..(tap + 1) * ci_n * co_n];
            for (ci, &value) in x.iter().enumerate() {
                let w = &w_tap[ci * co_n..(ci + 1) * co_n];
                for (a, &w) in acc.iter_mut().zip(w) {
                    *a = value.mul_add(w, *a);
                }
            }
        }
        if conv.relu {
            for a in acc.iter_mut() {
                *a = super::relu(*a);
            }
        }
    }
}

/// The gradient of the loss with respect to the weights,
/// `[9][in_channels][out_channels]`: for each tap, the sum over interior
/// pixels of input(pixel + tap) × output_gradient(pixel). Maps are
/// processed in parallel, each summing its pixels in raster order; the
/// per-map sums are then added in map order.
pub fn conv3x3_weight_grad(
    input: &[f32],
    output_grad: &[f32],
    geometry: &Geometry,
    conv: &Conv3x3,
) -> Vec<f32> {
    conv3x3_weight_grad_on(input, output_grad, geometry, conv, Isa::Detect)
}

/// [`conv3x3_weight_grad`] on the path `isa`.
pub(super) fn conv3x3_weight_grad_on(
    input: &[f32],
    output_grad: &[f32],
    geometry: &Geometry,
    conv: &Conv3x3,
    isa: Isa,
) -> Vec<f32> {
    conv.check(geometry);
    let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
    assert_eq!(input.len(), geometry.pixels() * ci_n);
    assert_eq!(output_grad.len(), geometry.pixels() * co_n);
    let offsets = conv.tap_offsets(geometry);
    let detect = isa == Isa::Detect;
    let avx512 = detect && has_avx512() && co_n.is_multiple_of(16);
    let avx2 = detect && has_avx2_fma();
    let job = WeightGradJob {
        input,
        output_grad,
        geometry,
        offsets,
        conv,
    };
    let per_map: Vec<Vec<f32>> = (0..geometry.n)
        .into_par_iter()
        .map(|map| {
            let mut grad = vec![0.0f32; 9 * ci_n * co_n];
            #[cfg(target_arch = "x86_64")]
            if avx512 {
                // SAFETY: AVX-512F is present; taps stay inside the map's
                // padded area (padding ≥ dilation).
                unsafe { avx512::weight_grad_map(&job, map, &mut grad) };
                return grad;
            }
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: AVX2 and FMA are present.
                unsafe { weight_grad_map_avx2(&job, map, &mut grad) };
                return grad;
            }
            let _ = (avx512, avx2);
            weight_grad_map_portable(&job, map, &mut grad);
            grad
        })
        .collect();
    let mut total = vec![0.0f32; 9 * ci_n * co_n];
    for grad in &per_map {
        for (t, g) in total.iter_mut().zip(grad) {
            *t += g;
        }
    }
    total
}

/// The operands of a weight gradient.
struct WeightGradJob<'a> {
    input: &'a [f32],
    output_grad: &'a [f32],
    geometry: &'a Geometry,
    offsets: [isize; 9],
    conv: &'a Conv3x3<'a>,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn weight_grad_map_avx2(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
    weight_grad_map_portable(job, map, grad)
}

/// One map's contribution to the weight gradient (added to `grad`).
#[inline(always)]
fn weight_grad_map_portable(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
    let &WeightGradJob {
        input,
        output_grad,
        geometry,
        offsets,
        conv,
    } = job;
    let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
    for row in 0..geometry.height {
        for col in 0..geometry.width {
            let pixel = geometry.pixel(map, row, col);
            let g = &output_grad[pixel * co_n..(pixel + 1) * co_n];
            for (tap, &offset) in offsets.iter().enumerate() {
                let source = pixel.wrapping_add_signed(offset);
                let x = &input[source * ci_n..(source + 1) * ci_n];
                let grad_tap = &mut grad[tap * ci_n * co_n..(tap + 1) * ci_n * co_n];
                for (ci, &value) in x.iter().enumerate() {
                    let acc = &mut grad_tap[ci * co_n..(ci + 1) * co_n];
                    for (a, &g) in acc.iter_mut().zip(g) {
                        *a = value.mul_add(g, *a);
                    }
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    //! AVX-512 micro-kernels: output channels 16 or 32 at a time (one or two
    //! registers), several pixels at a time so each weight load feeds
    //! several FMAs. Same summation order as the portable kernels.

    use std::arch::x86_64::*;

    use super::{Conv3x3, Geometry, WeightGradJob};

    /// Pixels per forward tile.
    const PIXELS: usize = 8;
    /// Input channels per weight-gradient tile.
    const IN_BLOCK: usize = 8;

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn conv_row(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        width: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        let co_n = conv.out_channels;
        let mut co = 0;
        while co < co_n {
            let pair = co_n - co >= 32;
            let mut col = 0;
            while col < width {
                let rest = width - col;
                // SAFETY (all calls): pixels col..col + NB are inside the row
                // and their taps inside `input` (caller's contract).
                unsafe {
                    match (rest >= PIXELS, pair) {
                        (true, true) => {
                            tile::<PIXELS, 2>(input, out, first, col, co, offsets, conv)
                        }
                        (true, false) => {
                            tile::<PIXELS, 1>(input, out, first, col, co, offsets, conv)
                        }
                        (false, true) => tile::<1, 2>(input, out, first, col, co, offsets, conv),
                        (false, false) => tile::<1, 1>(input, out, first, col, co, offsets, conv),
                    }
                }
                col += if rest >= PIXELS { PIXELS } else { 1 };
            }
            co += if pair { 32 } else { 16 };
        }
    }

    /// Output channels `co..co + 16·LANES` of pixels `col..col + NB`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn tile<const NB: usize, const LANES: usize>(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        col: usize,
        co: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
        let mut acc = [[_mm512_setzero_ps(); LANES]; NB];
        if let Some(bias) = conv.bias {
            for lane in 0..LANES {
                // SAFETY: co + 16·LANES ≤ out_channels = bias.len().
                let b = unsafe { _mm512_loadu_ps(bias.as_ptr().add(co + 16 * lane)) };
                for a in acc.iter_mut() {
                    a[lane] = b;
                }
            }
        }
        let in_ptr = input.as_ptr();
        let w_ptr = conv.weights.as_ptr();
        for (tap, &offset) in offsets.iter().enumerate() {
            let pixel = (first + col).wrapping_add_signed(offset);
            // SAFETY: the taps of pixels col..col+NB are inside `input`.
            let x = unsafe { in_ptr.add(pixel * ci_n) };
            let w_tap = unsafe { w_ptr.add(tap * ci_n * co_n + co) };
            for ci in 0..ci_n {
                let mut w = [_mm512_setzero_ps(); LANES];
                for (lane, w) in w.iter_mut().enumerate() {
                    *w = unsafe { _mm512_loadu_ps(w_tap.add(ci * co_n + 16 * lane)) };
                }
                for (p, a) in acc.iter_mut().enumerate() {
                    let value = unsafe { _mm512_set1_ps(*x.add(p * ci_n + ci)) };
                    for lane in 0..LANES {
                        a[lane] = _mm512_fmadd_ps(value, w[lane], a[lane]);
                    }
                }
            }
        }
        let zero = _mm512_setzero_ps();
        for (p, a) in acc.iter().enumerate() {
            for (lane, &v) in a.iter().enumerate() {
                // max(0, v): NaN passes, as in `super::relu`.
                let v = if conv.relu { _mm512_max_ps(zero, v) } else { v };
                let index = (col + p) * co_n + co + 16 * lane;
                debug_assert!(index + 16 <= out.len());
                // SAFETY: pixel col + p < width, channel block inside co_n.
                unsafe { _mm512_storeu_ps(out.as_mut_ptr().add(index), v) };
            }
        }
    }

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn weight_grad_map(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
        let &WeightGradJob {
            input,
            output_grad,
            geometry,
            offsets,
            conv,
        } = job;
        let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
        for (tap, &offset) in offsets.iter().enumerate() {
            let mut ci = 0;
            while ci < ci_n {
                let rest = ci_n - ci;
                let mut co = 0;
                while co < co_n {
                    let pair = co_n - co >= 32;
                    // SAFETY (all calls): taps inside the padded map.
                    unsafe {
                        let args = (input, output_grad, geometry, map, offset, conv, tap, ci, co);
                        match (rest, pair) {
                            (IN_BLOCK.., true) => grad_tile::<IN_BLOCK, 2>(args, grad),
                            (IN_BLOCK.., false) => grad_tile::<IN_BLOCK, 1>(args, grad),
                            (4.., true) => grad_tile::<4, 2>(args, grad),
                            (4.., false) => grad_tile::<4, 1>(args, grad),
                            (2.., true) => grad_tile::<2, 2>(args, grad),
                            (2.., false) => grad_tile::<2, 1>(args, grad),
                            (_, true) => grad_tile::<1, 2>(args, grad),
                            (_, false) => grad_tile::<1, 1>(args, grad),
                        }
                    }
                    co += if pair { 32 } else { 16 };
                }
                ci += match rest {
                    IN_BLOCK.. => IN_BLOCK,
                    4.. => 4,
                    2.. => 2,
                    _ => 1,
                };
            }
        }
    }

    type GradArgs<'a> = (
        &'a [f32],
        &'a [f32],
        &'a Geometry,
        usize,
        isize,
        &'a Conv3x3<'a>,
        usize,
        usize,
        usize,
    );

    /// Input channels `ci..ci + CB` × output channels `co..co + 16·LANES`
    /// of tap `tap`, summed over the map's interior pixels in raster order
    /// and added to `grad`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn grad_tile<const CB: usize, const LANES: usize>(
        (input, output_grad, geometry, map, offset, conv, tap, ci, co): GradArgs,
        grad: &mut [f32],
    ) {
        let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
        let mut acc = [[_mm512_setzero_ps(); LANES]; CB];
        let in_ptr = input.as_ptr();
        let g_ptr = output_grad.as_ptr();
        for row in 0..geometry.height {
            let start = geometry.pixel(map, row, 0);
            for pixel in start..start + geometry.width {
                let mut g = [_mm512_setzero_ps(); LANES];
                for (lane, g) in g.iter_mut().enumerate() {
                    // SAFETY: interior pixel, channel block inside co_n.
                    *g = unsafe { _mm512_loadu_ps(g_ptr.add(pixel * co_n + co + 16 * lane)) };
                }
                let source = pixel.wrapping_add_signed(offset);
                // SAFETY: the tap of an interior pixel is inside the map.
                let x = unsafe { in_ptr.add(source * ci_n + ci) };
                for (c, a) in acc.iter_mut().enumerate() {
                    let value = unsafe { _mm512_set1_ps(*x.add(c)) };
                    for lane in 0..LANES {
                        a[lane] = _mm512_fmadd_ps(value, g[lane], a[lane]);
                    }
                }
            }
        }
        for (c, a) in acc.iter().enumerate() {
            for (lane, &v) in a.iter().enumerate() {
                let index = (tap * ci_n + ci + c) * co_n + co + 16 * lane;
                let slot = &mut grad[index..index + 16];
                // SAFETY: `slot` holds 16 floats.
                unsafe {
                    let sum = _mm512_add_ps(_mm512_loadu_ps(slot.as_ptr()), v);
                    _mm512_storeu_ps(slot.as_mut_ptr(), sum);
                }
            }
        }
    }
}
