//! `scanloc.track`: `scanloc track` from Python, the same library call
//! ([`track_named_recording`]) on a numpy stack or a recording file, with
//! the command's outputs rendered by the library
//! ([`outputs`](scanloc::run::track_recording::outputs)) and returned as
//! text for the package to read into DataFrames; nothing is written.
//!
//! The run's phases (locating, the calibration recordings, linking, the
//! bias correction) report to a [`Monitor`] whose bars this module sums
//! into the package's one tqdm bar. The run goes on a thread of its own
//! that owns its inputs: Ctrl-C returns from the call at once (as
//! `KeyboardInterrupt`) and sets the monitor's flag, which the run checks
//! before each phase and each stack it locates; a simulation under way
//! (a calibration or bias recording) finishes first.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc};

use indicatif::ProgressBar;
use numpy::{PyArray3, PyArrayMethods, PyUntypedArrayMethods};
use pyo3::prelude::*;
use scanloc::run::track_recording::{
    TrackMethod, TrackMonitor, TrackOptions, check_stated, planned_steps, read_recording,
    track_named_recording,
};
use scanloc::sim::SimParams;
use scanloc::types::{FrameStack, Recording};

use super::{POLL, interruptible, sim_params, to_py, unsupported_dtype, value_error};

/// What an array recording is called in errors (a file is named by its
/// path, as on the command line).
const ARRAY_NAME: &str = "recording";

/// The run's monitor: a hidden bar per phase, stopped by a flag.
struct Monitor {
    bars: Mutex<Vec<ProgressBar>>,
    stop: Arc<AtomicBool>,
}

impl TrackMonitor for Monitor {
    fn bar(&self, len: u64, _label: &str) -> ProgressBar {
        let bar = ProgressBar::hidden();
        bar.set_length(len);
        if let Ok(mut bars) = self.bars.lock() {
            bars.push(bar.clone());
        }
        bar
    }

