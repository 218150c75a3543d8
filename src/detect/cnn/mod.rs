//! The CNN localiser (detector `cnn`, `docs/detectors.md`): a small fully
//! convolutional network, trained on simulated frames, that outputs a
//! per-pixel centre score and a sub-pixel offset to the QD's *trajectory
//! centroid* (the label of the simulator's ground truth), not to the
//! brightest spot.
//!
//! Layout (as burn's mnist example): [`model`] the network, [`data`] frames
//! → normalised tensors and truth → targets, [`training`] the loop,
//! [`inference`] batched prediction and peak finding (throughput and AUC
//! benchmarks: the `bench` module). Runs on burn's `flex` CPU backend,
//! which is bit-deterministic whatever the thread count; weights are
//! initialised from ChaCha streams of the training seed, so the same data,
//! settings and seed give bit-identical weights.
//!
//! Predictions (TrackPy pixel coordinates, `x` column, `y` row, pixel centres
//! at integers) are the local maxima of the score map (within
//! `peak_radius_px`, ties broken by raster order) whose score (a sigmoid,
//! in (0, 1)) is at least `score_floor`; position = pixel centre + predicted
//! offset; score as [`CnnArchitecture::score`] says; uncertainty
//! (`sigma_x`, `sigma_y`) = the σ maps at the peak pixel.

pub mod data;
pub mod inference;
pub mod kernels;
pub mod model;
pub mod training;

use std::path::Path;

use burn::module::Module;
use burn::prelude::Device;
use burn::store::ModuleRecord;
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, input_error};
pub use training::{ValidationScore, ValidationSet, train, train_selecting_on};

/// The network's shape. Serialised with the model; every field has a
/// default: the network `bench train` compares with PyTorch. The paper
/// manifest trains two more layers (docs/detectors.md, "Architecture").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CnnArchitecture {
    /// Feature channels of every hidden 3×3 conv layer.
    pub channels: usize,
    /// Dilation of each hidden 3×3 conv layer, in order (one layer each).
    /// The receptive field is `1 + 2·Σ dilations` pixels across.
    pub dilations: Vec<usize>,
    /// Batch-normalise after every hidden conv.
    pub batch_norm: bool,
    /// Feed a second, all-ones input channel so the network can tell the
    /// frame's edges from the zero padding.
    pub edge_channel: bool,
    /// Half-size of the window in which a prediction must be the score
    /// map's maximum (Chebyshev radius in pixels; 1 = 3×3 window).
    pub peak_radius_px: usize,
    /// Position estimate: 0 = the peak pixel plus its predicted offset;
    /// r > 0 = the mean of pixel + offset over the (2r + 1)² window around
    /// the peak, weighted by the score map (sigmoid).
    pub refine_radius_px: usize,
    /// What a prediction's score is (the metric ranks by it).
    pub score: CnnScore,
}

/// The score a CNN prediction is ranked by, read at its peak pixel; each is
/// in [0, 1]. Which peaks become predictions does not depend on it (that is
/// the centre score against `score_floor`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CnnScore {
    /// The centre score map (sigmoid): how sure the network is that a QD's
    /// centroid is nearest this pixel.
    Heatmap,
    /// The within-1-px head (sigmoid): the network's probability that this
    /// localisation lies within 1 px of a centroid, trained against the
    /// realised error of its own offsets.
    #[serde(rename = "within_1px")]
    Within1px,
    /// The centre score times the probability, under the σ maps, that the
    /// error is within 1 px: `1 − exp(−1 / (2 σx σy))` (exact for σx = σy,
    /// the isotropic approximation otherwise).
    #[serde(rename = "gaussian_within_1px")]
    GaussianWithin1px,
}

impl Default for CnnArchitecture {
    fn default() -> Self {
        Self {
            channels: 32,
            dilations: vec![1, 1, 2, 4, 2, 1],
            batch_norm: true,
            edge_channel: true,
            peak_radius_px: 2,
            refine_radius_px: 0,
            score: CnnScore::Heatmap,
        }
    }
}

