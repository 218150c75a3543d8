//! How artefacts are stored as blobs, and read back.
//!
//! - dataset: `frames.npy` (uint16, or uint32 if a count needs it; shape
//!   `(n, H, W)`, the same `.npy` as `scanloc simulate` writes, so numpy can
//!   open a blob directly) and `truth.csv` (the truth CSV of `simulate`).
//! - model: `model.bin`, the detector's own serialisation.
//! - predictions: `predictions.csv`, `frame,x,y,score` (floats in Rust's
//!   shortest round-trip form, so reading gives back the same bits).
//! - evaluation: `score.json`, the metric's [`Score`] (with curves if the
//!   manifest keeps them).
//!
//! Bump [`FORMAT_VERSION`] when an encoding changes: it is part of every
//! content key, so old artefacts are then made again rather than misread.

use std::sync::Arc;

use anyhow::Context;
use npyz::{NpyFile, TypeChar};

use crate::io::{csv_tables, npy};
use crate::metrics::Score;
use crate::types::{Dataset, FrameStack, Prediction, TruthRow};

/// Version of the blob encodings below.
pub const FORMAT_VERSION: &str = "scanloc-blobs/1";

/// An artefact in memory.
#[derive(Debug, Clone)]
pub enum Artefact {
    Dataset(Arc<Dataset>),
    Model(Arc<Vec<u8>>),
    Predictions(Arc<Vec<Prediction>>),
    Evaluation(Arc<Score>),
}

impl Artefact {
    /// The artefact's blobs: (role, bytes), in role order.
    pub fn encode(&self) -> anyhow::Result<Vec<(String, Vec<u8>)>> {
        Ok(match self {
            Artefact::Dataset(dataset) => {
                let mut frames = Vec::new();
                npy::write_frames(&mut frames, &dataset.frames)?;
                let mut truth = Vec::new();
                csv_tables::write_truth_to(&mut truth, &dataset.truth)?;
                vec![
                    ("frames.npy".to_string(), frames),
                    ("truth.csv".to_string(), truth),
                ]
            }
            Artefact::Model(bytes) => vec![("model.bin".to_string(), bytes.as_ref().clone())],
            Artefact::Predictions(predictions) => {
                let mut text = String::from("frame,x,y,score\n");
                for p in predictions.iter() {
                    text.push_str(&format!("{},{},{},{}\n", p.frame, p.x, p.y, p.score));
                }
                vec![("predictions.csv".to_string(), text.into_bytes())]
            }
            Artefact::Evaluation(score) => {
                vec![(
                    "score.json".to_string(),
                    serde_json::to_vec(score.as_ref())?,
                )]
            }
        })
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

fn blob<'a>(blobs: &'a [(String, Vec<u8>)], role: &str) -> anyhow::Result<&'a [u8]> {
    blobs
        .iter()
        .find(|(r, _)| r == role)
        .map(|(_, b)| b.as_slice())
        .with_context(|| format!("the artefact has no {role} blob"))
}

/// Decodes a dataset from its `frames.npy` and `truth.csv` blobs.
pub fn decode_dataset(blobs: &[(String, Vec<u8>)]) -> anyhow::Result<Dataset> {
    let frames = decode_frames(blob(blobs, "frames.npy")?)?;
    let mut reader = csv::Reader::from_reader(blob(blobs, "truth.csv")?);
    let truth = reader
        .deserialize::<TruthRow>()
        .collect::<Result<Vec<_>, _>>()
        .context("decoding truth.csv")?;
    Ok(Dataset { frames, truth })
}

fn decode_frames(bytes: &[u8]) -> anyhow::Result<FrameStack> {
    let npy = NpyFile::new(bytes).context("decoding frames.npy")?;
    let shape: Vec<usize> = npy.shape().iter().map(|&d| d as usize).collect();
    let [n, height, width] = shape[..] else {
        anyhow::bail!("frames.npy has shape {shape:?}, expected (n, H, W)");
    };
    let npyz::DType::Plain(dtype) = npy.dtype() else {
        anyhow::bail!("frames.npy has a structured dtype");
    };
    let data: Vec<u32> = match (dtype.type_char(), dtype.size_field()) {
        (TypeChar::Uint, 2) => npy.into_vec::<u16>()?.into_iter().map(u32::from).collect(),
        (TypeChar::Uint, 4) => npy.into_vec::<u32>()?,
        _ => anyhow::bail!("frames.npy has dtype {dtype}, expected uint16 or uint32"),
    };
    FrameStack::from_vec(n, height, width, data)
}

/// Decodes predictions from their `predictions.csv` blob.
pub fn decode_predictions(blobs: &[(String, Vec<u8>)]) -> anyhow::Result<Vec<Prediction>> {
    let mut reader = csv::Reader::from_reader(blob(blobs, "predictions.csv")?);
    let mut predictions = Vec::new();
    for record in reader.records() {
        let record = record.context("decoding predictions.csv")?;
        let field = |i: usize| record.get(i).context("predictions.csv: short row");
        predictions.push(Prediction {
            frame: field(0)?.parse()?,
            x: field(1)?.parse()?,
            y: field(2)?.parse()?,
            score: field(3)?.parse()?,
        });
    }
    Ok(predictions)
}

/// Decodes an evaluation from its `score.json` blob.
pub fn decode_score(blobs: &[(String, Vec<u8>)]) -> anyhow::Result<Score> {
    serde_json::from_slice(blob(blobs, "score.json")?).context("decoding score.json")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{SimParams, simulate};

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
            Prediction {
                frame: 0,
                x: 0.1 + 0.2,
                y: -1.0 / 3.0,
                score: 1e-300,
            },
            Prediction {
                frame: 3,
                x: 12.0,
                y: 7.5,
                score: 123456.789,
            },
        ];
        let blobs = Artefact::Predictions(Arc::new(predictions.clone()))
            .encode()
            .unwrap();
        assert_eq!(decode_predictions(&blobs).unwrap(), predictions);
    }
}
