//! The extension module `scanloc._scanloc`: thin calls into the scanloc
//! library. Every function here converts Python values to the library's
//! types, calls one library function with the GIL released, and converts
//! the result back; the DataFrames are assembled by the Python package
//! (`scanloc/__init__.py`) from the arrays and CSV/JSON text returned here.
//!
//! Long work (locating, simulating) runs on a worker thread in chunks of
//! frames while the calling thread, every [`POLL`], takes the GIL to check
//! for a signal (Ctrl-C: the worker stops after its chunk and the call
//! raises `KeyboardInterrupt`) and to advance a `tqdm` bar from the
//! library's progress events.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use indicatif::ProgressBar;
use numpy::{
    IntoPyArray, PyArray1, PyArray3, PyArrayMethods, PyReadonlyArray1, PyUntypedArrayMethods,
};
use pyo3::exceptions::{PyFileNotFoundError, PyKeyboardInterrupt, PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use scanloc::detect::cnn::TrainedCnn;
use scanloc::detect::crocker_grier::{self, CrockerGrierParams, Feature, Pixel};
use scanloc::detect::likelihood::{self, LikelihoodParams};
use scanloc::error::{InputError, Stopped};
use scanloc::sim::SimParams;
use scanloc::sim::recording::{Blinking, RecordingParams};
use scanloc::track::Detection;
use scanloc::track::diffusion::tables::{TableSettings, estimate_table};
use scanloc::track::diffusion::{Exposure, ScanGeometry};
use scanloc::track::linker::{LinkerKind, LinkerRequest, Naming};
use scanloc::types::{FrameStack, LocalisationSigma, Prediction};

/// How often the calling thread checks for signals and draws progress.
const POLL: Duration = Duration::from_millis(25);

/// Pixels per chunk of a long locate: small enough that a chunk takes a
/// fraction of a second (Ctrl-C latency), large enough for every core.
const CHUNK_PIXELS: usize = 1 << 21;

/// A library error as the Python exception the CLI's exit code implies:
/// a missing file `FileNotFoundError`, bad input `ValueError`, anything
/// else `RuntimeError`; the message is the CLI's (`{:#}`, the whole chain).
fn to_py(error: anyhow::Error) -> PyErr {
    let message = format!("{error:#}");
    // A missing file: an io::Error in the chain, or one the library
    // folded into its one-line message ("FILE: cannot read: … (os error 2)").
    let not_found = error.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == std::io::ErrorKind::NotFound)
    }) || message.contains("(os error 2)");
    if not_found {
        PyFileNotFoundError::new_err(message)
    } else if error.chain().any(|cause| cause.is::<InputError>()) {
        PyValueError::new_err(message)
    } else {
        // An internal failure, or a check that found a difference
        // (`CheckFailed`: exit code 1 on the command line).
        PyRuntimeError::new_err(message)
    }
}

fn value_error(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}

/// Runs `work` on a worker thread with the GIL released, `total` steps of
/// progress shown by a `tqdm` bar labelled `desc` when `progress` is true
/// and tqdm is installed. The worker gets the library's progress bar
/// (hidden; its position is read here) and a flag it checks between
/// chunks: set when a signal handler raised (Ctrl-C), whose exception this
/// returns once the worker has stopped.
fn interruptible<T, F>(
    py: Python<'_>,
    total: u64,
    desc: &str,
    progress: bool,
    work: F,
) -> PyResult<T>
where
    T: Send,
    F: FnOnce(&ProgressBar, &AtomicBool) -> anyhow::Result<T> + Send,
{
    let tqdm = if progress {
        new_tqdm(py, total, desc)
    } else {
        None
    };
    let bar = ProgressBar::hidden();
    bar.set_length(total);
    let cancel = AtomicBool::new(false);
    let mut interrupted: Option<PyErr> = None;
    let outcome = py.allow_threads(|| {
        std::thread::scope(|scope| {
            let (done, finished) = mpsc::channel::<()>();
            let (progress, stop) = (&bar, &cancel);
            let worker = scope.spawn(move || {
                let result = work(progress, stop);
                let _ = done.send(());
                result
            });
            let mut shown = 0u64;
            let mut last_draw = Instant::now();
            loop {
                let finished_now = match finished.recv_timeout(POLL) {
                    Ok(()) | Err(mpsc::RecvTimeoutError::Disconnected) => true,
                    Err(mpsc::RecvTimeoutError::Timeout) => false,
                };
                let position = bar.position();
                let draw = tqdm.is_some()
                    && position > shown
                    && (finished_now || last_draw.elapsed() >= Duration::from_millis(100));
                if interrupted.is_none() || draw {
                    Python::with_gil(|py| {
                        if !finished_now
                            && interrupted.is_none()
                            && let Err(error) = py.check_signals()
                        {
                            cancel.store(true, Ordering::SeqCst);
                            interrupted = Some(error);
                        }
                        if draw && let Some(tqdm) = &tqdm {
                            let _ = tqdm.call_method1(py, "update", (position - shown,));
                            shown = position;
                            last_draw = Instant::now();
                        }
                    });
                }
                if finished_now {
                    break;
                }
            }
            worker.join()
        })
    });
    if let Some(tqdm) = &tqdm {
        let _ = tqdm.call_method0(py, "close");
    }
    if let Some(error) = interrupted {
        return Err(error);
    }
    match outcome {
        Ok(Ok(value)) => Ok(value),
        Ok(Err(error)) if error.is::<Stopped>() => Err(PyKeyboardInterrupt::new_err("interrupted")),
        Ok(Err(error)) => Err(to_py(error)),
        Err(_) => Err(PyRuntimeError::new_err(
            "internal error: the scanloc worker panicked (please report it)",
        )),
    }
}

