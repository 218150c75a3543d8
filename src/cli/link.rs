//! `scanloc link`: localisations to trajectories (docs/tracking.md#linking).

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::io::{PendingFile, localisation_table};
use crate::track::linker::{LinkerKind, LinkerRequest, Naming};
use crate::track::{self, trackpy::TrackpyParams};
use clap::{Args, ValueEnum};

/// Link localisations into trajectories (docs/tracking.md#linking).
///
/// Reads a localisation table (CSV with a header: frame, x, y in TrackPy
/// pixel coordinates; sigma_x, sigma_y used by --linker lap when present;
/// any other columns are copied) and writes the same rows and columns plus
/// `particle`, the trajectory label, sorted by frame (rows of one frame in
/// input order), as TrackPy's `link` returns its table; --linker lap adds
/// gate_x, gate_y, the extent (px) of the gate that admitted each row's link
/// (`scanloc diffusion` reads them). Unsorted input is sorted the same way.
/// Prints one summary line.
///
/// --linker trackpy (the default) gives TrackPy 0.7's `link` trajectories
/// (search range, memory), checked against TrackPy itself on committed
/// fixtures: the reference everyone's pipelines use, so results compare
/// with theirs. --linker lap links by global assignment with gap closing
/// over blinks (Jaqaman et al. 2008), costs from the localisation
/// uncertainty and the expected step: better where particles blink and
/// crowd, at the price of a diffusion model to state.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct LinkArgs {
    /// Localisation table (CSV with frame, x, y; optionally sigma_x, sigma_y).
    #[arg(long)]
    locs: PathBuf,
    /// Output track table: the input columns plus `particle` (and, from lap,
    /// gate_x, gate_y).
    #[arg(long)]
    out: PathBuf,
    /// The linker (see above).
    #[arg(long, value_enum, default_value_t = Linker::Trackpy)]
    linker: Linker,
    /// Largest displacement between consecutive frames, px (TrackPy's
    /// search_range). For lap: taken as 3 standard deviations of a frame's
    /// step, unless --diffusion gives the step.
    #[arg(long, allow_hyphen_values = true)]
    search_range: Option<f64>,
    /// trackpy: frames a particle may vanish for and still be linked
    /// (TrackPy's memory) [default: 0].
    #[arg(long, value_parser = super::whole_number::<usize>)]
    memory: Option<usize>,
    /// lap: the longest gap closed, in frames without the particle (0: none)
    /// [default: 2].
    #[arg(long, value_parser = super::whole_number::<usize>)]
    max_gap: Option<usize>,
    /// lap: diffusion coefficient D in µm²/s giving the expected step
    /// (2 D Δt per axis); needs --frame-time-ms and --pixel-size-um.
    #[arg(long, requires_all = ["frame_time_ms", "pixel_size_um"])]
    diffusion: Option<f64>,
    /// lap: time between frames, ms (e.g. 27.6 for the paper's 24 × 25 frames).
    #[arg(long, allow_hyphen_values = true)]
    frame_time_ms: Option<f64>,
    /// lap: pixel size, µm.
    #[arg(long, allow_hyphen_values = true)]
    pixel_size_um: Option<f64>,
    /// Link only the rows whose `score` column (as `scanloc locate` writes
    /// it) is at least this; the others are left out of the output. A
    /// detector's candidates below its best-F1 threshold are mostly noise
    /// that would start false links (the recordings' CNN: 0.3,
    /// docs/tracking.md, "From a recording to D").
    #[arg(long, allow_hyphen_values = true)]
    min_score: Option<f64>,
    /// lap: the gate, the largest Mahalanobis distance of a link's
    /// displacement [default: 3]. Each link's gate is written as its extent
    /// along x and y (gate_x, gate_y, px), which `scanloc diffusion` uses.
    #[arg(long, allow_hyphen_values = true)]
    gate: Option<f64>,
}

/// The linkers of `scanloc link`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Linker {
    /// TrackPy 0.7's link: subnetworks solved for the least sum of squared
    /// displacements, memory for blinks.
    Trackpy,
    /// Global assignment frame to frame and gap closing (Jaqaman et al. 2008).
    Lap,
}

