//! `scanloc locate`: localise QDs in a frame file.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::detect::cnn::TrainedCnn;
use crate::detect::crocker_grier::{self, CrockerGrierParams};
use crate::detect::likelihood::{self, LikelihoodParams};
use crate::error::input_error;
use crate::io::{self, csv_tables};
use crate::registry::{ModelOrigin, Registry};
use clap::{Args, ValueEnum};

/// Localise QDs in every frame of a .npy or .tif stack and write a CSV.
///
/// With `--method crocker-grier` (TrackPy's `locate`, same parameters and
/// defaults) the columns are frame,x,y,mass,size,ecc,signal,raw_mass,ep,score
/// (score = mass), ordered by frame then descending mass. With `--method cnn
/// --model MODEL` (a model folder saved by `scanloc train`, or a model of
/// the registry: RUN:DETECTOR or a content key) the columns are
/// frame,x,y,sigma_x,sigma_y,score: sigma_x, sigma_y are the network's
/// estimate of each localisation's error in pixels, the standard deviation
/// per axis (read from its within-1-px probability; filter on them as on an
/// SMLM localisation precision; `scanloc score` says how well they describe
/// the errors), score as the model's `architecture.score`; a model with
/// the categorical head gives a ranked list of guesses per frame (up to
/// its `architecture.max_candidates`, or --max-candidates), scored by
/// their posterior mass, and adds the column candidate, their rank;
/// a line on standard output names the model (its registry key, run and
/// detector, or folder) and the sha256 of its bytes, the same for a
/// registry model and its exported folder. With `--method likelihood` (a
/// particle filter under the simulator's model of the microscope its flags
/// or `--microscope FILE.yaml` describe, the paper's by default, at the
/// frames' size) the columns are frame,x,y,score: one row per frame, the posterior mean of
/// the QD's trajectory centroid and the posterior mass within
/// --score-radius-px of it (with --max-candidates N above 1: up to N rows
/// per frame and a column candidate, their rank).
///
/// Integer frames are photon counts. Float frames (float32/float64 .npy or
/// TIFF pages; fractional or negative values, e.g. background-subtracted)
/// are taken by crocker-grier as TrackPy takes a float array (threshold
/// 1/255 by default, peaks found on an 8-bit rescaling); the CNN needs
/// photon counts and refuses float values that are not whole and ≥ 0.
/// NaN and infinities are refused. A multi-channel ImageJ hyperstack needs
/// `--channel`. The CNN goes through the frames in batches of at most 2¹⁸
/// pixels, so its memory beyond the frames themselves does not grow with
/// the recording.
///
/// The methods and their parameters: docs/detectors.md.
#[derive(Debug, Args)]
#[command(allow_negative_numbers = true)]
pub(super) struct LocateArgs {
    /// Localisation method.
    #[arg(long, value_enum, default_value_t = Method::CrockerGrier)]
    method: Method,
    /// Input frames: FILE.npy (shape (n, H, W) or (H, W)) or FILE.tif.
    #[arg(long)]
    input: PathBuf,
    /// Output CSV.
    #[arg(long)]
    out: PathBuf,
    /// The channel to localise in (0-based), required for a multi-channel
    /// stack (an ImageJ hyperstack with channels).
    #[arg(long)]
    channel: Option<usize>,
    /// Crocker–Grier's parameters.
    #[command(flatten, next_help_heading = "With --method crocker-grier")]
    crocker_grier: CrockerGrierArgs,
    /// The CNN and where it is stored.
    #[command(flatten, next_help_heading = "With --method cnn")]
    cnn: CnnArgs,
    /// Ranked lists of guesses.
    #[command(
        flatten,
        next_help_heading = "With --method likelihood or a categorical CNN"
    )]
    candidates: CandidateArgs,
    /// The particle filter and the microscope it models.
    #[command(
        flatten,
        next_help_heading = "With --method likelihood (the microscope the filter models; a distribution is a prior)"
    )]
    likelihood: LikelihoodArgs,
}

