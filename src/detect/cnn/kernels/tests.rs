//! The kernels against burn's reference operations (on its flex backend,
//! with autodiff for the gradients) on seeded random shapes, dilations and
//! paddings.
//!
//! Tolerance: |kernel − burn| ≤ 1e-4 · (1 + max |burn|) per tensor: both
//! sum the same products in f32 in different orders (burn through im2col
//! and a blocked GEMM), which moves results by a few ulps of the largest
//! partial sums.

use burn::prelude::*;
use burn::tensor::activation::relu;
use burn::tensor::module::{batch_norm_train, conv2d};
use burn::tensor::ops::ConvOptions;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::body::{oihw_from_weights, weights_from_oihw};
use super::*;
use crate::detect::cnn::model::OUTPUT_CHANNELS;

const TOLERANCE: f32 = 1e-4;

fn random(rng: &mut ChaCha8Rng, len: usize) -> Vec<f32> {
    (0..len).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn assert_close(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let scale = 1.0 + want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(
            (g - w).abs() <= TOLERANCE * scale,
            "{what}[{i}]: kernel {g}, burn {w} (scale {scale})"
        );
    }
}

fn values<const D: usize>(tensor: Tensor<D>) -> Vec<f32> {
    tensor.into_data().try_to_vec::<f32>().expect("floats")
}

fn tensor<const D: usize>(data: &[f32], shape: [usize; D], device: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(data.to_vec(), shape), device)
}

/// A random case: `(n, height, width, in, out, dilation, pad)`, the pad at
/// least the dilation.
fn random_case(rng: &mut ChaCha8Rng) -> (usize, usize, usize, usize, usize, usize, usize) {
    let n = rng.random_range(1..=3);
    let height = rng.random_range(1..=11);
    let width = rng.random_range(1..=13);
    let channels = [1, 2, 3, 5, 8, 16, 17, 24, 32, 48];
    let in_channels = channels[rng.random_range(0..channels.len())];
    let out_channels = channels[rng.random_range(0..channels.len())];
    let dilation = rng.random_range(1..=4);
    let pad = dilation + rng.random_range(0..=2);
    (n, height, width, in_channels, out_channels, dilation, pad)
}

