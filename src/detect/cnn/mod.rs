//! The CNN localiser (detector `cnn`, `docs/cnn.md`): a small fully
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
//!
//! A model may be a deep ensemble (`training.members` > 1): several
//! networks trained from seeds of their own, whose output maps are
//! combined per pixel before the peaks are found (docs/cnn.md,
//! "Ensembles"); a single network is stored and predicts exactly as before
//! ensembles existed.

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

use crate::detect::candidates::MAX_CANDIDATES;
use crate::error::{FieldError, input_error};
pub use training::{ValidationScore, ValidationSet, train, train_selecting_on};

/// The network's shape. Serialised with the model; every field has a
/// default: the network `bench train` compares with PyTorch. The paper
/// manifest trains two more layers (docs/cnn.md, "Architecture").
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
    /// What a prediction's score is (the metric ranks by it; with the
    /// categorical head every guess is scored by its posterior mass
    /// instead).
    pub score: CnnScore,
    /// How the score map is trained and read: per-pixel peaks (the
    /// default) or one categorical distribution over the frame's pixels
    /// decoded into a ranked list of guesses (docs/cnn.md, "Candidates").
    /// Left out of the serialised architecture when `peaks`, so models
    /// trained before it existed keep their bytes and content keys.
    #[serde(default, skip_serializing_if = "CnnHead::is_peaks")]
    pub head: CnnHead,
    /// With the categorical head: guesses per frame (1..=
    /// [`MAX_CANDIDATES`]), from the greedy disc cover of the posterior
    /// the head gives ([`crate::detect::candidates`]), each scored by the
    /// mass it newly covers and ranked in [`crate::types::Prediction::candidate`].
    /// Left out of the serialised architecture when 1.
    #[serde(
        default = "crate::detect::candidates::one_candidate",
        skip_serializing_if = "crate::detect::candidates::is_one_candidate"
    )]
    pub max_candidates: usize,
    /// With the categorical head: radius (px, > 0) of the cover's discs,
    /// the ε the list is placed for. Left out when 1.
    #[serde(
        default = "crate::detect::candidates::unit_radius",
        skip_serializing_if = "crate::detect::candidates::is_unit_radius"
    )]
    pub candidate_radius_px: f64,
}

/// How the CNN's score map is trained and decoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CnnHead {
    /// A sigmoid per pixel (focal loss against a Gaussian around each
    /// centroid); every local maximum above the score floor is a
    /// localisation. Any number of QDs per frame.
    #[default]
    Peaks,
    /// A softmax over the frame's pixels: the probability that the
    /// centroid is nearest each pixel (cross-entropy against the pixel
    /// nearest the centroid), each pixel's mass placed at pixel + offset
    /// and spread by the σ maps ([`inference::categorical_guesses`]).
    /// That posterior is decoded by the greedy disc cover into up to
    /// `max_candidates` ranked guesses, each scored by its mass. Frames of
    /// exactly one QD (the paper's datasets); training refuses others.
    Categorical,
}