/// Largest accepted channel count and dilation: far beyond anything useful
/// on frames of this kind, low enough to catch typos before allocating.
const MAX_CHANNELS: usize = 1024;
const MAX_DILATION: usize = 256;
/// Most hidden layers (entries of `dilations`).
const MAX_LAYERS: usize = 64;

impl CnnArchitecture {
    /// Checks every field; the error names the field and says what is
    /// allowed.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.channels == 0 || self.channels > MAX_CHANNELS {
            return Err(FieldError::new(
                "architecture.channels",
                format!("must be in 1..={MAX_CHANNELS}, got {}", self.channels),
            ));
        }
        if self.dilations.is_empty() {
            return Err(FieldError::new(
                "architecture.dilations",
                "needs at least one layer",
            ));
        }
        if self.dilations.len() > MAX_LAYERS {
            return Err(FieldError::new(
                "architecture.dilations",
                format!("at most {MAX_LAYERS} layers, got {}", self.dilations.len()),
            ));
        }
        if let Some(bad) = self.dilations.iter().find(|&&d| d == 0 || d > MAX_DILATION) {
            return Err(FieldError::new(
                "architecture.dilations",
                format!("each must be in 1..={MAX_DILATION}, got {bad}"),
            ));
        }
        if self.peak_radius_px == 0 || self.peak_radius_px > 64 {
            return Err(FieldError::new(
                "architecture.peak_radius_px",
                format!("must be in 1..=64, got {}", self.peak_radius_px),
            ));
        }
        if self.refine_radius_px > 16 {
            return Err(FieldError::new(
                "architecture.refine_radius_px",
                format!("must be in 0..=16, got {}", self.refine_radius_px),
            ));
        }
        Ok(())
    }

    /// Number of input channels (the normalised frame, plus the edge channel).
    pub fn input_channels(&self) -> usize {
        if self.edge_channel { 2 } else { 1 }
    }

    /// Receptive field of an output pixel, in pixels across.
    pub fn receptive_field_px(&self) -> usize {
        1 + 2 * self.dilations.iter().sum::<usize>()
    }
}

/// How to train. Every field has a default; see [`train`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainingSettings {
    /// Passes over the training data (fixed training split plus the fresh
    /// frames of that epoch).
    pub epochs: usize,
    /// Frames per optimiser step.
    pub batch_size: usize,
    /// Adam's (peak) learning rate.
    pub learning_rate: f64,
    /// Decay the learning rate along a cosine from `learning_rate` at the
    /// first step to 0 after the last (else constant).
    pub cosine_decay: bool,
    /// Fraction of the given dataset's frames held out (seeded shuffle) to
    /// select the best epoch by validation AUC. 0 = no validation (the last
    /// epoch is kept); 1 = the whole dataset validates and training uses
    /// fresh frames only.
    pub validation_fraction: f64,
    /// Frames simulated anew for every epoch (0 = the fixed dataset only).
    /// Needs simulator parameters (`fresh_frames` of [`train`]).
    pub fresh_frames_per_epoch: usize,
    /// Lowest score a prediction may have (scores are in (0, 1)).
    pub score_floor: f64,
    /// Standard deviation of the Gaussian score target, pixels.
    pub heatmap_sigma_px: f64,
    /// Offsets are supervised within this Chebyshev radius of the pixel
    /// nearest the centroid (0 = that pixel only, as CenterNet).
    pub offset_radius_px: usize,
    /// Weight of the L1 offset loss against the focal score loss.
    pub offset_loss_weight: f64,
    /// Weight of the Gaussian negative log-likelihood that trains the σ
    /// maps on the offsets' realised error at each target centre's pixel
    /// (offsets not moved by it).
    pub sigma_loss_weight: f64,
    /// Weight of the binary cross-entropy that trains the within-1-px head
    /// on whether each pixel's localisation lands within 1 px of a centroid
    /// (offsets not moved by it).
    pub within_loss_weight: f64,
}

impl Default for TrainingSettings {
    fn default() -> Self {
        Self {
            epochs: 20,
            batch_size: 64,
            learning_rate: 2e-3,
            cosine_decay: true,
            validation_fraction: 0.1,
            fresh_frames_per_epoch: 0,
            score_floor: 0.02,
            heatmap_sigma_px: 1.0,
            offset_radius_px: 1,
            offset_loss_weight: 1.0,
            sigma_loss_weight: 1.0,
            within_loss_weight: 1.0,
        }
    }
}

