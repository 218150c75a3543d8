//! Batch norm (with the batch's own statistics, as in training) followed by
//! ReLU, and its backward pass, on the padded channels-last layout.
//!
//! Sums over the batch are taken per map (interior pixels in raster order,
//! in f32) and the per-map sums are added in map order in f64, so they do
//! not depend on the thread count. Statistics match burn's
//! `batch_norm_train`: the mean, then the biased variance from the centred
//! values.

use rayon::prelude::*;

use super::Geometry;

/// Per-channel statistics of one batch: the mean and the biased variance
/// over the batch's interior pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct NormStatistics {
    pub mean: Vec<f32>,
    pub variance: Vec<f32>,
}

/// Calls `f(pixel)` for each interior pixel of `map`, in raster order.
#[inline(always)]
fn interior_pixels(geometry: &Geometry, map: usize, mut f: impl FnMut(usize)) {
    for row in 0..geometry.height {
        let start = geometry.pixel(map, row, 0);
        for pixel in start..start + geometry.width {
            f(pixel);
        }
    }
}

/// Per-channel sums of `term(pixel, channel sums)` over each map (in
/// parallel), then over maps in map order, in f64.
fn batch_sums<const K: usize>(
    geometry: &Geometry,
    channels: usize,
    term: impl Fn(usize, &mut [Vec<f32>; K]) + Sync,
) -> [Vec<f64>; K] {
    let per_map: Vec<[Vec<f32>; K]> = (0..geometry.n)
        .into_par_iter()
        .map(|map| {
            let mut sums: [Vec<f32>; K] = std::array::from_fn(|_| vec![0.0f32; channels]);
            interior_pixels(geometry, map, |pixel| term(pixel, &mut sums));
            sums
        })
        .collect();
    let mut total: [Vec<f64>; K] = std::array::from_fn(|_| vec![0.0f64; channels]);
    for sums in &per_map {
        for (total, sums) in total.iter_mut().zip(sums) {
            for (t, &s) in total.iter_mut().zip(sums) {
                *t += f64::from(s);
            }
        }
    }
    total
}

/// The batch statistics of `values` (padded, `channels` per pixel).
pub fn channel_statistics(values: &[f32], channels: usize, geometry: &Geometry) -> NormStatistics {
    assert_eq!(values.len(), geometry.pixels() * channels);
    let count = geometry.interior_pixels().max(1) as f64;
    let [sum] = batch_sums::<1>(geometry, channels, |pixel, [sum]| {
        let v = &values[pixel * channels..(pixel + 1) * channels];
        for (s, &v) in sum.iter_mut().zip(v) {
            *s += v;
        }
    });
    let mean: Vec<f32> = sum.iter().map(|&s| (s / count) as f32).collect();
    let [squares] = batch_sums::<1>(geometry, channels, |pixel, [squares]| {
        let v = &values[pixel * channels..(pixel + 1) * channels];
        for ((s, &v), &m) in squares.iter_mut().zip(v).zip(&mean) {
            let centred = v - m;
            *s += centred * centred;
        }
    });
    let variance = squares.iter().map(|&s| (s / count) as f32).collect();
    NormStatistics { mean, variance }
}

/// `output` interior ← max(z · scale + shift, 0) per channel (`z` and
/// `output` padded with `channels` per pixel; the border is left alone).
pub fn bn_relu_forward(
    z: &[f32],
    output: &mut [f32],
    channels: usize,
    geometry: &Geometry,
    scale: &[f32],
    shift: &[f32],
) {
    assert_eq!(z.len(), geometry.pixels() * channels);
    assert_eq!(output.len(), z.len());
    let map_floats = geometry.map_pixels() * channels;
    output
        .par_chunks_mut(map_floats)
        .enumerate()
        .for_each(|(map, out_map)| {
            let base = map * geometry.map_pixels();
            interior_pixels(geometry, map, |pixel| {
                let local = (pixel - base) * channels;
                let out = &mut out_map[local..local + channels];
                let z = &z[pixel * channels..(pixel + 1) * channels];
                for (((o, &z), &a), &b) in out.iter_mut().zip(z).zip(scale).zip(shift) {
                    *o = (z * a + b).max(0.0);
                }
            });
        });
}

