//! `scanloc simulate`: write simulated frames and their ground truth.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::io::{self, PendingFile};
use crate::sim;
use clap::Args;

/// Simulate point-scanning 2PM frames of diffusing QDs (docs/simulator.md).
///
/// Every parameter defaults to the paper's microscope. Frame i of a dataset
/// depends only on (parameters, seed, i): the same frames come out whatever
/// the thread count.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct SimulateArgs {
    /// Number of frames (at most 10,000,000, and 2³¹ pixels in all: the
    /// limits a manifest's datasets have).
    #[arg(long, default_value_t = 100)]
    frames: usize,
    /// Master seed of the dataset.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The microscope (every field of a manifest's `microscope` section).
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
    /// Output frames: FILE.npy (uint16, or uint32 if needed; shape (n, H, W)) or FILE.tif.
    #[arg(long)]
    out: PathBuf,
    /// Output ground truth CSV: frame,x,y,x_start,y_start,x_end,y_end,z_mean,diffusion.
    #[arg(long)]
    truth: Option<PathBuf>,
}

pub(super) fn run(args: SimulateArgs) -> anyhow::Result<ExitCode> {
    let params = args.microscope.params()?;
    params
        .validate()
        .map_err(|e| input_error(format!("invalid simulation parameter: {e}")))?;
    // The manifest's limits, checked by the same functions.
    crate::limits::check_dataset_size("--frames", args.frames, params.height, params.width)?;
    // The memory the dataset takes, before any of it is allocated: a
    // failed allocation would end the process without a word.
    crate::limits::check_memory(
        "--frames",
        sim::dataset_bytes(&params, args.frames),
        crate::limits::available_memory_bytes(),
    )?;
    io::FrameFormat::from_path(&args.out)?;
    let mut outputs = vec![("--out", args.out.as_path())];
    outputs.extend(args.truth.as_deref().map(|truth| ("--truth", truth)));
    io::refuse_shared_paths(&[], &outputs)?;
    // Every output is opened (and dropped) before simulating, so that an
    // unwritable destination fails now; the files are opened again only
    // once the frames are made, so that a simulation stopped part way (by
    // an error or a signal) leaves no partial file behind, and nothing is
    // renamed into place unless everything succeeded.
    let open_outputs = || -> anyhow::Result<(PendingFile, Option<PendingFile>)> {
        Ok((
            PendingFile::create(&args.out)?,
            args.truth.as_deref().map(PendingFile::create).transpose()?,
        ))
    };
    drop(open_outputs()?);

    let bar = crate::progress::bar(args.frames as u64, "simulating");
    let dataset = sim::simulate(&params, args.seed, 0..args.frames, &bar)?;
    bar.finish_and_clear();

    let (mut frames_out, mut truth_out) = open_outputs()?;

    io::fill_frames(&mut frames_out, &dataset.frames)?;
    if let Some(pending) = truth_out.as_mut() {
        io::csv_tables::fill_truth(pending, &dataset.truth)?;
    }
    frames_out.commit()?;
    if let Some(pending) = truth_out {
        pending.commit()?;
    }
    Ok(ExitCode::SUCCESS)
}