/// TrackPy's `locate` parameters, with its defaults.
#[derive(Debug, Args)]
struct CrockerGrierArgs {
    /// Feature diameter in pixels (odd, ≥ 3).
    #[arg(long, default_value_t = 7)]
    diameter: usize,
    /// Minimum integrated brightness (features need mass > minmass).
    #[arg(long)]
    minmass: Option<f64>,
    /// Maximum radius of gyration.
    #[arg(long)]
    maxsize: Option<f64>,
    /// Minimum separation between features [default: diameter + 1].
    #[arg(long)]
    separation: Option<f64>,
    /// Width of the Gaussian low pass in pixels.
    #[arg(long, default_value_t = 1.0)]
    noise_size: f64,
    /// Side of the boxcar background in pixels, odd [default: diameter].
    #[arg(long)]
    smoothing_size: Option<usize>,
    /// Band-pass values below this are set to 0 [default: 1; 1/255 for
    /// float frames].
    #[arg(long)]
    threshold: Option<f64>,
    /// Peaks must be brighter than this percentile of non-zero pixels.
    #[arg(long, default_value_t = 64.0)]
    percentile: f64,
    /// Keep only the N brightest features per frame.
    #[arg(long)]
    topn: Option<usize>,
    /// Maximum centroid refinement steps.
    #[arg(long, default_value_t = 10)]
    max_iterations: usize,
    /// Band-pass the frames before finding peaks (default).
    #[arg(long, overrides_with = "no_preprocess")]
    preprocess: bool,
    /// Find peaks in the raw frames.
    #[arg(long)]
    no_preprocess: bool,
}

impl CrockerGrierArgs {
    /// The detector's parameters, checked.
    fn params(&self) -> anyhow::Result<CrockerGrierParams> {
        let params = CrockerGrierParams {
            diameter: self.diameter,
            minmass: self.minmass,
            maxsize: self.maxsize,
            separation: self.separation,
            noise_size: self.noise_size,
            smoothing_size: self.smoothing_size,
            threshold: self.threshold,
            percentile: self.percentile,
            topn: self.topn,
            preprocess: !self.no_preprocess,
            max_iterations: self.max_iterations,
        };
        params
            .validate()
            .map_err(|e| input_error(format!("invalid crocker-grier parameter: {e}")))?;
        Ok(params)
    }
}

/// The CNN to locate with.
#[derive(Debug, Args)]
struct CnnArgs {
    /// A model folder (written by `scanloc train` or `scanloc registry
    /// model`), or a model in the registry named RUN:DETECTOR (a run id or
    /// unique prefix, and the detector's name in its manifest) or by its
    /// content key or a unique prefix. An existing path is taken as a
    /// folder.
    #[arg(long, required_if_eq("method", "cnn"))]
    model: Option<String>,
    /// The registry `--model` names a model of (when it is not a folder).
    #[command(flatten)]
    registry: super::RegistryDir,
}

/// How many guesses per frame, for the methods that give a ranked list.
#[derive(Debug, Args)]
struct CandidateArgs {
    /// Guesses per frame; above 1 a ranked list (column candidate, 1 = the
    /// frame's best) from the greedy disc cover of the posterior, each
    /// scored by the mass it newly covers. Likelihood: default 1. CNN: a
    /// model with the categorical head only, default the model's own
    /// `architecture.max_candidates`.
    #[arg(long)]
    max_candidates: Option<usize>,
    /// Radius (px) of the cover's discs [likelihood: 1; CNN: the model's].
    #[arg(long)]
    candidate_radius_px: Option<f64>,
}

/// The particle filter's settings and the microscope it models.
#[derive(Debug, Args)]
struct LikelihoodArgs {
    /// Particles per frame.
    #[arg(long, default_value_t = 20_000)]
    particles: usize,
    /// The score is the posterior mass within this many pixels of the
    /// estimate.
    #[arg(long, default_value_t = 1.0)]
    score_radius_px: f64,
    /// Seed of the particle filter (frame i draws from stream i of it).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The microscope the filter assumes (a distribution is a prior,
    /// marginalised; the margin bounds the prior over the QD's start; the
    /// frame size is the input's).
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
}

/// Localisation methods.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Method {
    /// The Crocker–Grier algorithm of TrackPy's `locate`.
    CrockerGrier,
    /// A CNN trained on simulated frames (needs --model).
    Cnn,
    /// A particle filter under the simulator's forward model (slow).
    Likelihood,
}

/// The CNN named by `reference` (RUN:DETECTOR or a key) in `registry`,
/// decoded, with where it came from.
pub(super) fn registry_cnn(
    registry: &Registry,
    reference: &str,
) -> anyhow::Result<(TrainedCnn, ModelOrigin)> {
    let stored = registry.stored_model(reference, crate::types::DetectorKind::Cnn)?;
    let model = TrainedCnn::from_bytes(&stored.bytes)
        .map_err(|e| input_error(format!("{reference}: {e:#}")))?;
    Ok((model, stored.origin))
}

/// "detector D of run R" for a model read from the registry.
pub(super) fn describe_origin(origin: &ModelOrigin) -> String {
    match &origin.run {
        Some(run) => format!("detector {} of run {run}", origin.detector),
        None => format!("detector {}", origin.detector),
    }
}

