//! Checkpoint directories: `model.safetensors` (every weight, target critics and log α included)
//! and `checkpoint.json` (what the weights are). Each file is written to a temporary name and
//! renamed, JSON last; the JSON records the CRC-32 of the weights, so a torn or mixed-up pair is
//! caught at load time instead of producing a silently wrong policy.

use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::{EncoderKind, NetConfig, Policy, SacConfig, SacModel};
use crate::config::GaitConfig;

pub const MODEL_FILE: &str = "model.safetensors";
pub const META_FILE: &str = "checkpoint.json";
pub const FORMAT_VERSION: u32 = 1;
/// Present while a trainer's save is under way or was interrupted (`train::run_dir`).
pub const PENDING_SAVE_FILE: &str = "save-pending.json";
/// The most a checkpoint's weights may hold (the Ant's models are 1–4 MB; an encoder with a
/// latent of thousands still fits): nothing larger is read.
pub const MAX_WEIGHTS_BYTES: u64 = 256 << 20;
/// The most a checkpoint.json may hold (a few KB in practice).
pub const MAX_META_BYTES: u64 = 1 << 20;

/// `checkpoint.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckpointMeta {
    pub format_version: u32,
    pub gaitscope_version: String,
    pub net: NetConfig,
    pub sac: SacConfig,
    /// The env and damage config the model was trained under.
    pub env: GaitConfig,
    pub seed: u64,
    pub steps_done: u64,
    pub episodes_done: u64,
    pub wall_time_s: f64,
    /// Every tensor in `model.safetensors`: name → shape.
    pub tensors: BTreeMap<String, Vec<usize>>,
    /// CRC-32 of `model.safetensors`.
    pub model_crc32: u32,
    /// Where an imported model came from (absent for models gaitscope trained).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub imported_from: Option<Provenance>,
}

/// The origin of an imported checkpoint.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Provenance {
    /// The framework, e.g. `stable-baselines3`.
    pub source: String,
    /// File name of the imported archive.
    pub file: String,
    /// The framework's version, as the archive records it.
    pub version: String,
    /// SHA-256 of the archive, hex.
    pub sha256: String,
}

#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("checkpoint directory {0} does not exist")]
    NoSuchDir(PathBuf),
    #[error(
        "{0} is a Stable-Baselines3 archive, not a gaitscope checkpoint folder; convert it first:\n  gaitscope import-sb3 {0} --out checkpoints/<name>"
    )]
    Sb3Archive(PathBuf),
    #[error(
        "{0} is a file, not a checkpoint folder (one with checkpoint.json and model.safetensors)"
    )]
    NotADir(PathBuf),
    #[error("{dir} is a folder of runs, not one checkpoint; pass one of:\n{}", list_paths(.runs))]
    FolderOfRuns { dir: PathBuf, runs: Vec<PathBuf> },
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} is not a valid checkpoint.json: {reason}")]
    BadMeta {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("checkpoint {dir} holds a '{found}' model, expected '{expected}'")]
    WrongKind {
        dir: PathBuf,
        expected: EncoderKind,
        found: EncoderKind,
    },
    #[error(
        "{path} does not match its checkpoint.json (CRC-32 {found:08x}, expected {expected:08x}): truncated, corrupt, or from another save"
    )]
    CrcMismatch {
        path: PathBuf,
        expected: u32,
        found: u32,
    },
    #[error(
        "{0} is in the middle of a save (or one was interrupted): try again, or `gaitscope train --resume` it to complete the save"
    )]
    SavePending(PathBuf),
    #[error("{path} is not a readable safetensors file: {reason}")]
    BadWeights {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("checkpoint {dir}: tensor '{name}' is missing from model.safetensors")]
    MissingTensor { dir: PathBuf, name: String },
    #[error("checkpoint {dir}: unexpected tensor '{name}' (not part of a '{kind}' model)")]
    UnexpectedTensor {
        dir: PathBuf,
        name: String,
        kind: EncoderKind,
    },
    #[error("checkpoint {dir}: tensor '{name}' has shape {found:?}, the model needs {expected:?}")]
    ShapeMismatch {
        dir: PathBuf,
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    #[error("checkpoint {dir}: tensor '{name}' is {dtype}, expected f32")]
    WrongDtype {
        dir: PathBuf,
        name: String,
        dtype: String,
    },
    #[error("checkpoint {dir}: tensor '{name}' contains NaN or infinite values")]
    NonFinite { dir: PathBuf, name: String },
    #[error("tensor error: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// Training bookkeeping stored next to the weights.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingRecord {
    pub env: GaitConfig,
    pub sac: SacConfig,
    pub seed: u64,
    pub steps_done: u64,
    pub episodes_done: u64,
    pub wall_time_s: f64,
    pub imported_from: Option<Provenance>,
}

