//! The network: a stack of dilated 3×3 convolutions (each followed by batch
//! norm and ReLU) that keeps the frame size, and a 1×1 head giving six maps
//! per pixel: the centre score logit, the sub-pixel offsets (dx, dy) from
//! the pixel centre to the QD's trajectory centroid, and the localisation's
//! uncertainty read two ways: ln σx, ln σy of the offsets' error, and the
//! logit of the probability that pixel + offset lies within 1 px of a
//! centroid.
//!
//! Every conv pads by its dilation, so the output has exactly the input's
//! height and width whatever the frame size: the model trained on 24×25
//! frames runs unchanged on a 512×512 recording.
//!
//! Weights are drawn from a ChaCha stream of the training seed (not from
//! burn's global RNG), so initialisation is reproducible even when several
//! models are built concurrently in one process.

use burn::module::{Param, ParamId, RunningState};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::optim::GradientsParams;
use burn::prelude::*;
#[cfg(test)]
use burn::tensor::activation::relu;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution as _, Normal};

use super::CnnArchitecture;
use super::kernels::body::{self, BodyLayer, LayerNorm, Tape};
use super::kernels::{Head, head_backward, head_forward};

/// Output channel holding the centre score logit.
pub const SCORE_CHANNEL: usize = 0;
/// Output channel holding the column offset (x) in pixels.
pub const OFFSET_X_CHANNEL: usize = 1;
/// Output channel holding the row offset (y) in pixels.
pub const OFFSET_Y_CHANNEL: usize = 2;
/// Output channel holding ln σx, the natural log of the standard deviation
/// (pixels) of the true centroid's column about pixel + offset.
pub const LOG_SIGMA_X_CHANNEL: usize = 3;
/// Output channel holding ln σy (rows), as [`LOG_SIGMA_X_CHANNEL`].
pub const LOG_SIGMA_Y_CHANNEL: usize = 4;
/// Output channel holding the logit of the probability that this pixel's
/// localisation (pixel + offset) lies within 1 px of a trajectory centroid.
pub const WITHIN_1PX_CHANNEL: usize = 5;
/// Number of output maps.
pub const OUTPUT_CHANNELS: usize = 6;

/// Prior probability that a pixel is a QD centre, used to set the initial
/// score bias (as CenterNet does) so that early training is not swamped by
/// the loss of the many background pixels; also the initial probability of
/// a pixel's localisation being within 1 px of a centroid, for the same
/// reason.
const INITIAL_CENTRE_PRIOR: f64 = 0.01;
/// Initial σ (pixels) of the uncertainty maps: about the offsets' error
/// early in training, so the first likelihood gradients are moderate.
const INITIAL_SIGMA_PX: f64 = 0.5;

/// Bounds of ln σ: σ from 0.007 to 20 px. In training they bound the σ
/// maps in the likelihood (a pixel whose offset happens to be exact cannot
/// drive its σ, and the loss, towards −∞); at inference they bound every
/// reported σ.
pub const LOG_SIGMA_RANGE: (f64, f64) = (-5.0, 3.0);

/// One dilated 3×3 convolution, optionally batch-normalised, then ReLU.
#[derive(Module, Debug)]
pub(crate) struct ConvBlock {
    conv: Conv2d,
    norm: Option<BatchNorm>,
}

impl ConvBlock {
    #[cfg(test)]
    fn forward(&self, input: Tensor<4>) -> Tensor<4> {
        let x = self.conv.forward(input);
        let x = match &self.norm {
            Some(norm) => norm.forward(x),
            None => x,
        };
        relu(x)
    }
}

/// The fully convolutional localiser.
#[derive(Module, Debug)]
pub(crate) struct Net {
    blocks: Vec<ConvBlock>,
    head: Conv2d,
}