    fn stop_requested(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
}

impl Monitor {
    /// The steps done over every phase so far.
    fn steps(&self) -> u64 {
        self.bars.lock().map_or(0, |bars| {
            bars.iter()
                .map(|b| b.position().min(b.length().unwrap_or(0)))
                .sum()
        })
    }
}

/// `frames` (a 3-D array) as photon counts: integers as they are, floats
/// as the command line reads a float file (whole numbers ≥ 0, else its
/// error); always a copy, into the `u32` counts the pipeline takes.
fn counts_of(frames: &Bound<'_, PyAny>) -> PyResult<FrameStack> {
    fn integers<P: numpy::Element + Copy + Into<u32>>(
        array: &Bound<'_, PyArray3<P>>,
    ) -> PyResult<FrameStack> {
        let shape = array.shape();
        let data: Vec<u32> = array
            .readonly()
            .as_array()
            .iter()
            .map(|&v| v.into())
            .collect();
        FrameStack::from_vec(shape[0], shape[1], shape[2], data).map_err(to_py)
    }
    fn reals<P: numpy::Element + Copy + Into<f64>>(
        array: &Bound<'_, PyArray3<P>>,
    ) -> PyResult<FrameStack> {
        let shape = array.shape();
        let data: Vec<f64> = array
            .readonly()
            .as_array()
            .iter()
            .map(|&v| v.into())
            .collect();
        let real = scanloc::types::RealFrameStack::from_vec(shape[0], shape[1], shape[2], data)
            .map_err(|e| to_py(scanloc::error::input_error(format!("{ARRAY_NAME}: {e:#}"))))?;
        Recording::Real(real)
            .into_counts()
            .map_err(|e| to_py(scanloc::error::input_error(format!("{ARRAY_NAME}: {e:#}"))))
    }
    let stack = if let Ok(a) = frames.downcast::<PyArray3<u8>>() {
        integers(a)
    } else if let Ok(a) = frames.downcast::<PyArray3<u16>>() {
        integers(a)
    } else if let Ok(a) = frames.downcast::<PyArray3<u32>>() {
        integers(a)
    } else if let Ok(a) = frames.downcast::<PyArray3<f32>>() {
        reals(a)
    } else if let Ok(a) = frames.downcast::<PyArray3<f64>>() {
        reals(a)
    } else {
        Err(value_error(unsupported_dtype(frames)))
    }?;
    scanloc::limits::check_stack_shape(ARRAY_NAME, stack.n, stack.height, stack.width)
        .map_err(to_py)?;
    Ok(stack)
}

/// The options `scanloc track`'s flags give, each `None` its default.
#[allow(clippy::too_many_arguments)]
fn options(
    method: &str,
    diameter: Option<usize>,
    min_score: Option<f64>,
    search_range: Option<f64>,
    max_gap: Option<usize>,
    ensemble_margin_px: Option<f64>,
    max_diffusion: Option<f64>,
    min_points: Option<usize>,
    bias_correction: bool,
    bias_recordings: Option<usize>,
    dead_time_ms: Option<f64>,
    seed: Option<u64>,
) -> PyResult<TrackOptions> {
    let method = match method {
        "crocker-grier" => TrackMethod::CrockerGrier,
        other => {
            return Err(value_error(format!(
                "method: expected \"crocker-grier\", got {other:?}"
            )));
        }
    };
    let default = TrackOptions::default();
    Ok(TrackOptions {
        method,
        diameter_px: diameter,
        min_score,
        search_range_px: search_range,
        max_gap,
        ensemble_margin_px,
        max_diffusion_um2_s: max_diffusion.unwrap_or(default.max_diffusion_um2_s),
        min_points: min_points.unwrap_or(default.min_points),
        bias_correction,
        bias_recordings: bias_recordings.unwrap_or(default.bias_recordings),
        dead_time_ms: dead_time_ms.unwrap_or(default.dead_time_ms),
        seed: seed.unwrap_or(default.seed),
        ..default
    })
}

/// What `_track` returns: tracks.csv, diffusion.csv and settings.json as
/// `scanloc track` writes them, and the summary its `--json` prints.
type Outputs = (String, String, String, String);

/// `scanloc.track`: `recording` a path (`.npy` or TIFF, read as the
/// command reads it) or a 3-D array; `microscope` a `Microscope`'s JSON
/// and its stated fields.
#[pyfunction]
#[pyo3(signature = (recording, microscope, stated, method, diameter, min_score, search_range, max_gap, ensemble_margin_px, max_diffusion, min_points, bias_correction, bias_recordings, dead_time_ms, seed, progress))]
#[allow(clippy::too_many_arguments)]
fn _track(
    py: Python<'_>,
    recording: &Bound<'_, PyAny>,
    microscope: &str,
    stated: Vec<String>,
    method: &str,
    diameter: Option<usize>,
    min_score: Option<f64>,
    search_range: Option<f64>,
    max_gap: Option<usize>,
    ensemble_margin_px: Option<f64>,
    max_diffusion: Option<f64>,
    min_points: Option<usize>,
    bias_correction: bool,
    bias_recordings: Option<usize>,
    dead_time_ms: Option<f64>,
    seed: Option<u64>,
    progress: bool,
) -> PyResult<Outputs> {
    // As the command: the microscope, the flags, then the recording.
    let params: SimParams = sim_params(microscope)?;
    check_stated(&stated.into_iter().collect::<BTreeSet<String>>()).map_err(to_py)?;
    let options = options(
        method,
        diameter,
        min_score,
        search_range,
        max_gap,
        ensemble_margin_px,
        max_diffusion,
        min_points,
        bias_correction,
        bias_recordings,
        dead_time_ms,
        seed,
    )?;
    options.check(&params).map_err(to_py)?;
    let (name, frames) = match recording.extract::<std::path::PathBuf>() {
        Ok(path) => {
            let frames = py.allow_threads(|| read_recording(&path)).map_err(to_py)?;
            (path.display().to_string(), frames)
        }
        Err(_) => (ARRAY_NAME.to_string(), counts_of(recording)?),
    };
    let total = planned_steps(frames.n, &options);
    let stop = Arc::new(AtomicBool::new(false));
    let monitor = Arc::new(Monitor {
        bars: Mutex::new(Vec::new()),
        stop: Arc::clone(&stop),
    });
    let (done, finished) = mpsc::channel::<anyhow::Result<Outputs>>();
    // The run owns its inputs: on Ctrl-C the call returns at once, and the
    // run stops at its next stop point (a simulation under way ends first).
    let run_monitor = Arc::clone(&monitor);
    std::thread::spawn(move || {
        let outputs = track_named_recording(&name, &frames, &params, &options, &*run_monitor)
            .and_then(|result| {
                let text = |bytes: Vec<u8>| String::from_utf8_lossy(&bytes).into_owned();
                Ok((
                    text(result.tracks_csv()?),
                    text(result.diffusion_csv()?),
                    result.settings_json()?,
                    serde_json::to_string(&result.summary_json())?,
                ))
            });
        let _ = done.send(outputs);
    });
    interruptible(py, total, "tracking", progress, move |bar, cancel| {
        loop {
            match finished.recv_timeout(POLL) {
                Ok(outputs) => {
                    bar.set_position(monitor.steps().min(total));
                    return outputs;
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {
                    if cancel.load(Ordering::SeqCst) {
                        stop.store(true, Ordering::SeqCst);
                        return Err(anyhow::anyhow!("interrupted"));
                    }
                    bar.set_position(monitor.steps().min(total));
                }
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    return Err(anyhow::anyhow!(
                        "internal error: the scanloc tracking thread panicked (please report it)"
                    ));
                }
            }
        }
    })
}

pub(crate) fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_track, m)?)?;
    Ok(())
}
