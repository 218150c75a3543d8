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
pub(crate) struct Conv3x3<'a> {
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
    pub(crate) fn transposed_weights(&self) -> Vec<f32> {
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
pub(crate) fn conv3x3_forward(
    input: &[f32],
    output: &mut [f32],
    geometry: &Geometry,
    conv: &Conv3x3,
) {
    conv3x3_forward_on(input, output, geometry, conv, Isa::Detect)
}

/// Which instruction-set path a kernel takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Isa {
    /// The fastest the CPU has.
    Detect,
    /// The AVX2 kernels even where the CPU has AVX-512 (portable where it
    /// has neither), so that tests on an AVX-512 machine check them too.
    #[cfg_attr(not(test), allow(dead_code))]
    Avx2,
    /// Plain Rust (for checking that the paths agree bit for bit).
    #[cfg_attr(not(test), allow(dead_code))]
    Portable,
}

/// The vector kernels a convolution with `out_channels` can take on `isa`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Path {
    /// The tiled AVX-512 kernels.
    Avx512,
    /// The tiled AVX2 kernels.
    Avx2,
    /// The portable loops compiled for AVX2 and FMA (channel counts that
    /// are not whole registers; the compiler vectorises what it can).
    Avx2Loops,
    /// The portable loops as the crate is built (SSE2 on x86-64).
    Portable,
}