impl Net {
    /// Builds the network described by `arch` on `device`, with weights drawn
    /// from ChaCha8 seeded by `seed` (He-normal for the ReLU layers, small
    /// normal for the head, score bias set from `INITIAL_CENTRE_PRIOR`).
    ///
    /// Parameter ids are numbered 1, 2, … in construction order (burn would
    /// draw them at random), so the saved record of a model is a pure
    /// function of its weights.
    pub(crate) fn new(arch: &CnnArchitecture, seed: u64, device: &Device) -> Self {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut next_id = 0u64;
        let mut id = || {
            next_id += 1;
            ParamId::from(next_id)
        };
        let mut in_channels = arch.input_channels();
        let mut blocks = Vec::with_capacity(arch.dilations.len());
        for &dilation in &arch.dilations {
            let config = Conv2dConfig::new([in_channels, arch.channels], [3, 3])
                .with_dilation([dilation, dilation])
                .with_padding(PaddingConfig2d::Explicit(
                    dilation, dilation, dilation, dilation,
                ))
                // Batch norm's shift makes a conv bias redundant.
                .with_bias(!arch.batch_norm);
            let mut conv = config.init(device);
            let fan_in = in_channels * 9;
            let std = (2.0 / fan_in as f64).sqrt();
            conv.weight = normal_param(&mut rng, [arch.channels, in_channels, 3, 3], std, device)
                .with_id(id());
            if let Some(bias) = conv.bias.as_mut() {
                *bias = constant_param(0.0, arch.channels, device).with_id(id());
            }
            let norm = arch.batch_norm.then(|| {
                let mut norm = BatchNormConfig::new(arch.channels).init(device);
                norm.gamma = constant_param(1.0, arch.channels, device).with_id(id());
                norm.beta = constant_param(0.0, arch.channels, device).with_id(id());
                norm.running_mean =
                    RunningState::with_id(id(), Tensor::zeros([arch.channels], device));
                norm.running_var =
                    RunningState::with_id(id(), Tensor::ones([arch.channels], device));
                norm
            });
            blocks.push(ConvBlock { conv, norm });
            in_channels = arch.channels;
        }
        let mut head = Conv2dConfig::new([in_channels, OUTPUT_CHANNELS], [1, 1])
            .with_bias(true)
            .init(device);
        head.weight = normal_param(&mut rng, [OUTPUT_CHANNELS, in_channels, 1, 1], 0.01, device)
            .with_id(id());
        let mut bias = vec![0.0f32; OUTPUT_CHANNELS];
        let prior_logit = (INITIAL_CENTRE_PRIOR / (1.0 - INITIAL_CENTRE_PRIOR)).ln() as f32;
        bias[SCORE_CHANNEL] = prior_logit;
        bias[WITHIN_1PX_CHANNEL] = prior_logit;
        bias[LOG_SIGMA_X_CHANNEL] = INITIAL_SIGMA_PX.ln() as f32;
        bias[LOG_SIGMA_Y_CHANNEL] = INITIAL_SIGMA_PX.ln() as f32;
        head.bias =
            Some(Param::from_data(TensorData::new(bias, [OUTPUT_CHANNELS]), device).with_id(id()));
        Self { blocks, head }
    }

    /// Maps normalised input `[batch, input_channels, H, W]` to the raw
    /// output `[batch, OUTPUT_CHANNELS, H, W]`, channels as the `*_CHANNEL`
    /// constants (score logit, offset x, offset y, ln σx, ln σy, within-1-px
    /// logit), with burn's own operations: the reference the kernels of
    /// [`forward_inference`](Self::forward_inference) and
    /// [`forward_training`](Self::forward_training) are tested against (so
    /// compiled for the tests only).
    #[cfg(test)]
    pub(crate) fn forward(&self, input: Tensor<4>) -> Tensor<4> {
        let mut x = input;
        for block in &self.blocks {
            x = block.forward(x);
        }
        self.head.forward(x)
    }

