//! Simulator throughput on the paper's datasets (29,838 training + 6,850
//! test frames = 36,688 frames of 24×25 pixels).

use std::time::Instant;

use crate::progress::hidden;
use crate::sim::{SimParams, simulate};

/// The paper's total number of frames.
pub(crate) const PAPER_FRAMES: usize = 36_688;

/// One timing of the simulator.
#[derive(Debug, Clone, serde::Serialize)]
pub(crate) struct SimulateTiming {
    pub frames: usize,
    pub threads: usize,
    /// Best of the repeats, in seconds.
    pub seconds: f64,
    pub frames_per_second: f64,
}

/// Simulates `frames` frames with `params` `repeats` times (after one
/// warm-up) and reports the best time.
pub(crate) fn time_simulator(
    params: &SimParams,
    frames: usize,
    repeats: usize,
) -> anyhow::Result<SimulateTiming> {
    simulate(params, 0, 0..frames.min(1000), &hidden())?;
    let mut best = f64::INFINITY;
    for repeat in 0..repeats.max(1) {
        let start = Instant::now();
        let dataset = simulate(params, repeat as u64, 0..frames, &hidden())?;
        best = best.min(start.elapsed().as_secs_f64());
        std::hint::black_box(dataset);
    }
    Ok(SimulateTiming {
        frames,
        threads: rayon::current_num_threads(),
        seconds: best,
        frames_per_second: frames as f64 / best,
    })
}
