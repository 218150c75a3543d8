//! Batch norm (with the batch's own statistics, as in training) followed by
//! ReLU, and its backward pass, on the padded channels-last layout.
//!
//! Sums over the batch are taken per map (interior pixels in raster order,
//! in f32) and the per-map sums are added in map order in f64, so they do
//! not depend on the thread count. Statistics match burn's
//! `batch_norm_train`: the mean, then the biased variance from the centred
//! values.
//!
//! The loops over a row's pixels ([`RowKernel`]) are compiled for the
//! widest vector instructions the CPU has and for the usual channel counts
//! (see [`vectorised`]). They use no fused multiply-add, so every build
//! gives the same bits.

use std::ops::Range;

use rayon::prelude::*;

use super::Geometry;

/// A loop over the pixels of one interior row (`channels` floats a pixel,
/// channels innermost), the unit [`vectorised`] compiles per instruction
/// set: inputs borrowed for `'d`, outputs for `'o`. Each runs
/// [`RowKernel::run`] on the loop's function of the same name.
enum RowKernel<'d, 'o> {
    /// `sum[c] += v[c]`.
    Sum {
        values: &'d [f32],
        sum: &'o mut [f32],
    },
    /// `squares[c] += (v[c] − mean[c])²`.
    Squares {
        values: &'d [f32],
        mean: &'d [f32],
        squares: &'o mut [f32],
    },
    /// `out = max(z · scale + shift, 0)`.
    BnRelu {
        z: &'d [f32],
        out: &'o mut [f32],
        scale: &'d [f32],
        shift: &'d [f32],
    },
    /// The two sums of batch norm's backward pass.
    BackwardSums {
        output_grad: &'d [f32],
        z: &'d [f32],
        gate: ReluGate<'d>,
        statistics: Standardise<'d>,
        sum_grad: &'o mut [f32],
        sum_grad_normalised: &'o mut [f32],
    },
    /// The gradient through a ReLU alone.
    ReluGrad {
        output_grad: &'d [f32],
        z: &'d [f32],
        gate: ReluGate<'d>,
        out: &'o mut [f32],
    },
    /// The gradient with respect to batch norm's input.
    BnReluGrad {
        output_grad: &'d [f32],
        z: &'d [f32],
        gate: ReluGate<'d>,
        statistics: Standardise<'d>,
        coefficients: BackwardCoefficients<'d>,
        out: &'o mut [f32],
    },
}

/// The forward pass's map before its ReLU, per channel: the ReLU passed
/// the gradient of a value where `z · scale + shift > 0`, exactly where its
/// output `max(z · scale + shift, 0)` was positive (NaN fails both tests).
/// The backward pass reads this from `z`, which it reads anyway, instead of
/// reading the activations too: the loops are bound by memory.
#[derive(Clone, Copy)]
pub(crate) struct ReluGate<'a> {
    pub scale: &'a [f32],
    pub shift: &'a [f32],
}

/// Per channel: `(z − mean) · inv_std` standardises a value.
#[derive(Clone, Copy)]
struct Standardise<'a> {
    mean: &'a [f32],
    inv_std: &'a [f32],
}

/// Per channel: `scale = γ · inv_std` and the batch means of the gradient
/// and of the gradient times the standardised value.
#[derive(Clone, Copy)]
struct BackwardCoefficients<'a> {
    scale: &'a [f32],
    mean_grad: &'a [f32],
    mean_grad_normalised: &'a [f32],
}