/// Writes `bytes` to `path` atomically: a sibling temp file, fsync, rename. Only onto a new
/// name or a regular file (through symlinks): a FIFO, a device or a folder at `path` is refused,
/// never renamed over (as root a rename would replace `/dev/full` itself), and a temp name
/// that is not a regular file is never opened in a way that could block.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CheckpointError> {
    use std::io::Write;
    let tmp = path.with_extension(format!(
        "{}.tmp",
        path.extension().and_then(|e| e.to_str()).unwrap_or("")
    ));
    crate::files::check_replaceable(path).map_err(|source| CheckpointError::Write {
        path: path.to_owned(),
        source,
    })?;
    let write = || -> std::io::Result<()> {
        let mut file = crate::files::create_regular(&tmp)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    };
    write().map_err(|source| {
        let _ = std::fs::remove_file(&tmp);
        CheckpointError::Write {
            path: path.to_owned(),
            source,
        }
    })
}

/// Serialises named tensors to safetensors bytes, in the given order.
pub fn safetensors_bytes<'a>(
    tensors: impl Iterator<Item = (&'a str, &'a Tensor)>,
) -> Result<Vec<u8>, CheckpointError> {
    let owned: Vec<(String, Tensor)> = tensors.map(|(n, t)| (n.to_string(), t.clone())).collect();
    let views = owned
        .iter()
        .map(|(name, t)| {
            let data: Vec<f32> = t.flatten_all()?.to_vec1::<f32>()?;
            let bytes: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
            Ok((name.clone(), t.dims().to_vec(), bytes))
        })
        .collect::<Result<Vec<_>, candle_core::Error>>()?;
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = views
        .iter()
        .map(|(name, shape, bytes)| {
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape.clone(), bytes)
                .map(|v| (name.clone(), v))
        })
        .collect::<Result<_, _>>()
        .map_err(|e| CheckpointError::BadWeights {
            path: PathBuf::from("<memory>"),
            reason: e.into(),
        })?;
    safetensors::serialize(views, None).map_err(|e| CheckpointError::BadWeights {
        path: PathBuf::from("<memory>"),
        reason: e.into(),
    })
}

/// Reads safetensors bytes into named f32 tensors, checking each against `expected` (name →
/// shape) exactly: nothing missing, nothing extra, right shapes, all finite.
pub fn load_expected_tensors(
    dir: &Path,
    path: &Path,
    bytes: &[u8],
    expected: &BTreeMap<String, Vec<usize>>,
    kind: EncoderKind,
    device: &Device,
) -> Result<BTreeMap<String, Tensor>, CheckpointError> {
    let file =
        safetensors::SafeTensors::deserialize(bytes).map_err(|e| CheckpointError::BadWeights {
            path: path.to_owned(),
            reason: e.into(),
        })?;
    let dir = dir.to_owned();
    for name in file.names() {
        if !expected.contains_key(&name.to_string()) {
            return Err(CheckpointError::UnexpectedTensor {
                dir,
                name: name.to_string(),
                kind,
            });
        }
    }
    let mut out = BTreeMap::new();
    for (name, shape) in expected {
        let view = file
            .tensor(name)
            .map_err(|_| CheckpointError::MissingTensor {
                dir: dir.clone(),
                name: name.clone(),
            })?;
        if view.dtype() != safetensors::Dtype::F32 {
            return Err(CheckpointError::WrongDtype {
                dir,
                name: name.clone(),
                dtype: format!("{:?}", view.dtype()),
            });
        }
        if view.shape() != shape.as_slice() {
            return Err(CheckpointError::ShapeMismatch {
                dir,
                name: name.clone(),
                expected: shape.clone(),
                found: view.shape().to_vec(),
            });
        }
        let values: Vec<f32> = view
            .data()
            .as_chunks::<4>()
            .0
            .iter()
            .map(|b| f32::from_le_bytes(*b))
            .collect();
        if values.iter().any(|v| !v.is_finite()) {
            return Err(CheckpointError::NonFinite {
                dir,
                name: name.clone(),
            });
        }
        out.insert(
            name.clone(),
            Tensor::from_vec(values, shape.as_slice(), device)?,
        );
    }
    Ok(out)
}

