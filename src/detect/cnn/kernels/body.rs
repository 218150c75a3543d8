//! The CNN's body (the stack of dilated 3×3 conv → batch norm → ReLU
//! blocks) on the kernels of this module: inference with batch norm folded
//! into the convolutions and ReLU fused, and a training forward pass that
//! records what its backward pass needs.
//!
//! Inputs and outputs are row-major `[n, channels, height, width]` (burn's
//! layout), so the head and the loss stay in burn.

use super::norm::{NormGradients, NormStatistics, ReluGate, bn_relu_backward, bn_relu_forward};
use super::{
    Conv3x3, Geometry, channel_statistics, conv3x3_forward, conv3x3_weight_grad, nchw_from_padded,
    padded_from_nchw,
};

/// Batch norm parameters and running statistics of one layer.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LayerNorm {
    pub gamma: Vec<f32>,
    pub beta: Vec<f32>,
    pub running_mean: Vec<f32>,
    pub running_var: Vec<f32>,
    pub epsilon: f64,
    pub momentum: f64,
}

/// One hidden layer: a dilated 3×3 convolution (weights
/// `[9][in_channels][out_channels]`, see [`weights_from_oihw`]), then
/// batch norm if `norm` is set, then ReLU.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct BodyLayer {
    pub dilation: usize,
    pub in_channels: usize,
    pub out_channels: usize,
    pub weights: Vec<f32>,
    pub bias: Option<Vec<f32>>,
    pub norm: Option<LayerNorm>,
}

/// burn's conv weights `[out][in][3][3]` as `[9][in][out]`.
pub(crate) fn weights_from_oihw(oihw: &[f32], in_channels: usize, out_channels: usize) -> Vec<f32> {
    assert_eq!(oihw.len(), 9 * in_channels * out_channels);
    let mut out = vec![0.0; oihw.len()];
    for co in 0..out_channels {
        for ci in 0..in_channels {
            for tap in 0..9 {
                out[(tap * in_channels + ci) * out_channels + co] =
                    oihw[(co * in_channels + ci) * 9 + tap];
            }
        }
    }
    out
}

/// `[9][in][out]` weights as burn's `[out][in][3][3]`.
pub(crate) fn oihw_from_weights(
    weights: &[f32],
    in_channels: usize,
    out_channels: usize,
) -> Vec<f32> {
    assert_eq!(weights.len(), 9 * in_channels * out_channels);
    let mut out = vec![0.0; weights.len()];
    for co in 0..out_channels {
        for ci in 0..in_channels {
            for tap in 0..9 {
                out[(co * in_channels + ci) * 9 + tap] =
                    weights[(tap * in_channels + ci) * out_channels + co];
            }
        }
    }
    out
}

/// The padding every layer's buffers get: the largest dilation.
fn body_pad(layers: &[BodyLayer]) -> usize {
    layers.iter().map(|l| l.dilation).max().unwrap_or(0)
}

/// Inference output of every layer with `scale · conv + shift` folded into
/// the convolution: batch norm with the running statistics
/// (`scale = γ / √(running_var + ε)`, `shift = β − running_mean · scale`).
struct FoldedLayer {
    weights: Vec<f32>,
    bias: Vec<f32>,
    dilation: usize,
    in_channels: usize,
    out_channels: usize,
}

fn fold(layer: &BodyLayer) -> FoldedLayer {
    let co_n = layer.out_channels;
    let conv_bias = layer.bias.clone().unwrap_or_else(|| vec![0.0; co_n]);
    let (scale, bias) = match &layer.norm {
        Some(norm) => {
            let scale: Vec<f32> = (0..co_n)
                .map(|c| {
                    (f64::from(norm.gamma[c])
                        / (f64::from(norm.running_var[c]) + norm.epsilon).sqrt())
                        as f32
                })
                .collect();
            let bias = (0..co_n)
                .map(|c| {
                    ((f64::from(conv_bias[c]) - f64::from(norm.running_mean[c]))
                        * f64::from(scale[c])
                        + f64::from(norm.beta[c])) as f32
                })
                .collect();
            (scale, bias)
        }
        None => (vec![1.0; co_n], conv_bias),
    };
    let weights = layer
        .weights
        .chunks_exact(co_n)
        .flat_map(|row| row.iter().zip(&scale).map(|(w, s)| w * s))
        .collect();
    FoldedLayer {
        weights,
        bias,
        dilation: layer.dilation,
        in_channels: layer.in_channels,
        out_channels: co_n,
    }
}

/// Padded pixels of activations processed per group at inference, so a
/// group's activations stay in the cores' caches through all layers.
const INFERENCE_GROUP_PIXELS: usize = 8192;

