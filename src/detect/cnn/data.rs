//! Frames → network input, and ground truth → training targets.
//!
//! Input: channel 0 is the frame normalised as `(counts − m) / √max(m, 1)`
//! with `m` the frame's mean count, i.e. photon counts relative to the
//! frame's level in units of its Poisson noise. This needs no knowledge of
//! the microscope's background and works for frames of any size. When the
//! architecture asks for it, channel 1 is all ones: the convolutions pad
//! with zeros, so this channel tells the network where the frame ends.
//!
//! Targets, per emitter with trajectory centroid `(x, y)` (TrackPy pixel
//! coordinates) and nearest pixel `(round(y), round(x))`:
//! - score map: `exp(−((c−x)² + (r−y)²) / 2σ²)` (maximum over emitters), set
//!   to exactly 1 at the nearest pixel, which is the one positive pixel of
//!   the focal loss;
//! - offsets: `(x − c, y − r)` at every pixel within `offset_radius_px`
//!   (Chebyshev) of the nearest pixel, so that the offset read at a score
//!   peak one pixel off the nearest pixel still points at the centroid.
//!
//! An emitter whose nearest pixel lies outside the frame has no target. A
//! frame may hold any number of emitters: none (every pixel a full-weight
//! negative, no offset supervised), one, or several (one positive pixel
//! each; where offset boxes overlap, the nearer emitter's offset).

use crate::types::{FrameStack, TruthRow};

/// The normalised input of a batch of `height × width` frames, row-major
/// `[n, channels, H, W]`.
pub(crate) fn normalised_input<'a>(
    frames: impl ExactSizeIterator<Item = &'a [u32]>,
    frame_len: usize,
    edge_channel: bool,
) -> Vec<f32> {
    let channels = if edge_channel { 2 } else { 1 };
    let mut input = Vec::with_capacity(frames.len() * channels * frame_len);
    for counts in frames {
        debug_assert_eq!(counts.len(), frame_len);
        let mean = if frame_len == 0 {
            0.0
        } else {
            counts.iter().map(|&c| c as f64).sum::<f64>() / frame_len as f64
        };
        let inv_noise = 1.0 / mean.max(1.0).sqrt();
        input.extend(
            counts
                .iter()
                .map(|&c| ((c as f64 - mean) * inv_noise) as f32),
        );
        if edge_channel {
            input.extend(std::iter::repeat_n(1.0f32, frame_len));
        }
    }
    input
}

/// Training targets of one batch, each row-major over `[n, channels, H, W]`.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Targets {
    /// Weight of each negative pixel in the focal loss, `(1 − heat)⁴` off
    /// the positive pixels and 0 on them; 1 channel.
    pub negative_weight: Vec<f32>,
    /// 1 at each emitter's nearest pixel, else 0; 1 channel.
    pub positive: Vec<f32>,
    /// Offset target (x then y channel), 2 channels.
    pub offset: Vec<f32>,
    /// 1 where the offset is supervised, else 0; 1 channel.
    pub offset_mask: Vec<f32>,
}

/// The target settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct TargetShape {
    pub sigma_px: f64,
    pub offset_radius_px: usize,
}

/// Builds the targets of a batch of `height × width` frames from the
/// emitters `(x, y)` of each frame.
pub(crate) fn targets(
    height: usize,
    width: usize,
    emitters: &[&[(f64, f64)]],
    shape: TargetShape,
) -> Targets {
    let len = height * width;
    let n = emitters.len();
    let mut out = Targets {
        negative_weight: vec![0.0; n * len],
        positive: vec![0.0; n * len],
        offset: vec![0.0; 2 * n * len],
        offset_mask: vec![0.0; n * len],
    };
    // Which emitter owns each pixel's offset: the nearest one (by the
    // Gaussian value), so overlapping boxes of close emitters stay coherent.
    let mut owner_weight = vec![0.0f64; len];
    let inv_two_sigma2 = 1.0 / (2.0 * shape.sigma_px * shape.sigma_px);
    let radius = shape.offset_radius_px as isize;
    let mut heat = vec![0.0f32; len];
    for (b, frame_emitters) in emitters.iter().enumerate() {
        owner_weight.fill(-1.0);
        heat.fill(0.0);
        let positive = &mut out.positive[b * len..(b + 1) * len];
        let mask = &mut out.offset_mask[b * len..(b + 1) * len];
        let (offset_x, offset_y) = out.offset[2 * b * len..2 * (b + 1) * len].split_at_mut(len);
        for &(x, y) in frame_emitters.iter() {
            let (cx, cy) = (x.round(), y.round());
            if !(cx >= 0.0 && cy >= 0.0 && cx < width as f64 && cy < height as f64) {
                continue;
            }
            let (cx, cy) = (cx as isize, cy as isize);
            for r in 0..height {
                for c in 0..width {
                    let (dx, dy) = (x - c as f64, y - r as f64);
                    let g = (-(dx * dx + dy * dy) * inv_two_sigma2).exp();
                    let p = r * width + c;
                    heat[p] = heat[p].max(g as f32);
                    let near =
                        (c as isize - cx).abs() <= radius && (r as isize - cy).abs() <= radius;
                    if near && g > owner_weight[p] {
                        owner_weight[p] = g;
                        offset_x[p] = dx as f32;
                        offset_y[p] = dy as f32;
                        mask[p] = 1.0;
                    }
                }
            }
            let p = cy as usize * width + cx as usize;
            heat[p] = 1.0;
            positive[p] = 1.0;
        }
        let negative = &mut out.negative_weight[b * len..(b + 1) * len];
        for ((weight, &h), &pos) in negative.iter_mut().zip(&heat).zip(positive.iter()) {
            *weight = if pos > 0.0 { 0.0 } else { (1.0 - h).powi(4) };
        }
    }
    out
}