#[test]
fn convolution_and_its_gradients_match_burn() {
    let mut rng = ChaCha8Rng::seed_from_u64(16);
    let device = Device::flex().autodiff();
    for case in 0..40 {
        let (n, height, width, ci_n, co_n, dilation, pad) = random_case(&mut rng);
        let geometry = Geometry {
            n,
            height,
            width,
            pad,
        };
        let x = random(&mut rng, n * ci_n * height * width);
        let oihw = random(&mut rng, co_n * ci_n * 9);
        let bias = random(&mut rng, co_n);
        let output_grad = random(&mut rng, n * co_n * height * width);
        let with_bias = case % 2 == 0;
        let relu_fused = case % 3 == 0;
        let what = format!(
            "case {case} (n {n}, {height}×{width}, {ci_n}→{co_n}, dilation {dilation}, pad {pad})"
        );

        // burn: forward, then the gradients of Σ output · output_grad.
        let x_ref = tensor(&x, [n, ci_n, height, width], &device).require_grad();
        let w_ref = tensor(&oihw, [co_n, ci_n, 3, 3], &device).require_grad();
        let options = ConvOptions::new([1, 1], [dilation, dilation], [dilation, dilation], 1);
        let b_ref = with_bias.then(|| tensor(&bias, [co_n], &device));
        let mut y_ref = conv2d(x_ref.clone(), w_ref.clone(), b_ref, options);
        if relu_fused {
            y_ref = relu(y_ref);
        }
        let loss = (y_ref.clone() * tensor(&output_grad, [n, co_n, height, width], &device)).sum();
        let grads = loss.backward();

        let weights = weights_from_oihw(&oihw, ci_n, co_n);
        let conv = Conv3x3 {
            weights: &weights,
            bias: with_bias.then_some(bias.as_slice()),
            in_channels: ci_n,
            out_channels: co_n,
            dilation,
            relu: relu_fused,
        };
        let padded_x = padded_from_nchw(&x, ci_n, &geometry);
        let mut y = geometry.zeros(co_n);
        conv3x3_forward(&padded_x, &mut y, &geometry, &conv);
        assert_close(
            &format!("{what} forward"),
            &nchw_from_padded(&y, co_n, &geometry),
            &values(y_ref),
        );
        // The border stays zero.
        let interior: f32 = nchw_from_padded(&y, co_n, &geometry)
            .iter()
            .map(|v| v.abs())
            .sum();
        let all: f32 = y.iter().map(|v| v.abs()).sum();
        assert!(
            (interior - all).abs() <= 1e-3 * (1.0 + all),
            "{what}: border written"
        );

        if relu_fused {
            continue;
        }
        let padded_grad = padded_from_nchw(&output_grad, co_n, &geometry);
        let weight_grad = conv3x3_weight_grad(&padded_x, &padded_grad, &geometry, &conv);
        assert_close(
            &format!("{what} weight gradient"),
            &oihw_from_weights(&weight_grad, ci_n, co_n),
            &values(w_ref.grad(&grads).expect("weight gradient")),
        );
        let transposed = conv.transposed_weights();
        let back = Conv3x3 {
            weights: &transposed,
            bias: None,
            in_channels: co_n,
            out_channels: ci_n,
            dilation,
            relu: false,
        };
        let mut x_grad = geometry.zeros(ci_n);
        conv3x3_forward(&padded_grad, &mut x_grad, &geometry, &back);
        assert_close(
            &format!("{what} input gradient"),
            &nchw_from_padded(&x_grad, ci_n, &geometry),
            &values(x_ref.grad(&grads).expect("input gradient")),
        );
    }
}

#[test]
fn batch_norm_relu_and_its_gradients_match_burn() {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let device = Device::flex().autodiff();
    for case in 0..20 {
        let (n, height, width, _, channels, _, pad) = random_case(&mut rng);
        let geometry = Geometry {
            n,
            height,
            width,
            pad,
        };
        let what = format!("case {case} (n {n}, {height}×{width}, {channels} channels)");
        let z = random(&mut rng, n * channels * height * width)
            .iter()
            .map(|v| 3.0 * v + 0.5)
            .collect::<Vec<_>>();
        let gamma = random(&mut rng, channels);
        let beta = random(&mut rng, channels);
        let output_grad = random(&mut rng, n * channels * height * width);
        let epsilon = 1e-5;

        let z_ref = tensor(&z, [n, channels, height, width], &device).require_grad();
        let gamma_ref = tensor(&gamma, [channels], &device).require_grad();
        let beta_ref = tensor(&beta, [channels], &device).require_grad();
        let result = batch_norm_train(z_ref.clone(), gamma_ref.clone(), beta_ref.clone(), epsilon);
        let a_ref = relu(result.output);
        let loss =
            (a_ref.clone() * tensor(&output_grad, [n, channels, height, width], &device)).sum();
        let grads = loss.backward();

        let padded_z = padded_from_nchw(&z, channels, &geometry);
        let stats = channel_statistics(&padded_z, channels, &geometry);
        assert_close(&format!("{what} mean"), &stats.mean, &values(result.mean));
        assert_close(
            &format!("{what} variance"),
            &stats.variance,
            &values(result.variance),
        );
        let scale: Vec<f32> = (0..channels)
            .map(|c| gamma[c] / (stats.variance[c] as f64 + epsilon).sqrt() as f32)
            .collect();
        let shift: Vec<f32> = (0..channels)
            .map(|c| beta[c] - stats.mean[c] * scale[c])
            .collect();
        let mut a = geometry.zeros(channels);
        bn_relu_forward(&padded_z, &mut a, channels, &geometry, &scale, &shift);
        assert_close(
            &format!("{what} forward"),
            &nchw_from_padded(&a, channels, &geometry),
            &values(a_ref),
        );
        let padded_grad = padded_from_nchw(&output_grad, channels, &geometry);
        let gradients = bn_relu_backward(
            &padded_grad,
            &padded_z,
            ReluGate {
                scale: &scale,
                shift: &shift,
            },
            channels,
            &geometry,
            Some((&stats, &gamma, epsilon)),
            geometry.zeros(channels),
        );
        assert_close(
            &format!("{what} input gradient"),
            &nchw_from_padded(&gradients.z_grad, channels, &geometry),
            &values(z_ref.grad(&grads).expect("input gradient")),
        );
        assert_close(
            &format!("{what} gamma gradient"),
            &gradients.gamma_grad,
            &values(gamma_ref.grad(&grads).expect("gamma gradient")),
        );
        assert_close(
            &format!("{what} beta gradient"),
            &gradients.beta_grad,
            &values(beta_ref.grad(&grads).expect("beta gradient")),
        );
    }
}

