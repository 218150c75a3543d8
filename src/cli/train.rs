//! `scanloc train`: train the CNN localiser on simulated frames.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use crate::detect::cnn::{self, CnnArchitecture, CnnHead, CnnScore, TrainingSettings};
use crate::error::input_error;
use crate::metrics;
use crate::sim::{self, EmitterCount, SimParams};
use crate::types::derive_seed;
use clap::{Args, ValueEnum};

/// Train the CNN localiser on simulated frames and save it (docs/detectors.md).
///
/// Simulates `--frames` frames of the microscope the flags describe (the
/// paper's by default, with D drawn per frame and a margin of 4 px; or
/// `--microscope FILE.yaml`; per-frame parameters a number or drawn per
/// frame from uniform:LOW,HIGH) as the fixed dataset, of which
/// `--validation-fraction` selects the best epoch, optionally adds
/// `--fresh-frames-per-epoch` newly simulated frames every epoch, trains, and
/// writes the model folder `--out` (model.bpk in burn's record format,
/// config.json, training.json; with `--members K`, model-2.bpk and
/// training-2.json up to K for the other networks of the ensemble). Unset
/// network and training options take the library defaults (the best
/// measured setting). Same options and seed →
/// bit-identical weights.
///
/// With `--test-frames`, also simulates a test set per `--test-diffusion`
/// value (seeds distinct from training) and prints the AUC table.
///
/// A training that diverges (a non-finite loss or network output, e.g.
/// from too high a learning rate) stops with exit code 2, naming the epoch
/// and batch: the settings are at fault, not the program.
#[derive(Debug, Args)]
#[command(
    mut_arg("margin_px", |arg| arg.default_value("4")),
    mut_arg("diffusion", |arg| arg.default_value("uniform:0.75,1.75"))
)]
pub(super) struct TrainArgs {
    /// Frames of the fixed (simulated) dataset.
    #[arg(long, default_value_t = 2000)]
    frames: usize,
    /// The microscope of the training frames (and of the test sets, but for
    /// D and the QDs per frame).
    #[command(flatten)]
    microscope: super::MicroscopeArgs,
    /// Master seed: derives the dataset's seed, the fresh frames', the
    /// weight initialisation, the split and the batch order.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Hidden conv channels.
    #[arg(long)]
    channels: Option<usize>,
    /// Dilations of the hidden 3×3 conv layers, comma-separated.
    #[arg(long, value_delimiter = ',')]
    dilations: Option<Vec<usize>>,
    /// Half-size of the peak window at inference, pixels.
    #[arg(long)]
    peak_radius_px: Option<usize>,
    /// What a peak's score is (the peaks head).
    #[arg(long, value_enum)]
    score: Option<ScoreArg>,
    /// How the score map is trained and read: `peaks`, a sigmoid per pixel
    /// whose local maxima are the localisations, or `categorical`, a softmax
    /// over the frame's pixels (frames of one QD) decoded into a ranked list
    /// of up to --max-candidates guesses (needs --offset-radius-px 0).
    #[arg(long, value_enum, default_value_t = HeadArg::Peaks)]
    head: HeadArg,
    /// With --head categorical: guesses per frame (a ranked list, column
    /// candidate of `scanloc locate`), each scored by its posterior mass.
    #[arg(long)]
    max_candidates: Option<usize>,
    /// With --head categorical: radius (px) of the discs the guesses cover.
    #[arg(long)]
    candidate_radius_px: Option<f64>,
    /// Epochs.
    #[arg(long)]
    epochs: Option<usize>,
    /// Frames per optimiser step.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Adam's peak learning rate.
    #[arg(long)]
    learning_rate: Option<f64>,
    /// Keep the learning rate constant instead of the cosine decay.
    #[arg(long)]
    constant_learning_rate: bool,
    /// Fraction of the fixed dataset held out for selecting the best epoch.
    #[arg(long)]
    validation_fraction: Option<f64>,
    /// The first epoch whose network is validated and may be kept (1 =
    /// every epoch; the epochs before it train without being scored).
    #[arg(long)]
    validate_from_epoch: Option<usize>,
    /// Frames simulated anew every epoch (0 = fixed dataset only).
    #[arg(long)]
    fresh_frames_per_epoch: Option<usize>,
    /// Lowest score of a prediction, in [0, 1).
    #[arg(long)]
    score_floor: Option<f64>,
    /// σ of the Gaussian score target, pixels.
    #[arg(long)]
    heatmap_sigma_px: Option<f64>,
    /// Offsets are supervised within this radius of the centroid's pixel.
    #[arg(long)]
    offset_radius_px: Option<usize>,
    /// Weight of the offset loss.
    #[arg(long)]
    offset_loss_weight: Option<f64>,
    /// Weight of the Gaussian likelihood that trains the σ maps (0 = the σ
    /// maps stay untrained). The reported sigma_x, sigma_y come from the
    /// within-1-px head unless --within-loss-weight is 0.
    #[arg(long)]
    sigma_loss_weight: Option<f64>,
    /// Weight of the cross-entropy that trains the within-1-px head (0 = the
    /// head stays untrained, and the reported sigma_x, sigma_y are read from
    /// the σ maps instead).
    #[arg(long)]
    within_loss_weight: Option<f64>,
    /// Networks of a deep ensemble (1–16): each trained from its own seed
    /// as a single network is, their output maps averaged at inference
    /// (member 1 is the network a single training would give).
    #[arg(long)]
    members: Option<usize>,
    /// Posterior targets: the simulated training frames with one QD are
    /// labelled by the likelihood detector with this many particles per
    /// frame instead of by the true centroid: the peaks head learns its
    /// posterior mean, the categorical head its posterior over the pixels
    /// (0 = the truth; 2,000 takes ≈ 17 ms of CPU per 24 × 25 frame).
    #[arg(long)]
    teacher_particles: Option<usize>,
    /// With --teacher-particles: teach every epoch's fresh frames too
    /// (--fresh-frames-per-epoch), at the teacher's cost per fresh frame.
    #[arg(long)]
    teacher_fresh_frames: bool,
    /// Test frames per test diffusion coefficient (0 = no test).
    #[arg(long, default_value_t = 0)]
    test_frames: usize,
    #[command(flatten)]
    test_diffusion: super::TestDiffusionArgs,
    /// QDs per test frame (same forms as --emitters); the test sets have
    /// the training frames' start depth.
    #[arg(long, default_value = "1")]
    test_emitters: EmitterCount,
    /// Output model folder, written whole or not at all: a new path, or a
    /// model folder, which is replaced.
    #[arg(long)]
    out: PathBuf,
}