impl SacModel {
    /// Name → shape of every tensor this model saves.
    pub fn tensor_shapes(&self) -> BTreeMap<String, Vec<usize>> {
        self.all_params()
            .map(|(n, v)| (n.to_string(), v.dims().to_vec()))
            .collect()
    }

    /// The bytes of `model.safetensors` and the `checkpoint.json` that describes them.
    pub fn checkpoint_bytes(
        &self,
        record: &TrainingRecord,
    ) -> Result<(Vec<u8>, CheckpointMeta), CheckpointError> {
        let bytes = safetensors_bytes(self.all_params().map(|(n, v)| (n, v.as_tensor())))?;
        let meta = CheckpointMeta {
            format_version: FORMAT_VERSION,
            gaitscope_version: env!("CARGO_PKG_VERSION").to_string(),
            net: self.net.clone(),
            sac: record.sac.clone(),
            env: record.env.clone(),
            seed: record.seed,
            steps_done: record.steps_done,
            episodes_done: record.episodes_done,
            wall_time_s: record.wall_time_s,
            tensors: self.tensor_shapes(),
            model_crc32: crc32fast::hash(&bytes),
            imported_from: record.imported_from.clone(),
        };
        Ok((bytes, meta))
    }

    /// Writes `model.safetensors`, then `checkpoint.json`, each atomically (a trainer saves
    /// them as one set with the rest of its run instead: `train::run_dir`).
    pub fn save(
        &self,
        dir: &Path,
        record: &TrainingRecord,
    ) -> Result<CheckpointMeta, CheckpointError> {
        std::fs::create_dir_all(dir).map_err(|source| CheckpointError::Write {
            path: dir.to_owned(),
            source,
        })?;
        let (bytes, meta) = self.checkpoint_bytes(record)?;
        write_atomic(&dir.join(MODEL_FILE), &bytes)?;
        write_atomic(&dir.join(META_FILE), &meta_json(dir, &meta)?)?;
        Ok(meta)
    }

    /// Loads a checkpoint directory, checking everything; `expected` rejects another model kind.
    pub fn load(
        dir: &Path,
        expected: Option<EncoderKind>,
        device: &Device,
    ) -> Result<(Self, CheckpointMeta), CheckpointError> {
        let meta = read_meta(dir)?;
        if let Some(expected) = expected
            && expected != meta.net.encoder
        {
            return Err(CheckpointError::WrongKind {
                dir: dir.to_owned(),
                expected,
                found: meta.net.encoder,
            });
        }
        let model = Self::new(meta.net.clone(), 1.0, 0, device)?;
        let shapes = model.tensor_shapes();
        if shapes != meta.tensors {
            let meta_path = dir.join(META_FILE);
            let reason = describe_shape_difference(&shapes, &meta.tensors);
            return Err(CheckpointError::BadMeta {
                path: meta_path,
                reason: reason.into(),
            });
        }
        let path = dir.join(MODEL_FILE);
        let bytes = crate::files::read_capped(&path, MAX_WEIGHTS_BYTES).map_err(|source| {
            CheckpointError::Read {
                path: path.clone(),
                source,
            }
        })?;
        let found = crc32fast::hash(&bytes);
        if found != meta.model_crc32 {
            if dir.join(PENDING_SAVE_FILE).exists() {
                return Err(CheckpointError::SavePending(dir.to_owned()));
            }
            return Err(CheckpointError::CrcMismatch {
                path,
                expected: meta.model_crc32,
                found,
            });
        }
        let tensors = load_expected_tensors(dir, &path, &bytes, &shapes, meta.net.encoder, device)?;
        for (name, var) in model.all_params() {
            var.set(&tensors[name])?;
        }
        Ok((model, meta))
    }
}