#[test]
fn head_and_its_gradients_match_burn() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let device = Device::flex().autodiff();
    for case in 0..30 {
        let (n, height, width, ci_n, co_n, _, _) = random_case(&mut rng);
        let pixels = height * width;
        let what = format!("case {case} (n {n}, {height}×{width}, {ci_n}→{co_n})");
        let x = random(&mut rng, n * ci_n * pixels);
        let weights = random(&mut rng, co_n * ci_n);
        let bias = random(&mut rng, co_n);
        let output_grad = random(&mut rng, n * co_n * pixels);

        let x_ref = tensor(&x, [n, ci_n, height, width], &device).require_grad();
        let w_ref = tensor(&weights, [co_n, ci_n, 1, 1], &device).require_grad();
        let b_ref = tensor(&bias, [co_n], &device).require_grad();
        let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
        let y_ref = conv2d(x_ref.clone(), w_ref.clone(), Some(b_ref.clone()), options);
        let loss = (y_ref.clone() * tensor(&output_grad, [n, co_n, height, width], &device)).sum();
        let grads = loss.backward();

        let head = Head {
            weights: weights.clone(),
            bias: bias.clone(),
            in_channels: ci_n,
            out_channels: co_n,
        };
        let y = head_forward(&head, &x, n, pixels);
        assert_close(&format!("{what} forward"), &y, &values(y_ref));
        let got = head_backward(&head, &x, &output_grad, [n, pixels]);
        assert_close(
            &format!("{what} weight gradient"),
            &got.weights,
            &values(w_ref.grad(&grads).expect("weight gradient")),
        );
        assert_close(
            &format!("{what} bias gradient"),
            &got.bias,
            &values(b_ref.grad(&grads).expect("bias gradient")),
        );
        assert_close(
            &format!("{what} input gradient"),
            &got.features,
            &values(x_ref.grad(&grads).expect("input gradient")),
        );
    }
}

/// The default architecture with `dilations`, on a batch of random frames.
fn net_and_input(
    dilations: Vec<usize>,
    batch_norm: bool,
    device: &Device,
) -> (crate::detect::cnn::model::Net, Vec<f32>, [usize; 3]) {
    let arch = crate::detect::cnn::CnnArchitecture {
        channels: 16,
        dilations,
        batch_norm,
        ..Default::default()
    };
    let net = crate::detect::cnn::model::Net::new(&arch, 3, device);
    let mut rng = ChaCha8Rng::seed_from_u64(18);
    let (n, height, width) = (3, 9, 11);
    let mut input = random(&mut rng, n * 2 * height * width);
    // The edge channel is all ones.
    for map in 0..n {
        let start = (map * 2 + 1) * height * width;
        input[start..start + height * width].fill(1.0);
    }
    (net, input, [n, height, width])
}