/// A `tqdm.auto.tqdm` bar, or `None` without tqdm.
fn new_tqdm(py: Python<'_>, total: u64, desc: &str) -> Option<Py<PyAny>> {
    let module = py.import("tqdm.auto").ok()?;
    let kwargs = PyDict::new(py);
    kwargs.set_item("total", total).ok()?;
    kwargs.set_item("desc", desc).ok()?;
    kwargs.set_item("leave", false).ok()?;
    let bar = module.getattr("tqdm").ok()?.call((), Some(&kwargs)).ok()?;
    Some(bar.unbind())
}

/// The frames of a 3-D array as a C-order slice: the array's own memory
/// when it is C-contiguous (zero copy), else a C-order copy.
enum Pixels<'a, P> {
    Borrowed(&'a [P]),
    Owned(Vec<P>),
}

impl<P> Pixels<'_, P> {
    fn slice(&self) -> &[P] {
        match self {
            Pixels::Borrowed(slice) => slice,
            Pixels::Owned(values) => values,
        }
    }
}

fn pixels<'a, P: numpy::Element + Copy>(
    array: &'a numpy::PyReadonlyArray3<'_, P>,
) -> Pixels<'a, P> {
    // `as_slice` also takes a Fortran-ordered array (its memory in
    // column-major order): only a C-ordered one is read in place.
    match array.as_slice() {
        Ok(slice) if array.is_c_contiguous() => Pixels::Borrowed(slice),
        _ => Pixels::Owned(array.as_array().iter().copied().collect()),
    }
}

/// Whether `frames` would be read without a copy (C-contiguous, of a
/// dtype the locator takes as it is).
#[pyfunction]
fn _is_zero_copy(frames: &Bound<'_, PyAny>) -> bool {
    macro_rules! try_dtype {
        ($($t:ty),*) => {$(
            if let Ok(array) = frames.downcast::<PyArray3<$t>>() {
                return array.is_c_contiguous();
            }
        )*};
    }
    try_dtype!(u8, u16, u32, f32, f64);
    false
}

/// The first non-finite value of `values` (a float stack), as an error.
fn check_finite<P: Pixel>(values: &[P], offset: usize) -> anyhow::Result<()> {
    if P::INTEGER {
        return Ok(());
    }
    match values.iter().position(|v| !v.value().is_finite()) {
        Some(index) => Err(scanloc::error::input_error(format!(
            "frames: value at flat index {} is {}; frames must hold finite numbers",
            offset + index,
            values[index].value()
        ))),
        None => Ok(()),
    }
}

/// Crocker–Grier over the frames of `array`, in chunks.
fn locate_cg<P: Pixel + numpy::Element>(
    py: Python<'_>,
    array: &Bound<'_, PyArray3<P>>,
    params: &CrockerGrierParams,
    integer_max: u64,
    progress: bool,
) -> PyResult<Vec<(usize, Feature)>> {
    let readonly = array.readonly();
    let [n, height, width] = [array.shape()[0], array.shape()[1], array.shape()[2]];
    let data = pixels(&readonly);
    let data = data.slice();
    let frame_len = height * width;
    let chunk = (CHUNK_PIXELS / frame_len.max(1)).max(1);
    interruptible(py, n as u64, "locating", progress, |bar, cancel| {
        let mut features = Vec::new();
        let mut start = 0;
        while start < n {
            if cancel.load(Ordering::SeqCst) {
                return Err(anyhow::Error::new(Stopped));
            }
            let end = (start + chunk).min(n);
            let values = &data[start * frame_len..end * frame_len];
            check_finite(values, start * frame_len)?;
            let found = crocker_grier::locate_frames_in_range(
                values,
                end - start,
                height,
                width,
                params,
                integer_max,
                bar,
            )?;
            features.extend(found.into_iter().map(|(frame, f)| (frame + start, f)));
            start = end;
        }
        Ok(features)
    })
}

