//! Evaluation and throughput measurements of the CNN, for the `scanloc
//! bench` sub-benchmarks (the test-set table is [`crate::run::test_sets`]'s,
//! shared with `scanloc train --test-frames`).
//!
//! Seeds: every data set and training run draws from
//! [`derive_seed`]`(seed, kind, name)` of the seed it is given, as the
//! artefacts of a manifest do.

use std::time::Instant;

use indicatif::ProgressBar;
use serde::Serialize;

use crate::detect::cnn::{self, CnnArchitecture, TrainingSettings};
use crate::metrics;
use crate::sim::{self, SimParams};
use crate::types::Dataset;
use crate::types::derive_seed;

pub(crate) use crate::run::test_sets::{auc_table, format_auc_table};

/// Throughput of training and inference.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Throughput {
    pub architecture: CnnArchitecture,
    pub batch_size: usize,
    pub threads: usize,
    /// Training samples (frames) per second over `train_samples` samples,
    /// including target building and the optimiser step (no validation).
    pub train_samples_per_second: f64,
    pub train_samples: usize,
    /// Inference frames per second in batches of 256, peak finding included.
    pub locate_frames_per_second: f64,
    pub locate_frames: usize,
    /// CPU seconds (user + system, all threads of the process) the
    /// training and the inference took: on a loaded machine, samples per
    /// CPU second of a one-thread run estimate the idle rate.
    pub train_cpu_seconds: f64,
    pub locate_cpu_seconds: f64,
}

/// CPU seconds (user + system) this process has used so far.
pub(crate) fn process_cpu_seconds() -> f64 {
    let mut usage = std::mem::MaybeUninit::<libc::rusage>::zeroed();
    // SAFETY: getrusage fills the struct it is given.
    let usage = unsafe {
        libc::getrusage(libc::RUSAGE_SELF, usage.as_mut_ptr());
        usage.assume_init()
    };
    let seconds = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
    seconds(usage.ru_utime) + seconds(usage.ru_stime)
}

/// Measures training and inference throughput of `arch` on frames of
/// microscope `params` (`scanloc bench train`: the paper's with brightness
/// 7, margin 4, D uniform [0.75, 1.75], unless told otherwise): trains one epoch
/// on `train_samples` fresh frames, then locates `locate_frames` frames.
/// The training seed is `derive_seed(seed, "detector", "throughput")`, the
/// located frames' `derive_seed(seed, "dataset", "throughput-locate")`.
pub(crate) fn throughput(
    arch: &CnnArchitecture,
    params: &SimParams,
    batch_size: usize,
    train_samples: usize,
    locate_frames: usize,
    seed: u64,
) -> anyhow::Result<Throughput> {
    let settings = TrainingSettings {
        epochs: 1,
        batch_size,
        validation_fraction: 0.0,
        fresh_frames_per_epoch: train_samples,
        ..TrainingSettings::default()
    };
    let empty = Dataset::default();
    let cpu_started = process_cpu_seconds();
    let started = Instant::now();
    // No validation frames: the score is never computed.
    let model = cnn::train(
        arch,
        &settings,
        &empty,
        Some(params),
        derive_seed(seed, "detector", "throughput"),
        &metrics::paper_aucs,
        &ProgressBar::hidden(),
    )?;
    let train_seconds = started.elapsed().as_secs_f64();
    let train_cpu_seconds = process_cpu_seconds() - cpu_started;
    let test = sim::simulate(
        params,
        derive_seed(seed, "dataset", "throughput-locate"),
        0..locate_frames,
        &ProgressBar::hidden(),
    )?;
    let cpu_started = process_cpu_seconds();
    let started = Instant::now();
    model.locate(&test.frames, &ProgressBar::hidden())?;
    let locate_seconds = started.elapsed().as_secs_f64();
    let locate_cpu_seconds = process_cpu_seconds() - cpu_started;
    Ok(Throughput {
        architecture: arch.clone(),
        batch_size,
        threads: rayon::current_num_threads(),
        train_samples_per_second: train_samples as f64 / train_seconds.max(1e-9),
        train_samples,
        locate_frames_per_second: locate_frames as f64 / locate_seconds.max(1e-9),
        locate_frames,
        train_cpu_seconds,
        locate_cpu_seconds,
    })
}

/// Environment under which the PyTorch reference runs: glibc's malloc
/// keeps PyTorch's large buffers instead of returning them to the system
/// after every step (as PyTorch deployments usually configure it); malloc
/// reads these at start-up, so they are set when the interpreter is
/// spawned (the script also re-executes itself with them).
pub(crate) const TORCH_MALLOC_ENV: [(&str, &str); 2] = [
    ("MALLOC_MMAP_THRESHOLD_", "33554432"),
    ("MALLOC_TRIM_THRESHOLD_", "4294967296"),
];

/// Where and how to run the PyTorch reference of [`compare_with_torch`].
#[derive(Debug, Clone)]
pub(crate) struct TorchReference {
    pub python: String,
    pub script: std::path::PathBuf,
}

/// Training samples/s and inference frames/s of one timed run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub(crate) struct Rates {
    pub train_samples_per_second: f64,
    pub frames_per_second: f64,
    /// The same per CPU second of the process (see [`Throughput`]).
    pub train_samples_per_cpu_second: f64,
    pub frames_per_cpu_second: f64,
}