/// The body's output (`[n, out_channels, height, width]`) for `input`
/// (`[n, in_channels, height, width]`), batch norm with its running
/// statistics folded into the convolutions. Maps are processed in groups;
/// a map's output does not depend on the others.
pub(crate) fn infer(
    layers: &[BodyLayer],
    input: &[f32],
    n: usize,
    height: usize,
    width: usize,
) -> Vec<f32> {
    let folded: Vec<FoldedLayer> = layers.iter().map(fold).collect();
    let pad = body_pad(layers);
    let in_channels = layers.first().map_or(0, |l| l.in_channels);
    let out_channels = layers.last().map_or(in_channels, |l| l.out_channels);
    let map_in = in_channels * height * width;
    let one = Geometry {
        n: 1,
        height,
        width,
        pad,
    };
    let group = (INFERENCE_GROUP_PIXELS / one.map_pixels()).clamp(1, n.max(1));
    let mut out = Vec::with_capacity(n * out_channels * height * width);
    for start in (0..n).step_by(group) {
        let end = (start + group).min(n);
        let geometry = Geometry {
            n: end - start,
            ..one
        };
        let mut x = padded_from_nchw(&input[start * map_in..end * map_in], in_channels, &geometry);
        let mut channels = in_channels;
        for layer in &folded {
            let mut y = geometry.buffer(layer.out_channels);
            let conv = Conv3x3 {
                weights: &layer.weights,
                bias: Some(&layer.bias),
                in_channels: layer.in_channels,
                out_channels: layer.out_channels,
                dilation: layer.dilation,
                relu: true,
            };
            conv3x3_forward(&x, &mut y, &geometry, &conv);
            geometry.recycle(channels, std::mem::replace(&mut x, y));
            channels = layer.out_channels;
        }
        out.extend(nchw_from_padded(&x, channels, &geometry));
        geometry.recycle(channels, x);
    }
    out
}

/// What the backward pass of one training step needs.
#[derive(Debug)]
pub(crate) struct Tape {
    geometry: Geometry,
    /// The input and each layer's output (after ReLU), padded.
    activations: Vec<Vec<f32>>,
    /// Channels of each of `activations`.
    activation_channels: Vec<usize>,
    /// Each layer's convolution output, padded.
    pre_norm: Vec<Vec<f32>>,
    /// Each layer's batch statistics (batch norm layers).
    statistics: Vec<Option<NormStatistics>>,
    /// Each layer's `(scale, shift)` before its ReLU (see [`ReluGate`]).
    gates: Vec<(Vec<f32>, Vec<f32>)>,
}

impl Drop for Tape {
    /// Gives the buffers back for the next step.
    fn drop(&mut self) {
        let activations = std::mem::take(&mut self.activations);
        for (buffer, &channels) in activations.into_iter().zip(&self.activation_channels) {
            self.geometry.recycle(channels, buffer);
        }
        let pre_norm = std::mem::take(&mut self.pre_norm);
        // Each layer's conv output has the channels of its activation.
        for (buffer, &channels) in pre_norm.into_iter().zip(&self.activation_channels[1..]) {
            self.geometry.recycle(channels, buffer);
        }
    }
}

/// One layer's updated running statistics after a training forward pass.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct RunningStatistics {
    pub mean: Vec<f32>,
    pub var: Vec<f32>,
}

