//! The CNN localiser (detector `cnn`, `docs/cnn.md`): a small fully
//! convolutional network, trained on simulated frames, that outputs a
//! per-pixel centre score and a sub-pixel offset to the QD's *trajectory
//! centroid* (the label of the simulator's ground truth), not to the
//! brightest spot.
//!
//! Layout (as burn's mnist example): `config.rs` the settings a manifest
//! states, `model_folder.rs` a trained model as stored (blob or folder),
//! [`model`] the network, [`data`] frames
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

mod config;
pub(crate) mod data;
mod ensemble;
pub mod inference;
pub(crate) mod kernels;
mod loss;
pub mod model;
mod model_folder;
mod streams;
mod teacher;
pub mod training;

use burn::prelude::Device;

pub use config::{
    CnnArchitecture, CnnHead, CnnScore, MAX_MEMBERS, TrainingSettings, validate_recipe,
};
pub use model_folder::{
    CONFIG_FILE, EpochRecord, TRAINING_FILE, TrainedCnn, TrainingRecord, WEIGHTS_FILE,
    check_model_destination, is_model_file, training_file, weights_file,
};
pub use training::{ValidationScore, ValidationSet, train, train_selecting_on};

/// Names the serialisation format; bump on any incompatible change.
pub(crate) const FORMAT: &str = "scanloc-cnn/2";
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
pub(crate) const TEACHER_CODE_VERSION: &str = "scanloc-cnn/3+scanloc-likelihood/2";
/// The code version of a categorical head's model trained with a teacher:
/// [`TEACHER_CODE_VERSION`] and `posterior/1`, the teacher's whole
/// posterior over the pixels as the softmax's target (before it, such a
/// model learnt the pixel of the posterior mean, as a peaks head does).
pub(crate) const CATEGORICAL_TEACHER_CODE_VERSION: &str =
    "scanloc-cnn/3+scanloc-likelihood/2+posterior/1";

/// The code version of a model of `head` trained with a teacher
/// (`training.teacher_particles` > 0).
pub(crate) fn teacher_code_version(head: CnnHead) -> &'static str {
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
pub(crate) const DECODE_VERSION: &str = "scanloc-cnn/3+decode/1";

/// The device models run on: burn's pure-Rust CPU backend.
pub(crate) fn inference_device() -> Device {
    Device::flex()
}

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