pub(super) fn run(
    args: TrainArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let (architecture, settings) = network_and_settings(&args)?;
    let (params, test_params) = microscopes(&args)?;
    cnn::check_model_destination(&args.out)?;

    let bar = crate::progress::bar(args.frames as u64, "simulating");
    let dataset = sim::simulate(
        &params,
        derive_seed(args.seed, "dataset", "training"),
        0..args.frames,
        &bar,
    )?;
    bar.finish_and_clear();

    let bar = crate::progress::bar(0, "training");
    let started = Instant::now();
    let model = cnn::train(
        &architecture,
        &settings,
        &dataset,
        Some(&params),
        args.seed,
        &metrics::paper_aucs,
        &bar,
    )?;
    let seconds = started.elapsed().as_secs_f64();
    bar.finish_and_clear();
    model.save(&args.out)?;
    write_epochs(&model, stderr)?;
    write_summary(&model, seconds, &args.out, stdout)?;

    if args.test_frames > 0 {
        let table = crate::run::test_sets::auc_table(
            &model,
            &test_params,
            args.test_diffusion.checked()?,
            args.test_frames,
            derive_seed(args.seed, "dataset", "test"),
        )?;
        write!(
            stdout,
            "{}",
            crate::run::test_sets::format_auc_table(&table)
        )?;
    }
    Ok(ExitCode::SUCCESS)
}

/// The network and its training settings: the flags given, the library's
/// defaults for the rest, checked.
fn network_and_settings(args: &TrainArgs) -> anyhow::Result<(CnnArchitecture, TrainingSettings)> {
    let defaults = CnnArchitecture::default();
    let architecture = CnnArchitecture {
        channels: args.channels.unwrap_or(defaults.channels),
        dilations: args.dilations.clone().unwrap_or(defaults.dilations),
        peak_radius_px: args.peak_radius_px.unwrap_or(defaults.peak_radius_px),
        score: args.score.map_or(defaults.score, ScoreArg::kind),
        head: args.head.kind(),
        max_candidates: args.max_candidates.unwrap_or(defaults.max_candidates),
        candidate_radius_px: args
            .candidate_radius_px
            .unwrap_or(defaults.candidate_radius_px),
        ..defaults
    };
    let defaults = TrainingSettings::default();
    let settings = TrainingSettings {
        epochs: args.epochs.unwrap_or(defaults.epochs),
        batch_size: args.batch_size.unwrap_or(defaults.batch_size),
        learning_rate: args.learning_rate.unwrap_or(defaults.learning_rate),
        cosine_decay: !args.constant_learning_rate,
        validation_fraction: args
            .validation_fraction
            .unwrap_or(defaults.validation_fraction),
        validate_from_epoch: args
            .validate_from_epoch
            .unwrap_or(defaults.validate_from_epoch),
        fresh_frames_per_epoch: args
            .fresh_frames_per_epoch
            .unwrap_or(defaults.fresh_frames_per_epoch),
        score_floor: args.score_floor.unwrap_or(defaults.score_floor),
        heatmap_sigma_px: args.heatmap_sigma_px.unwrap_or(defaults.heatmap_sigma_px),
        offset_radius_px: args.offset_radius_px.unwrap_or(defaults.offset_radius_px),
        offset_loss_weight: args
            .offset_loss_weight
            .unwrap_or(defaults.offset_loss_weight),
        sigma_loss_weight: args.sigma_loss_weight.unwrap_or(defaults.sigma_loss_weight),
        within_loss_weight: args
            .within_loss_weight
            .unwrap_or(defaults.within_loss_weight),
        members: args.members.unwrap_or(defaults.members),
        teacher_particles: args.teacher_particles.unwrap_or(defaults.teacher_particles),
        teacher_fresh_frames: args.teacher_fresh_frames,
    };
    cnn::validate_recipe(&architecture, &settings)?;
    Ok((architecture, settings))
}

