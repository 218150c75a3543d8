//! The network's head — a 1×1 convolution from the body's features to the
//! output maps — and its backward pass, on plain row-major `[n, channels,
//! height · width]` buffers.
//!
//! Why not burn's convolution: the head's weight and bias gradients sum
//! over every pixel of the batch, and burn's `flex` backend takes such sums
//! through a blocked GEMM whose block sizes follow the CPU's caches and
//! through reductions whose lane count follows its vector width (8 with
//! AVX2, 16 with AVX-512). Its sums are fixed for one machine but not
//! across machines, so the same seed trained different weights on
//! different CPUs. Here every sum has one order on every CPU: products and
//! additions are separate IEEE operations (Rust never contracts them into
//! fused multiply-adds, and the compiler may not reorder them), sums over
//! pixels run in [`LANES`] interleaved partial sums combined in a fixed
//! tree, and per-map partial sums are added in map order. Work is
//! split over maps only, so the thread count does not matter either.

use std::ops::AddAssign;

use rayon::prelude::*;

/// Interleaved partial sums of a reduction over pixels: pixel `p` goes to
/// partial `p mod LANES`. A fixed number, independent of the CPU, so the
/// compiler's vector code for it gives the same bits everywhere.
const LANES: usize = 16;

/// The head's parameters: `weights[o · in_channels + c]` (output channel
/// `o`, input channel `c`) and one bias per output channel.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Head {
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
    pub in_channels: usize,
    pub out_channels: usize,
}

/// The head's gradients (see [`head_backward`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct HeadGradients {
    /// `[out_channels][in_channels]`, as [`Head::weights`].
    pub weights: Vec<f32>,
    pub bias: Vec<f32>,
    /// With respect to the features, `[n, in_channels, pixels]`.
    pub features: Vec<f32>,
}

/// The head's output `[n, out_channels, pixels]` for `features` `[n,
/// in_channels, pixels]`: `bias[o] + Σ_c weights[o][c] · features[c]`, the
/// terms added in channel order after the bias.
pub(crate) fn head_forward(head: &Head, features: &[f32], n: usize, pixels: usize) -> Vec<f32> {
    let (ci_n, co_n) = (head.in_channels, head.out_channels);
    assert_eq!(head.weights.len(), ci_n * co_n, "head weights");
    assert_eq!(head.bias.len(), co_n, "head bias");
    let (map_in, map_out) = (ci_n * pixels, co_n * pixels);
    assert_eq!(features.len(), n * map_in, "features are n whole maps");
    let mut output = vec![0.0f32; n * map_out];
    if map_out == 0 {
        return output;
    }
    output
        .par_chunks_mut(map_out)
        .enumerate()
        .for_each(|(map, out)| {
            let x = &features[map * map_in..(map + 1) * map_in];
            for (o, out) in out.chunks_exact_mut(pixels).enumerate() {
                out.fill(head.bias[o]);
                let weights = &head.weights[o * ci_n..(o + 1) * ci_n];
                for (&w, x) in weights.iter().zip(x.chunks_exact(pixels)) {
                    for (y, &x) in out.iter_mut().zip(x) {
                        *y += w * x;
                    }
                }
            }
        });
    output
}

/// The backward pass of [`head_forward`] from the gradient of the loss
/// with respect to its output (`[n, out_channels, pixels]`).
pub(crate) fn head_backward(
    head: &Head,
    features: &[f32],
    output_grad: &[f32],
    [n, pixels]: [usize; 2],
) -> HeadGradients {
    let (ci_n, co_n) = (head.in_channels, head.out_channels);
    let (map_in, map_out) = (ci_n * pixels, co_n * pixels);
    assert_eq!(features.len(), n * map_in, "features are n whole maps");
    assert_eq!(output_grad.len(), n * map_out, "one gradient an output");
    if pixels == 0 {
        return HeadGradients {
            weights: vec![0.0; co_n * ci_n],
            bias: vec![0.0; co_n],
            features: Vec::new(),
        };
    }
    let mut features_grad = vec![0.0f32; features.len()];
    // Per map: the features' gradient, and the map's partial sums of the
    // parameters' gradients (`co_n · ci_n` weights, then `co_n` biases).
    let map_gradients = |map: usize, x_grad: &mut [f32]| {
        let x = &features[map * map_in..(map + 1) * map_in];
        let y_grad = &output_grad[map * map_out..(map + 1) * map_out];
        for (c, x_grad) in x_grad.chunks_exact_mut(pixels).enumerate() {
            for (o, y_grad) in y_grad.chunks_exact(pixels).enumerate() {
                let w = head.weights[o * ci_n + c];
                for (g, &d) in x_grad.iter_mut().zip(y_grad) {
                    *g += w * d;
                }
            }
        }
        let mut sums = Vec::with_capacity(co_n * ci_n + co_n);
        for y_grad in y_grad.chunks_exact(pixels) {
            sums.extend(x.chunks_exact(pixels).map(|x| dot(y_grad, x)));
        }
        sums.extend(y_grad.chunks_exact(pixels).map(sum));
        sums
    };
    let partials: Vec<Vec<f32>> = if map_in == 0 {
        (0..n).map(|map| map_gradients(map, &mut [])).collect()
    } else {
        features_grad
            .par_chunks_mut(map_in)
            .enumerate()
            .map(|(map, x_grad)| map_gradients(map, x_grad))
            .collect()
    };
    let mut totals = vec![0.0f32; co_n * ci_n + co_n];
    for partial in &partials {
        for (total, &value) in totals.iter_mut().zip(partial) {
            *total += value;
        }
    }
    let bias = totals.split_off(co_n * ci_n);
    HeadGradients {
        weights: totals,
        bias,
        features: features_grad,
    }
}