impl RowKernel<'_, '_> {
    /// The loop, with `channels` floats a pixel (a constant where inlined
    /// with one, so the channel loops unroll into whole vectors). The
    /// loops are functions of their slices, which so arrive as arguments
    /// the compiler knows do not overlap, and vectorise.
    #[inline(always)]
    fn run(self, channels: usize) {
        match self {
            Self::Sum { values, sum } => sum_row(values, sum, channels),
            Self::Squares {
                values,
                mean,
                squares,
            } => squares_row(values, mean, squares, channels),
            Self::BnRelu {
                z,
                out,
                scale,
                shift,
            } => bn_relu_row(z, out, scale, shift, channels),
            Self::BackwardSums {
                output_grad,
                z,
                gate,
                statistics,
                sum_grad,
                sum_grad_normalised,
            } => backward_sums_row(
                [output_grad, z],
                gate,
                statistics,
                [sum_grad, sum_grad_normalised],
                channels,
            ),
            Self::ReluGrad {
                output_grad,
                z,
                gate,
                out,
            } => relu_grad_row([output_grad, z], gate, out, channels),
            Self::BnReluGrad {
                output_grad,
                z,
                gate,
                statistics,
                coefficients,
                out,
            } => bn_relu_grad_row(
                [output_grad, z],
                gate,
                statistics,
                coefficients,
                out,
                channels,
            ),
        }
    }
}

/// Runs `kernel` compiled for AVX-512 or AVX2 if the CPU has it (the
/// crate's baseline build is SSE2, four lanes) and for the channel counts
/// 16, 32 and 64 as constants. Without fused multiply-adds (Rust does not
/// contract `a * b + c`) and with each channel's values combined in the
/// same order, every build gives the same bits.
#[inline(always)]
fn vectorised(kernel: RowKernel, channels: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use crate::detect::cpu::{has_avx2_fma, has_avx512};
        if has_avx512() {
            // SAFETY: the CPU has AVX-512F.
            return unsafe { run_avx512(kernel, channels) };
        }
        if has_avx2_fma() {
            // SAFETY: the CPU has AVX2 and FMA.
            return unsafe { run_avx2(kernel, channels) };
        }
    }
    run_specialised(kernel, channels)
}

