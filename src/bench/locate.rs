//! Crocker–Grier throughput on paper-like frames.

use std::time::Instant;

use crate::detect::crocker_grier::{CrockerGrierParams, locate_stack};
use crate::progress::hidden;
use crate::types::FrameStack;

/// Locates features in every frame `repeats` times (after a warm-up) and
/// returns the best frames/s.
pub(crate) fn time_crocker_grier(
    frames: &FrameStack,
    params: &CrockerGrierParams,
    repeats: usize,
) -> anyhow::Result<f64> {
    locate_stack(frames, params, &hidden())?;
    let mut best = f64::INFINITY;
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        std::hint::black_box(locate_stack(frames, params, &hidden())?);
        best = best.min(start.elapsed().as_secs_f64());
    }
    Ok(frames.n as f64 / best)
}