/// Gradients of [`bn_relu_forward`] with the batch's statistics.
#[derive(Debug, Clone, PartialEq)]
pub struct NormGradients {
    /// Gradient with respect to `z` (padded, border zero).
    pub z_grad: Vec<f32>,
    /// With respect to gamma (empty without batch norm).
    pub gamma_grad: Vec<f32>,
    /// With respect to beta (or the conv bias without batch norm).
    pub beta_grad: Vec<f32>,
}

/// The backward pass of ReLU after batch norm (`norm = Some((stats,
/// gamma, epsilon))`) or after a plain bias (`norm = None`): `output_grad`
/// is the gradient with respect to the ReLU's output `activation`, `z` the
/// batch norm's input (all padded, `channels` per pixel).
pub fn bn_relu_backward(
    output_grad: &[f32],
    activation: &[f32],
    z: &[f32],
    channels: usize,
    geometry: &Geometry,
    norm: Option<(&NormStatistics, &[f32], f64)>,
) -> NormGradients {
    let floats = geometry.pixels() * channels;
    assert_eq!(output_grad.len(), floats);
    assert_eq!(activation.len(), floats);
    assert_eq!(z.len(), floats);
    let count = geometry.interior_pixels().max(1) as f64;
    let inv_std: Vec<f32> = match norm {
        Some((stats, _, epsilon)) => stats
            .variance
            .iter()
            .map(|&v| (1.0 / (f64::from(v) + epsilon).sqrt()) as f32)
            .collect(),
        None => vec![1.0; channels],
    };
    let zeros = vec![0.0f32; channels];
    let mean = norm.map_or(zeros.as_slice(), |(stats, _, _)| stats.mean.as_slice());
    let [sum_grad, sum_grad_normalised] =
        batch_sums::<2>(geometry, channels, |pixel, [sg, sgx]| {
            let range = pixel * channels..(pixel + 1) * channels;
            let g = &output_grad[range.clone()];
            let a = &activation[range.clone()];
            let z = &z[range];
            for c in 0..channels {
                let g = if a[c] > 0.0 { g[c] } else { 0.0 };
                sg[c] += g;
                sgx[c] += g * ((z[c] - mean[c]) * inv_std[c]);
            }
        });
    let mut z_grad = geometry.zeros(channels);
    let Some((_, gamma, _)) = norm else {
        let map_floats = geometry.map_pixels() * channels;
        z_grad
            .par_chunks_mut(map_floats)
            .enumerate()
            .for_each(|(map, out_map)| {
                let base = map * geometry.map_pixels();
                interior_pixels(geometry, map, |pixel| {
                    let local = (pixel - base) * channels;
                    for c in 0..channels {
                        let i = pixel * channels + c;
                        out_map[local + c] = if activation[i] > 0.0 {
                            output_grad[i]
                        } else {
                            0.0
                        };
                    }
                });
            });
        return NormGradients {
            z_grad,
            gamma_grad: Vec::new(),
            beta_grad: sum_grad.iter().map(|&s| s as f32).collect(),
        };
    };
    let mean_grad: Vec<f32> = sum_grad.iter().map(|&s| (s / count) as f32).collect();
    let mean_grad_normalised: Vec<f32> = sum_grad_normalised
        .iter()
        .map(|&s| (s / count) as f32)
        .collect();
    let scale: Vec<f32> = gamma.iter().zip(&inv_std).map(|(&g, &s)| g * s).collect();
    let map_floats = geometry.map_pixels() * channels;
    z_grad
        .par_chunks_mut(map_floats)
        .enumerate()
        .for_each(|(map, out_map)| {
            let base = map * geometry.map_pixels();
            interior_pixels(geometry, map, |pixel| {
                let local = (pixel - base) * channels;
                for c in 0..channels {
                    let i = pixel * channels + c;
                    let g = if activation[i] > 0.0 {
                        output_grad[i]
                    } else {
                        0.0
                    };
                    let normalised = (z[i] - mean[c]) * inv_std[c];
                    out_map[local + c] =
                        scale[c] * ((g - mean_grad[c]) - normalised * mean_grad_normalised[c]);
                }
            });
        });
    NormGradients {
        z_grad,
        gamma_grad: sum_grad_normalised.iter().map(|&s| s as f32).collect(),
        beta_grad: sum_grad.iter().map(|&s| s as f32).collect(),
    }
}