impl TrainingSettings {
    /// How many of a `frames`-frame training set are held out for
    /// validation: `validation_fraction` of them, rounded to nearest.
    pub fn held_out_frames(&self, frames: usize) -> usize {
        ((frames as f64) * self.validation_fraction).round() as usize
    }

    /// Checks every field; the error names the field and says what is
    /// allowed.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.epochs == 0 {
            return Err(FieldError::new("training.epochs", "must be ≥ 1, got 0"));
        }
        if self.batch_size == 0 || self.batch_size > crate::limits::MAX_FRAMES {
            return Err(FieldError::new(
                "training.batch_size",
                format!(
                    "must be between 1 and {}, got {}",
                    crate::limits::MAX_FRAMES,
                    self.batch_size
                ),
            ));
        }
        if self.fresh_frames_per_epoch > 0 {
            crate::limits::check_frame_count(
                "training.fresh_frames_per_epoch",
                self.fresh_frames_per_epoch as u64,
            )?;
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return Err(FieldError::new(
                "training.learning_rate",
                format!("must be a finite number > 0, got {}", self.learning_rate),
            ));
        }
        if !(0.0..=1.0).contains(&self.validation_fraction) {
            return Err(FieldError::new(
                "training.validation_fraction",
                format!("must be in [0, 1], got {}", self.validation_fraction),
            ));
        }
        if !(self.score_floor.is_finite() && (0.0..1.0).contains(&self.score_floor)) {
            return Err(FieldError::new(
                "training.score_floor",
                format!("must be in [0, 1), got {}", self.score_floor),
            ));
        }
        if !(self.heatmap_sigma_px.is_finite() && self.heatmap_sigma_px > 0.0) {
            return Err(FieldError::new(
                "training.heatmap_sigma_px",
                format!("must be a finite number > 0, got {}", self.heatmap_sigma_px),
            ));
        }
        crate::limits::check_feature_px("training.heatmap_sigma_px", self.heatmap_sigma_px)?;
        if self.offset_radius_px > 16 {
            return Err(FieldError::new(
                "training.offset_radius_px",
                format!("must be in 0..=16, got {}", self.offset_radius_px),
            ));
        }
        for (field, weight) in [
            ("training.offset_loss_weight", self.offset_loss_weight),
            ("training.sigma_loss_weight", self.sigma_loss_weight),
            ("training.within_loss_weight", self.within_loss_weight),
        ] {
            if !(weight.is_finite() && weight >= 0.0) {
                return Err(FieldError::new(
                    field,
                    format!("must be a finite number ≥ 0, got {weight}"),
                ));
            }
        }
        Ok(())
    }
}

/// What happened in one epoch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpochRecord {
    /// 1-based epoch number.
    pub epoch: usize,
    /// Frames trained on in this epoch.
    pub samples: usize,
    /// Learning rate of the epoch's first step.
    pub learning_rate: f64,
    /// Mean total loss over the epoch's steps.
    pub loss: f64,
    /// Mean focal score loss.
    pub score_loss: f64,
    /// Mean L1 offset loss (pixels).
    pub offset_loss: f64,
    /// Mean Gaussian negative log-likelihood of the σ maps (per target
    /// centre and axis, without the constant ½ ln 2π).
    pub sigma_loss: f64,
    /// Mean within-1-px cross-entropy (per target centre).
    pub within_loss: f64,
    /// Validation AUC at ε = 1, 2, 3 px (empty without validation).
    pub validation_auc: Vec<f64>,
    /// Mean of `validation_auc`, the selection criterion (None without validation).
    pub validation_mean_auc: Option<f64>,
}

/// The history of a training run. Holds no wall-clock times, so that the
/// same inputs always give the same bytes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainingRecord {
    /// The seed the run was given.
    pub seed: u64,
    /// Frames of the fixed dataset trained on.
    pub training_frames: usize,
    /// Frames validated on after each epoch: split off the training set, or
    /// a validation set of their own (a cross-validation's held-out fold).
    pub validation_frames: usize,
    pub epochs: Vec<EpochRecord>,
    /// The 1-based epoch whose weights were kept (best validation mean
    /// AUC, earliest on ties; the last epoch without validation).
    pub best_epoch: usize,
}