impl CnnHead {
    fn is_peaks(&self) -> bool {
        *self == CnnHead::Peaks
    }
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
            head: CnnHead::Peaks,
            max_candidates: 1,
            candidate_radius_px: 1.0,
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
        if !(1..=MAX_CANDIDATES).contains(&self.max_candidates) {
            return Err(FieldError::new(
                "architecture.max_candidates",
                format!(
                    "must be in 1..={MAX_CANDIDATES}, got {}",
                    self.max_candidates
                ),
            ));
        }
        if self.head == CnnHead::Peaks && self.max_candidates != 1 {
            return Err(FieldError::new(
                "architecture.max_candidates",
                "needs `head: categorical` (the peaks head gives one localisation per peak)",
            ));
        }
        if !(self.candidate_radius_px.is_finite() && self.candidate_radius_px > 0.0)
            || self.candidate_radius_px > 64.0
        {
            return Err(FieldError::new(
                "architecture.candidate_radius_px",
                format!(
                    "must be a number in (0, 64], got {}",
                    self.candidate_radius_px
                ),
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
    /// The first epoch whose network is validated and may be kept: the
    /// epochs before it train without being scored (with the cosine decay
    /// the best epoch comes late, and scoring the validation frames after
    /// every epoch costs time). 1 = every epoch. At most `epochs`. Left out
    /// of the serialised settings when 1, so models trained before it
    /// existed keep their bytes and content keys.
    #[serde(default = "first_epoch", skip_serializing_if = "is_first_epoch")]
    pub validate_from_epoch: usize,
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
    /// Networks of the deep ensemble (1..=[`MAX_MEMBERS`]), trained one
    /// after another from seeds of their own and averaged per pixel at
    /// inference (docs/cnn.md, "Ensembles"). Left out of the
    /// serialised settings when 1, so single-network models keep their
    /// bytes and content keys.
    #[serde(default = "one_member", skip_serializing_if = "is_one_member")]
    pub members: usize,
    /// 0: the score map and the offsets learn the true centroids. N > 0:
    /// on the fixed training frames that hold one QD a teacher, the
    /// likelihood detector with N particles per frame (computed once per
    /// training, under the training frames' own simulator parameters,
    /// their distributions of D, brightness and background as priors),
    /// replaces the truth: the peaks head's score map and offsets learn its
    /// posterior mean of the centroid, the categorical head's softmax its
    /// whole posterior over the pixels (its offsets and σ maps keep the
    /// truth). The within-1-px head still learns from the truth, and fresh
    /// frames keep their truth unless `teacher_fresh_frames` (docs/cnn.md,
    /// "Posterior targets"). Needs the simulator parameters of the training
    /// frames. Left out of the serialised settings when 0, so models
    /// trained without a teacher keep their bytes and content keys.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub teacher_particles: usize,
    /// With a teacher, also label every epoch's fresh frames that hold one
    /// QD with its posteriors (computed for each epoch's frames as
    /// they are simulated, from a seed of the member and the epoch): every
    /// sample the network learns from is taught, at the teacher's cost for
    /// `fresh_frames_per_epoch × epochs × members` more frames. Needs
    /// `teacher_particles` > 0 and `fresh_frames_per_epoch` > 0. Left out
    /// of the serialised settings when false.
    #[serde(default, skip_serializing_if = "is_false")]
    pub teacher_fresh_frames: bool,
}

fn first_epoch() -> usize {
    1
}

fn is_first_epoch(epoch: &usize) -> bool {
    *epoch == 1
}

fn is_zero(value: &usize) -> bool {
    *value == 0
}

fn is_false(value: &bool) -> bool {
    !*value
}

/// Most member networks of an ensemble: each costs a full training and a
/// forward pass per frame; averaging gains little beyond a handful.
pub const MAX_MEMBERS: usize = 16;

fn one_member() -> usize {
    1
}

fn is_one_member(members: &usize) -> bool {
    *members == 1
}

impl Default for TrainingSettings {
    fn default() -> Self {
        Self {
            epochs: 20,
            batch_size: 64,
            learning_rate: 2e-3,
            cosine_decay: true,
            validation_fraction: 0.1,
            validate_from_epoch: first_epoch(),
            fresh_frames_per_epoch: 0,
            score_floor: 0.02,
            heatmap_sigma_px: 1.0,
            offset_radius_px: 1,
            offset_loss_weight: 1.0,
            sigma_loss_weight: 1.0,
            within_loss_weight: 1.0,
            members: one_member(),
            teacher_particles: 0,
            teacher_fresh_frames: false,
        }
    }
}

/// Checks a recipe: the architecture's fields, the training settings'
/// fields, and what one asks of the other (the categorical head needs
/// offsets supervised at the centroid's pixel only, `offset_radius_px: 0`:
/// each pixel's offset is then the centroid given that it is nearest that
/// pixel, which is how the decoding reads it; a wider window would pull
/// every offset towards the posterior mean and merge the modes the list is
/// made of). The error names the field.
pub fn validate_recipe(
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
) -> Result<(), FieldError> {
    arch.validate()?;
    settings.validate()?;
    if arch.head == CnnHead::Categorical && settings.offset_radius_px != 0 {
        return Err(FieldError::new(
            "training.offset_radius_px",
            format!(
                "the categorical head needs 0 (offsets supervised at the centroid's pixel only), got {}",
                settings.offset_radius_px
            ),
        ));
    }
    Ok(())
}

impl TrainingSettings {
    /// How many of a `frames`-frame training set are held out for
    /// validation: `validation_fraction` of them, rounded to nearest.
    pub fn held_out_frames(&self, frames: usize) -> usize {
        ((frames as f64) * self.validation_fraction).round() as usize
    }

    /// Whether no frame of the given training set ever trains
    /// (`validation_fraction` 1: the set only selects the epoch, fresh
    /// frames train). A cross-validation keeps to this: its fold models
    /// train on fresh frames only too, selected on their held-out fold.
    pub fn trains_on_fresh_frames_only(&self) -> bool {
        self.validation_fraction == 1.0
    }

    /// Checks every field; the error names the field and says what is
    /// allowed.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.epochs == 0 {
            return Err(FieldError::new("training.epochs", "must be ≥ 1, got 0"));
        }
        if !(1..=self.epochs).contains(&self.validate_from_epoch) {
            return Err(FieldError::new(
                "training.validate_from_epoch",
                format!(
                    "must be between 1 and training.epochs ({}), got {}",
                    self.epochs, self.validate_from_epoch
                ),
            ));
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
        if !(1..=MAX_MEMBERS).contains(&self.members) {
            return Err(FieldError::new(
                "training.members",
                format!("must be in 1..={MAX_MEMBERS}, got {}", self.members),
            ));
        }
        if self.teacher_particles != 0
            && !(2..=crate::detect::likelihood::MAX_PARTICLES).contains(&self.teacher_particles)
        {
            return Err(FieldError::new(
                "training.teacher_particles",
                format!(
                    "must be 0 (no teacher) or between 2 and {}, got {}",
                    crate::detect::likelihood::MAX_PARTICLES,
                    self.teacher_particles
                ),
            ));
        }
        if self.teacher_fresh_frames {
            let missing = if self.teacher_particles == 0 {
                Some("there is no teacher (training.teacher_particles is 0)")
            } else if self.fresh_frames_per_epoch == 0 {
                Some("there are no fresh frames (training.fresh_frames_per_epoch is 0)")
            } else {
                None
            };
            if let Some(missing) = missing {
                return Err(FieldError::new(
                    "training.teacher_fresh_frames",
                    format!("cannot teach the fresh frames: {missing}"),
                ));
            }
        }
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
    /// Validation AUC at ε = 1, 2, 3 px (empty without validation frames
    /// and for epochs before `validate_from_epoch`).
    pub validation_auc: Vec<f64>,
    /// Mean of `validation_auc`, the selection criterion (None where it is
    /// empty).
    pub validation_mean_auc: Option<f64>,
}

/// The history of a training run. Holds no wall-clock times, so that the
/// same inputs always give the same bytes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainingRecord {
    /// The seed this network was trained from: the training seed for a
    /// single network and an ensemble's first member, a seed derived from
    /// it for the other members.
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

/// A trained localiser: its member networks (on burn's flex CPU device; one
/// unless `settings.members` > 1), its architecture, the settings it was
/// trained with and every member's training record.
#[derive(Debug, Clone)]
pub struct TrainedCnn {
    /// The member networks in member order, `settings.members` of them.
    pub(crate) nets: Vec<model::Net>,
    pub architecture: CnnArchitecture,
    pub settings: TrainingSettings,
    /// Member 1's training record (the only one of a single network).
    pub record: TrainingRecord,
    /// The training records of members 2, 3, … in order (empty for a
    /// single network).
    pub other_records: Vec<TrainingRecord>,
}

/// Everything but the weights, as stored in the self-describing blob.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct BlobHeader {
    format: String,
    architecture: CnnArchitecture,
    settings: TrainingSettings,
    record: TrainingRecord,
    /// Members 2, 3, …'s training records; absent for a single network,
    /// whose blob is unchanged by ensembles.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    other_records: Vec<TrainingRecord>,
    /// Byte length of each member's weights, in member order (the weights
    /// follow the header concatenated); absent for a single network, whose
    /// weights are the rest of the blob.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    weight_lengths: Vec<u64>,
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
/// data augmentation, selection, and the validation predictions the best
/// epoch is chosen by), so cached models made by the old code are not
/// reused. Kept apart from [`FORMAT`], which only names the encoding.
///
/// `scanloc-cnn/3`: the head's forward and backward passes and the loss's
/// reported sums moved from burn to the kernels' fixed summation order, so
/// a seed trains the same weights on every x86-64 CPU (before, burn's
/// reductions followed the CPU's vector width and caches).
pub const CODE_VERSION: &str = "scanloc-cnn/3";
/// The code version of a model trained with a teacher
/// (`training.teacher_particles` > 0): the training's and the likelihood
/// detector's ([`crate::detect::likelihood::CODE_VERSION`]), whose
/// predictions became its targets, so a change to either renews it.
pub const TEACHER_CODE_VERSION: &str = "scanloc-cnn/3+scanloc-likelihood/2";
/// The code version of a categorical head's model trained with a teacher:
/// [`TEACHER_CODE_VERSION`] and `posterior/1`, the teacher's whole
/// posterior over the pixels as the softmax's target (before it, such a
/// model learnt the pixel of the posterior mean, as a peaks head does).
pub const CATEGORICAL_TEACHER_CODE_VERSION: &str = "scanloc-cnn/3+scanloc-likelihood/2+posterior/1";

/// The code version of a model of `head` trained with a teacher
/// (`training.teacher_particles` > 0).
pub fn teacher_code_version(head: CnnHead) -> &'static str {
    match head {
        CnnHead::Peaks => TEACHER_CODE_VERSION,
        CnnHead::Categorical => CATEGORICAL_TEACHER_CODE_VERSION,
    }
}
/// Version of the decoding (output maps → predictions: peaks, positions,
/// scores, σ), the code version of every CNN prediction's content key:
/// bump its second part when a change alters predictions but not the
/// trained weights, so cached models stay valid while their predictions
/// are made anew. It names [`CODE_VERSION`] too, so a training change
/// also renews the predictions.
///
/// `decode/1`: σ from the within-1-px head (docs/cnn.md,
/// "Uncertainty"); before it, the predictions' key had [`CODE_VERSION`]
/// alone.
pub const DECODE_VERSION: &str = "scanloc-cnn/3+decode/1";
/// First bytes of a [`TrainedCnn::to_bytes`] blob.
const MAGIC: &[u8] = b"SCANLOC-CNN\n";
/// File names inside a saved model folder: member 1's weights and training
/// record (a single network's only ones; see [`weights_file`] and
/// [`training_file`] for the other members'), and the shared config.
pub const WEIGHTS_FILE: &str = "model.bpk";
pub const CONFIG_FILE: &str = "config.json";
pub const TRAINING_FILE: &str = "training.json";

/// The weights file of member `member` (1-based) in a model folder:
/// `model.bpk` for member 1, `model-2.bpk`, `model-3.bpk`, … for the others.
pub fn weights_file(member: usize) -> String {
    member_file(WEIGHTS_FILE, member)
}

/// The training record of member `member` (1-based) in a model folder:
/// `training.json` for member 1, `training-2.json`, … for the others.
pub fn training_file(member: usize) -> String {
    member_file(TRAINING_FILE, member)
}

/// `name` for member 1, `name` with `-{member}` before its extension for
/// the others.
fn member_file(name: &str, member: usize) -> String {
    if member == 1 {
        return name.to_string();
    }
    match name.rsplit_once('.') {
        Some((stem, extension)) => format!("{stem}-{member}.{extension}"),
        None => format!("{name}-{member}"),
    }
}

/// The device models run on: burn's pure-Rust CPU backend.
pub fn inference_device() -> Device {
    Device::flex()
}

/// Checks that a model can be saved at `dir`: a path that does not exist
/// yet, or a folder holding only the regular files of a model folder
/// ([`is_model_file`]); see [`PendingFolder`](crate::io::PendingFolder).
/// Checked before training, so a long training does not end in an
/// unwritable destination.
pub fn check_model_destination(dir: &Path) -> anyhow::Result<()> {
    crate::io::PendingFolder::check(dir, is_model_file)
}

/// Whether `name` is a file a model folder holds: `config.json`, and a
/// member's weights or training record ([`weights_file`],
/// [`training_file`]) for members 1 to [`MAX_MEMBERS`] (and one more, the
/// extra member [`TrainedCnn::load`] refuses).
pub fn is_model_file(name: &str) -> bool {
    name == CONFIG_FILE
        || (1..=MAX_MEMBERS + 1).any(|m| name == weights_file(m) || name == training_file(m))
}

/// One member as read from storage: its training record and weights, and
/// where the weights came from (for errors).
struct StoredMember {
    record: TrainingRecord,
    weights: ModuleRecord,
    source: String,
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

    /// Checks a stored model's architecture and settings (so the member
    /// count can be trusted before the members are read).
    fn check_description(
        architecture: &CnnArchitecture,
        settings: &TrainingSettings,
        source: &str,
    ) -> anyhow::Result<()> {
        architecture
            .validate()
            .map_err(|e| input_error(format!("{source}: architecture: {e}")))?;
        settings
            .validate()
            .map_err(|e| input_error(format!("{source}: training settings: {e}")))?;
        Ok(())
    }

    /// A model from its checked description and its members (as many as
    /// `settings.members`, which the callers ensure).
    fn from_parts(
        architecture: CnnArchitecture,
        settings: TrainingSettings,
        members: Vec<StoredMember>,
    ) -> anyhow::Result<Self> {
        let device = inference_device();
        let mut nets = Vec::with_capacity(members.len());
        let mut records = Vec::with_capacity(members.len());
        for member in members {
            let net = model::Net::new(&architecture, 0, &device)
                .try_load_record(member.weights)
                .map_err(|e| {
                    input_error(format!(
                        "{}: weights do not fit the architecture: {e}",
                        member.source
                    ))
                })?;
            nets.push(net);
            records.push(member.record);
        }
        Self::from_members(architecture, settings, nets, records)
    }

    /// A model from its member networks and their training records, both
    /// in member order: member 1's record becomes [`record`](Self::record),
    /// the others [`other_records`](Self::other_records).
    pub(crate) fn from_members(
        architecture: CnnArchitecture,
        settings: TrainingSettings,
        nets: Vec<model::Net>,
        records: Vec<TrainingRecord>,
    ) -> anyhow::Result<Self> {
        let mut records = records.into_iter();
        let record = records
            .next()
            .ok_or_else(|| input_error("CNN model: holds no member network"))?;
        Ok(Self {
            nets,
            architecture,
            settings,
            record,
            other_records: records.collect(),
        })
    }

    /// How many member networks the model averages (1 for a single network).
    pub fn members(&self) -> usize {
        self.nets.len()
    }

    /// Every member's training record, in member order.
    pub fn records(&self) -> impl Iterator<Item = &TrainingRecord> {
        std::iter::once(&self.record).chain(&self.other_records)
    }

    /// Member `index` (0-based) as a model of its own: its network and
    /// training record, the same architecture and settings but for
    /// `members` = 1. `None` past the last member. For looking at one
    /// member's output beside the ensemble's.
    pub fn member(&self, index: usize) -> Option<TrainedCnn> {
        let net = self.nets.get(index)?.clone();
        let record = self.records().nth(index)?.clone();
        Some(TrainedCnn {
            nets: vec![net],
            architecture: self.architecture.clone(),
            settings: TrainingSettings {
                members: 1,
                ..self.settings.clone()
            },
            record,
            other_records: Vec::new(),
        })
    }

    /// Each member's weights in burn's burnpack record format, in member
    /// order.
    fn weight_bytes(&self) -> anyhow::Result<Vec<burn::tensor::Bytes>> {
        self.nets
            .iter()
            .map(|net| {
                net.clone()
                    .into_record()
                    .into_bytes()
                    .map_err(|e| anyhow::anyhow!("serialising CNN weights: {e}"))
            })
            .collect()
    }

    /// One self-describing blob: magic, the JSON header length (u64 LE),
    /// the JSON header (format, architecture, settings, training record;
    /// for an ensemble also the other members' records and every member's
    /// weight length), then the weights in burn's burnpack format (the
    /// members' concatenated in member order). Deterministic: the same
    /// model always gives the same bytes.
    pub fn to_bytes(&self) -> anyhow::Result<Vec<u8>> {
        let weights = self.weight_bytes()?;
        let weight_lengths = if weights.len() > 1 {
            weights.iter().map(|w| w.len() as u64).collect()
        } else {
            Vec::new()
        };
        let header = BlobHeader {
            format: FORMAT.to_string(),
            architecture: self.architecture.clone(),
            settings: self.settings.clone(),
            record: self.record.clone(),
            other_records: self.other_records.clone(),
            weight_lengths,
        };
        let header = serde_json::to_vec(&header)?;
        let weights_len: usize = weights.iter().map(|w| w.len()).sum();
        let mut out = Vec::with_capacity(MAGIC.len() + 8 + header.len() + weights_len);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        for member in &weights {
            out.extend_from_slice(member);
        }
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
        Self::check_description(&header.architecture, &header.settings, source)?;
        let weights = &rest[header_len..];
        let members = header.settings.members;
        // A single network's weights are the rest of the blob; an
        // ensemble's header says where each member's end.
        let lengths = if members == 1 {
            vec![weights.len() as u64]
        } else {
            header.weight_lengths.clone()
        };
        let counts_agree = lengths.len() == members
            && header.other_records.len() == members - 1
            && (members > 1 || header.weight_lengths.is_empty());
        if !counts_agree {
            crate::bail_input!(
                "{source}: header: training.members is {members} but the blob holds {} member records and {} weight lengths",
                1 + header.other_records.len(),
                header.weight_lengths.len()
            );
        }
        let total = lengths
            .iter()
            .try_fold(0u64, |sum, &len| sum.checked_add(len))
            .filter(|&sum| sum == weights.len() as u64);
        if total.is_none() {
            crate::bail_input!(
                "{source}: the member weight lengths do not add up to the {} bytes of weights",
                weights.len()
            );
        }
        let records = std::iter::once(header.record).chain(header.other_records);
        let mut start = 0usize;
        let mut stored = Vec::with_capacity(members);
        for (index, (record, &len)) in records.zip(&lengths).enumerate() {
            let end = start + len as usize;
            let source = if members > 1 {
                format!("{source} (member {})", index + 1)
            } else {
                source.to_string()
            };
            let weights = ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(
                weights[start..end].to_vec(),
            ))
            .map_err(|e| input_error(format!("{source}: weights: {e}")))?;
            stored.push(StoredMember {
                record,
                weights,
                source,
            });
            start = end;
        }
        Self::from_parts(header.architecture, header.settings, stored)
    }

    /// Saves into folder `dir`: each member's weights in burn's burnpack
    /// record format and its training record ([`weights_file`],
    /// [`training_file`]: `model.bpk` and `training.json` for member 1,
    /// `model-2.bpk` and `training-2.json` for member 2, …) and
    /// `config.json` (format, architecture, settings). The folder is
    /// written whole or not at all and replaces a model folder there
    /// before; `dir` must be a new path or such a folder (see
    /// [`check_model_destination`] and
    /// [`PendingFolder`](crate::io::PendingFolder)).
    pub fn save(&self, dir: &Path) -> anyhow::Result<()> {
        let folder = crate::io::PendingFolder::create(dir, is_model_file)?;
        let config = SavedConfig {
            format: FORMAT.to_string(),
            architecture: self.architecture.clone(),
            settings: self.settings.clone(),
        };
        let weights = self.weight_bytes()?;
        for (index, member) in weights.iter().enumerate() {
            crate::io::write_atomically(&folder.file(&weights_file(index + 1)), |w| {
                Ok(w.write_all(member)?)
            })?;
        }
        crate::io::write_atomically(&folder.file(CONFIG_FILE), |w| {
            serde_json::to_writer_pretty(&mut *w, &config)?;
            Ok(w.write_all(b"\n")?)
        })?;
        for (index, record) in self.records().enumerate() {
            crate::io::write_atomically(&folder.file(&training_file(index + 1)), |w| {
                serde_json::to_writer_pretty(&mut *w, record)?;
                Ok(w.write_all(b"\n")?)
            })?;
        }
        folder.commit()
    }

    /// Loads a folder written by [`save`](Self::save). Every member that
    /// `config.json`'s `training.members` names must be there, and no more.
    pub fn load(dir: &Path) -> anyhow::Result<Self> {
        let read = |path: &Path| {
            std::fs::read(path)
                .map_err(|e| input_error(format!("{}: cannot read: {e}", path.display())))
        };
        let config_path = dir.join(CONFIG_FILE);
        let config: SavedConfig = serde_json::from_slice(&read(&config_path)?)
            .map_err(|e| input_error(format!("{}: {e}", config_path.display())))?;
        let source = config_path.display().to_string();
        Self::check_format(&config.format, &source)?;
        Self::check_description(&config.architecture, &config.settings, &source)?;
        let members = config.settings.members;
        let mut stored = Vec::with_capacity(members);
        for member in 1..=members {
            let training_path = dir.join(training_file(member));
            let record: TrainingRecord = serde_json::from_slice(&read(&training_path)?)
                .map_err(|e| input_error(format!("{}: {e}", training_path.display())))?;
            let weights_path = dir.join(weights_file(member));
            let weights =
                ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(read(&weights_path)?))
                    .map_err(|e| input_error(format!("{}: {e}", weights_path.display())))?;
            stored.push(StoredMember {
                record,
                weights,
                source: weights_path.display().to_string(),
            });
        }
        let extra = dir.join(weights_file(members + 1));
        if extra.exists() {
            crate::bail_input!(
                "{}: one member more than the {members} that {}'s training.members names",
                extra.display(),
                config_path.display()
            );
        }
        Self::from_parts(config.architecture, config.settings, stored)
    }
}