/// The training forward pass: batch norm normalises with the batch's own
/// statistics. Returns the body's output `[n, out_channels, height,
/// width]`, the tape for [`backward`], and each batch-norm layer's running
/// statistics updated as burn's `BatchNorm` does
/// (`running · (1 − momentum) + batch · momentum`, biased variance).
pub(crate) fn train_forward(
    layers: &[BodyLayer],
    input: &[f32],
    n: usize,
    height: usize,
    width: usize,
) -> (Vec<f32>, Tape, Vec<Option<RunningStatistics>>) {
    let geometry = Geometry {
        n,
        height,
        width,
        pad: body_pad(layers),
    };
    let in_channels = layers.first().map_or(0, |l| l.in_channels);
    let mut activations = vec![padded_from_nchw(input, in_channels, &geometry)];
    let mut pre_norm = Vec::with_capacity(layers.len());
    let mut statistics = Vec::with_capacity(layers.len());
    let mut gates = Vec::with_capacity(layers.len());
    let mut running = Vec::with_capacity(layers.len());
    for layer in layers {
        let x = activations.last().expect("the input is first");
        let mut z = geometry.buffer(layer.out_channels);
        let conv = Conv3x3 {
            weights: &layer.weights,
            bias: layer.bias.as_deref(),
            in_channels: layer.in_channels,
            out_channels: layer.out_channels,
            dilation: layer.dilation,
            relu: false,
        };
        conv3x3_forward(x, &mut z, &geometry, &conv);
        let mut a = geometry.buffer(layer.out_channels);
        match &layer.norm {
            Some(norm) => {
                let stats = channel_statistics(&z, layer.out_channels, &geometry);
                let scale: Vec<f32> = (0..layer.out_channels)
                    .map(|c| {
                        let (mean, variance) = (stats.mean[c], stats.variance[c]);
                        if !(mean.is_finite() && variance.is_finite()) {
                            // The layer's values overflow: the training
                            // diverged; NaN carries that to the loss.
                            return f32::NAN;
                        }
                        norm.gamma[c] * (1.0 / (f64::from(variance) + norm.epsilon).sqrt()) as f32
                    })
                    .collect();
                let shift: Vec<f32> = (0..layer.out_channels)
                    .map(|c| norm.beta[c] - stats.mean[c] * scale[c])
                    .collect();
                bn_relu_forward(&z, &mut a, layer.out_channels, &geometry, &scale, &shift);
                gates.push((scale, shift));
                let keep = (1.0 - norm.momentum) as f32;
                let take = norm.momentum as f32;
                let update = |old: &[f32], new: &[f32]| -> Vec<f32> {
                    old.iter()
                        .zip(new)
                        .map(|(o, b)| o * keep + b * take)
                        .collect()
                };
                running.push(Some(RunningStatistics {
                    mean: update(&norm.running_mean, &stats.mean),
                    var: update(&norm.running_var, &stats.variance),
                }));
                statistics.push(Some(stats));
            }
            None => {
                let ones = vec![1.0; layer.out_channels];
                let zeros = vec![0.0; layer.out_channels];
                bn_relu_forward(&z, &mut a, layer.out_channels, &geometry, &ones, &zeros);
                gates.push((ones, zeros));
                running.push(None);
                statistics.push(None);
            }
        }
        pre_norm.push(z);
        activations.push(a);
    }
    let out_channels = layers.last().map_or(in_channels, |l| l.out_channels);
    let output = nchw_from_padded(
        activations.last().expect("the input is first"),
        out_channels,
        &geometry,
    );
    (
        output,
        Tape {
            geometry,
            activation_channels: std::iter::once(in_channels)
                .chain(layers.iter().map(|l| l.out_channels))
                .collect(),
            activations,
            pre_norm,
            statistics,
            gates,
        },
        running,
    )
}

/// Gradients of one layer's parameters.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LayerGradients {
    /// `[9][in_channels][out_channels]`.
    pub weights: Vec<f32>,
    /// Conv bias (layers without batch norm).
    pub bias: Option<Vec<f32>>,
    /// Batch norm's gamma and beta.
    pub gamma: Option<Vec<f32>>,
    pub beta: Option<Vec<f32>>,
}

/// The backward pass of [`train_forward`]: from the gradient of the loss
/// with respect to the body's output (`[n, out_channels, height, width]`)
/// to the gradients of every layer's parameters, in layer order.
pub(crate) fn backward(
    layers: &[BodyLayer],
    tape: &Tape,
    output_grad: &[f32],
) -> Vec<LayerGradients> {
    let geometry = &tape.geometry;
    let out_channels = layers.last().map_or(0, |l| l.out_channels);
    let mut grad = padded_from_nchw(output_grad, out_channels, geometry);
    let mut gradients = Vec::with_capacity(layers.len());
    for (index, layer) in layers.iter().enumerate().rev() {
        let norm = layer.norm.as_ref().map(|norm| {
            (
                tape.statistics[index]
                    .as_ref()
                    .expect("batch norm layers have statistics"),
                norm.gamma.as_slice(),
                norm.epsilon,
            )
        });
        let NormGradients {
            z_grad,
            gamma_grad,
            beta_grad,
        } = bn_relu_backward(
            &grad,
            &tape.pre_norm[index],
            ReluGate {
                scale: &tape.gates[index].0,
                shift: &tape.gates[index].1,
            },
            layer.out_channels,
            geometry,
            norm,
            geometry.buffer(layer.out_channels),
        );
        let conv = Conv3x3 {
            weights: &layer.weights,
            bias: None,
            in_channels: layer.in_channels,
            out_channels: layer.out_channels,
            dilation: layer.dilation,
            relu: false,
        };
        let weights = conv3x3_weight_grad(&tape.activations[index], &z_grad, geometry, &conv);
        if index > 0 {
            let transposed = conv.transposed_weights();
            let back = Conv3x3 {
                weights: &transposed,
                bias: None,
                in_channels: layer.out_channels,
                out_channels: layer.in_channels,
                dilation: layer.dilation,
                relu: false,
            };
            let mut input_grad = geometry.buffer(layer.in_channels);
            conv3x3_forward(&z_grad, &mut input_grad, geometry, &back);
            geometry.recycle(layer.out_channels, std::mem::replace(&mut grad, input_grad));
        }
        geometry.recycle(layer.out_channels, z_grad);
        let with_norm = layer.norm.is_some();
        gradients.push(LayerGradients {
            weights,
            bias: (!with_norm).then(|| beta_grad.clone()),
            gamma: with_norm.then_some(gamma_grad),
            beta: with_norm.then_some(beta_grad),
        });
    }
    if let Some(first) = layers.first() {
        geometry.recycle(first.out_channels, grad);
    }
    gradients.reverse();
    gradients
}