#[test]
fn inference_with_folded_batch_norm_matches_burns_forward() {
    for batch_norm in [true, false] {
        let device = Device::flex().autodiff();
        let (net, input, [n, height, width]) = net_and_input(vec![1, 2, 4, 1], batch_norm, &device);
        // A training step first, so the running statistics are not 0 and 1.
        let _ = net.forward(tensor(&input, [n, 2, height, width], &device));
        let net = net.valid();
        let inference = Device::flex();
        let want = values(net.forward(tensor(&input, [n, 2, height, width], &inference)));
        let got = values(net.forward_inference(&input, [n, height, width], &inference));
        assert_close(&format!("batch norm {batch_norm}"), &got, &want);
    }
}

#[test]
fn a_training_step_on_the_kernels_matches_burns() {
    use burn::optim::{GradientsParams, SgdConfig};
    for batch_norm in [true, false] {
        let device = Device::flex().autodiff();
        let (net, input, [n, height, width]) = net_and_input(vec![1, 3, 2], batch_norm, &device);
        let target = tensor(
            &random(
                &mut ChaCha8Rng::seed_from_u64(19),
                n * OUTPUT_CHANNELS * height * width,
            ),
            [n, OUTPUT_CHANNELS, height, width],
            &device,
        );
        let loss_of = |output: Tensor<4>| (output * target.clone()).sum();
        let reference_net = net.clone();
        // burn all the way.
        let output = reference_net.forward(tensor(&input, [n, 2, height, width], &device));
        let want_output = values(output.clone());
        let grads = GradientsParams::from_grads(loss_of(output).backward(), &reference_net);
        let reference_net = SgdConfig::new().init().step(1.0, reference_net, grads);
        // The kernels for the body.
        let (output, network_step) = net.forward_training(&input, [n, height, width], &device);
        assert_close(
            &format!("batch norm {batch_norm}: output"),
            &values(output.clone()),
            &want_output,
        );
        let grads = network_step.gradients(loss_of(output).backward(), &net);
        let net = SgdConfig::new().init().step(1.0, net, grads);
        for (index, (got, want)) in net
            .body_layers()
            .iter()
            .zip(reference_net.body_layers())
            .enumerate()
        {
            let what = format!("batch norm {batch_norm}, layer {index}");
            assert_close(&format!("{what} weights"), &got.weights, &want.weights);
            assert_eq!(got.bias.is_some(), want.bias.is_some());
            if let (Some(got), Some(want)) = (&got.bias, &want.bias) {
                assert_close(&format!("{what} bias"), got, want);
            }
            if let (Some(got), Some(want)) = (&got.norm, &want.norm) {
                assert_close(&format!("{what} gamma"), &got.gamma, &want.gamma);
                assert_close(&format!("{what} beta"), &got.beta, &want.beta);
                assert_close(
                    &format!("{what} mean"),
                    &got.running_mean,
                    &want.running_mean,
                );
                assert_close(&format!("{what} var"), &got.running_var, &want.running_var);
            }
        }
        // The head's update.
        let inference = Device::flex();
        assert_close(
            &format!("batch norm {batch_norm}: updated output"),
            &values(
                net.valid()
                    .forward(tensor(&input, [n, 2, height, width], &inference)),
            ),
            &values(reference_net.valid().forward(tensor(
                &input,
                [n, 2, height, width],
                &inference,
            ))),
        );
    }
}

/// A one-epoch training of the default architecture on 16 simulated
/// frames on `threads` threads: the model's bytes and its raw output on
/// four other frames.
fn tiny_training(threads: usize) -> (Vec<u8>, Vec<f32>) {
    use crate::detect::cnn::{CnnArchitecture, TrainingSettings, train};
    let arch = CnnArchitecture::default();
    let settings = TrainingSettings {
        epochs: 1,
        batch_size: 8,
        validation_fraction: 0.0,
        fresh_frames_per_epoch: 16,
        ..TrainingSettings::default()
    };
    let params = crate::sim::SimParams::default();
    let score = |_: &[crate::types::Prediction], _: &crate::types::Dataset| Ok(vec![]);
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(|| {
            let model = train(
                &arch,
                &settings,
                &crate::types::Dataset::default(),
                Some(&params),
                7,
                &score,
                &indicatif::ProgressBar::hidden(),
            )
            .expect("training runs");
            let frames = crate::sim::simulate(&params, 8, 0..4, &indicatif::ProgressBar::hidden())
                .expect("simulation")
                .frames;
            (
                model.to_bytes().expect("serialises"),
                model.raw_output(&frames).expect("inference"),
            )
        })
}