/// `scanloc.locate(method="crocker-grier")`: TrackPy's `locate` on every
/// frame (`trackpy.batch`). Returns the columns y, x, mass, size, ecc,
/// signal, raw_mass, ep, frame as arrays.
#[pyfunction]
#[pyo3(signature = (frames, diameter, minmass, maxsize, separation, noise_size, smoothing_size, threshold, percentile, topn, preprocess, max_iterations, progress))]
#[allow(clippy::too_many_arguments)]
fn _locate_crocker_grier<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    diameter: usize,
    minmass: Option<f64>,
    maxsize: Option<f64>,
    separation: Option<f64>,
    noise_size: f64,
    smoothing_size: Option<usize>,
    threshold: Option<f64>,
    percentile: f64,
    topn: Option<usize>,
    preprocess: bool,
    max_iterations: usize,
    progress: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let params = CrockerGrierParams {
        diameter,
        minmass,
        maxsize,
        separation,
        noise_size,
        smoothing_size,
        threshold,
        percentile,
        topn,
        preprocess,
        max_iterations,
    };
    params
        .validate()
        .map_err(|e| value_error(format!("invalid crocker-grier parameter: {e}")))?;
    // TrackPy rescales to the gamut of the array's integer type (255 for
    // floats): `scalefactor_to_gamut`.
    let features = if let Ok(a) = frames.downcast::<PyArray3<u8>>() {
        locate_cg(py, a, &params, u8::MAX.into(), progress)?
    } else if let Ok(a) = frames.downcast::<PyArray3<u16>>() {
        locate_cg(py, a, &params, u16::MAX.into(), progress)?
    } else if let Ok(a) = frames.downcast::<PyArray3<u32>>() {
        locate_cg(py, a, &params, u32::MAX.into(), progress)?
    } else if let Ok(a) = frames.downcast::<PyArray3<f32>>() {
        locate_cg(py, a, &params, u8::MAX.into(), progress)?
    } else if let Ok(a) = frames.downcast::<PyArray3<f64>>() {
        locate_cg(py, a, &params, u8::MAX.into(), progress)?
    } else {
        return Err(value_error(unsupported_dtype(frames)));
    };
    let column =
        |f: fn(&Feature) -> f64| -> Vec<f64> { features.iter().map(|(_, x)| f(x)).collect() };
    let out = PyDict::new(py);
    out.set_item("y", column(|f| f.y).into_pyarray(py))?;
    out.set_item("x", column(|f| f.x).into_pyarray(py))?;
    out.set_item("mass", column(|f| f.mass).into_pyarray(py))?;
    out.set_item("size", column(|f| f.size).into_pyarray(py))?;
    out.set_item("ecc", column(|f| f.ecc).into_pyarray(py))?;
    out.set_item("signal", column(|f| f.signal).into_pyarray(py))?;
    out.set_item("raw_mass", column(|f| f.raw_mass).into_pyarray(py))?;
    out.set_item("ep", column(|f| f.ep).into_pyarray(py))?;
    let frame: Vec<i64> = features.iter().map(|(frame, _)| *frame as i64).collect();
    out.set_item("frame", frame.into_pyarray(py))?;
    Ok(out)
}

fn unsupported_dtype(frames: &Bound<'_, PyAny>) -> String {
    let dtype = frames
        .getattr("dtype")
        .map(|d| d.to_string())
        .unwrap_or_else(|_| "?".to_string());
    format!(
        "frames: expected an array of shape (n, H, W) of uint8, uint16, uint32, float32 or float64, got dtype {dtype}"
    )
}

/// The frames of `frames` as photon counts (a copy: the CNN and the
/// particle filter take `u32` counts); floats must be whole and ≥ 0.
fn counts(frames: &Bound<'_, PyAny>) -> PyResult<FrameStack> {
    fn whole<P: numpy::Element + Copy>(
        array: &Bound<'_, PyArray3<P>>,
        convert: impl Fn(P) -> Option<u32>,
        shown: impl Fn(P) -> String,
    ) -> PyResult<FrameStack> {
        let readonly = array.readonly();
        let shape = array.shape();
        let view = readonly.as_array();
        let mut data = Vec::with_capacity(view.len());
        for (index, &value) in view.iter().enumerate() {
            match convert(value) {
                Some(count) => data.push(count),
                None => {
                    return Err(value_error(format!(
                        "frames: value at flat index {index} is {}; this method needs photon counts (whole numbers ≥ 0)",
                        shown(value)
                    )));
                }
            }
        }
        FrameStack::from_vec(shape[0], shape[1], shape[2], data).map_err(to_py)
    }
    let from_float = |v: f64| {
        (v.is_finite() && v >= 0.0 && v.fract() == 0.0 && v <= f64::from(u32::MAX))
            .then_some(v as u32)
    };
    if let Ok(a) = frames.downcast::<PyArray3<u8>>() {
        whole(a, |v| Some(u32::from(v)), |v| v.to_string())
    } else if let Ok(a) = frames.downcast::<PyArray3<u16>>() {
        whole(a, |v| Some(u32::from(v)), |v| v.to_string())
    } else if let Ok(a) = frames.downcast::<PyArray3<u32>>() {
        whole(a, Some, |v| v.to_string())
    } else if let Ok(a) = frames.downcast::<PyArray3<f32>>() {
        whole(a, |v| from_float(f64::from(v)), |v| v.to_string())
    } else if let Ok(a) = frames.downcast::<PyArray3<f64>>() {
        whole(a, from_float, |v| v.to_string())
    } else {
        Err(value_error(unsupported_dtype(frames)))
    }
}