    /// The head's parameters as plain vectors, for the kernels.
    fn head_parameters(&self) -> Head {
        let [out_channels, in_channels, _, _] = self.head.weight.dims();
        Head {
            // `[out, in, 1, 1]` row-major is `[out][in]`.
            weights: float_values(self.head.weight.val()),
            bias: self
                .head
                .bias
                .as_ref()
                .map_or_else(|| vec![0.0; out_channels], |b| float_values(b.val())),
            in_channels,
            out_channels,
        }
    }

    /// The hidden layers' parameters as plain vectors, for the kernels.
    pub(crate) fn body_layers(&self) -> Vec<BodyLayer> {
        self.blocks
            .iter()
            .map(|block| {
                let [out_channels, in_channels, _, _] = block.conv.weight.dims();
                let oihw = float_values(block.conv.weight.val());
                BodyLayer {
                    dilation: block.conv.dilation[0],
                    in_channels,
                    out_channels,
                    weights: body::weights_from_oihw(&oihw, in_channels, out_channels),
                    bias: block.conv.bias.as_ref().map(|b| float_values(b.val())),
                    norm: block.norm.as_ref().map(|norm| LayerNorm {
                        gamma: float_values(norm.gamma.val()),
                        beta: float_values(norm.beta.val()),
                        running_mean: float_values(norm.running_mean.value()),
                        running_var: float_values(norm.running_var.value()),
                        epsilon: norm.epsilon,
                        momentum: norm.momentum,
                    }),
                }
            })
            .collect()
    }

    /// Inference on row-major input `[n, input_channels, height, width]`:
    /// the body on the deterministic kernels with batch norm folded into
    /// the convolutions, then the head. Returns `[n, OUTPUT_CHANNELS,
    /// height, width]` on `device`.
    pub(crate) fn forward_inference(
        &self,
        input: &[f32],
        [n, height, width]: [usize; 3],
        device: &Device,
    ) -> Tensor<4> {
        let layers = self.body_layers();
        let channels = layers.last().map_or(0, |l| l.out_channels);
        let features = body::infer(&layers, input, n, height, width);
        let head = self.head_parameters();
        debug_assert_eq!(head.in_channels, channels);
        let output = head_forward(&head, &features, n, height * width);
        Tensor::from_data(
            TensorData::new(output, [n, head.out_channels, height, width]),
            device,
        )
    }

    /// A training forward pass on row-major input `[n, input_channels,
    /// height, width]` (`self` on an autodiff device): the body on the
    /// deterministic kernels (batch norm with the batch's statistics, the
    /// running statistics updated), the head in burn. Returns the output
    /// and the step whose [`NetworkStep::gradients`] completes the backward
    /// pass.
    pub(crate) fn forward_training(
        &self,
        input: &[f32],
        [n, height, width]: [usize; 3],
        device: &Device,
    ) -> (Tensor<4>, NetworkStep) {
        let layers = self.body_layers();
        let channels = layers.last().map_or(0, |l| l.out_channels);
        let (features, tape, running) = body::train_forward(&layers, input, n, height, width);
        for (block, running) in self.blocks.iter().zip(running) {
            if let (Some(norm), Some(running)) = (&block.norm, running) {
                let len = running.mean.len();
                norm.running_mean.update(Tensor::from_data(
                    TensorData::new(running.mean, [len]),
                    device,
                ));
                norm.running_var.update(Tensor::from_data(
                    TensorData::new(running.var, [len]),
                    device,
                ));
            }
        }
        let head = self.head_parameters();
        debug_assert_eq!(head.in_channels, channels);
        let pixels = height * width;
        let output = head_forward(&head, &features, n, pixels);
        let output = Tensor::<4>::from_data(
            TensorData::new(output, [n, head.out_channels, height, width]),
            device,
        )
        .require_grad();
        (
            output.clone(),
            NetworkStep {
                layers,
                tape,
                head,
                features,
                shape: [n, pixels],
                output,
            },
        )
    }
}

/// A parameter's values as a row-major vector.
fn float_values<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor
        .into_data()
        .try_to_vec::<f32>()
        .expect("float parameters")
}

