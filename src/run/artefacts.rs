//! How artefacts are stored as blobs, and read back.
//!
//! - dataset: `frames.npy` (uint16, or uint32 if a count needs it; shape
//!   `(n, H, W)`, the same `.npy` as `scanloc simulate` writes, so numpy can
//!   open a blob directly) and `truth.csv` (the truth CSV of `simulate`).
//! - model: `model.bin`, the detector's own serialisation.
//! - predictions: `predictions.csv`, `frame,x,y,score`, with
//!   `sigma_x,sigma_y` before `score` when the detector estimates its
//!   error (the predictions CSV of `locate`; floats in Rust's shortest round-trip form, so reading
//!   gives back the same bits).
//! - evaluation: `score.json`, the metric's [`Score`] (with curves if the
//!   manifest keeps them).
//! - recording (a dataset): `frames.npy` as a dataset's and `truth.csv`,
//!   the recording truth of `scanloc simulate-recording` (one row per QD
//!   per frame, with a `qd` column).
//! - tracks (predictions of a tracking pipeline): `predictions.csv`, the
//!   tracks table (`frame,x,y[,sigma_x,sigma_y],particle`).
//! - tracking evaluation: `score.json`, the [`TrackEvaluation`] (with a
//!   top-level `tracking` object).
//!
//! Every encoding is the one writer and reader of its format in
//! [`crate::io`]. Bump [`FORMAT_VERSION`] when an encoding changes: it is part of every
//! content key, so old artefacts are then made again rather than misread.

use std::sync::Arc;

use anyhow::Context;

use crate::io::{csv_tables, npy};
use crate::metrics::Score;
use crate::registry::BlobRole;
use crate::track::pipeline::TrackEvaluation;
use crate::types::{Dataset, FrameStack, Prediction, RecordingTruthRow, Track};

/// A recording as stored: its frames and its truth (one row per QD per
/// frame it is in the field).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct RecordingData {
    pub frames: FrameStack,
    pub truth: Vec<RecordingTruthRow>,
}

/// Version of the blob encodings below.
pub(crate) const FORMAT_VERSION: &str = "scanloc-blobs/1";

/// An artefact in memory.
#[derive(Debug, Clone)]
pub enum Artefact {
    Dataset(Arc<Dataset>),
    Model(Arc<Vec<u8>>),
    Predictions(Arc<Vec<Prediction>>),
    Evaluation(Arc<Score>),
    Recording(Arc<RecordingData>),
    Tracks(Arc<Vec<Track>>),
    TrackEvaluation(Arc<TrackEvaluation>),
}

impl Artefact {
    /// The artefact's blobs: (role, bytes), in role order.
    pub fn encode(&self) -> anyhow::Result<Vec<(BlobRole, Vec<u8>)>> {
        Ok(match self {
            Artefact::Dataset(dataset) => {
                let mut frames = Vec::new();
                npy::write_frames(&mut frames, &dataset.frames)?;
                let mut truth = Vec::new();
                csv_tables::write_truth_to(&mut truth, &dataset.truth)?;
                vec![(BlobRole::Frames, frames), (BlobRole::Truth, truth)]
            }
            Artefact::Model(bytes) => vec![(BlobRole::Model, bytes.as_ref().clone())],
            Artefact::Predictions(predictions) => {
                let mut csv = Vec::new();
                csv_tables::write_predictions_to(&mut csv, predictions)?;
                vec![(BlobRole::Predictions, csv)]
            }
            Artefact::Evaluation(score) => {
                vec![(BlobRole::Score, serde_json::to_vec(score.as_ref())?)]
            }
            Artefact::Recording(recording) => {
                let mut frames = Vec::new();
                npy::write_frames(&mut frames, &recording.frames)?;
                let mut truth = Vec::new();
                crate::io::tracks::write_recording_truth_to(&mut truth, &recording.truth)?;
                vec![(BlobRole::Frames, frames), (BlobRole::Truth, truth)]
            }
            Artefact::Tracks(tracks) => {
                let mut csv = Vec::new();
                crate::io::tracks::write_tracks_to(&mut csv, tracks)?;
                vec![(BlobRole::Predictions, csv)]
            }
            Artefact::TrackEvaluation(evaluation) => {
                vec![(BlobRole::Score, serde_json::to_vec(evaluation.as_ref())?)]
            }
        })
    }