/// Predictions as columns frame, x, y, score (+ sigma_x, sigma_y,
/// candidate where any prediction has them).
fn prediction_columns<'py>(
    py: Python<'py>,
    predictions: &[Prediction],
) -> PyResult<Bound<'py, PyDict>> {
    let out = PyDict::new(py);
    let frame: Vec<i64> = predictions.iter().map(|p| p.frame as i64).collect();
    out.set_item("frame", frame.into_pyarray(py))?;
    let x: Vec<f64> = predictions.iter().map(|p| p.x).collect();
    let y: Vec<f64> = predictions.iter().map(|p| p.y).collect();
    out.set_item("x", x.into_pyarray(py))?;
    out.set_item("y", y.into_pyarray(py))?;
    if predictions.iter().any(|p| p.sigma.is_some()) {
        let sx: Vec<f64> = predictions
            .iter()
            .map(|p| p.sigma.map_or(f64::NAN, |s| s.x))
            .collect();
        let sy: Vec<f64> = predictions
            .iter()
            .map(|p| p.sigma.map_or(f64::NAN, |s| s.y))
            .collect();
        out.set_item("sigma_x", sx.into_pyarray(py))?;
        out.set_item("sigma_y", sy.into_pyarray(py))?;
    }
    let score: Vec<f64> = predictions.iter().map(|p| p.score).collect();
    out.set_item("score", score.into_pyarray(py))?;
    if predictions.iter().any(|p| p.candidate.is_some()) {
        let rank: Vec<i64> = predictions
            .iter()
            .map(|p| p.candidate.map_or(0, i64::from))
            .collect();
        out.set_item("candidate", rank.into_pyarray(py))?;
    }
    Ok(out)
}

/// `scanloc.locate(method="cnn")`: the CNN of a model folder or of a
/// registry (`RUN:DETECTOR` or a content key). Returns (columns, the
/// model's description).
#[pyfunction]
#[pyo3(signature = (frames, model, registry, max_candidates, candidate_radius_px, progress))]
fn _locate_cnn<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    model: &str,
    registry: &str,
    max_candidates: Option<usize>,
    candidate_radius_px: Option<f64>,
    progress: bool,
) -> PyResult<(Bound<'py, PyDict>, String)> {
    let stack = counts(frames)?;
    let (mut cnn, origin) = py
        .allow_threads(|| -> anyhow::Result<(TrainedCnn, String)> {
            let folder = Path::new(model);
            if folder.exists() {
                return Ok((TrainedCnn::load(folder)?, format!("folder {model}")));
            }
            let registry = scanloc::registry::Registry::open_existing(Path::new(registry))
                .map_err(|e| {
                    scanloc::error::input_error(format!(
                        "model {model}: not a model folder, and {e:#}"
                    ))
                })?;
            let stored = registry.stored_model(model, scanloc::types::DetectorKind::Cnn)?;
            let cnn = TrainedCnn::from_bytes(&stored.bytes)
                .map_err(|e| scanloc::error::input_error(format!("{model}: {e:#}")))?;
            Ok((cnn, stored.origin.model_key.clone()))
        })
        .map_err(to_py)?;
    if let Some(count) = max_candidates {
        cnn.architecture.max_candidates = count;
    }
    if let Some(radius) = candidate_radius_px {
        cnn.architecture.candidate_radius_px = radius;
    }
    cnn.architecture.validate().map_err(|e| {
        value_error(format!(
            "max_candidates/candidate_radius_px with this model: {e}"
        ))
    })?;
    let frame_len = stack.frame_len();
    let chunk = (CHUNK_PIXELS / frame_len.max(1)).max(1);
    let predictions = interruptible(py, stack.n as u64, "locating", progress, |bar, cancel| {
        let mut all = Vec::new();
        for start in (0..stack.n).step_by(chunk) {
            if cancel.load(Ordering::SeqCst) {
                return Err(anyhow::Error::new(Stopped));
            }
            let end = (start + chunk).min(stack.n);
            let part = FrameStack {
                n: end - start,
                height: stack.height,
                width: stack.width,
                data: stack.data[start * frame_len..end * frame_len].to_vec(),
            };
            for mut p in cnn.locate(&part, bar)? {
                p.frame += start;
                all.push(p);
            }
        }
        Ok(all)
    })?;
    Ok((prediction_columns(py, &predictions)?, origin))
}