pub(super) fn run(args: LinkArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let linker = LinkerRequest {
        linker: match args.linker {
            Linker::Trackpy => LinkerKind::Trackpy,
            Linker::Lap => LinkerKind::Lap,
        },
        search_range: args.search_range,
        memory: args.memory,
        max_gap: args.max_gap,
        diffusion: args.diffusion,
        frame_time_ms: args.frame_time_ms,
        pixel_size_um: args.pixel_size_um,
        gate: args.gate,
    }
    .configure(Naming::Flags)?;
    if let Some(least) = args.min_score.filter(|least| !least.is_finite()) {
        return Err(input_error(format!(
            "--min-score: must be a finite number, got {}",
            crate::error::readable(least)
        )));
    }
    crate::io::refuse_shared_paths(&[("--locs", &args.locs)], &[("--out", &args.out)])?;
    let mut pending = PendingFile::create(&args.out)?;
    let mut table = localisation_table::read_localisation_table(&args.locs)?;
    let left_out = match args.min_score {
        Some(least) => table
            .retain_scoring_at_least(least, &args.locs.display().to_string())
            .map_err(|e| e.context("--min-score"))?,
        None => 0,
    };
    let detections = track::detections(&table);
    let linking = linker
        .link(&detections)
        .map_err(|e| e.context(format!("{}: linking", args.locs.display())))?;
    let order = track::frame_order(&detections);
    localisation_table::fill_track_table(
        &mut pending,
        &table,
        &order,
        &linking.particle,
        linking.gates.as_deref(),
    )?;
    pending.commit()?;
    let trajectories = linking.particle.iter().max().map_or(0, |&m| m + 1);
    let below = args.min_score.map_or(String::new(), |least| {
        format!(" ({left_out} scoring below {least} left out)")
    });
    writeln!(
        stdout,
        "linked {} localisations{below} into {trajectories} trajectories ({}; {} links, {} over \
         gaps, {} contested subnetworks, largest {}) -> {}",
        detections.len(),
        linker.describe(),
        linking.stats.links,
        linking.stats.gap_links,
        linking.stats.contested,
        linking.stats.largest,
        args.out.display()
    )?;
    Ok(ExitCode::SUCCESS)
}

/// `scanloc bench link`: random walks of particles that appear, disappear
/// and blink, linked by `--linker trackpy` and by TrackPy 0.7 (python3
/// with trackpy; skipped with a message if it cannot run).
#[derive(Debug, Args)]
pub(super) struct LinkBench {
    /// Particles over the recording.
    #[arg(long, default_value_t = 400)]
    particles: usize,
    /// Frames of the recording.
    #[arg(long, default_value_t = 200)]
    frames: usize,
    /// Particles per px² of the field.
    #[arg(long, default_value_t = 0.004, allow_hyphen_values = true)]
    density: f64,
    /// Standard deviation of a frame's step per axis, px.
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    step: f64,
    /// Probability that a detection is missing (a blink).
    #[arg(long, default_value_t = 0.05, allow_hyphen_values = true)]
    blink: f64,
    /// Search range, px.
    #[arg(long, default_value_t = 4.0, allow_hyphen_values = true)]
    search_range: f64,
    /// Memory, frames.
    #[arg(long, default_value_t = 2)]
    memory: usize,
    /// Seed of the walks.
    #[arg(long, default_value_t = 38)]
    seed: u64,
    /// Timed repeats of scanloc; the best is reported.
    #[arg(long, default_value_t = 20)]
    repeats: usize,
    /// Timed repeats of TrackPy (about 2 s each on the default walks); the
    /// best is reported.
    #[arg(long, default_value_t = 3)]
    reference_repeats: usize,
    /// Python interpreter with trackpy 0.7 (the reference is skipped if missing).
    #[arg(long, default_value = "python3")]
    python: String,
    /// The TrackPy reference script.
    #[arg(long, default_value = "benches/reference/trackpy_link.py")]
    reference: PathBuf,
}

pub(super) fn bench(args: LinkBench, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    use crate::bench::link as bench_link;
    let spec = bench_link::WalkSpec {
        particles: args.particles,
        frames: args.frames,
        density_per_px2: args.density,
        step_px: args.step,
        blink: args.blink,
        seed: args.seed,
    };
    spec.validate()?;
    let params = TrackpyParams {
        search_range: args.search_range,
        memory: args.memory,
    };
    params.validate()?;
    let detections = bench_link::random_walks(&spec);
    let (seconds, linking) = bench_link::time_trackpy_link(&detections, &params, args.repeats)?;
    let rate = detections.len() as f64 / seconds;
    writeln!(
        stdout,
        "scanloc link (trackpy): {} localisations in {} frames in {:.4} s = {rate:.0} localisations/s \
         ({} contested subnetworks, largest {})",
        detections.len(),
        args.frames,
        seconds,
        linking.stats.contested,
        linking.stats.largest
    )?;
    let folder = tempfile::tempdir()?;
    let input = folder.path().join("locs.csv");
    let output = folder.path().join("tracks.csv");
    bench_link::write_detections(&input, &detections)?;
    let figures = crate::bench::reference::run_python_figures(
        &args.python,
        &args.reference,
        &[
            "--input",
            &input.to_string_lossy(),
            "--out",
            &output.to_string_lossy(),
            "--search-range",
            &args.search_range.to_string(),
            "--memory",
            &args.memory.to_string(),
            "--repeats",
            &args.reference_repeats.to_string(),
        ],
        &[],
        ["localisations_per_second"],
    );
    match figures {
        Ok([reference]) => {
            let labels = bench_link::read_reference_labels(&output, detections.len())?;
            let same = track::same_partition(&labels, &linking.particle);
            writeln!(
                stdout,
                "trackpy 0.7 link: {reference:.0} localisations/s; scanloc is {:.0}× faster; \
                 same trajectories: {}",
                rate / reference,
                if same { "yes" } else { "NO" }
            )?;
        }
        Err(reason) => writeln!(stdout, "trackpy reference skipped: {reason}")?,
    }
    Ok(ExitCode::SUCCESS)
}