/// A trained localiser: the network (on burn's flex CPU device), its
/// architecture, the settings it was trained with and its training record.
#[derive(Debug, Clone)]
pub struct TrainedCnn {
    pub(crate) net: model::Net,
    pub architecture: CnnArchitecture,
    pub settings: TrainingSettings,
    pub record: TrainingRecord,
}

/// Everything but the weights, as stored in the self-describing blob.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct BlobHeader {
    format: String,
    architecture: CnnArchitecture,
    settings: TrainingSettings,
    record: TrainingRecord,
}

/// `config.json` of a saved model folder.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SavedConfig {
    format: String,
    architecture: CnnArchitecture,
    settings: TrainingSettings,
}

/// Names the serialisation format; bump on any incompatible change.
pub const FORMAT: &str = "scanloc-cnn/2";
/// Version of the training and inference code, part of the content key of
/// every model and prediction in the registry: bump it whenever a change
/// would alter trained weights (initialisation, batching, loss, optimiser,
/// data augmentation, selection) or the predictions made from them
/// (decoding, peak suppression), so cached models made by the old code are
/// not reused. Kept apart from [`FORMAT`], which only names the encoding.
pub const CODE_VERSION: &str = "scanloc-cnn/2";
/// First bytes of a [`TrainedCnn::to_bytes`] blob.
const MAGIC: &[u8] = b"SCANLOC-CNN\n";
/// File names inside a saved model folder.
pub const WEIGHTS_FILE: &str = "model.bpk";
pub const CONFIG_FILE: &str = "config.json";
pub const TRAINING_FILE: &str = "training.json";

/// The device models run on: burn's pure-Rust CPU backend.
pub fn inference_device() -> Device {
    Device::flex()
}

/// Checks that a model can be saved at `dir`: a folder or a path that
/// does not exist yet (not a file, which a model folder would replace).
/// Checked before training, so a long training does not end in an
/// unwritable destination.
pub fn check_model_destination(dir: &Path) -> anyhow::Result<()> {
    match std::fs::metadata(dir) {
        Ok(metadata) if !metadata.is_dir() => crate::bail_input!(
            "{}: exists and is not a folder; a model is saved as a folder (give a new path or a folder)",
            dir.display()
        ),
        _ => Ok(()),
    }
}

impl TrainedCnn {
    fn check_format(format: &str, source: &str) -> anyhow::Result<()> {
        if format != FORMAT {
            crate::bail_input!(
                "{source}: model format {format:?} is not supported (expected {FORMAT:?})"
            );
        }
        Ok(())
    }

    fn from_parts(
        architecture: CnnArchitecture,
        settings: TrainingSettings,
        record: TrainingRecord,
        weights: ModuleRecord,
        source: &str,
    ) -> anyhow::Result<Self> {
        architecture
            .validate()
            .map_err(|e| input_error(format!("{source}: architecture: {e}")))?;
        settings
            .validate()
            .map_err(|e| input_error(format!("{source}: training settings: {e}")))?;
        let device = inference_device();
        let net = model::Net::new(&architecture, 0, &device)
            .try_load_record(weights)
            .map_err(|e| {
                input_error(format!(
                    "{source}: weights do not fit the architecture: {e}"
                ))
            })?;
        Ok(Self {
            net,
            architecture,
            settings,
            record,
        })
    }

    /// The network's weights in burn's burnpack record format.
    fn weight_bytes(&self) -> anyhow::Result<burn::tensor::Bytes> {
        self.net
            .clone()
            .into_record()
            .into_bytes()
            .map_err(|e| anyhow::anyhow!("serialising CNN weights: {e}"))
    }