/// `scanloc.locate(method="likelihood")`: the particle filter under the
/// microscope (JSON of its parameters, at the frames' size).
#[pyfunction]
#[pyo3(signature = (frames, microscope, stated, particles, score_radius_px, seed, max_candidates, candidate_radius_px, progress))]
#[allow(clippy::too_many_arguments)]
fn _locate_likelihood<'py>(
    py: Python<'py>,
    frames: &Bound<'py, PyAny>,
    microscope: &str,
    stated: Vec<String>,
    particles: usize,
    score_radius_px: f64,
    seed: u64,
    max_candidates: Option<usize>,
    candidate_radius_px: Option<f64>,
    progress: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let defaults = LikelihoodParams::default();
    let settings = LikelihoodParams {
        particles,
        score_radius_px,
        max_candidates: max_candidates.unwrap_or(defaults.max_candidates),
        candidate_radius_px: candidate_radius_px.unwrap_or(defaults.candidate_radius_px),
        ..defaults
    };
    settings
        .validate()
        .map_err(|e| value_error(format!("invalid likelihood parameter: {e}")))?;
    let mut params = sim_params(microscope)?;
    let stack = counts(frames)?;
    for (field, stated_size, actual) in [
        ("height", params.height, stack.height),
        ("width", params.width, stack.width),
    ] {
        if stated.iter().any(|s| s == field) && stated_size != actual {
            return Err(value_error(format!(
                "{field}: the microscope's frames have {stated_size} pixels, those of frames {actual}"
            )));
        }
    }
    params.height = stack.height;
    params.width = stack.width;
    params
        .validate()
        .map_err(|e| value_error(format!("invalid microscope parameter: {e}")))?;
    let predictions = interruptible(py, stack.n as u64, "locating", progress, |bar, cancel| {
        let mut all = Vec::new();
        let indices: Vec<usize> = (0..stack.n).collect();
        // Frame i draws from stream i of the seed whatever the chunk.
        for which in indices.chunks(4) {
            if cancel.load(Ordering::SeqCst) {
                return Err(anyhow::Error::new(Stopped));
            }
            all.extend(likelihood::locate_frames(
                &stack, which, &params, &settings, seed, bar,
            )?);
        }
        Ok(all)
    })?;
    prediction_columns(py, &predictions)
}

/// The simulator's parameters from their JSON (a `Microscope`'s).
fn sim_params(json: &str) -> PyResult<SimParams> {
    serde_json::from_str(json).map_err(|e| value_error(format!("microscope: {e}")))
}

/// `Microscope(...)`: the `microscope:` section of YAML/JSON `text` (from
/// `source`) over the CLI's defaults. Returns (the parameters as JSON, the
/// fields stated).
#[pyfunction]
fn _microscope(py: Python<'_>, source: &str, text: &str) -> PyResult<(String, Vec<String>)> {
    let (params, stated) = py
        .allow_threads(|| {
            scanloc::manifest::microscope_from_text(source, text, &SimParams::default())
        })
        .map_err(to_py)?;
    let json = serde_json::to_string(&params).map_err(|e| to_py(e.into()))?;
    Ok((json, stated))
}

/// `Microscope.from_yaml(path)`: as `scanloc --microscope FILE.yaml`.
#[pyfunction]
fn _microscope_file(py: Python<'_>, path: &str) -> PyResult<(String, Vec<String>)> {
    let (params, stated) = py
        .allow_threads(|| {
            scanloc::manifest::load_microscope(Path::new(path), &SimParams::default())
        })
        .map_err(to_py)?;
    let json = serde_json::to_string(&params).map_err(|e| to_py(e.into()))?;
    Ok((json, stated))
}

/// Checks a microscope's parameters as `scanloc simulate` does.
#[pyfunction]
fn _validate_microscope(microscope: &str) -> PyResult<()> {
    sim_params(microscope)?
        .validate()
        .map_err(|e| value_error(format!("invalid simulation parameter: {e}")))
}

/// Frames as the CLI writes them: uint16 when every count fits, else uint32.
fn frames_array<'py>(py: Python<'py>, stack: FrameStack) -> PyResult<Bound<'py, PyAny>> {
    let shape = [stack.n, stack.height, stack.width];
    if stack.max_count() <= u32::from(u16::MAX) {
        let data: Vec<u16> = stack.data.iter().map(|&c| c as u16).collect();
        Ok(data.into_pyarray(py).reshape(shape)?.into_any())
    } else {
        Ok(stack.data.into_pyarray(py).reshape(shape)?.into_any())
    }
}