/// The microscope of the training frames and that of the test sets (its
/// QDs per frame from --test-emitters), checked with the test diffusion
/// coefficients and the dataset sizes.
fn microscopes(args: &TrainArgs) -> anyhow::Result<(SimParams, SimParams)> {
    let params = args.microscope.params()?;
    let test_params = SimParams {
        emitters: args.test_emitters.clone(),
        ..params.clone()
    };
    for params in [&params, &test_params] {
        params
            .validate()
            .map_err(|e| input_error(format!("invalid simulation parameter: {e}")))?;
    }
    args.test_diffusion.checked()?;
    // The manifest's limits, checked by the same functions.
    crate::limits::check_dataset_size("--frames", args.frames, params.height, params.width)?;
    if args.test_frames > 0 {
        crate::limits::check_dataset_size(
            "--test-frames",
            args.test_frames,
            params.height,
            params.width,
        )?;
    }
    Ok((params, test_params))
}

/// One line per epoch of every member: its losses and validation AUCs.
fn write_epochs(model: &cnn::TrainedCnn, stderr: &mut dyn Write) -> anyhow::Result<()> {
    for (index, record) in model.records().enumerate() {
        let member = if model.members() > 1 {
            format!("member {}/{} ", index + 1, model.members())
        } else {
            String::new()
        };
        for epoch in &record.epochs {
            writeln!(
                stderr,
                "{member}epoch {:>3}: loss {:.4} (score {:.4}, offset {:.4}) validation AUC {}",
                epoch.epoch,
                epoch.loss,
                epoch.score_loss,
                epoch.offset_loss,
                epoch
                    .validation_auc
                    .iter()
                    .map(|a| format!("{a:.3}"))
                    .collect::<Vec<_>>()
                    .join("/")
            )?;
        }
    }
    Ok(())
}

/// The line saying what was trained, how fast, which epochs were kept and
/// where the model went.
fn write_summary(
    model: &cnn::TrainedCnn,
    seconds: f64,
    out: &Path,
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    let samples: usize = model
        .records()
        .flat_map(|record| &record.epochs)
        .map(|e| e.samples)
        .sum();
    let kept: Vec<String> = model
        .records()
        .map(|record| record.best_epoch.to_string())
        .collect();
    let (networks, kept_epochs) = if model.members() > 1 {
        (format!("{} networks × ", model.members()), "epochs")
    } else {
        (String::new(), "epoch")
    };
    writeln!(
        stdout,
        "trained {networks}{} epochs ({samples} samples) in {seconds:.1} s ({:.0} samples/s); kept {kept_epochs} {}; saved {}",
        model.record.epochs.len(),
        samples as f64 / seconds,
        kept.join(", "),
        out.display()
    )?;
    Ok(())
}

/// `--head`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum HeadArg {
    /// A sigmoid per pixel; its local maxima are the localisations.
    Peaks,
    /// A softmax over the frame's pixels, decoded into ranked guesses.
    Categorical,
}

impl HeadArg {
    fn kind(self) -> CnnHead {
        match self {
            HeadArg::Peaks => CnnHead::Peaks,
            HeadArg::Categorical => CnnHead::Categorical,
        }
    }
}

/// `--score`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum ScoreArg {
    /// The centre score map (sigmoid).
    Heatmap,
    /// The within-1-px head's probability.
    #[value(name = "within-1px")]
    Within1px,
    /// The centre score times the σ maps' probability of lying within 1 px.
    #[value(name = "gaussian-within-1px")]
    GaussianWithin1px,
}

impl ScoreArg {
    fn kind(self) -> CnnScore {
        match self {
            ScoreArg::Heatmap => CnnScore::Heatmap,
            ScoreArg::Within1px => CnnScore::Within1px,
            ScoreArg::GaussianWithin1px => CnnScore::GaussianWithin1px,
        }
    }
}