/// `Σ_p a[p] · b[p]` in [`LANES`] interleaved partial sums (see the module
/// docs).
fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut partial = [0.0f32; LANES];
    let (a_body, a_tail) = a.split_at(a.len() - a.len() % LANES);
    let (b_body, b_tail) = b.split_at(a_body.len());
    for (a, b) in a_body.chunks_exact(LANES).zip(b_body.chunks_exact(LANES)) {
        for ((s, &a), &b) in partial.iter_mut().zip(a).zip(b) {
            *s += a * b;
        }
    }
    for ((s, &a), &b) in partial.iter_mut().zip(a_tail).zip(b_tail) {
        *s += a * b;
    }
    combine(partial)
}

/// `Σ_p a[p]` in [`LANES`] interleaved partial sums.
fn sum(a: &[f32]) -> f32 {
    let mut partial = [0.0f32; LANES];
    let (body, tail) = a.split_at(a.len() - a.len() % LANES);
    for a in body.chunks_exact(LANES) {
        for (s, &a) in partial.iter_mut().zip(a) {
            *s += a;
        }
    }
    for (s, &a) in partial.iter_mut().zip(tail) {
        *s += a;
    }
    combine(partial)
}

/// The partial sums added pairwise: lanes `i` and `i + half`, halving
/// until one is left.
fn combine<T: Copy + AddAssign>(mut partial: [T; LANES]) -> T {
    let mut half = LANES / 2;
    while half > 0 {
        for i in 0..half {
            let upper = partial[i + half];
            partial[i] += upper;
        }
        half /= 2;
    }
    partial[0]
}

/// A fixed-order sum of any number of f32 values into f64 (the loss's
/// reported terms), in [`LANES`] interleaved partial sums: the same bits
/// on every CPU, unlike a backend's reduction.
pub(crate) fn fixed_order_sum(values: &[f32]) -> f64 {
    let mut partial = [0.0f64; LANES];
    for chunk in values.chunks(LANES) {
        for (s, &v) in partial.iter_mut().zip(chunk) {
            *s += f64::from(v);
        }
    }
    combine(partial)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The order the module docs promise, written out one term at a time.
    fn reference_sum<T: Copy + AddAssign>(terms: &[T], zero: T) -> T {
        let mut partial = [zero; LANES];
        for (p, &term) in terms.iter().enumerate() {
            partial[p % LANES] += term;
        }
        let mut width = LANES;
        while width > 1 {
            width /= 2;
            for i in 0..width {
                let upper = partial[i + width];
                partial[i] += upper;
            }
        }
        partial[0]
    }

    #[test]
    fn sums_follow_the_documented_order() {
        let mut state = 0x9e37_79b9u32;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state as f32 / u32::MAX as f32) * 2.0 - 1.0
        };
        for len in [0, 1, 5, 15, 16, 17, 33, 100, 4096] {
            let a: Vec<f32> = (0..len).map(|_| next() * 1e3).collect();
            let b: Vec<f32> = (0..len).map(|_| next()).collect();
            let products: Vec<f32> = a.iter().zip(&b).map(|(a, b)| a * b).collect();
            let wide: Vec<f64> = a.iter().map(|&v| f64::from(v)).collect();
            assert_eq!(
                dot(&a, &b).to_bits(),
                reference_sum(&products, 0.0).to_bits(),
                "{len}"
            );
            assert_eq!(sum(&a).to_bits(), reference_sum(&a, 0.0).to_bits(), "{len}");
            assert_eq!(
                fixed_order_sum(&a).to_bits(),
                reference_sum(&wide, 0.0).to_bits(),
                "{len}"
            );
        }
    }
}
