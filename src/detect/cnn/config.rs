//! The CNN's settings as a manifest states them: the network's shape
//! ([`CnnArchitecture`], its head and score) and its training recipe
//! ([`TrainingSettings`]), each checked field by field.

use serde::{Deserialize, Serialize};

use crate::detect::candidates::MAX_CANDIDATES;
use crate::error::FieldError;

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
        self.check_schedule()?;
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
        self.check_teacher()?;
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

    /// Checks the epochs, batches and frames of the training, and its
    /// learning rate.
    fn check_schedule(&self) -> Result<(), FieldError> {
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
        Ok(())
    }

    /// Checks the teacher's particles and which frames it teaches.
    fn check_teacher(&self) -> Result<(), FieldError> {
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
        Ok(())
    }
}
