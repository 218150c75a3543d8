//! A trained model as it is stored: [`TrainedCnn`] with its training
//! records, as one self-describing blob (the registry's) or as a model
//! folder (`config.json`, and each member's weights and training record).

use std::io::Write as _;
use std::path::Path;

use burn::module::Module;
use burn::store::ModuleRecord;
use serde::{Deserialize, Serialize};

use super::{CnnArchitecture, FORMAT, MAX_MEMBERS, TrainingSettings, inference_device, model};
use crate::error::input_error;

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