fn describe_shape_difference(
    model: &BTreeMap<String, Vec<usize>>,
    listed: &BTreeMap<String, Vec<usize>>,
) -> String {
    if let Some(name) = model.keys().find(|n| !listed.contains_key(*n)) {
        return format!("its tensor list lacks '{name}', which its net config implies");
    }
    if let Some(name) = listed.keys().find(|n| !model.contains_key(*n)) {
        return format!("it lists tensor '{name}', which its net config does not have");
    }
    let (name, shape) = model
        .iter()
        .find(|(n, s)| listed.get(*n) != Some(s))
        .expect("maps differ");
    format!(
        "it lists '{name}' as {:?}, its net config implies {shape:?}",
        listed[name]
    )
}

/// `checkpoint.json`'s bytes (`dir` only names the file in an error).
pub fn meta_json(dir: &Path, meta: &CheckpointMeta) -> Result<Vec<u8>, CheckpointError> {
    serde_json::to_vec_pretty(meta).map_err(|e| CheckpointError::BadMeta {
        path: dir.join(META_FILE),
        reason: e.into(),
    })
}

fn list_paths(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| format!("  {}", p.display()))
        .collect::<Vec<_>>()
        .join("\n")
}

/// What a path given as a checkpoint is, when it is not one: an SB3 zip, a plain file, a
/// folder of run folders (`checkpoints/seeds`). `None` when nothing more specific fits.
fn misplaced_checkpoint(dir: &Path) -> Option<CheckpointError> {
    if dir.is_file() {
        let mut magic = [0u8; 4];
        let is_zip = std::fs::File::open(dir)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut magic))
            .is_ok()
            && magic == *b"PK\x03\x04";
        return Some(if is_zip {
            CheckpointError::Sb3Archive(dir.to_owned())
        } else {
            CheckpointError::NotADir(dir.to_owned())
        });
    }
    if dir.is_dir() && !dir.join(META_FILE).exists() {
        let mut runs: Vec<PathBuf> = std::fs::read_dir(dir)
            .ok()?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.join(META_FILE).is_file())
            .collect();
        runs.sort();
        if !runs.is_empty() {
            return Some(CheckpointError::FolderOfRuns {
                dir: dir.to_owned(),
                runs,
            });
        }
    }
    None
}

/// Reads and parses `checkpoint.json`.
pub fn read_meta(dir: &Path) -> Result<CheckpointMeta, CheckpointError> {
    if let Some(err) = misplaced_checkpoint(dir) {
        return Err(err);
    }
    if !dir.is_dir() {
        return Err(CheckpointError::NoSuchDir(dir.to_owned()));
    }
    let path = dir.join(META_FILE);
    let text = crate::files::read_text_capped(&path, MAX_META_BYTES).map_err(|source| {
        CheckpointError::Read {
            path: path.clone(),
            source,
        }
    })?;
    let meta: CheckpointMeta =
        serde_json::from_str(&text).map_err(|e| CheckpointError::BadMeta {
            path: path.clone(),
            reason: e.into(),
        })?;
    if meta.format_version != FORMAT_VERSION {
        return Err(CheckpointError::BadMeta {
            path,
            reason: format!(
                "format version {} (this gaitscope reads {FORMAT_VERSION})",
                meta.format_version
            )
            .into(),
        });
    }
    // An oracle's input size follows from its privileged inputs; a hand-edited file that
    // disagrees would feed the network the wrong values.
    if meta.net.privileged != super::Privileged::None {
        meta.net
            .check_inputs()
            .map_err(|reason| CheckpointError::BadMeta {
                path,
                reason: reason.into(),
            })?;
    }
    Ok(meta)
}

impl Policy {
    /// Loads the actor of a checkpoint for inference.
    pub fn load(dir: &Path, expected: Option<EncoderKind>) -> Result<Self, CheckpointError> {
        let device = Device::Cpu;
        let (model, meta) = SacModel::load(dir, expected, &device)?;
        Ok(Policy::new(meta, model.actor, device))
    }
}

/// Label of a checkpoint in tables, legends and views: its folder name.
pub fn model_label(dir: &Path) -> String {
    dir.file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("model")
        .to_string()
}
