//! Batched inference and peak finding.

use indicatif::ProgressBar;

use super::data::input_tensor;
use super::model::{Net, OFFSET_X_CHANNEL, OFFSET_Y_CHANNEL, OUTPUT_CHANNELS, SCORE_CHANNEL};
use super::{CnnArchitecture, TrainedCnn, inference_device};
use crate::types::{FrameStack, Prediction};

/// Frames per forward pass in [`TrainedCnn::locate`].
pub const INFERENCE_BATCH: usize = 256;

impl TrainedCnn {
    /// Localises QDs in every frame of `frames` (any frame size), in
    /// batches of [`INFERENCE_BATCH`]; `progress` advances by one per frame.
    ///
    /// Predictions are ordered by frame, then raster order of their peak
    /// pixel. Fails (naming the frame) if the network outputs a non-finite
    /// value.
    pub fn locate(
        &self,
        frames: &FrameStack,
        progress: &ProgressBar,
    ) -> anyhow::Result<Vec<Prediction>> {
        locate_with(
            &self.net,
            &self.architecture,
            self.settings.score_floor,
            frames,
            INFERENCE_BATCH,
            progress,
        )
    }

    /// The architecture's receptive field etc. are public; the raw score
    /// and offset maps of `frames` are exposed for diagnostics: row-major
    /// `[n, 3, H, W]` with channel 0 the score logit, 1 the x offset, 2 the
    /// y offset.
    pub fn raw_output(&self, frames: &FrameStack) -> anyhow::Result<Vec<f32>> {
        let device = inference_device();
        let mut out = Vec::with_capacity(frames.n * OUTPUT_CHANNELS * frames.frame_len());
        for start in (0..frames.n).step_by(INFERENCE_BATCH) {
            let end = (start + INFERENCE_BATCH).min(frames.n);
            let input = input_tensor(frames, start..end, self.architecture.edge_channel, &device);
            let values = self
                .net
                .forward(input)
                .into_data()
                .try_to_vec::<f32>()
                .map_err(|e| anyhow::anyhow!("reading the network output: {e:?}"))?;
            out.extend(values);
        }
        Ok(out)
    }
}

/// Runs `net` over `frames` in batches of `batch` and extracts the peaks.
pub(crate) fn locate_with(
    net: &Net,
    arch: &CnnArchitecture,
    score_floor: f64,
    frames: &FrameStack,
    batch: usize,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Prediction>> {
    let device = inference_device();
    let (height, width) = (frames.height, frames.width);
    let len = frames.frame_len();
    let mut predictions = Vec::new();
    if len == 0 {
        progress.inc(frames.n as u64);
        return Ok(predictions);
    }
    // The floor compared on logits (sigmoid is monotone), so no pixel's
    // sigmoid needs computing unless it is a candidate.
    let logit_floor = if score_floor > 0.0 {
        (score_floor / (1.0 - score_floor)).ln()
    } else {
        f64::NEG_INFINITY
    };
    for start in (0..frames.n).step_by(batch.max(1)) {
        let end = (start + batch).min(frames.n);
        let input = input_tensor(frames, start..end, arch.edge_channel, &device);
        let output = net
            .forward(input)
            .into_data()
            .try_to_vec::<f32>()
            .map_err(|e| anyhow::anyhow!("reading the network output: {e:?}"))?;
        for (offset, maps) in output.chunks_exact(OUTPUT_CHANNELS * len).enumerate() {
            let frame = start + offset;
            if let Some(bad) = maps.iter().position(|v| !v.is_finite()) {
                anyhow::bail!(
                    "CNN output of frame {frame} is not finite (channel {}, pixel {}): the model is damaged",
                    bad / len,
                    bad % len
                );
            }
            let logits = &maps[SCORE_CHANNEL * len..(SCORE_CHANNEL + 1) * len];
            let dx = &maps[OFFSET_X_CHANNEL * len..(OFFSET_X_CHANNEL + 1) * len];
            let dy = &maps[OFFSET_Y_CHANNEL * len..(OFFSET_Y_CHANNEL + 1) * len];
            for (row, col) in local_maxima(logits, height, width, arch.peak_radius_px) {
                let p = row * width + col;
                let logit = logits[p] as f64;
                if logit < logit_floor {
                    continue;
                }
                let (x, y) = if arch.refine_radius_px == 0 {
                    (col as f64 + dx[p] as f64, row as f64 + dy[p] as f64)
                } else {
                    refined_position(
                        logits,
                        dx,
                        dy,
                        width,
                        height,
                        (row, col),
                        arch.refine_radius_px,
                    )
                };
                predictions.push(Prediction {
                    frame,
                    x,
                    y,
                    score: sigmoid(logit),
                });
            }
            progress.inc(1);
        }
    }
    Ok(predictions)
}

fn sigmoid(logit: f64) -> f64 {
    1.0 / (1.0 + (-logit).exp())
}

/// The score-weighted mean of pixel + offset over the window of `radius`
/// around `peak` (clipped at the edges).
fn refined_position(
    logits: &[f32],
    dx: &[f32],
    dy: &[f32],
    width: usize,
    height: usize,
    (row, col): (usize, usize),
    radius: usize,
) -> (f64, f64) {
    let (mut sum_w, mut sum_x, mut sum_y) = (0.0, 0.0, 0.0);
    for r in row.saturating_sub(radius)..(row + radius + 1).min(height) {
        for c in col.saturating_sub(radius)..(col + radius + 1).min(width) {
            let p = r * width + c;
            let w = sigmoid(logits[p] as f64);
            sum_w += w;
            sum_x += w * (c as f64 + dx[p] as f64);
            sum_y += w * (r as f64 + dy[p] as f64);
        }
    }
    // The peak itself has weight > 0, so sum_w > 0.
    (sum_x / sum_w, sum_y / sum_w)
}

/// Pixels `(row, col)` of a row-major `height × width` map that are the
/// maximum of the `(2·radius + 1)²` window around them (clipped at the
/// edges). A plateau yields one pixel: a pixel must be strictly greater than
/// window neighbours earlier in raster order and at least equal to later
/// ones. Returned in raster order.
pub fn local_maxima(
    map: &[f32],
    height: usize,
    width: usize,
    radius: usize,
) -> Vec<(usize, usize)> {
    let mut peaks = Vec::new();
    for row in 0..height {
        let rows = row.saturating_sub(radius)..(row + radius + 1).min(height);
        'pixel: for col in 0..width {
            let value = map[row * width + col];
            let cols = col.saturating_sub(radius)..(col + radius + 1).min(width);
            for r in rows.clone() {
                for c in cols.clone() {
                    let other = map[r * width + c];
                    let earlier = (r, c) < (row, col);
                    if other > value || (earlier && other == value) {
                        continue 'pixel;
                    }
                }
            }
            peaks.push((row, col));
        }
    }
    peaks
}

#[cfg(test)]
mod tests {
    use super::local_maxima;

    #[test]
    fn plateaus_give_one_peak_and_separate_peaks_all_count() {
        #[rustfmt::skip]
        let map = [
            0.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            0.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            0.0, 0.0, 0.0, 0.0, 0.0, 3.0,
        ];
        assert_eq!(local_maxima(&map, 3, 6, 1), vec![(0, 1), (2, 5)]);
        // A larger window lets the stronger peak suppress the weaker one.
        assert_eq!(local_maxima(&map, 3, 6, 4), vec![(0, 1)]);
    }
}