/// Groups truth rows by frame: entry `i` lists `(x, y)` of frame `i`'s
/// emitters. Rows naming a frame ≥ `n_frames` are an error.
pub(crate) fn truth_by_frame(
    truth: &[TruthRow],
    n_frames: usize,
) -> anyhow::Result<Vec<Vec<(f64, f64)>>> {
    let mut grouped = vec![Vec::new(); n_frames];
    for row in truth {
        let Some(slot) = grouped.get_mut(row.frame) else {
            crate::bail_input!(
                "training data: truth row names frame {} but the stack has {n_frames} frames",
                row.frame
            );
        };
        if !(row.x.is_finite() && row.y.is_finite()) {
            crate::bail_input!(
                "training data: truth of frame {} is not finite (x {}, y {})",
                row.frame,
                row.x,
                row.y
            );
        }
        slot.push((row.x, row.y));
    }
    Ok(grouped)
}

/// Frames and their emitters, the unit batches are drawn from.
pub(super) struct Source<'a> {
    pub(super) frames: &'a FrameStack,
    /// Per frame, the positions the score map and the offsets learn: the
    /// true centroids, or the teacher's posterior means.
    pub(super) emitters: Vec<Vec<(f64, f64)>>,
    /// Per frame, the true centroids when `emitters` are the teacher's
    /// (the within-1-px head learns whether a localisation lands within
    /// 1 px of the truth, not of the teacher); `None`: `emitters` are the
    /// truth.
    pub(super) true_centroids: Option<Vec<Vec<(f64, f64)>>>,
    /// Per frame, the teacher's posterior of the centroid as the
    /// categorical head's softmax learns it: the probability that the
    /// centroid is nearest each pixel (row-major index), the pixels with
    /// none left out; empty for a frame the teacher did not label (its
    /// one true centroid's pixel is the target). `None`: no teacher, or
    /// the peaks head (whose teacher moves `emitters`).
    pub(super) posterior: Option<Vec<PixelPosterior>>,
}

/// A frame's posterior over its pixels: `(row-major pixel, probability)`,
/// the probabilities summing to 1.
pub(super) type PixelPosterior = Vec<(u32, f32)>;