    /// The frames of a dataset or a recording.
    pub fn frames(&self) -> anyhow::Result<&FrameStack> {
        match self {
            Artefact::Dataset(d) => Ok(&d.frames),
            Artefact::Recording(r) => Ok(&r.frames),
            _ => anyhow::bail!("expected a dataset or recording artefact"),
        }
    }

    pub fn recording(&self) -> anyhow::Result<&Arc<RecordingData>> {
        match self {
            Artefact::Recording(r) => Ok(r),
            _ => anyhow::bail!("expected a recording artefact"),
        }
    }

    pub fn tracks(&self) -> anyhow::Result<&Arc<Vec<Track>>> {
        match self {
            Artefact::Tracks(t) => Ok(t),
            _ => anyhow::bail!("expected a tracks artefact"),
        }
    }

    pub fn track_evaluation(&self) -> anyhow::Result<&Arc<TrackEvaluation>> {
        match self {
            Artefact::TrackEvaluation(e) => Ok(e),
            _ => anyhow::bail!("expected a tracking evaluation artefact"),
        }
    }

    pub fn dataset(&self) -> anyhow::Result<&Arc<Dataset>> {
        match self {
            Artefact::Dataset(d) => Ok(d),
            _ => anyhow::bail!("expected a dataset artefact"),
        }
    }

    pub fn model(&self) -> anyhow::Result<&Arc<Vec<u8>>> {
        match self {
            Artefact::Model(m) => Ok(m),
            _ => anyhow::bail!("expected a model artefact"),
        }
    }

    pub fn predictions(&self) -> anyhow::Result<&Arc<Vec<Prediction>>> {
        match self {
            Artefact::Predictions(p) => Ok(p),
            _ => anyhow::bail!("expected a predictions artefact"),
        }
    }

    pub fn evaluation(&self) -> anyhow::Result<&Arc<Score>> {
        match self {
            Artefact::Evaluation(s) => Ok(s),
            _ => anyhow::bail!("expected an evaluation artefact"),
        }
    }
}

fn blob(blobs: &[(BlobRole, Vec<u8>)], role: BlobRole) -> anyhow::Result<&[u8]> {
    blobs
        .iter()
        .find(|(r, _)| *r == role)
        .map(|(_, b)| b.as_slice())
        .with_context(|| format!("the artefact has no {role} blob"))
}