pub(super) fn run(args: LocateArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let model_folder = args
        .cnn
        .model
        .as_deref()
        .map(Path::new)
        .filter(|path| path.exists());
    let mut inputs = vec![("--input", args.input.as_path())];
    inputs.extend(model_folder.map(|model| ("--model", model)));
    io::refuse_shared_paths(&inputs, &[("--out", &args.out)])?;
    match args.method {
        Method::CrockerGrier => locate_crocker_grier(&args),
        Method::Cnn => locate_cnn(&args, model_folder, stdout),
        Method::Likelihood => locate_likelihood(&args),
    }?;
    Ok(ExitCode::SUCCESS)
}

fn locate_crocker_grier(args: &LocateArgs) -> anyhow::Result<()> {
    let params = args.crocker_grier.params()?;
    let frames = io::read_recording_of_channel(&args.input, args.channel)?;
    let bar = crate::progress::bar(frames.shape().0 as u64, "locating");
    let features = crocker_grier::locate_recording(&frames, &params, &bar)?;
    bar.finish_and_clear();
    csv_tables::write_localisations(
        &args.out,
        crocker_grier::FEATURE_COLUMNS,
        features
            .iter()
            .map(|(frame, f)| (f.prediction(*frame), f.column_values())),
    )
}

/// The CNN of `--model` (a folder if `model_folder` is `Some`, else a
/// registry model), described for the report line.
fn load_cnn(cnn: &CnnArgs, model_folder: Option<&Path>) -> anyhow::Result<(TrainedCnn, String)> {
    let reference = cnn
        .model
        .as_deref()
        .ok_or_else(|| input_error("--model: required with --method cnn"))?;
    if let Some(folder) = model_folder {
        return Ok((
            TrainedCnn::load(folder)?,
            format!("folder {}", folder.display()),
        ));
    }
    let registry = Registry::open_existing(&cnn.registry.dir).map_err(|e| {
        input_error(format!(
            "--model {reference}: not a model folder, and {e:#}"
        ))
    })?;
    let (model, origin) = registry_cnn(&registry, reference)?;
    Ok((
        model,
        format!("{} ({})", origin.model_key, describe_origin(&origin)),
    ))
}

fn locate_cnn(
    args: &LocateArgs,
    model_folder: Option<&Path>,
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    let (mut model, origin) = load_cnn(&args.cnn, model_folder)?;
    let model_sha256 = crate::registry::hashing::sha256_hex(&model.to_bytes()?);
    decode_as_asked(&mut model, &args.candidates)?;
    let frames = io::read_frames_of_channel(&args.input, args.channel)?;
    let bar = crate::progress::bar(frames.n as u64, "locating");
    let predictions = model.locate(&frames, &bar)?;
    bar.finish_and_clear();
    csv_tables::write_predictions(&args.out, &predictions)?;
    writeln!(
        stdout,
        "located {} QDs in {} frames with model {origin}, model.bin sha256 {model_sha256}; wrote {}",
        predictions.len(),
        frames.n,
        args.out.display()
    )?;
    Ok(())
}

/// The model's decoding with `--max-candidates` / `--candidate-radius-px`
/// where given (a list needs the categorical head), checked.
fn decode_as_asked(model: &mut TrainedCnn, asked: &CandidateArgs) -> anyhow::Result<()> {
    let architecture = &mut model.architecture;
    if let Some(count) = asked.max_candidates {
        architecture.max_candidates = count;
    }
    if let Some(radius) = asked.candidate_radius_px {
        architecture.candidate_radius_px = radius;
    }
    architecture.validate().map_err(|e| {
        input_error(format!(
            "--max-candidates/--candidate-radius-px with this model: {e}"
        ))
    })
}

fn locate_likelihood(args: &LocateArgs) -> anyhow::Result<()> {
    let filter = &args.likelihood;
    let defaults = LikelihoodParams::default();
    let settings = LikelihoodParams {
        particles: filter.particles,
        score_radius_px: filter.score_radius_px,
        max_candidates: args
            .candidates
            .max_candidates
            .unwrap_or(defaults.max_candidates),
        candidate_radius_px: args
            .candidates
            .candidate_radius_px
            .unwrap_or(defaults.candidate_radius_px),
        ..defaults
    };
    settings
        .validate()
        .map_err(|e| input_error(format!("invalid likelihood parameter: {e}")))?;
    let microscope = filter.microscope.resolve()?;
    let frames = io::read_frames_of_channel(&args.input, args.channel)?;
    let microscope = microscope.at_frame_size(frames.height, frames.width)?;
    microscope
        .validate()
        .map_err(|e| input_error(format!("invalid microscope parameter: {e}")))?;
    let bar = crate::progress::bar(frames.n as u64, "locating");
    let predictions = likelihood::locate_stack(&frames, &microscope, &settings, filter.seed, &bar)?;
    bar.finish_and_clear();
    csv_tables::write_predictions(&args.out, &predictions)
}