impl Source<'_> {
    /// The true centroids of frame `i`, which the within-1-px head learns
    /// against.
    pub(super) fn truth(&self, i: usize) -> &[(f64, f64)] {
        self.true_centroids.as_ref().unwrap_or(&self.emitters)[i].as_slice()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_mark_the_nearest_pixel_and_point_offsets_at_the_centroid() {
        let shape = TargetShape {
            sigma_px: 1.0,
            offset_radius_px: 1,
        };
        // One emitter at x = 2.3 (column), y = 1.6 (row) in a 4×5 frame,
        // and one outside the frame (ignored).
        let emitters: [&[(f64, f64)]; 1] = [&[(2.3, 1.6), (9.0, 9.0)]];
        let t = targets(4, 5, &emitters, shape);
        let nearest = 2 * 5 + 2;
        assert_eq!(t.positive.iter().filter(|&&p| p > 0.0).count(), 1);
        assert_eq!(t.positive[nearest], 1.0);
        assert_eq!(t.negative_weight[nearest], 0.0);
        assert_eq!(t.offset_mask.iter().filter(|&&m| m > 0.0).count(), 9);
        let len = 20;
        // Pixel (row 1, col 3): offsets (2.3 − 3, 1.6 − 1).
        let p = 5 + 3;
        assert!((t.offset[p] - -0.7).abs() < 1e-6);
        assert!((t.offset[len + p] - 0.6).abs() < 1e-6);
        // Far pixels weigh almost fully as negatives.
        assert!(t.negative_weight[0] > 0.9);
    }

    #[test]
    fn two_qds_get_a_positive_each_and_share_offsets_by_nearness() {
        let shape = TargetShape {
            sigma_px: 1.0,
            offset_radius_px: 1,
        };
        // A 3×5 frame with A at (x 0.2, y 1.1) → pixel (row 1, col 0) and
        // B at (x 2.4, y 1.0) → pixel (row 1, col 2). Their offset boxes
        // (cols 0–1 and 1–3, rows 0–2) overlap in column 1, which is A's:
        // 0.8 px from A's centroid along x against 1.4 px from B's.
        let emitters: [&[(f64, f64)]; 1] = [&[(0.2, 1.1), (2.4, 1.0)]];
        let t = targets(3, 5, &emitters, shape);
        let len = 15;
        let pixel = |row: usize, col: usize| row * 5 + col;
        let positives: Vec<usize> = (0..len).filter(|&p| t.positive[p] > 0.0).collect();
        assert_eq!(positives, vec![pixel(1, 0), pixel(1, 2)]);
        assert_eq!(t.negative_weight[pixel(1, 0)], 0.0);
        assert_eq!(t.negative_weight[pixel(1, 2)], 0.0);
        // Supervised offsets: the union of both boxes, columns 0–3.
        let masked: Vec<usize> = (0..len).filter(|&p| t.offset_mask[p] > 0.0).collect();
        let expected: Vec<usize> = (0..3)
            .flat_map(|row| (0..4).map(move |col| pixel(row, col)))
            .collect();
        assert_eq!(masked, expected);
        let offset = |row, col| (t.offset[pixel(row, col)], t.offset[len + pixel(row, col)]);
        let close =
            |(a, b): (f32, f32), (x, y): (f32, f32)| (a - x).abs() < 1e-6 && (b - y).abs() < 1e-6;
        // Column 1 belongs to A: (0.2 − 1, 1.1 − row).
        assert!(close(offset(1, 1), (-0.8, 0.1)));
        assert!(close(offset(0, 1), (-0.8, 1.1)));
        // Columns 2 and 3 are B's: (2.4 − col, 1.0 − row).
        assert!(close(offset(1, 2), (0.4, 0.0)));
        assert!(close(offset(2, 3), (-0.6, -1.0)));
        // Column 0 is A's own pixel.
        assert!(close(offset(1, 0), (0.2, 0.1)));
        // Negative weight at (1, 1): the larger Gaussian is A's,
        // exp(−(0.8² + 0.1²)/2); B's is exp(−1.4²/2).
        let heat = (-(0.64f64 + 0.01) / 2.0).exp();
        assert!(heat > (-1.96f64 / 2.0).exp());
        let weight = (1.0 - heat as f32).powi(4);
        assert!((t.negative_weight[pixel(1, 1)] - weight).abs() < 1e-6);
        // Column 4 is off both boxes.
        assert_eq!(t.offset_mask[pixel(1, 4)], 0.0);
    }

    #[test]
    fn an_empty_frame_is_all_negative_and_leaves_its_neighbours_alone() {
        let shape = TargetShape {
            sigma_px: 1.0,
            offset_radius_px: 1,
        };
        let one: &[(f64, f64)] = &[(1.0, 1.0)];
        let none: &[(f64, f64)] = &[];
        // The empty frame between two copies of the same one-QD frame.
        let t = targets(3, 3, &[one, none, one], shape);
        let len = 9;
        let frame = |values: &[f32], b: usize, channels: usize| {
            values[channels * b * len..channels * (b + 1) * len].to_vec()
        };
        assert!(frame(&t.positive, 1, 1).iter().all(|&p| p == 0.0));
        assert!(frame(&t.offset_mask, 1, 1).iter().all(|&m| m == 0.0));
        assert!(frame(&t.offset, 1, 2).iter().all(|&o| o == 0.0));
        // Every pixel of an empty frame is a full-weight negative.
        assert!(frame(&t.negative_weight, 1, 1).iter().all(|&w| w == 1.0));
        // The frames around it are each other's copies, with their QD.
        for (values, channels) in [
            (&t.positive, 1),
            (&t.negative_weight, 1),
            (&t.offset, 2),
            (&t.offset_mask, 1),
        ] {
            assert_eq!(frame(values, 0, channels), frame(values, 2, channels));
        }
        assert_eq!(t.positive[4], 1.0);
        assert_eq!(t.offset_mask.iter().filter(|&&m| m > 0.0).count(), 18);
    }

    #[test]
    fn input_is_centred_and_scaled_by_poisson_noise() {
        let frames = FrameStack::from_vec(1, 1, 4, vec![4, 4, 4, 16]).unwrap();
        let input = normalised_input((0..1).map(|i| frames.frame(i)), 4, true);
        // Mean 7, noise √7.
        let s = 7f64.sqrt();
        let expected = [-3.0 / s, -3.0 / s, -3.0 / s, 9.0 / s, 1.0, 1.0, 1.0, 1.0];
        for (a, b) in input.iter().zip(expected) {
            assert!((*a as f64 - b).abs() < 1e-6);
        }
    }
}