/// The frames of a dataset or a recording, from its `frames.npy` blob.
fn decode_frames(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<FrameStack> {
    let frames_npy = blob(blobs, BlobRole::Frames)?;
    npy::read_frames_from(
        frames_npy,
        frames_npy.len() as u64,
        BlobRole::Frames.as_str(),
    )
}

/// Decodes a dataset from its `frames.npy` and `truth.csv` blobs.
pub(crate) fn decode_dataset(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<Dataset> {
    let frames = decode_frames(blobs)?;
    let truth =
        csv_tables::read_truth_from(blob(blobs, BlobRole::Truth)?, BlobRole::Truth.as_str())?;
    Ok(Dataset { frames, truth })
}

/// Whether a dataset's blobs hold a recording (its truth has a `qd`
/// column) rather than per-frame frames.
pub(crate) fn holds_recording(blobs: &[(BlobRole, Vec<u8>)]) -> bool {
    header_has(blobs, BlobRole::Truth, "qd")
}

/// Whether a predictions artefact's blobs hold tracks (a `particle` column).
pub(crate) fn holds_tracks(blobs: &[(BlobRole, Vec<u8>)]) -> bool {
    header_has(blobs, BlobRole::Predictions, "particle")
}

/// Whether an evaluation's `score.json` is a tracking evaluation (a
/// top-level `tracking` object).
pub(crate) fn holds_track_evaluation(blobs: &[(BlobRole, Vec<u8>)]) -> bool {
    blob(blobs, BlobRole::Score).is_ok_and(|json| {
        serde_json::from_slice::<serde_json::Value>(json)
            .is_ok_and(|v| v.get("tracking").is_some_and(|t| t.is_object()))
    })
}

/// Whether the first line of CSV blob `role` names column `column`.
fn header_has(blobs: &[(BlobRole, Vec<u8>)], role: BlobRole, column: &str) -> bool {
    blob(blobs, role).is_ok_and(|bytes| {
        let line = bytes.split(|&b| b == b'\n').next().unwrap_or_default();
        line.split(|&b| b == b',')
            .any(|name| name.trim_ascii() == column.as_bytes())
    })
}

/// Decodes a recording from its `frames.npy` and `truth.csv` blobs.
pub(crate) fn decode_recording(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<RecordingData> {
    let frames = decode_frames(blobs)?;
    let truth = crate::io::tracks::read_recording_truth_from(
        blob(blobs, BlobRole::Truth)?,
        BlobRole::Truth.as_str(),
    )?;
    Ok(RecordingData { frames, truth })
}

/// Decodes tracks from their `predictions.csv` blob.
pub(crate) fn decode_tracks(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<Vec<Track>> {
    crate::io::tracks::read_tracks_from(
        blob(blobs, BlobRole::Predictions)?,
        BlobRole::Predictions.as_str(),
    )
}

/// Decodes a tracking evaluation from its `score.json` blob.
pub(crate) fn decode_track_evaluation(
    blobs: &[(BlobRole, Vec<u8>)],
) -> anyhow::Result<TrackEvaluation> {
    serde_json::from_slice(blob(blobs, BlobRole::Score)?).context("decoding score.json")
}

/// Decodes predictions from their `predictions.csv` blob.
pub(crate) fn decode_predictions(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<Vec<Prediction>> {
    csv_tables::read_predictions_from(
        blob(blobs, BlobRole::Predictions)?,
        BlobRole::Predictions.as_str(),
    )
}

/// Decodes an evaluation from its `score.json` blob.
pub(crate) fn decode_score(blobs: &[(BlobRole, Vec<u8>)]) -> anyhow::Result<Score> {
    serde_json::from_slice(blob(blobs, BlobRole::Score)?).context("decoding score.json")
}

#[cfg(test)]
mod tests {
    use rand::{RngExt, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::registry::hashing::sha256_hex;
    use crate::sim::{Distribution, RandomDistribution, SimParams, simulate};

    #[test]
    fn datasets_and_predictions_round_trip_bit_for_bit() {
        let params = SimParams::default();
        let dataset = simulate(&params, 5, 0..4, &crate::progress::hidden()).unwrap();
        let artefact = Artefact::Dataset(Arc::new(dataset.clone()));
        let blobs = artefact.encode().unwrap();
        let back = decode_dataset(&blobs).unwrap();
        assert_eq!(back, dataset);
        for (a, b) in back.truth.iter().zip(&dataset.truth) {
            assert_eq!(a.x.to_bits(), b.x.to_bits());
        }
        let predictions = vec![
            Prediction::new(0, 0.1 + 0.2, -1.0 / 3.0, 1e-300),
            Prediction::new(3, 12.0, 7.5, 123456.789),
        ];
        let blobs = Artefact::Predictions(Arc::new(predictions.clone()))
            .encode()
            .unwrap();
        assert_eq!(decode_predictions(&blobs).unwrap(), predictions);
        // A detector's uncertainty is stored and read back too.
        let with_sigma: Vec<Prediction> = predictions
            .iter()
            .map(|&p| Prediction {
                sigma: Some(crate::types::LocalisationSigma {
                    x: 0.1 + 0.2,
                    y: 7.0,
                }),
                ..p
            })
            .collect();
        let blobs = Artefact::Predictions(Arc::new(with_sigma.clone()))
            .encode()
            .unwrap();
        assert_eq!(decode_predictions(&blobs).unwrap(), with_sigma);
    }

    /// The SHA-256 of each blob of `dataset`'s artefact, by role.
    fn dataset_blob_hashes(params: &SimParams, seed: u64, frames: usize) -> Vec<(String, String)> {
        let dataset = simulate(params, seed, 0..frames, &crate::progress::hidden()).unwrap();
        Artefact::Dataset(Arc::new(dataset))
            .encode()
            .unwrap()
            .into_iter()
            .map(|(role, bytes)| (role.as_str().to_string(), sha256_hex(&bytes)))
            .collect()
    }

    #[test]
    fn dataset_blobs_keep_the_bytes_registries_hold() {
        // Pinned from `scanloc simulate` of the same parameters before the
        // registry and the CLI shared one encoder per format: stored blobs
        // must stay byte-identical (uint16 and uint32 frames, with and
        // without cut-off, several emitters).
        let pairs = |frames: &str, truth: &str| {
            vec![
                ("frames.npy".to_string(), frames.to_string()),
                ("truth.csv".to_string(), truth.to_string()),
            ]
        };
        assert_eq!(
            dataset_blob_hashes(&SimParams::default(), 5, 4),
            pairs(
                "b87653a5409d32e75e166624ee91f2f0f636cf284be4dc43cf5b8b037b9711c4",
                "a354dcba605af8adcee6a6b131c8a3c95d2abd5ef2c9fa89e292188361dd66ba"
            )
        );
        let crowded = SimParams {
            emitters: 3.into(),
            substeps: 2,
            margin_px: 4.0,
            z_start: Distribution::Random(RandomDistribution::Uniform([-0.5, 0.5])),
            psf_cutoff_sigma: Some(3.0),
            diffusion_um2_s: Distribution::Random(RandomDistribution::Uniform([0.5, 2.0])),
            brightness: 300.0.into(),
            ..SimParams::default()
        };
        assert_eq!(
            dataset_blob_hashes(&crowded, 9, 6),
            pairs(
                "2962e0975b9bb1aa077a5be84e2b376bdd68018f157b8eb94498f8d0131f7189",
                "99911c91b8e2bc33a73c7a3dac466d529b88f904aeadb54eb9902038cbea4334"
            )
        );
        let bright = SimParams {
            brightness: 100_000.0.into(),
            ..SimParams::default()
        };
        assert_eq!(
            dataset_blob_hashes(&bright, 3, 2),
            pairs(
                "a4c7e630ecae67e0ce3dfc986b0ff3e98b8ba25ad2892981d0c9430174f78d03",
                "c8b1e0c67c18097f4d03a622cebdb368eb4beccbd2c3e0d1053c47d293c7d502"
            )
        );
    }

    /// The predictions encoder the registry used before it shared
    /// `csv_tables::write_predictions_to` with `scanloc locate`: the bytes
    /// existing registries hold.
    fn encoding_before_sharing(predictions: &[Prediction]) -> Vec<u8> {
        let mut text = String::from("frame,x,y,score\n");
        for p in predictions {
            text.push_str(&format!("{},{},{},{}\n", p.frame, p.x, p.y, p.score));
        }
        text.into_bytes()
    }

    #[test]
    fn prediction_blobs_keep_the_bytes_registries_hold() {
        let encode = |predictions: &[Prediction]| {
            let blobs = Artefact::Predictions(Arc::new(predictions.to_vec()))
                .encode()
                .unwrap();
            assert_eq!(blobs.len(), 1);
            assert_eq!(blobs[0].0.as_str(), "predictions.csv");
            blobs[0].1.clone()
        };
        let awkward = [
            (0, 0.1 + 0.2, -1.0 / 3.0, 1e-300),
            (3, 12.0, 7.5, 123456.789),
            (7, -0.0, f64::MIN_POSITIVE, 1e300),
            (usize::MAX, f64::MAX, -f64::MAX, f64::EPSILON),
            (1, f64::NAN, f64::INFINITY, f64::NEG_INFINITY),
        ]
        .map(|(frame, x, y, score)| Prediction::new(frame, x, y, score));
        let two = [
            Prediction::new(0, 0.1 + 0.2, -1.0 / 3.0, 0.5),
            Prediction::new(3, 12.0, 7.5, 123456.789),
        ];
        assert_eq!(
            String::from_utf8(encode(&two)).unwrap(),
            "frame,x,y,score\n0,0.30000000000000004,-0.3333333333333333,0.5\n3,12,7.5,123456.789\n"
        );
        assert_eq!(encode(&[]), b"frame,x,y,score\n");
        assert_eq!(encode(&awkward), encoding_before_sharing(&awkward));
        // Detector-like values: pixel coordinates and scores of all sizes.
        let mut rng = ChaCha8Rng::seed_from_u64(17);
        let many: Vec<Prediction> = (0..2000)
            .map(|i| {
                Prediction::new(
                    i / 3,
                    rng.random::<f64>() * 25.0 - 0.5,
                    rng.random::<f64>() * 24.0 - 0.5,
                    rng.random::<f64>() * 10f64.powi(rng.random_range(-12..12)),
                )
            })
            .collect();
        assert_eq!(encode(&many), encoding_before_sharing(&many));
    }
}