fn bits(values: &[f32]) -> Vec<u32> {
    values.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn training_gives_the_same_bits_on_one_and_two_threads() {
    let (one_weights, one_output) = tiny_training(1);
    let (two_weights, two_output) = tiny_training(2);
    assert!(
        one_weights == two_weights,
        "weights differ between 1 and 2 threads"
    );
    assert_eq!(bits(&one_output), bits(&two_output));
}

/// The SHA-256 of the tiny training's model bytes and of its output's
/// bits (little-endian), as recorded on an AVX2-only CPU (AMD EPYC, Zen
/// 3). CI runs on AVX-512 CPUs, so this test is what holds the promise
/// that a seed trains the same model on every x86-64 CPU. Change the
/// values only with a deliberate change to training or to the model's
/// format (and then bump the CNN's code version).
const TINY_TRAINING_SHA256: [&str; 2] = [
    "2a15da79fc14f0ba314230db7c4ff5817d0744b0e54e49d261a05dd073115d90",
    "a95ee18c5c973163091e2ce34360fd0b9d11d963f23215442e29ca2ee96673c1",
];

#[test]
fn training_gives_the_recorded_bits_on_every_cpu() {
    use sha2::{Digest, Sha256};
    let (weights, output) = tiny_training(2);
    let output_bytes: Vec<u8> = output.iter().flat_map(|x| x.to_le_bytes()).collect();
    let got = [
        hex::encode(Sha256::digest(&weights)),
        hex::encode(Sha256::digest(&output_bytes)),
    ];
    assert_eq!(got, TINY_TRAINING_SHA256, "[model, output] digests");
}

#[test]
fn the_vector_paths_give_the_portable_paths_bits() {
    use super::conv::{Isa, conv3x3_forward_on, conv3x3_weight_grad_on};
    let mut rng = ChaCha8Rng::seed_from_u64(20);
    for case in 0..40 {
        let (n, height, width, ci_n, co_n, dilation, pad) = random_case(&mut rng);
        let geometry = Geometry {
            n,
            height,
            width,
            pad,
        };
        let x = padded_from_nchw(
            &random(&mut rng, n * ci_n * height * width),
            ci_n,
            &geometry,
        );
        let g = padded_from_nchw(
            &random(&mut rng, n * co_n * height * width),
            co_n,
            &geometry,
        );
        let weights = random(&mut rng, 9 * ci_n * co_n);
        let bias = random(&mut rng, co_n);
        let conv = Conv3x3 {
            weights: &weights,
            bias: (case % 2 == 0).then_some(bias.as_slice()),
            in_channels: ci_n,
            out_channels: co_n,
            dilation,
            relu: case % 3 == 0,
        };
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let mut portable = geometry.zeros(co_n);
        conv3x3_forward_on(&x, &mut portable, &geometry, &conv, Isa::Portable);
        let portable_grad = conv3x3_weight_grad_on(&x, &g, &geometry, &conv, Isa::Portable);
        // The fastest path, and the AVX2 kernels even on an AVX-512 CPU.
        for isa in [Isa::Detect, Isa::Avx2] {
            let mut fast = geometry.zeros(co_n);
            conv3x3_forward_on(&x, &mut fast, &geometry, &conv, isa);
            assert_eq!(
                bits(&fast),
                bits(&portable),
                "case {case}: forward, {isa:?}"
            );
            assert_eq!(
                bits(&conv3x3_weight_grad_on(&x, &g, &geometry, &conv, isa)),
                bits(&portable_grad),
                "case {case}: weight gradient, {isa:?}"
            );
        }
    }
}