/// The network's part of one training step (see
/// [`Net::forward_training`]): the body and the head ran on the kernels;
/// burn computes the loss from the output and its gradient with respect to
/// the output, and [`NetworkStep::gradients`] takes it back through the head
/// and the body.
pub(crate) struct NetworkStep {
    layers: Vec<BodyLayer>,
    tape: Tape,
    head: Head,
    /// The body's output `[n, channels, pixels]`, the head's input.
    features: Vec<f32>,
    /// `[n, pixels]`.
    shape: [usize; 2],
    /// The network's output as the loss saw it (a leaf that records its
    /// gradient).
    output: Tensor<4>,
}

impl NetworkStep {
    /// The gradients of every parameter of `net` from the gradients of a
    /// loss computed from this step's output, by the kernels' backward
    /// passes of the head and the body (sums in a fixed order, so the same
    /// bits on every CPU and thread count).
    pub(crate) fn gradients(
        self,
        mut grads: burn::tensor::Gradients,
        net: &Net,
    ) -> GradientsParams {
        let output_grad = self
            .output
            .grad_remove(&mut grads)
            .map(|g| g.into_data().try_to_vec::<f32>().expect("float gradients"));
        let mut params = GradientsParams::from_grads(grads, net);
        let Some(output_grad) = output_grad else {
            // The loss does not depend on the network.
            return params;
        };
        let device = super::inference_device();
        let head_grads = head_backward(&self.head, &self.features, &output_grad, self.shape);
        let vector = |values: Vec<f32>| {
            let len = values.len();
            Tensor::<1>::from_data(TensorData::new(values, [len]), &device)
        };
        let (ci_n, co_n) = (self.head.in_channels, self.head.out_channels);
        params.register(
            net.head.weight.id,
            Tensor::<4>::from_data(
                TensorData::new(head_grads.weights, [co_n, ci_n, 1, 1]),
                &device,
            ),
        );
        if let Some(bias) = &net.head.bias {
            params.register(bias.id, vector(head_grads.bias));
        }
        let layer_grads = body::backward(&self.layers, &self.tape, &head_grads.features);
        for ((block, layer), grads) in net.blocks.iter().zip(&self.layers).zip(layer_grads) {
            let (ci_n, co_n) = (layer.in_channels, layer.out_channels);
            let weights = body::oihw_from_weights(&grads.weights, ci_n, co_n);
            params.register(
                block.conv.weight.id,
                Tensor::<4>::from_data(TensorData::new(weights, [co_n, ci_n, 3, 3]), &device),
            );
            if let (Some(bias), Some(grad)) = (&block.conv.bias, grads.bias) {
                params.register(bias.id, vector(grad));
            }
            if let (Some(norm), Some(gamma), Some(beta)) = (&block.norm, grads.gamma, grads.beta) {
                params.register(norm.gamma.id, vector(gamma));
                params.register(norm.beta.id, vector(beta));
            }
        }
        params
    }
}

/// Sets a parameter's id.
trait WithId {
    fn with_id(self, id: ParamId) -> Self;
}

impl<const D: usize> WithId for Param<Tensor<D>> {
    fn with_id(mut self, id: ParamId) -> Self {
        self.id = id;
        self
    }
}

/// A 1-D parameter of `len` entries all equal to `value`.
fn constant_param(value: f32, len: usize, device: &Device) -> Param<Tensor<1>> {
    Param::from_data(TensorData::new(vec![value; len], [len]), device)
}

/// A parameter of `shape` with entries N(0, std²) drawn from `rng`.
fn normal_param<const D: usize>(
    rng: &mut ChaCha8Rng,
    shape: [usize; D],
    std: f64,
    device: &Device,
) -> Param<Tensor<D>> {
    let len: usize = shape.iter().product();
    let normal = Normal::new(0.0, std).expect("a finite positive standard deviation");
    let values: Vec<f32> = (0..len).map(|_| normal.sample(rng) as f32).collect();
    Param::from_data(TensorData::new(values, shape), device)
}