/// `kernel` with its channel count as a constant for the usual widths.
#[inline(always)]
fn run_specialised(kernel: RowKernel, channels: usize) {
    match channels {
        16 => kernel.run(16),
        32 => kernel.run(32),
        64 => kernel.run(64),
        channels => kernel.run(channels),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn run_avx512(kernel: RowKernel, channels: usize) {
    run_specialised(kernel, channels)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn run_avx2(kernel: RowKernel, channels: usize) {
    run_specialised(kernel, channels)
}

#[inline(always)]
fn sum_row(values: &[f32], sum: &mut [f32], channels: usize) {
    let sum = &mut sum[..channels];
    for v in values.chunks_exact(channels) {
        for (s, &v) in sum.iter_mut().zip(v) {
            *s += v;
        }
    }
}

#[inline(always)]
fn squares_row(values: &[f32], mean: &[f32], squares: &mut [f32], channels: usize) {
    let squares = &mut squares[..channels];
    let mean = &mean[..channels];
    for v in values.chunks_exact(channels) {
        for ((s, &v), &m) in squares.iter_mut().zip(v).zip(mean) {
            let centred = v - m;
            *s += centred * centred;
        }
    }
}

#[inline(always)]
fn bn_relu_row(z: &[f32], out: &mut [f32], scale: &[f32], shift: &[f32], channels: usize) {
    let (scale, shift) = (&scale[..channels], &shift[..channels]);
    for (out, z) in out.chunks_exact_mut(channels).zip(z.chunks_exact(channels)) {
        for (((o, &z), &a), &b) in out.iter_mut().zip(z).zip(scale).zip(shift) {
            *o = super::relu(z * a + b);
        }
    }
}

/// With `g` the output gradient passed by the ReLU: `sum_grad[c] += g` and
/// `sum_grad_normalised[c] += g · (z − mean) · inv_std`.
#[inline(always)]
fn backward_sums_row(
    [output_grad, z]: [&[f32]; 2],
    gate: ReluGate,
    statistics: Standardise,
    [sum_grad, sum_grad_normalised]: [&mut [f32]; 2],
    channels: usize,
) {
    let sum_g = &mut sum_grad[..channels];
    let sum_gx = &mut sum_grad_normalised[..channels];
    let (mean, inv_std) = (
        &statistics.mean[..channels],
        &statistics.inv_std[..channels],
    );
    let (scale, shift) = (&gate.scale[..channels], &gate.shift[..channels]);
    let pixels = output_grad
        .chunks_exact(channels)
        .zip(z.chunks_exact(channels));
    for (g, z) in pixels {
        let lanes = sum_g
            .iter_mut()
            .zip(sum_gx.iter_mut())
            .zip(g.iter().zip(scale.iter().zip(shift)))
            .zip(z.iter().zip(mean.iter().zip(inv_std)));
        for (((sg, sgx), (&g, (&a, &b))), (&z, (&m, &s))) in lanes {
            let g = if z * a + b > 0.0 { g } else { 0.0 };
            *sg += g;
            *sgx += g * ((z - m) * s);
        }
    }
}

/// `out = g` where the ReLU passed it, else 0.
#[inline(always)]
fn relu_grad_row([output_grad, z]: [&[f32]; 2], gate: ReluGate, out: &mut [f32], channels: usize) {
    let (scale, shift) = (&gate.scale[..channels], &gate.shift[..channels]);
    let pixels = out
        .chunks_exact_mut(channels)
        .zip(output_grad.chunks_exact(channels))
        .zip(z.chunks_exact(channels));
    for ((out, g), z) in pixels {
        let lanes = out
            .iter_mut()
            .zip(g.iter().zip(z))
            .zip(scale.iter().zip(shift));
        for ((o, (&g, &z)), (&a, &b)) in lanes {
            *o = if z * a + b > 0.0 { g } else { 0.0 };
        }
    }
}

/// `out = scale · ((g − mean_grad) − (z − mean) · inv_std ·
/// mean_grad_normalised)`, with `g` the output gradient passed by the ReLU.
#[inline(always)]
fn bn_relu_grad_row(
    [output_grad, z]: [&[f32]; 2],
    gate: ReluGate,
    statistics: Standardise,
    coefficients: BackwardCoefficients,
    out: &mut [f32],
    channels: usize,
) {
    let (mean, inv_std) = (
        &statistics.mean[..channels],
        &statistics.inv_std[..channels],
    );
    let (gate_scale, gate_shift) = (&gate.scale[..channels], &gate.shift[..channels]);
    let scale = &coefficients.scale[..channels];
    let mean_grad = &coefficients.mean_grad[..channels];
    let mean_grad_normalised = &coefficients.mean_grad_normalised[..channels];
    let pixels = out
        .chunks_exact_mut(channels)
        .zip(output_grad.chunks_exact(channels))
        .zip(z.chunks_exact(channels));
    for ((out, g), z) in pixels {
        let lanes = out
            .iter_mut()
            .zip(g.iter().zip(gate_scale.iter().zip(gate_shift)))
            .zip(z.iter().zip(mean.iter().zip(inv_std)))
            .zip(scale.iter().zip(mean_grad.iter().zip(mean_grad_normalised)));
        for (((o, (&g, (&a, &b))), (&z, (&m, &s))), (&k, (&mg, &mgn))) in lanes {
            let g = if z * a + b > 0.0 { g } else { 0.0 };
            let normalised = (z - m) * s;
            *o = k * ((g - mg) - normalised * mgn);
        }
    }
}

/// Per-channel statistics of one batch: the mean and the biased variance
/// over the batch's interior pixels.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct NormStatistics {
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

/// Per-channel sums over each map's interior rows (maps in parallel, rows
/// in order) by the row kernel `kernel(row floats, the map's channel sums)`
/// makes, then over maps in map order, in f64.
fn batch_sums<'d, const K: usize>(
    geometry: &Geometry,
    channels: usize,
    kernel: impl for<'o> Fn(Range<usize>, &'o mut [Vec<f32>; K]) -> RowKernel<'d, 'o> + Sync,
) -> [Vec<f64>; K] {
    let per_map: Vec<[Vec<f32>; K]> = (0..geometry.n)
        .into_par_iter()
        .map(|map| {
            let mut sums: [Vec<f32>; K] = std::array::from_fn(|_| vec![0.0f32; channels]);
            for row in interior_rows(geometry, map, channels) {
                vectorised(kernel(row, &mut sums), channels);
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

/// Runs the row kernel `kernel(row floats, that row of the map's output)`
/// makes for each interior row of every map of `output` (maps in
/// parallel).
fn for_each_output_row<'d>(
    output: &mut [f32],
    geometry: &Geometry,
    channels: usize,
    kernel: impl for<'o> Fn(Range<usize>, &'o mut [f32]) -> RowKernel<'d, 'o> + Sync,
) {
    let map_floats = geometry.map_pixels() * channels;
    output
        .par_chunks_mut(map_floats)
        .enumerate()
        .for_each(|(map, out_map)| {
            let base = map * map_floats;
            for row in interior_rows(geometry, map, channels) {
                let out = &mut out_map[row.start - base..row.end - base];
                vectorised(kernel(row, out), channels);
            }
        });
}

/// The batch statistics of `values` (padded, `channels` per pixel).
pub(crate) fn channel_statistics(
    values: &[f32],
    channels: usize,
    geometry: &Geometry,
) -> NormStatistics {
    assert_eq!(values.len(), geometry.pixels() * channels);
    let count = geometry.interior_pixels().max(1) as f64;
    let [sum] = batch_sums::<1>(geometry, channels, |row, [sum]| RowKernel::Sum {
        values: &values[row],
        sum,
    });
    let mean: Vec<f32> = sum.iter().map(|&s| (s / count) as f32).collect();
    let [squares] = batch_sums::<1>(geometry, channels, |row, [squares]| RowKernel::Squares {
        values: &values[row],
        mean: &mean,
        squares,
    });
    let variance = squares.iter().map(|&s| (s / count) as f32).collect();
    NormStatistics { mean, variance }
}

/// `output` interior ← max(z · scale + shift, 0) per channel (`z` and
/// `output` padded with `channels` per pixel; the border is left alone).
pub(crate) fn bn_relu_forward(
    z: &[f32],
    output: &mut [f32],
    channels: usize,
    geometry: &Geometry,
    scale: &[f32],
    shift: &[f32],
) {
    assert_eq!(z.len(), geometry.pixels() * channels);
    assert_eq!(output.len(), z.len());
    for_each_output_row(output, geometry, channels, |row, out| RowKernel::BnRelu {
        z: &z[row],
        out,
        scale,
        shift,
    });
}

/// Gradients of [`bn_relu_forward`] with the batch's statistics.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct NormGradients {
    /// Gradient with respect to `z` (padded, border zero).
    pub z_grad: Vec<f32>,
    /// With respect to gamma (empty without batch norm).
    pub gamma_grad: Vec<f32>,
    /// With respect to beta (or the conv bias without batch norm).
    pub beta_grad: Vec<f32>,
}

/// The backward pass of ReLU after batch norm (`norm = Some((stats,
/// gamma, epsilon))`) or after a plain bias (`norm = None`): `output_grad`
/// is the gradient with respect to the ReLU's output, `z` the batch norm's
/// input (both padded, `channels` per pixel), `gate` the forward pass's
/// `scale` and `shift` (those given to [`bn_relu_forward`]). `z_grad` is
/// written into `z_grad_buffer` (padded, border zero; every interior value
/// is overwritten).
pub(crate) fn bn_relu_backward(
    output_grad: &[f32],
    z: &[f32],
    gate: ReluGate,
    channels: usize,
    geometry: &Geometry,
    norm: Option<(&NormStatistics, &[f32], f64)>,
    mut z_grad: Vec<f32>,
) -> NormGradients {
    let floats = geometry.pixels() * channels;
    assert_eq!(output_grad.len(), floats);
    assert_eq!(gate.scale.len(), channels);
    assert_eq!(gate.shift.len(), channels);
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
    let statistics = Standardise {
        mean,
        inv_std: &inv_std,
    };
    let [sum_grad, sum_grad_normalised] = batch_sums::<2>(
        geometry,
        channels,
        |row, [sum_grad, sum_grad_normalised]| RowKernel::BackwardSums {
            output_grad: &output_grad[row.clone()],
            z: &z[row],
            gate,
            statistics,
            sum_grad,
            sum_grad_normalised,
        },
    );
    let Some((_, gamma, _)) = norm else {
        for_each_output_row(&mut z_grad, geometry, channels, |row, out| {
            RowKernel::ReluGrad {
                output_grad: &output_grad[row.clone()],
                z: &z[row],
                gate,
                out,
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
    let coefficients = BackwardCoefficients {
        scale: &scale,
        mean_grad: &mean_grad,
        mean_grad_normalised: &mean_grad_normalised,
    };
    for_each_output_row(&mut z_grad, geometry, channels, |row, out| {
        RowKernel::BnReluGrad {
            output_grad: &output_grad[row.clone()],
            z: &z[row],
            gate,
            statistics,
            coefficients,
            out,
        }
    });
    NormGradients {
        z_grad,
        gamma_grad: sum_grad_normalised.iter().map(|&s| s as f32).collect(),
        beta_grad: sum_grad.iter().map(|&s| s as f32).collect(),
    }
}

#[cfg(test)]
mod tests {
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    /// Every row kernel gives the same bits on the CPU's widest vector
    /// build (what training runs) as on the baseline build, for channel
    /// counts with and without a constant build, and for values around
    /// the ReLU's threshold (zeros, negative zeros and NaN included).
    #[test]
    fn the_vector_builds_give_the_baseline_bits() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        for channels in [1, 3, 16, 32, 48, 64] {
            let pixels = 27;
            let mut random = |len: usize| -> Vec<f32> {
                (0..len)
                    .map(|i| match i % 23 {
                        0 => 0.0,
                        1 => -0.0,
                        2 if channels > 1 => f32::NAN,
                        _ => rng.random_range(-2.0f32..2.0),
                    })
                    .collect()
            };
            let [values, grad] = [random(pixels * channels), random(pixels * channels)];
            let [mean, inv_std, scale, shift, k, mg, mgn] =
                std::array::from_fn(|_| random(channels));
            let gate = ReluGate {
                scale: &scale,
                shift: &shift,
            };
            let statistics = Standardise {
                mean: &mean,
                inv_std: &inv_std,
            };
            let coefficients = BackwardCoefficients {
                scale: &k,
                mean_grad: &mg,
                mean_grad_normalised: &mgn,
            };
            // Each kernel's outputs, run through `run` (the vector build,
            // where the CPU has one) or the baseline.
            let outputs = |vector: bool| -> Vec<Vec<u32>> {
                let run = |kernel: RowKernel| {
                    if vector {
                        vectorised(kernel, channels)
                    } else {
                        run_specialised(kernel, channels)
                    }
                };
                let (mut sum, mut squares) = (vec![0.5f32; channels], vec![0.25f32; channels]);
                let (mut sum_g, mut sum_gx) = (vec![0.0f32; channels], vec![0.0f32; channels]);
                let mut out = [(); 3].map(|_| vec![0.0f32; pixels * channels]);
                run(RowKernel::Sum {
                    values: &values,
                    sum: &mut sum,
                });
                run(RowKernel::Squares {
                    values: &values,
                    mean: &mean,
                    squares: &mut squares,
                });
                let [bn_relu, relu_grad, bn_relu_grad] = &mut out;
                run(RowKernel::BnRelu {
                    z: &values,
                    out: bn_relu,
                    scale: &scale,
                    shift: &shift,
                });
                run(RowKernel::BackwardSums {
                    output_grad: &grad,
                    z: &values,
                    gate,
                    statistics,
                    sum_grad: &mut sum_g,
                    sum_grad_normalised: &mut sum_gx,
                });
                run(RowKernel::ReluGrad {
                    output_grad: &grad,
                    z: &values,
                    gate,
                    out: relu_grad,
                });
                run(RowKernel::BnReluGrad {
                    output_grad: &grad,
                    z: &values,
                    gate,
                    statistics,
                    coefficients,
                    out: bn_relu_grad,
                });
                [sum, squares, sum_g, sum_gx]
                    .into_iter()
                    .chain(out)
                    .map(|v| v.iter().map(|x| x.to_bits()).collect())
                    .collect()
            };
            assert_eq!(outputs(true), outputs(false), "{channels} channels");
        }
    }
}