/// Medians over the repetitions at one thread count; `torch` is `None`
/// (with the reason in `torch_skipped`) when the reference could not run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub(crate) struct Comparison {
    pub threads: usize,
    pub repeats: usize,
    pub scanloc: Rates,
    pub torch: Option<Rates>,
    pub torch_skipped: Option<String>,
}

fn median(values: &mut [f64]) -> f64 {
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    if values.len().is_multiple_of(2) {
        (values[mid - 1] + values[mid]) / 2.0
    } else {
        values[mid]
    }
}

/// Runs [`throughput`] and the PyTorch reference of the same network
/// (`reference`, on synthetic batches of the same frame size; see its
/// docstring) `repeats` times each, alternating scanloc and torch so that
/// changes of the machine's load hit both alike, once per entry of
/// `threads` (scanloc in a rayon pool of that size, torch with that many
/// intra-op threads). Reports the medians. If the first torch run fails
/// (no interpreter, no torch) the rest of the torch runs are skipped.
#[allow(clippy::too_many_arguments)]
pub(crate) fn compare_with_torch(
    arch: &CnnArchitecture,
    params: &SimParams,
    batch_size: usize,
    train_samples: usize,
    locate_frames: usize,
    seed: u64,
    threads: &[usize],
    repeats: usize,
    reference: Option<&TorchReference>,
) -> anyhow::Result<Vec<Comparison>> {
    let mut skipped: Option<String> = reference.is_none().then(|| "not requested".to_string());
    let mut out = Vec::with_capacity(threads.len());
    for &thread_count in threads {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(thread_count)
            .build()?;
        let (mut ours, mut theirs) = (Vec::new(), Vec::new());
        for _ in 0..repeats.max(1) {
            let result = pool.install(|| {
                throughput(arch, params, batch_size, train_samples, locate_frames, seed)
            })?;
            ours.push(Rates {
                train_samples_per_second: result.train_samples_per_second,
                frames_per_second: result.locate_frames_per_second,
                train_samples_per_cpu_second: train_samples as f64
                    / result.train_cpu_seconds.max(1e-9),
                frames_per_cpu_second: locate_frames as f64 / result.locate_cpu_seconds.max(1e-9),
            });
            let Some(reference) = reference.filter(|_| skipped.is_none()) else {
                continue;
            };
            let run = TorchRun {
                threads: thread_count,
                batch_size,
                train_samples,
                locate_frames,
            };
            match torch_rates(reference, arch, params, &run) {
                Ok(rates) => theirs.push(rates),
                Err(reason) => skipped = Some(reason),
            }
        }
        let torch_ran = skipped.is_none() && !theirs.is_empty();
        out.push(Comparison {
            threads: thread_count,
            repeats: repeats.max(1),
            scanloc: median_rates(&ours),
            torch: torch_ran.then(|| median_rates(&theirs)),
            torch_skipped: skipped.clone(),
        });
    }
    Ok(out)
}

/// The sizes of one PyTorch reference run.
struct TorchRun {
    threads: usize,
    batch_size: usize,
    train_samples: usize,
    locate_frames: usize,
}

/// PyTorch's rates for the same network and sizes, from the reference
/// script; `Err` with the reason it could not run.
fn torch_rates(
    reference: &TorchReference,
    arch: &CnnArchitecture,
    params: &SimParams,
    run: &TorchRun,
) -> Result<Rates, String> {
    let dilations = arch
        .dilations
        .iter()
        .map(|d| d.to_string())
        .collect::<Vec<_>>()
        .join(",");
    let numbers = [
        run.threads,
        run.train_samples,
        run.locate_frames,
        run.batch_size,
        crate::detect::cnn::inference::INFERENCE_BATCH,
        arch.channels,
        arch.input_channels(),
        crate::detect::cnn::model::OUTPUT_CHANNELS,
        params.height,
        params.width,
    ]
    .map(|n| n.to_string());
    let flags = [
        "--threads",
        "--samples",
        "--locate-frames",
        "--batch-size",
        "--inference-batch",
        "--channels",
        "--input-channels",
        "--output-channels",
        "--height",
        "--width",
    ];
    let mut args: Vec<&str> = Vec::new();
    for (flag, value) in flags.iter().zip(&numbers) {
        args.extend([*flag, value.as_str()]);
    }
    args.extend(["--dilations", &dilations]);
    let thread_text = run.threads.to_string();
    let mut env = TORCH_MALLOC_ENV.to_vec();
    env.push(("OMP_NUM_THREADS", &thread_text));
    let [train, frames, train_cpu, frames_cpu] = crate::bench::reference::run_python_figures(
        &reference.python,
        &reference.script,
        &args,
        &env,
        [
            "train_samples_per_second",
            "frames_per_second",
            "train_samples_per_cpu_second",
            "frames_per_cpu_second",
        ],
    )?;
    Ok(Rates {
        train_samples_per_second: train,
        frames_per_second: frames,
        train_samples_per_cpu_second: train_cpu,
        frames_per_cpu_second: frames_cpu,
    })
}

/// The median of each rate over repeated runs.
fn median_rates(rates: &[Rates]) -> Rates {
    let of = |figure: fn(&Rates) -> f64| median(&mut rates.iter().map(figure).collect::<Vec<_>>());
    Rates {
        train_samples_per_second: of(|r| r.train_samples_per_second),
        frames_per_second: of(|r| r.frames_per_second),
        train_samples_per_cpu_second: of(|r| r.train_samples_per_cpu_second),
        frames_per_cpu_second: of(|r| r.frames_per_cpu_second),
    }
}
