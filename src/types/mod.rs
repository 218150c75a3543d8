//! The data every layer shares: frame stacks, ground truth and predictions,
//! the kinds of detector, per-frame parameter distributions and seed
//! derivation.
//!
//! A leaf of the crate: it imports nothing of scanloc but [`crate::error`],
//! so the simulator, the detectors, the metric and the file formats can all
//! use these types without importing each other. Coordinates follow TrackPy:
//! `x` is the column, `y` the row, pixel centres at integers.

pub mod detector_kind;
pub mod distribution;
pub mod frames;
pub mod names;
pub mod prediction;
pub mod seed;
pub mod tracks;
pub mod truth;

pub use detector_kind::DetectorKind;
pub use distribution::{Distribution, RandomDistribution};
pub use frames::{FrameStack, Frames, RealFrameStack, Recording};
pub use prediction::{LocalisationSigma, Prediction};
pub use seed::derive_seed;
pub use tracks::{Track, TrackPoint};
pub use truth::{Dataset, RecordingTruthRow, TruthRow};