/// `scanloc.simulate`: frames and the truth table as CSV text (the CLI's).
#[pyfunction]
fn _simulate<'py>(
    py: Python<'py>,
    microscope: &str,
    frames: usize,
    seed: u64,
    progress: bool,
) -> PyResult<(Bound<'py, PyAny>, String)> {
    let params = sim_params(microscope)?;
    params
        .validate()
        .map_err(|e| value_error(format!("invalid simulation parameter: {e}")))?;
    scanloc::limits::check_dataset_size("frames", frames, params.height, params.width)
        .map_err(|e| to_py(e.into()))?;
    scanloc::limits::check_memory(
        "frames",
        scanloc::sim::dataset_bytes(&params, frames),
        scanloc::limits::available_memory_bytes(),
    )
    .map_err(|e| to_py(e.into()))?;
    let chunk = (CHUNK_PIXELS / (params.height * params.width).max(1)).max(1);
    let dataset = interruptible(py, frames as u64, "simulating", progress, |bar, cancel| {
        let mut all = scanloc::types::Dataset {
            frames: FrameStack::zeros(0, params.height, params.width),
            truth: Vec::new(),
        };
        for start in (0..frames).step_by(chunk) {
            if cancel.load(Ordering::SeqCst) {
                return Err(anyhow::Error::new(Stopped));
            }
            // Frame i depends only on (parameters, seed, i).
            let part =
                scanloc::sim::simulate(&params, seed, start..(start + chunk).min(frames), bar)?;
            all.frames.append(part.frames)?;
            all.truth.extend(part.truth);
        }
        Ok(all)
    })?;
    let mut truth = Vec::new();
    scanloc::io::csv_tables::write_truth_to(&mut truth, &dataset.truth).map_err(to_py)?;
    let stack = if dataset.frames.n == 0 {
        FrameStack::zeros(0, params.height, params.width)
    } else {
        dataset.frames
    };
    Ok((
        frames_array(py, stack)?,
        String::from_utf8_lossy(&truth).into_owned(),
    ))
}

/// `scanloc.simulate_recording`: a continuous recording (the
/// `simulate-recording` command's parameters) and its truth as CSV text.
#[pyfunction]
#[pyo3(signature = (microscope, frames, seed, qd_density, qd_count, margin_um, half_depth_um, blink_on_ms, blink_off_ms, dead_time_ms, progress))]
#[allow(clippy::too_many_arguments)]
fn _simulate_recording<'py>(
    py: Python<'py>,
    microscope: &str,
    frames: usize,
    seed: u64,
    qd_density: f64,
    qd_count: Option<u64>,
    margin_um: f64,
    half_depth_um: f64,
    blink_on_ms: Option<f64>,
    blink_off_ms: Option<f64>,
    dead_time_ms: f64,
    progress: bool,
) -> PyResult<(Bound<'py, PyAny>, String, usize)> {
    let given = sim_params(microscope)?;
    let blinking = match (blink_on_ms, blink_off_ms) {
        (Some(on_ms), Some(off_ms)) => Some(Blinking { on_ms, off_ms }),
        (None, None) => None,
        _ => {
            return Err(value_error(
                "blink_on_ms and blink_off_ms: give both or neither",
            ));
        }
    };
    let params = RecordingParams {
        microscope: SimParams {
            height: given.height,
            width: given.width,
            pixel_size_um: given.pixel_size_um,
            dwell_us: given.dwell_us,
            retrace_ms: given.retrace_ms,
            sigma_xy_um: given.sigma_xy_um,
            sigma_z_um: given.sigma_z_um,
            substeps: given.substeps,
            brightness: given.brightness,
            background: given.background,
            diffusion_um2_s: given.diffusion_um2_s,
            ..SimParams::default()
        },
        frames,
        density_per_um3: qd_density,
        qd_count,
        lateral_margin_um: margin_um,
        half_depth_um,
        blinking,
        dead_time_ms,
    };
    params
        .validate()
        .map_err(|e| value_error(format!("invalid recording parameter: {e}")))?;
    scanloc::limits::check_memory(
        "frames",
        params.dataset_bytes(),
        scanloc::limits::available_memory_bytes(),
    )
    .map_err(|e| to_py(e.into()))?;
    // One walk that cannot be split: it asks for a stop before each frame.
    let recording = interruptible(py, frames as u64, "simulating", progress, |bar, cancel| {
        let stop = || cancel.load(Ordering::SeqCst);
        scanloc::sim::recording::simulate_recording_stoppable(&params, seed, true, bar, &stop)
    })?;
    let mut truth = Vec::new();
    scanloc::io::tracks::write_recording_truth_to(&mut truth, &recording.truth).map_err(to_py)?;
    Ok((
        frames_array(py, recording.frames)?,
        String::from_utf8_lossy(&truth).into_owned(),
        recording.qds,
    ))
}

