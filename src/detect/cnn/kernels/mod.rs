//! Deterministic CPU kernels for the CNN's body (dilated 3×3 convolutions,
//! batch norm and ReLU) on a zero-padded channels-last layout, used instead
//! of burn's im2col convolutions where the network spends its time, and
//! for its 1×1 head ([`head_forward`], on plain channels-first maps; see
//! its module for why the head is not left to burn either).
//!
//! Layout: a batch of `n` maps of `height × width` pixels is stored as
//! `[n, height + 2·pad, width + 2·pad, channels]` (row-major, channels
//! last) with a border of `pad` zero pixels around every map
//! ([`Geometry`]). With `pad` ≥ the largest dilation, every tap of a 3×3
//! convolution reads valid memory, and the border stands for the zero
//! padding of the convolution, so the inner loops need no bounds checks.
//! Kernels write only the interior; the border stays zero.
//!
//! Determinism: each output value is computed by one task with a fixed
//! summation order (taps in raster order, then input channels in order,
//! or pixels in raster order for reductions; per-map partial sums are
//! combined in map order), so results do not depend on the thread count or
//! on scheduling. Every multiply-add of the body is fused (`f32::mul_add`, or the
//! vector FMA instructions), so the AVX-512, AVX2 and portable paths give
//! the same bits.
//!
//! Divergence: NaN passes through ReLU, and batch statistics that are not
//! finite (squared deviations beyond f32's range) make the layer's output
//! NaN, so a training that blows up ends in a non-finite loss.

pub(crate) mod body;
mod conv;
mod head;
mod norm;

pub(crate) use conv::{Conv3x3, conv3x3_forward, conv3x3_weight_grad};
pub(crate) use head::{Head, fixed_order_sum, head_backward, head_forward};
pub(crate) use norm::channel_statistics;
#[cfg(test)]
pub(crate) use norm::{ReluGate, bn_relu_backward, bn_relu_forward};

/// The shape of a zero-padded channels-last batch of maps (see the module
/// docs): `n` maps of `height × width` interior pixels, each surrounded by
/// `pad` zero pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Geometry {
    pub n: usize,
    pub height: usize,
    pub width: usize,
    pub pad: usize,
}

impl Geometry {
    /// Pixels per padded row.
    pub(crate) fn padded_width(&self) -> usize {
        self.width + 2 * self.pad
    }

    /// Rows per padded map.
    pub(crate) fn padded_height(&self) -> usize {
        self.height + 2 * self.pad
    }

    /// Pixels per padded map.
    pub(crate) fn map_pixels(&self) -> usize {
        self.padded_width() * self.padded_height()
    }

    /// Pixels of the whole padded batch.
    pub(crate) fn pixels(&self) -> usize {
        self.n * self.map_pixels()
    }

    /// Interior pixels of the whole batch (what batch norm averages over).
    pub(crate) fn interior_pixels(&self) -> usize {
        self.n * self.height * self.width
    }

    /// Index of interior pixel (`row`, `col`) of map `map` in the padded
    /// batch, in pixels (multiply by the channel count for floats).
    pub(crate) fn pixel(&self, map: usize, row: usize, col: usize) -> usize {
        map * self.map_pixels() + (row + self.pad) * self.padded_width() + col + self.pad
    }

    /// A zeroed padded buffer of `channels` per pixel.
    pub(crate) fn zeros(&self, channels: usize) -> Vec<f32> {
        vec![0.0; self.pixels() * channels]
    }

    /// A padded buffer of `channels` per pixel whose border is zero and
    /// whose interior is unspecified: a buffer given back with
    /// [`recycle`](Self::recycle) if one of this shape is free, else a new
    /// zeroed one. For outputs of which every interior value is written
    /// (as every kernel here does); reusing buffers spares the page
    /// faults of fresh large allocations at every training step.
    pub(crate) fn buffer(&self, channels: usize) -> Vec<f32> {
        let mut pool = BUFFER_POOL.lock().unwrap_or_else(|e| e.into_inner());
        match pool
            .iter()
            .position(|(geometry, c, _)| geometry == self && *c == channels)
        {
            Some(index) => pool.swap_remove(index).2,
            None => {
                drop(pool);
                self.zeros(channels)
            }
        }
    }

    /// Gives back a buffer of this shape whose border is still zero (one
    /// from [`buffer`](Self::buffer) or [`zeros`](Self::zeros) written only
    /// in its interior) for reuse.
    pub(crate) fn recycle(&self, channels: usize, buffer: Vec<f32>) {
        debug_assert_eq!(buffer.len(), self.pixels() * channels);
        let mut pool = BUFFER_POOL.lock().unwrap_or_else(|e| e.into_inner());
        if pool.len() == POOL_BUFFERS {
            // Forget the oldest: shapes change rarely (frame size, batch).
            pool.remove(0);
        }
        pool.push((*self, channels, buffer));
    }
}

/// Most buffers kept for reuse (a training step of the default network
/// uses about 16 at a time).
const POOL_BUFFERS: usize = 24;

/// Free padded buffers with their shape (see [`Geometry::buffer`]).
static BUFFER_POOL: std::sync::Mutex<Vec<(Geometry, usize, Vec<f32>)>> =
    std::sync::Mutex::new(Vec::new());

/// Calls `f(padded, planar)` for every interior pixel of `geometry`: the
/// float index of its channel 0 in the padded channels-last buffer and in
/// the row-major `[n, channels, height, width]` array (where channel `c` is
/// `c · height · width` further).
fn for_each_interior_pixel(geometry: &Geometry, channels: usize, mut f: impl FnMut(usize, usize)) {
    let Geometry {
        n, height, width, ..
    } = *geometry;
    let plane = height * width;
    for map in 0..n {
        for row in 0..height {
            for col in 0..width {
                f(
                    geometry.pixel(map, row, col) * channels,
                    map * channels * plane + row * width + col,
                );
            }
        }
    }
}

/// Row-major `[n, channels, height, width]` values as a zero-padded
/// channels-last buffer of `geometry`.
pub(crate) fn padded_from_nchw(values: &[f32], channels: usize, geometry: &Geometry) -> Vec<f32> {
    assert_eq!(values.len(), geometry.interior_pixels() * channels);
    let plane = geometry.height * geometry.width;
    let mut out = geometry.buffer(channels);
    for_each_interior_pixel(geometry, channels, |padded, planar| {
        for c in 0..channels {
            out[padded + c] = values[planar + c * plane];
        }
    });
    out
}

/// The interior of a zero-padded channels-last buffer as row-major
/// `[n, channels, height, width]` values.
pub(crate) fn nchw_from_padded(values: &[f32], channels: usize, geometry: &Geometry) -> Vec<f32> {
    assert_eq!(values.len(), geometry.pixels() * channels);
    let plane = geometry.height * geometry.width;
    let mut out = vec![0.0; geometry.interior_pixels() * channels];
    for_each_interior_pixel(geometry, channels, |padded, planar| {
        for c in 0..channels {
            out[planar + c * plane] = values[padded + c];
        }
    });
    out
}

/// ReLU that lets NaN through (as burn's does, so a diverged network's NaN
/// reaches the loss instead of being clamped to 0): `0 > v ? 0 : v`, the
/// semantics of the `vmaxps(0, v)` instruction the vector kernels use.
#[inline(always)]
pub(crate) fn relu(v: f32) -> f32 {
    if 0.0 > v { 0.0 } else { v }
}

#[cfg(test)]
mod tests;