impl Isa {
    /// The path for `out_channels` output channels: the tiled kernels need
    /// whole registers of them (16 lanes with AVX-512, 8 with AVX2).
    fn path(self, out_channels: usize) -> Path {
        let avx2 = self != Isa::Portable && has_avx2_fma();
        if self == Isa::Detect && has_avx512() && out_channels.is_multiple_of(16) {
            Path::Avx512
        } else if avx2 && out_channels.is_multiple_of(8) {
            Path::Avx2
        } else if avx2 {
            Path::Avx2Loops
        } else {
            Path::Portable
        }
    }
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
    let path = isa.path(conv.out_channels);
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
            let width = geometry.width;
            // SAFETY (both vector paths): the CPU has the path's features
            // (`Isa::path`) and the channel count is whole registers; every
            // tap of every interior pixel lies inside `input` because the
            // padding is at least the dilation (checked in `check`).
            #[cfg(target_arch = "x86_64")]
            match path {
                Path::Avx512 => {
                    return unsafe {
                        tiled::conv_row_avx512(input, out, first, width, &offsets, conv)
                    };
                }
                Path::Avx2 => {
                    return unsafe {
                        tiled::conv_row_avx2(input, out, first, width, &offsets, conv)
                    };
                }
                Path::Avx2Loops => {
                    return unsafe {
                        conv_row_avx2_loops(input, out, first, width, &offsets, conv)
                    };
                }
                Path::Portable => {}
            }
            conv_row_portable(input, out, first, width, &offsets, conv);
        });
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn conv_row_avx2_loops(
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
pub(crate) fn conv3x3_weight_grad(
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
    let path = isa.path(co_n);
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
            // SAFETY (both vector paths): the CPU has the path's features
            // and the channel count is whole registers; taps stay inside
            // the map's padded area (padding ≥ dilation).
            #[cfg(target_arch = "x86_64")]
            match path {
                Path::Avx512 => unsafe { tiled::weight_grad_map_avx512(&job, map, &mut grad) },
                Path::Avx2 => unsafe { tiled::weight_grad_map_avx2(&job, map, &mut grad) },
                Path::Avx2Loops => unsafe { weight_grad_map_avx2_loops(&job, map, &mut grad) },
                Path::Portable => weight_grad_map_portable(&job, map, &mut grad),
            }
            #[cfg(not(target_arch = "x86_64"))]
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
unsafe fn weight_grad_map_avx2_loops(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
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
mod tiled {
    //! Register-tiled micro-kernels, written once over [`Vector`] and
    //! compiled for AVX-512 (16 lanes) and AVX2 (8 lanes) by the entry
    //! points at the bottom: output channels two registers (or one) at a
    //! time, several pixels (forward) or input channels (weight gradient)
    //! at a time, so that each load feeds several FMAs from registers.
    //! Every output sums its terms in the portable kernels' order, so each
    //! build gives their bits.

    use std::arch::x86_64::*;

    use super::{Conv3x3, Geometry, WeightGradJob};

    /// One SIMD register of f32 lanes. The methods are `unsafe` because they
    /// need the CPU feature of their type; they are only ever inlined into
    /// the `#[target_feature]` entry points below.
    pub(super) trait Vector: Copy {
        /// Lanes per register.
        const WIDTH: usize;
        unsafe fn zero() -> Self;
        unsafe fn load(from: *const f32) -> Self;
        unsafe fn store(self, to: *mut f32);
        unsafe fn splat(value: f32) -> Self;
        /// `a · b + c`, fused.
        unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self;
        unsafe fn add(self, other: Self) -> Self;
        /// max(0, v), NaN and −0 passing as in [`super::super::relu`] (MAXPS
        /// returns its second operand when either is NaN or both are zero).
        unsafe fn relu(self) -> Self;
    }

    impl Vector for __m512 {
        const WIDTH: usize = 16;
        #[inline(always)]
        unsafe fn zero() -> Self {
            unsafe { _mm512_setzero_ps() }
        }
        #[inline(always)]
        unsafe fn load(from: *const f32) -> Self {
            unsafe { _mm512_loadu_ps(from) }
        }
        #[inline(always)]
        unsafe fn store(self, to: *mut f32) {
            unsafe { _mm512_storeu_ps(to, self) }
        }
        #[inline(always)]
        unsafe fn splat(value: f32) -> Self {
            unsafe { _mm512_set1_ps(value) }
        }
        #[inline(always)]
        unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
            unsafe { _mm512_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        unsafe fn add(self, other: Self) -> Self {
            unsafe { _mm512_add_ps(self, other) }
        }
        #[inline(always)]
        unsafe fn relu(self) -> Self {
            unsafe { _mm512_max_ps(_mm512_setzero_ps(), self) }
        }
    }

    impl Vector for __m256 {
        const WIDTH: usize = 8;
        #[inline(always)]
        unsafe fn zero() -> Self {
            unsafe { _mm256_setzero_ps() }
        }
        #[inline(always)]
        unsafe fn load(from: *const f32) -> Self {
            unsafe { _mm256_loadu_ps(from) }
        }
        #[inline(always)]
        unsafe fn store(self, to: *mut f32) {
            unsafe { _mm256_storeu_ps(to, self) }
        }
        #[inline(always)]
        unsafe fn splat(value: f32) -> Self {
            unsafe { _mm256_set1_ps(value) }
        }
        #[inline(always)]
        unsafe fn mul_add(a: Self, b: Self, c: Self) -> Self {
            unsafe { _mm256_fmadd_ps(a, b, c) }
        }
        #[inline(always)]
        unsafe fn add(self, other: Self) -> Self {
            unsafe { _mm256_add_ps(self, other) }
        }
        #[inline(always)]
        unsafe fn relu(self) -> Self {
            unsafe { _mm256_max_ps(_mm256_setzero_ps(), self) }
        }
    }

    /// Pixels per forward tile with AVX-512 (32 registers: 8 × 2
    /// accumulators, 2 weights, 1 input).
    const AVX512_PIXELS: usize = 8;
    /// Input channels per weight-gradient tile with AVX-512.
    const AVX512_IN_BLOCK: usize = 8;
    /// Pixels per forward tile with AVX2 (16 registers: 6 × 2 accumulators,
    /// 2 weights, 1 input).
    const AVX2_PIXELS: usize = 6;
    /// Input channels per weight-gradient tile with AVX2.
    const AVX2_IN_BLOCK: usize = 6;

    /// One output row with AVX-512; `out_channels` a multiple of 16.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn conv_row_avx512(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        width: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        // SAFETY: the caller's contract, and AVX-512F is enabled here.
        unsafe {
            conv_row::<__m512, AVX512_PIXELS>(input, out, first, width, offsets, conv);
        }
    }

    /// One output row with AVX2 and FMA; `out_channels` a multiple of 8.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn conv_row_avx2(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        width: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        // SAFETY: the caller's contract, and AVX2 and FMA are enabled here.
        unsafe {
            conv_row::<__m256, AVX2_PIXELS>(input, out, first, width, offsets, conv);
        }
    }

    /// One map's weight gradient with AVX-512; `out_channels` a multiple
    /// of 16.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn weight_grad_map_avx512(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
        // SAFETY: the caller's contract, and AVX-512F is enabled here.
        unsafe { weight_grad_map::<__m512, AVX512_IN_BLOCK>(job, map, grad) }
    }

    /// One map's weight gradient with AVX2 and FMA; `out_channels` a
    /// multiple of 8.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn weight_grad_map_avx2(job: &WeightGradJob, map: usize, grad: &mut [f32]) {
        // SAFETY: the caller's contract, and AVX2 and FMA are enabled here.
        unsafe { weight_grad_map::<__m256, AVX2_IN_BLOCK>(job, map, grad) }
    }

    /// The forward row: tiles of `PIXELS` pixels (then single pixels) by
    /// two registers of output channels (then one).
    #[inline(always)]
    unsafe fn conv_row<V: Vector, const PIXELS: usize>(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        width: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        let co_n = conv.out_channels;
        debug_assert!(co_n.is_multiple_of(V::WIDTH));
        let mut co = 0;
        while co < co_n {
            let pair = co_n - co >= 2 * V::WIDTH;
            let mut col = 0;
            while col < width {
                let whole = width - col >= PIXELS;
                // SAFETY (all calls): pixels col..col + NB are inside the row
                // and their taps inside `input` (caller's contract).
                unsafe {
                    match (whole, pair) {
                        (true, true) => {
                            tile::<V, PIXELS, 2>(input, out, first, col, co, offsets, conv)
                        }
                        (true, false) => {
                            tile::<V, PIXELS, 1>(input, out, first, col, co, offsets, conv)
                        }
                        (false, true) => tile::<V, 1, 2>(input, out, first, col, co, offsets, conv),
                        (false, false) => {
                            tile::<V, 1, 1>(input, out, first, col, co, offsets, conv)
                        }
                    }
                }
                col += if whole { PIXELS } else { 1 };
            }
            co += if pair { 2 } else { 1 } * V::WIDTH;
        }
    }

    /// Output channels `co..co + LANES · V::WIDTH` of pixels `col..col + NB`.
    #[inline(always)]
    unsafe fn tile<V: Vector, const NB: usize, const LANES: usize>(
        input: &[f32],
        out: &mut [f32],
        first: usize,
        col: usize,
        co: usize,
        offsets: &[isize; 9],
        conv: &Conv3x3,
    ) {
        let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
        let mut acc = [[unsafe { V::zero() }; LANES]; NB];
        if let Some(bias) = conv.bias {
            for lane in 0..LANES {
                // SAFETY: co + LANES · WIDTH ≤ out_channels = bias.len().
                let b = unsafe { V::load(bias.as_ptr().add(co + V::WIDTH * lane)) };
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
                let mut w = [unsafe { V::zero() }; LANES];
                for (lane, w) in w.iter_mut().enumerate() {
                    *w = unsafe { V::load(w_tap.add(ci * co_n + V::WIDTH * lane)) };
                }
                for (p, a) in acc.iter_mut().enumerate() {
                    let value = unsafe { V::splat(*x.add(p * ci_n + ci)) };
                    for lane in 0..LANES {
                        a[lane] = unsafe { V::mul_add(value, w[lane], a[lane]) };
                    }
                }
            }
        }
        for (p, a) in acc.iter().enumerate() {
            for (lane, &v) in a.iter().enumerate() {
                let v = if conv.relu { unsafe { v.relu() } } else { v };
                let index = (col + p) * co_n + co + V::WIDTH * lane;
                debug_assert!(index + V::WIDTH <= out.len());
                // SAFETY: pixel col + p < width, channel block inside co_n.
                unsafe { v.store(out.as_mut_ptr().add(index)) };
            }
        }
    }

    /// One map's weight gradient: for every tap, blocks of `IN_BLOCK` input
    /// channels (then 4, 2, 1) by two registers of output channels (then
    /// one).
    #[inline(always)]
    unsafe fn weight_grad_map<V: Vector, const IN_BLOCK: usize>(
        job: &WeightGradJob,
        map: usize,
        grad: &mut [f32],
    ) {
        let (ci_n, co_n) = (job.conv.in_channels, job.conv.out_channels);
        debug_assert!(co_n.is_multiple_of(V::WIDTH));
        for tap in 0..9 {
            let mut ci = 0;
            while ci < ci_n {
                let block = match ci_n - ci {
                    rest if rest >= IN_BLOCK => IN_BLOCK,
                    4.. => 4,
                    2.. => 2,
                    _ => 1,
                };
                let mut co = 0;
                while co < co_n {
                    let pair = co_n - co >= 2 * V::WIDTH;
                    let at = GradTile { map, tap, ci, co };
                    // SAFETY (all calls): taps inside the padded map.
                    unsafe {
                        match (block, pair) {
                            (4, true) => grad_tile::<V, 4, 2>(job, at, grad),
                            (4, false) => grad_tile::<V, 4, 1>(job, at, grad),
                            (2, true) => grad_tile::<V, 2, 2>(job, at, grad),
                            (2, false) => grad_tile::<V, 2, 1>(job, at, grad),
                            (1, true) => grad_tile::<V, 1, 2>(job, at, grad),
                            (1, false) => grad_tile::<V, 1, 1>(job, at, grad),
                            (_, true) => grad_tile::<V, IN_BLOCK, 2>(job, at, grad),
                            (_, false) => grad_tile::<V, IN_BLOCK, 1>(job, at, grad),
                        }
                    }
                    co += if pair { 2 } else { 1 } * V::WIDTH;
                }
                ci += block;
            }
        }
    }

    /// Where a weight-gradient tile lies.
    #[derive(Clone, Copy)]
    struct GradTile {
        map: usize,
        tap: usize,
        ci: usize,
        co: usize,
    }

    /// Input channels `ci..ci + CB` × output channels `co..co + LANES ·
    /// V::WIDTH` of tap `tap`, summed over the map's interior pixels in
    /// raster order and added to `grad`.
    #[inline(always)]
    unsafe fn grad_tile<V: Vector, const CB: usize, const LANES: usize>(
        job: &WeightGradJob,
        GradTile { map, tap, ci, co }: GradTile,
        grad: &mut [f32],
    ) {
        let (geometry, conv): (&Geometry, &Conv3x3) = (job.geometry, job.conv);
        let (ci_n, co_n) = (conv.in_channels, conv.out_channels);
        let offset = job.offsets[tap];
        let mut acc = [[unsafe { V::zero() }; LANES]; CB];
        let in_ptr = job.input.as_ptr();
        let g_ptr = job.output_grad.as_ptr();
        for row in 0..geometry.height {
            let start = geometry.pixel(map, row, 0);
            for pixel in start..start + geometry.width {
                let mut g = [unsafe { V::zero() }; LANES];
                for (lane, g) in g.iter_mut().enumerate() {
                    // SAFETY: interior pixel, channel block inside co_n.
                    *g = unsafe { V::load(g_ptr.add(pixel * co_n + co + V::WIDTH * lane)) };
                }
                let source = pixel.wrapping_add_signed(offset);
                // SAFETY: the tap of an interior pixel is inside the map.
                let x = unsafe { in_ptr.add(source * ci_n + ci) };
                for (c, a) in acc.iter_mut().enumerate() {
                    let value = unsafe { V::splat(*x.add(c)) };
                    for lane in 0..LANES {
                        a[lane] = unsafe { V::mul_add(value, g[lane], a[lane]) };
                    }
                }
            }
        }
        for (c, a) in acc.iter().enumerate() {
            for (lane, &v) in a.iter().enumerate() {
                let index = (tap * ci_n + ci + c) * co_n + co + V::WIDTH * lane;
                let slot = &mut grad[index..index + V::WIDTH];
                // SAFETY: `slot` holds WIDTH floats.
                unsafe { V::load(slot.as_ptr()).add(v).store(slot.as_mut_ptr()) };
            }
        }
    }
}