    /// One self-describing blob: magic, the JSON header length (u64 LE),
    /// the JSON header (format, architecture, settings, training record),
    /// then the weights in burn's burnpack format. Deterministic: the same
    /// model always gives the same bytes.
    pub fn to_bytes(&self) -> anyhow::Result<Vec<u8>> {
        let header = BlobHeader {
            format: FORMAT.to_string(),
            architecture: self.architecture.clone(),
            settings: self.settings.clone(),
            record: self.record.clone(),
        };
        let header = serde_json::to_vec(&header)?;
        let weights = self.weight_bytes()?;
        let mut out = Vec::with_capacity(MAGIC.len() + 8 + header.len() + weights.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        out.extend_from_slice(&weights);
        Ok(out)
    }

    /// Reads a blob written by [`to_bytes`](Self::to_bytes).
    pub fn from_bytes(bytes: &[u8]) -> anyhow::Result<Self> {
        let source = "CNN model blob";
        let rest = bytes
            .strip_prefix(MAGIC)
            .ok_or_else(|| input_error(format!("{source}: not a scanloc CNN model (bad magic)")))?;
        if rest.len() < 8 {
            crate::bail_input!("{source}: truncated header");
        }
        let header_len = u64::from_le_bytes(rest[..8].try_into()?) as usize;
        let rest = &rest[8..];
        if rest.len() < header_len {
            crate::bail_input!("{source}: truncated header");
        }
        let header: BlobHeader = serde_json::from_slice(&rest[..header_len])
            .map_err(|e| input_error(format!("{source}: header: {e}")))?;
        Self::check_format(&header.format, source)?;
        let weights = ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(
            rest[header_len..].to_vec(),
        ))
        .map_err(|e| input_error(format!("{source}: weights: {e}")))?;
        Self::from_parts(
            header.architecture,
            header.settings,
            header.record,
            weights,
            source,
        )
    }

    /// Saves into folder `dir` (created if missing): the weights in burn's
    /// burnpack record format (`model.bpk`), `config.json` (format,
    /// architecture, settings) and `training.json` (the training record).
    /// Each file is written atomically. `dir` must be a folder or a new
    /// path (see [`check_model_destination`]).
    pub fn save(&self, dir: &Path) -> anyhow::Result<()> {
        check_model_destination(dir)?;
        std::fs::create_dir_all(dir)
            .map_err(|e| input_error(format!("{}: cannot create: {e}", dir.display())))?;
        let config = SavedConfig {
            format: FORMAT.to_string(),
            architecture: self.architecture.clone(),
            settings: self.settings.clone(),
        };
        let weights = self.weight_bytes()?;
        crate::io::write_atomically(&dir.join(WEIGHTS_FILE), |w| Ok(w.write_all(&weights)?))?;
        crate::io::write_atomically(&dir.join(CONFIG_FILE), |w| {
            serde_json::to_writer_pretty(&mut *w, &config)?;
            Ok(w.write_all(b"\n")?)
        })?;
        crate::io::write_atomically(&dir.join(TRAINING_FILE), |w| {
            serde_json::to_writer_pretty(&mut *w, &self.record)?;
            Ok(w.write_all(b"\n")?)
        })?;
        Ok(())
    }

    /// Loads a folder written by [`save`](Self::save).
    pub fn load(dir: &Path) -> anyhow::Result<Self> {
        let read = |name: &str| {
            let path = dir.join(name);
            std::fs::read(&path)
                .map_err(|e| input_error(format!("{}: cannot read: {e}", path.display())))
        };
        let config_path = dir.join(CONFIG_FILE);
        let config: SavedConfig = serde_json::from_slice(&read(CONFIG_FILE)?)
            .map_err(|e| input_error(format!("{}: {e}", config_path.display())))?;
        let source = config_path.display().to_string();
        Self::check_format(&config.format, &source)?;
        let training_path = dir.join(TRAINING_FILE);
        let record: TrainingRecord = serde_json::from_slice(&read(TRAINING_FILE)?)
            .map_err(|e| input_error(format!("{}: {e}", training_path.display())))?;
        let weights_path = dir.join(WEIGHTS_FILE);
        let weights =
            ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(read(WEIGHTS_FILE)?))
                .map_err(|e| input_error(format!("{}: {e}", weights_path.display())))?;
        Self::from_parts(
            config.architecture,
            config.settings,
            record,
            weights,
            &weights_path.display().to_string(),
        )
    }
}

use std::io::Write as _;
