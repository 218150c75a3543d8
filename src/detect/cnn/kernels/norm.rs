//! Batch norm (with the batch's own statistics, as in training) followed by
//! ReLU, and its backward pass, on the padded channels-last layout.
//!
//! Sums over the batch are taken per map (interior pixels in raster order,
//! in f32) and the per-map sums are added in map order in f64, so they do
//! not depend on the thread count. Statistics match burn's
//! `batch_norm_train`: the mean, then the biased variance from the centred
//! values.

use std::ops::Range;

use rayon::prelude::*;

use super::Geometry;

/// Per-channel statistics of one batch: the mean and the biased variance
/// over the batch's interior pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct NormStatistics {
    pub mean: Vec<f32>,
    pub variance: Vec<f32>,
}

/// The interior rows of `map`, in raster order, as ranges of floats of a
/// padded buffer with `channels` per pixel.
fn interior_rows(
    geometry: &Geometry,
    map: usize,
    channels: usize,
) -> impl Iterator<Item = Range<usize>> {
    (0..geometry.height).map(move |row| {
        let start = geometry.pixel(map, row, 0) * channels;
        start..start + geometry.width * channels
    })
}

/// Per-channel sums of `term(row floats, channel sums)` over each map's
/// interior rows (maps in parallel, rows in order), then over maps in map
/// order, in f64.
fn batch_sums<const K: usize>(
    geometry: &Geometry,
    channels: usize,
    term: impl Fn(Range<usize>, &mut [Vec<f32>; K]) + Sync,
) -> [Vec<f64>; K] {
    let per_map: Vec<[Vec<f32>; K]> = (0..geometry.n)
        .into_par_iter()
        .map(|map| {
            let mut sums: [Vec<f32>; K] = std::array::from_fn(|_| vec![0.0f32; channels]);
            for row in interior_rows(geometry, map, channels) {
                term(row, &mut sums);
            }
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

/// Writes `f(row floats, that row of the map's output)` for each interior
/// row of every map of `output` (maps in parallel).
fn for_each_output_row(
    output: &mut [f32],
    geometry: &Geometry,
    channels: usize,
    f: impl Fn(Range<usize>, &mut [f32]) + Sync,
) {
    let map_floats = geometry.map_pixels() * channels;
    output
        .par_chunks_mut(map_floats)
        .enumerate()
        .for_each(|(map, out_map)| {
            let base = map * map_floats;
            for row in interior_rows(geometry, map, channels) {
                let out = &mut out_map[row.start - base..row.end - base];
                f(row, out);
            }
        });
}

/// The batch statistics of `values` (padded, `channels` per pixel).
pub fn channel_statistics(values: &[f32], channels: usize, geometry: &Geometry) -> NormStatistics {
    assert_eq!(values.len(), geometry.pixels() * channels);
    let count = geometry.interior_pixels().max(1) as f64;
    let [sum] = batch_sums::<1>(geometry, channels, |row, [sum]| {
        for v in values[row].chunks_exact(channels) {
            for (s, &v) in sum.iter_mut().zip(v) {
                *s += v;
            }
        }
    });
    let mean: Vec<f32> = sum.iter().map(|&s| (s / count) as f32).collect();
    let [squares] = batch_sums::<1>(geometry, channels, |row, [squares]| {
        for v in values[row].chunks_exact(channels) {
            for ((s, &v), &m) in squares.iter_mut().zip(v).zip(&mean) {
                let centred = v - m;
                *s += centred * centred;
            }
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
    for_each_output_row(output, geometry, channels, |row, out| {
        for (out, z) in out
            .chunks_exact_mut(channels)
            .zip(z[row].chunks_exact(channels))
        {
            for (((o, &z), &a), &b) in out.iter_mut().zip(z).zip(scale).zip(shift) {
                *o = super::relu(z * a + b);
            }
        }
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
/// batch norm's input (all padded, `channels` per pixel). `z_grad` is
/// written into `z_grad_buffer` (padded, border zero; every interior value
/// is overwritten).
pub fn bn_relu_backward(
    output_grad: &[f32],
    activation: &[f32],
    z: &[f32],
    channels: usize,
    geometry: &Geometry,
    norm: Option<(&NormStatistics, &[f32], f64)>,
    mut z_grad: Vec<f32>,
) -> NormGradients {
    let floats = geometry.pixels() * channels;
    assert_eq!(output_grad.len(), floats);
    assert_eq!(activation.len(), floats);
    assert_eq!(z.len(), floats);
    assert_eq!(z_grad.len(), floats);
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
        batch_sums::<2>(geometry, channels, |row, [sum_g, sum_gx]| {
            let pixels = output_grad[row.clone()]
                .chunks_exact(channels)
                .zip(activation[row.clone()].chunks_exact(channels))
                .zip(z[row].chunks_exact(channels));
            for ((g, a), z) in pixels {
                let lanes = sum_g
                    .iter_mut()
                    .zip(sum_gx.iter_mut())
                    .zip(g.iter().zip(a))
                    .zip(z.iter().zip(mean.iter().zip(&inv_std)));
                for (((sg, sgx), (&g, &a)), (&z, (&m, &s))) in lanes {
                    let g = if a > 0.0 { g } else { 0.0 };
                    *sg += g;
                    *sgx += g * ((z - m) * s);
                }
            }
        });
    let Some((_, gamma, _)) = norm else {
        for_each_output_row(&mut z_grad, geometry, channels, |row, out| {
            let lanes = out
                .iter_mut()
                .zip(&output_grad[row.clone()])
                .zip(&activation[row]);
            for ((o, &g), &a) in lanes {
                *o = if a > 0.0 { g } else { 0.0 };
            }
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
    for_each_output_row(&mut z_grad, geometry, channels, |row, out| {
        let pixels = out
            .chunks_exact_mut(channels)
            .zip(output_grad[row.clone()].chunks_exact(channels))
            .zip(activation[row.clone()].chunks_exact(channels))
            .zip(z[row].chunks_exact(channels));
        for (((out, g), a), z) in pixels {
            let lanes = out
                .iter_mut()
                .zip(g.iter().zip(a))
                .zip(z.iter().zip(mean.iter().zip(&inv_std)))
                .zip(
                    scale
                        .iter()
                        .zip(mean_grad.iter().zip(&mean_grad_normalised)),
                );
            for (((o, (&g, &a)), (&z, (&m, &s))), (&k, (&mg, &mgn))) in lanes {
                let g = if a > 0.0 { g } else { 0.0 };
                let normalised = (z - m) * s;
                *o = k * ((g - mg) - normalised * mgn);
            }
        }
    });
    NormGradients {
        z_grad,
        gamma_grad: sum_grad_normalised.iter().map(|&s| s as f32).collect(),
        beta_grad: sum_grad.iter().map(|&s| s as f32).collect(),
    }
}