use std::io::Write as _;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_teachers_code_version_names_both_codes_and_no_teacher_leaves_the_settings_as_they_were() {
        // A bump of either version must renew the models trained with a
        // teacher: the constant is written out, so this test says when it
        // has fallen behind.
        assert_eq!(
            TEACHER_CODE_VERSION,
            format!("{CODE_VERSION}+{}", crate::detect::likelihood::CODE_VERSION)
        );
        assert_eq!(
            CATEGORICAL_TEACHER_CODE_VERSION,
            format!("{TEACHER_CODE_VERSION}+posterior/1")
        );
        assert_eq!(
            teacher_code_version(CnnHead::Categorical),
            CATEGORICAL_TEACHER_CODE_VERSION
        );
        assert_eq!(teacher_code_version(CnnHead::Peaks), TEACHER_CODE_VERSION);
        let json = serde_json::to_string(&TrainingSettings::default()).unwrap();
        assert!(!json.contains("teacher"), "{json}");
        let taught = TrainingSettings {
            teacher_particles: 2000,
            ..TrainingSettings::default()
        };
        let json = serde_json::to_string(&taught).unwrap();
        assert!(json.contains("\"teacher_particles\":2000"), "{json}");
        assert!(!json.contains("teacher_fresh_frames"), "{json}");
        assert_eq!(
            serde_json::from_str::<TrainingSettings>(&json).unwrap(),
            taught
        );
        let all_taught = TrainingSettings {
            teacher_fresh_frames: true,
            ..taught
        };
        let json = serde_json::to_string(&all_taught).unwrap();
        assert!(json.contains("\"teacher_fresh_frames\":true"), "{json}");
        assert_eq!(
            serde_json::from_str::<TrainingSettings>(&json).unwrap(),
            all_taught
        );
    }

    #[test]
    fn a_single_network_serialises_without_a_member_count() {
        let single = serde_json::to_string(&TrainingSettings::default()).unwrap();
        assert!(!single.contains("members"), "{single}");
        let parsed: TrainingSettings = serde_json::from_str(&single).unwrap();
        assert_eq!(parsed.members, 1);
        let ensemble = TrainingSettings {
            members: 3,
            ..TrainingSettings::default()
        };
        let text = serde_json::to_string(&ensemble).unwrap();
        assert!(text.contains("\"members\":3"), "{text}");
        assert_eq!(
            serde_json::from_str::<TrainingSettings>(&text).unwrap(),
            ensemble
        );
    }

    #[test]
    fn member_counts_outside_1_to_16_are_refused_naming_the_field() {
        for members in [0, MAX_MEMBERS + 1] {
            let settings = TrainingSettings {
                members,
                ..TrainingSettings::default()
            };
            let error = settings.validate().unwrap_err();
            assert_eq!(error.field(), "training.members", "{error}");
        }
        for members in [1, 2, MAX_MEMBERS] {
            let settings = TrainingSettings {
                members,
                ..TrainingSettings::default()
            };
            assert!(settings.validate().is_ok());
        }
    }

    #[test]
    fn member_files_are_numbered_from_the_second() {
        assert_eq!(weights_file(1), WEIGHTS_FILE);
        assert_eq!(training_file(1), TRAINING_FILE);
        assert_eq!(weights_file(2), "model-2.bpk");
        assert_eq!(training_file(12), "training-12.json");
    }
}