/// Detections from columns, checked (finite coordinates, whole frames ≥ 0).
fn detections(
    frame: &PyReadonlyArray1<'_, i64>,
    x: &PyReadonlyArray1<'_, f64>,
    y: &PyReadonlyArray1<'_, f64>,
    sigma: Option<(&PyReadonlyArray1<'_, f64>, &PyReadonlyArray1<'_, f64>)>,
) -> PyResult<Vec<Detection>> {
    let (frame, x, y) = (frame.as_array(), x.as_array(), y.as_array());
    if x.len() != frame.len() || y.len() != frame.len() {
        return Err(value_error(
            "features: columns frame, x, y differ in length",
        ));
    }
    let sigma = sigma.map(|(sx, sy)| (sx.as_array(), sy.as_array()));
    let mut out = Vec::with_capacity(frame.len());
    for row in 0..frame.len() {
        let f = usize::try_from(frame[row])
            .ok()
            .filter(|&f| f <= scanloc::limits::MAX_FRAMES)
            .ok_or_else(|| {
                value_error(format!(
                    "features: row {row}: column frame: expected a frame index ≥ 0, got {}",
                    frame[row]
                ))
            })?;
        for (name, value) in [("x", x[row]), ("y", y[row])] {
            if !value.is_finite() {
                return Err(value_error(format!(
                    "features: row {row}: column {name}: expected a finite number, got {value}"
                )));
            }
        }
        let mut detection = Detection::new(f, x[row], y[row]);
        if let Some((sx, sy)) = &sigma {
            let (sx, sy) = (sx[row], sy[row]);
            if sx.is_finite() && sy.is_finite() && sx > 0.0 && sy > 0.0 {
                detection.sigma = Some(LocalisationSigma { x: sx, y: sy });
            }
        }
        out.push(detection);
    }
    Ok(out)
}

/// What `_link` returns: the particles, and the lap linker's gates.
type Linked<'py> = (Bound<'py, PyArray1<i64>>, Option<Bound<'py, PyDict>>);

/// `scanloc.link`: the particle of each row, indexed like the input.
#[pyfunction]
#[pyo3(signature = (frame, x, y, sigma_x, sigma_y, linker, search_range, memory, max_gap, diffusion, frame_time_ms, pixel_size_um, gate, progress))]
#[allow(clippy::too_many_arguments)]
fn _link<'py>(
    py: Python<'py>,
    frame: PyReadonlyArray1<'py, i64>,
    x: PyReadonlyArray1<'py, f64>,
    y: PyReadonlyArray1<'py, f64>,
    sigma_x: Option<PyReadonlyArray1<'py, f64>>,
    sigma_y: Option<PyReadonlyArray1<'py, f64>>,
    linker: &str,
    search_range: Option<f64>,
    memory: Option<usize>,
    max_gap: Option<usize>,
    diffusion: Option<f64>,
    frame_time_ms: Option<f64>,
    pixel_size_um: Option<f64>,
    gate: Option<f64>,
    progress: bool,
) -> PyResult<Linked<'py>> {
    let sigma = match (&sigma_x, &sigma_y) {
        (Some(sx), Some(sy)) => Some((sx, sy)),
        _ => None,
    };
    let detections = detections(&frame, &x, &y, sigma)?;
    let configured = LinkerRequest {
        linker: match linker {
            "trackpy" => LinkerKind::Trackpy,
            "lap" => LinkerKind::Lap,
            other => {
                return Err(value_error(format!(
                    "linker: expected \"trackpy\" or \"lap\", got {other:?}"
                )));
            }
        },
        search_range,
        memory,
        max_gap,
        diffusion,
        frame_time_ms,
        pixel_size_um,
        gate,
    }
    .configure(Naming::Keywords)
    .map_err(to_py)?;
    let linking = interruptible(py, 1, "linking", progress, |bar, _| {
        let linking = configured
            .link(&detections)
            .map_err(|e| e.context("features: linking"))?;
        bar.inc(1);
        Ok(linking)
    })?;
    // Converted in place (same size): no second array of labels.
    let particle: Vec<i64> = linking.particle.into_iter().map(|p| p as i64).collect();
    let gates = match &linking.gates {
        Some(gates) => {
            let out = PyDict::new(py);
            let gx: Vec<f64> = gates.iter().map(|g| g.map_or(f64::NAN, |g| g[0])).collect();
            let gy: Vec<f64> = gates.iter().map(|g| g.map_or(f64::NAN, |g| g[1])).collect();
            out.set_item("gate_x", gx.into_pyarray(py))?;
            out.set_item("gate_y", gy.into_pyarray(py))?;
            Some(out)
        }
        None => None,
    };
    Ok((particle.into_pyarray(py), gates))
}

/// `scanloc.diffusion`: D of each track of a tracks table (CSV text, the
/// CLI's format) and of the ensemble. Returns the CLI's rows as CSV text
/// (per track, ensemble) and its notes.
#[pyfunction]
#[pyo3(signature = (tracks_csv, microscope, dead_time_ms, exposure, min_points, detection_profile, ensemble_gate, ensemble_margin_px, given_sigma))]
#[allow(clippy::too_many_arguments)]
fn _diffusion(
    py: Python<'_>,
    tracks_csv: &str,
    microscope: &str,
    dead_time_ms: f64,
    exposure: &str,
    min_points: usize,
    detection_profile: bool,
    ensemble_gate: f64,
    ensemble_margin_px: f64,
    given_sigma: bool,
) -> PyResult<(String, String, Vec<String>)> {
    let params = sim_params(microscope)?;
    params
        .validate()
        .map_err(|e| value_error(format!("invalid microscope parameter: {e}")))?;
    if !(dead_time_ms.is_finite()
        && (0.0..=scanloc::sim::recording::MAX_DEAD_TIME_MS).contains(&dead_time_ms))
    {
        return Err(value_error(format!(
            "dead_time_ms: must be a finite number ≥ 0, got {dead_time_ms}"
        )));
    }
    let geometry = ScanGeometry::of(&params, dead_time_ms);
    let exposure = match exposure {
        "auto" => geometry.auto_exposure(),
        "whole-frame" => Exposure::WholeFrame,
        "rows" => Exposure::Rows,
        "frame-index" => Exposure::FrameIndex,
        "uniform-frame" => Exposure::UniformFrame,
        other => {
            return Err(value_error(format!(
                "exposure: expected auto, whole-frame, rows, frame-index or uniform-frame, got {other:?}"
            )));
        }
    };
    let settings = TableSettings {
        exposure,
        min_points,
        detection_profile,
        ensemble_gate,
        ensemble_margin_px,
        given_sigma,
    };
    let table = py
        .allow_threads(|| {
            let tracks = scanloc::io::tracks::read_tracks_from(tracks_csv.as_bytes(), "tracks")?;
            estimate_table(tracks, &geometry, &settings, "tracks")
        })
        .map_err(to_py)?;
    let header = "particle,points,method,d_um2_s,standard_error,low_95,high_95,localisation_variance_um2,interval_valid\n";
    let row = |label: &str,
               points: usize,
               method: scanloc::track::diffusion::Method,
               e: &scanloc::track::diffusion::Estimate| {
        format!(
            "{label},{points},{},{},{},{},{},{},{}\n",
            method.name(),
            e.d,
            e.standard_error,
            e.low,
            e.high,
            e.localisation_variance,
            e.interval_valid
        )
    };
    let mut per_track = header.to_string();
    for (index, track) in table.tracks.iter().enumerate() {
        for (method, e) in &table.estimates {
            if let Some(estimate) = &e.per_track[index] {
                per_track.push_str(&row(
                    &track.particle.to_string(),
                    table.points[index],
                    *method,
                    estimate,
                ));
            }
        }
    }
    let mut ensemble = header.to_string();
    for (method, e) in &table.estimates {
        if let Some(estimate) = &e.ensemble {
            ensemble.push_str(&row("ensemble", table.ensemble_points, *method, estimate));
        }
    }
    Ok((per_track, ensemble, table.notes))
}

/// `scanloc.score`: the AUC table of predictions (CSV text with frame, x,
/// y, score) against truth (CSV text with frame, x, y) over `frames`
/// frames, as JSON (the library's `Score`).
#[pyfunction]
fn _score(
    py: Python<'_>,
    truth_csv: &str,
    predictions_csv: &str,
    frames: usize,
    eps: Vec<f64>,
) -> PyResult<String> {
    py.allow_threads(|| -> anyhow::Result<String> {
        scanloc::metrics::check_radii("eps", &eps)?;
        let truth = scanloc::io::csv_tables::read_truth_from(truth_csv.as_bytes(), "truth")?;
        let predictions = scanloc::io::csv_tables::read_predictions_from(
            predictions_csv.as_bytes(),
            "predictions",
        )?;
        let score = scanloc::metrics::score(&predictions, &truth, frames, &eps, false)?;
        Ok(serde_json::to_string(&score)?)
    })
    .map_err(to_py)
}

/// The version of the library the module was built from.
#[pyfunction]
fn _version() -> &'static str {
    env!("CARGO_PKG_VERSION")
}

#[pymodule]
fn _scanloc(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(_is_zero_copy, m)?)?;
    m.add_function(wrap_pyfunction!(_locate_crocker_grier, m)?)?;
    m.add_function(wrap_pyfunction!(_locate_cnn, m)?)?;
    m.add_function(wrap_pyfunction!(_locate_likelihood, m)?)?;
    m.add_function(wrap_pyfunction!(_microscope, m)?)?;
    m.add_function(wrap_pyfunction!(_microscope_file, m)?)?;
    m.add_function(wrap_pyfunction!(_validate_microscope, m)?)?;
    m.add_function(wrap_pyfunction!(_simulate, m)?)?;
    m.add_function(wrap_pyfunction!(_simulate_recording, m)?)?;
    m.add_function(wrap_pyfunction!(_link, m)?)?;
    m.add_function(wrap_pyfunction!(_diffusion, m)?)?;
    m.add_function(wrap_pyfunction!(_score, m)?)?;
    m.add_function(wrap_pyfunction!(_version, m)?)?;
    registry::register(m)?;
    track::register(m)?;
    Ok(())
}

mod registry;
mod track;
