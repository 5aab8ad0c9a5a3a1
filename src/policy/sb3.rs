//! Stable-Baselines3 SAC archives (`model.zip`) → gaitscope checkpoints.
//!
//! An SB3 archive is a zip holding `data` (JSON: spaces, `policy_kwargs`, hyperparameters),
//! `policy.pth` (the policy's PyTorch state dict), `pytorch_variables.pth` (`log_ent_coef`) and
//! `_stable_baselines3_version`. The zip is read with the `zip` crate and the pickles with
//! candle's PyTorch reader; nothing here parses either format by hand.
//!
//! Names map one to one (PyTorch's `(out, in)` weights are transposed to our `(in, out)`, biases
//! become rows):
//!
//! | SB3                                  | gaitscope                      |
//! |--------------------------------------|--------------------------------|
//! | `actor.latent_pi.{2i}`               | `actor.trunk.{i}`              |
//! | `actor.mu`, `actor.log_std`          | `actor.mean`, `actor.log_std`  |
//! | `{critic,critic_target}.qf{j}.{2i}`  | `{critic,critic_target}.q{j}.{i}` |
//! | `*.features_extractor.P.weight_ih_l0` (one `nn.LSTM`, any path P) | `*.encoder.lstm.weight_ih` |
//! | `log_ent_coef`                       | `log_alpha`                    |
//!
//! The extractor contract (docs/sb3.md): the observation is gaitscope's folded window, 16 ×
//! (observation 29, action 8) oldest first then the current observation (621 values); the
//! extractor runs one LSTM(37 → H) over the 16 entries from zero state and returns
//! [h_T, current observation].

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::io::Read;
use std::path::{Path, PathBuf};

use super::checkpoint::{CheckpointError, Provenance, TrainingRecord};
use super::{EncoderKind, NetConfig, SacConfig, SacModel};
use crate::config::GaitConfig;
use crate::env::{ACT_DIM, OBS_DIM};

/// Window length of gaitscope's encoders, and so of the folded observation.
const CONTEXT_LEN: usize = 16;
/// The folded observation: CONTEXT_LEN × (obs, action), then the current obs.
const FOLDED_DIM: usize = CONTEXT_LEN * (OBS_DIM + ACT_DIM) + OBS_DIM;
const LSTM_SUFFIXES: [&str; 4] = ["weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"];

/// Which encoder the imported model gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImportEncoder {
    /// `none` for a 29-d observation, `lstm` for the 621-d folded window with one LSTM.
    Auto,
    None,
    Lstm,
}

#[derive(Debug, thiserror::Error)]
pub enum Sb3Error {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} is not a Stable-Baselines3 archive: {reason}")]
    NotAnArchive { path: PathBuf, reason: String },
    #[error("{path} is not a SAC model: {reason}")]
    NotSac { path: PathBuf, reason: String },
    #[error(
        "{path}: the observation has {found} values; gaitscope's task has {OBS_DIM} (baseline) or {FOLDED_DIM} (the folded 16-step window)"
    )]
    ObservationSize { path: PathBuf, found: String },
    #[error("{path}: the action space must be 8 values in [-1, 1]: {reason}")]
    ActionSpace { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Architecture { path: PathBuf, reason: String },
    #[error(
        "{path}: cannot map the features extractor ({reason}); it holds {tensors}. gaitscope maps one single-layer nn.LSTM({}, H) whose output is [h_T, current observation] (docs/sb3.md)",
        OBS_DIM + ACT_DIM
    )]
    Extractor {
        path: PathBuf,
        reason: String,
        tensors: String,
    },
    #[error("{path}: policy.pth lacks '{name}', which a SAC policy of this shape has")]
    MissingTensor { path: PathBuf, name: String },
    #[error(
        "{path}: policy.pth does not match a SAC policy of this shape: lacks {missing:?}; holds {unexpected:?}, which have no place in a gaitscope model (renamed, or parts gaitscope does not have)"
    )]
    TensorNames {
        path: PathBuf,
        missing: Vec<String>,
        unexpected: Vec<String>,
    },
    #[error("{path}: '{name}' has shape {found:?}, expected {expected:?}")]
    Shape {
        path: PathBuf,
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    #[error("{path}: '{name}' contains NaN or infinite values")]
    NonFinite { path: PathBuf, name: String },
    #[error("{path}: {what} is not a readable PyTorch file: {source}")]
    Pickle {
        path: PathBuf,
        what: &'static str,
        source: candle_core::Error,
    },
    #[error("{path}: {what} is refused: {reason}")]
    Unsafe {
        path: PathBuf,
        what: &'static str,
        reason: String,
    },
    #[error("{0} already exists; choose another --out or remove it")]
    OutputExists(PathBuf),
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("tensor error: {0}")]
    Tensor(#[from] candle_core::Error),
}

/// What an import produced.
#[derive(Debug, Clone)]
pub struct ImportSummary {
    pub net: NetConfig,
    pub provenance: Provenance,
    pub tensors: usize,
    pub alpha: f64,
    pub num_timesteps: u64,
}

/// The parts of an SB3 archive an import reads.
struct Archive {
    path: PathBuf,
    data: Value,
    version: String,
    sha256: String,
    policy_pth: Vec<u8>,
    variables_pth: Option<Vec<u8>>,
}

impl Archive {
    fn read(path: &Path) -> Result<Self, Sb3Error> {
        use sha2::Digest;
        if path.is_dir() {
            return Err(Sb3Error::NotAnArchive {
                path: path.to_owned(),
                reason: "it is a folder; import-sb3 expects the .zip file that SB3's \
                         `model.save()` wrote (e.g. sac_ant.zip)"
                    .into(),
            });
        }
        let not_archive = |reason: String| Sb3Error::NotAnArchive {
            path: path.to_owned(),
            reason,
        };
        // Only a regular file, and at most the bound: a FIFO or a device is refused before a
        // byte is read, a file past the bound before it is read.
        let bytes = crate::files::read_capped(path, MAX_ARCHIVE_BYTES).map_err(|source| {
            if source.kind() == std::io::ErrorKind::FileTooLarge {
                not_archive(format!(
                    "{source}; an SB3 SAC archive of the Ant is a few MB (at most {MAX_ARCHIVE_BYTES} read)"
                ))
            } else {
                Sb3Error::Read {
                    path: path.to_owned(),
                    source,
                }
            }
        })?;
        let mut zip = zip::ZipArchive::new(std::io::Cursor::new(&bytes))
            .map_err(|e| not_archive(format!("not a readable zip ({e})")))?;
        let mut entry = |name: &str| -> Result<Option<Vec<u8>>, Sb3Error> {
            let mut file = match zip.by_name(name) {
                Ok(file) => file,
                Err(zip::result::ZipError::FileNotFound) => return Ok(None),
                Err(e) => return Err(not_archive(format!("entry '{name}': {e}"))),
            };
            // The directory's size first (a zip bomb announces itself), then a bounded read
            // (a directory can lie).
            if file.size() > MAX_ENTRY_BYTES {
                return Err(not_archive(format!(
                    "entry '{name}' inflates to {} bytes (at most {MAX_ENTRY_BYTES})",
                    file.size()
                )));
            }
            let mut out = Vec::new();
            (&mut file)
                .take(MAX_ENTRY_BYTES + 1)
                .read_to_end(&mut out)
                .map_err(|e| not_archive(format!("entry '{name}' is damaged ({e})")))?;
            if out.len() as u64 > MAX_ENTRY_BYTES {
                return Err(not_archive(format!(
                    "entry '{name}' inflates past {MAX_ENTRY_BYTES} bytes"
                )));
            }
            Ok(Some(out))
        };
        let data = entry("data")?.ok_or_else(|| not_archive("it has no 'data' entry".into()))?;
        let policy_pth =
            entry("policy.pth")?.ok_or_else(|| not_archive("it has no 'policy.pth'".into()))?;
        let variables_pth = entry("pytorch_variables.pth")?;
        let version = entry("_stable_baselines3_version")?
            .map(|v| String::from_utf8_lossy(&v).trim().to_string())
            .unwrap_or_else(|| "unknown".into());
        let data: Value = serde_json::from_slice(&data)
            .map_err(|e| not_archive(format!("its 'data' is not JSON ({e})")))?;
        Ok(Self {
            path: path.to_owned(),
            data,
            version,
            sha256: format!("{:x}", sha2::Sha256::digest(&bytes)),
            policy_pth,
            variables_pth,
        })
    }

    fn field(&self, key: &str) -> Option<&Value> {
        self.data.get(key)
    }

    /// `policy_kwargs[key]`, where SB3 wrote it readably.
    fn policy_kwarg(&self, key: &str) -> Option<&Value> {
        self.data.get("policy_kwargs")?.get(key)
    }
}

/// SB3 writes a Box's bounds as numpy's repr, e.g. `"[-1. -1. ...]"`.
fn parse_numpy_vector(value: &Value) -> Option<Vec<f64>> {
    match value {
        Value::Array(items) => items.iter().map(Value::as_f64).collect(),
        Value::String(text) => text
            .trim()
            .trim_start_matches('[')
            .trim_end_matches(']')
            .split_whitespace()
            .map(|t| t.trim_end_matches(',').parse::<f64>().ok())
            .collect(),
        _ => None,
    }
}

fn space_shape(space: &Value) -> Option<Vec<usize>> {
    space
        .get("_shape")?
        .as_array()?
        .iter()
        .map(|d| d.as_u64().map(|d| d as usize))
        .collect()
}

/// Checks the archive is SB3 SAC on gaitscope's spaces; returns the observation size.
fn check_spaces(archive: &Archive) -> Result<usize, Sb3Error> {
    let path = archive.path.clone();
    let policy_class = archive
        .field("policy_class")
        .ok_or_else(|| Sb3Error::NotAnArchive {
            path: path.clone(),
            reason: "its 'data' has no policy_class".into(),
        })?;
    let module = policy_class
        .get("__module__")
        .and_then(Value::as_str)
        .unwrap_or("an unknown module");
    if module != "stable_baselines3.sac.policies" {
        return Err(Sb3Error::NotSac {
            path,
            reason: format!("its policy class comes from {module}"),
        });
    }
    if archive.field("use_sde").and_then(Value::as_bool) == Some(true) {
        return Err(Sb3Error::Architecture {
            path,
            reason: "it uses gSDE exploration (use_sde=True), which gaitscope's actor lacks".into(),
        });
    }
    let obs_shape = archive
        .field("observation_space")
        .and_then(space_shape)
        .ok_or_else(|| Sb3Error::ObservationSize {
            path: path.clone(),
            found: "an unreadable number of".into(),
        })?;
    let obs_dim = match obs_shape.as_slice() {
        [n] if *n == OBS_DIM || *n == FOLDED_DIM => *n,
        other => {
            return Err(Sb3Error::ObservationSize {
                path,
                found: format!("shape {other:?}, i.e. not {OBS_DIM} or {FOLDED_DIM},"),
            });
        }
    };
    let action = archive
        .field("action_space")
        .ok_or_else(|| Sb3Error::ActionSpace {
            path: path.clone(),
            reason: "there is none".into(),
        })?;
    let bad_action = |reason: String| Sb3Error::ActionSpace {
        path: path.clone(),
        reason,
    };
    let shape = space_shape(action).ok_or_else(|| bad_action("its shape is unreadable".into()))?;
    if shape != [ACT_DIM] {
        return Err(bad_action(format!("its shape is {shape:?}")));
    }
    for (key, bound) in [("low", -1.0), ("high", 1.0)] {
        let values = action
            .get(key)
            .and_then(parse_numpy_vector)
            .ok_or_else(|| bad_action(format!("its '{key}' bounds are unreadable")))?;
        if values.len() != ACT_DIM || values.iter().any(|&v| v != bound) {
            return Err(bad_action(format!("its '{key}' bounds are {values:?}")));
        }
    }
    if let Some(activation) = archive.policy_kwarg("activation_fn") {
        let text = activation.as_str().unwrap_or_default();
        if !text.contains("ReLU") {
            return Err(Sb3Error::Architecture {
                path,
                reason: format!("its activation_fn is {activation}; gaitscope's networks use ReLU"),
            });
        }
    }
    Ok(obs_dim)
}

/// The largest archive read, the largest entry inflated (both far above a SAC policy's few MB).
const MAX_ARCHIVE_BYTES: u64 = 1 << 30;
const MAX_ENTRY_BYTES: u64 = 256 << 20;
/// The most elements one tensor may declare (a 256 × 256 layer has 65,536).
const MAX_TENSOR_ELEMENTS: usize = 16 << 20;

thread_local! {
    /// Set while this thread runs third-party parsing whose panics we catch and report.
    static CATCHING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f`, catching a panic without the panic hook printing it (message and backtrace) first:
/// the caller turns it into one clear error line. Only panics on this thread while `f` runs are
/// kept quiet; every other panic reaches the hook that was installed before.
fn quietly<T>(f: impl FnOnce() -> T) -> std::thread::Result<T> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if !CATCHING.with(|c| c.get()) {
                previous(info);
            }
        }));
    });
    CATCHING.with(|c| c.set(true));
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    CATCHING.with(|c| c.set(false));
    result
}

/// Runs a dependency's reader on untrusted bytes: a panic in it is this archive's error, not
/// the process's end.
fn guarded<T>(
    archive: &Archive,
    what: &'static str,
    read: impl FnOnce() -> candle_core::Result<T>,
) -> Result<T, Sb3Error> {
    match quietly(read) {
        Ok(result) => result.map_err(|source| Sb3Error::Pickle {
            path: archive.path.clone(),
            what,
            source,
        }),
        Err(panic) => Err(Sb3Error::Unsafe {
            path: archive.path.clone(),
            what,
            reason: format!(
                "the pickle reader failed on it ({})",
                panic
                    .downcast_ref::<String>()
                    .map(String::as_str)
                    .or_else(|| panic.downcast_ref::<&str>().copied())
                    .unwrap_or("a panic")
            ),
        }),
    }
}

/// Reads a PyTorch pickle (bytes from the archive) through a temporary file, as candle's reader
/// takes a path. Every tensor's dtype and declared size are checked from the pickle before any
/// storage is allocated: only float tensors of bounded size are read.
fn read_pth(
    archive: &Archive,
    what: &'static str,
    bytes: &[u8],
    scratch: &Path,
) -> Result<BTreeMap<String, Tensor>, Sb3Error> {
    check_pickles(archive, what, bytes)?;
    let file = scratch.join(what);
    std::fs::write(&file, bytes).map_err(|source| Sb3Error::Write {
        path: file.clone(),
        source,
    })?;
    let checked = guarded(archive, what, || {
        candle_core::pickle::read_pth_tensor_info(&file, false, None)
    })
    .and_then(|infos| {
        for info in &infos {
            let unsafe_tensor = |reason: String| Sb3Error::Unsafe {
                path: archive.path.clone(),
                what,
                reason: format!("tensor '{}' {reason}", info.name),
            };
            if !matches!(
                info.dtype,
                DType::F16 | DType::BF16 | DType::F32 | DType::F64
            ) {
                return Err(unsafe_tensor(format!(
                    "has dtype {:?}; SB3's weights are floats",
                    info.dtype
                )));
            }
            let elements = info
                .layout
                .dims()
                .iter()
                .try_fold(1usize, |n, &d| n.checked_mul(d))
                .filter(|&n| n <= MAX_TENSOR_ELEMENTS);
            if elements.is_none() || info.storage_size > MAX_TENSOR_ELEMENTS {
                return Err(unsafe_tensor(format!(
                    "declares shape {:?} (storage {}); at most {MAX_TENSOR_ELEMENTS} elements",
                    info.layout.dims(),
                    info.storage_size
                )));
            }
        }
        Ok(())
    });
    let read =
        checked.and_then(|()| guarded(archive, what, || candle_core::pickle::read_all(&file)));
    let _ = std::fs::remove_file(&file);
    let mut out = BTreeMap::new();
    for (name, tensor) in read? {
        out.insert(name, tensor.to_dtype(DType::F32)?);
    }
    Ok(out)
}

/// Every `data.pkl` inside a .pth (itself a zip) through [`super::pickle_guard::check`]: its
/// nesting and size bounded before candle's reader builds anything.
fn check_pickles(archive: &Archive, what: &'static str, pth: &[u8]) -> Result<(), Sb3Error> {
    let refuse = |reason: String| Sb3Error::Unsafe {
        path: archive.path.clone(),
        what,
        reason,
    };
    let mut zip = zip::ZipArchive::new(std::io::Cursor::new(pth))
        .map_err(|e| refuse(format!("not a readable zip ({e})")))?;
    for i in 0..zip.len() {
        let mut file = zip
            .by_index(i)
            .map_err(|e| refuse(format!("entry {i}: {e}")))?;
        let is_pickle = file.name().is_ok_and(|n| n.ends_with("data.pkl"));
        if !is_pickle {
            continue;
        }
        if file.size() > MAX_ENTRY_BYTES {
            return Err(refuse(format!(
                "its pickle inflates to {} bytes",
                file.size()
            )));
        }
        let mut pkl = Vec::new();
        (&mut file)
            .take(MAX_ENTRY_BYTES)
            .read_to_end(&mut pkl)
            .map_err(|e| refuse(format!("its pickle is damaged ({e})")))?;
        super::pickle_guard::check(&pkl).map_err(|e| refuse(format!("its pickle: {e}")))?;
    }
    Ok(())
}

/// The policy's state dict, by name.
struct StateDict {
    path: PathBuf,
    tensors: BTreeMap<String, Tensor>,
}

impl StateDict {
    fn get(&self, name: &str) -> Result<Tensor, Sb3Error> {
        let tensor = self
            .tensors
            .get(name)
            .ok_or_else(|| Sb3Error::MissingTensor {
                path: self.path.clone(),
                name: name.to_string(),
            })?
            .clone();
        Ok(tensor)
    }

    fn shape(&self, name: &str) -> Option<Vec<usize>> {
        self.tensors.get(name).map(|t| t.dims().to_vec())
    }

    /// Output sizes of a `Sequential` of Linear/ReLU pairs (`{prefix}.{0,2,4,…}.weight`).
    fn linear_stack(&self, prefix: &str) -> Vec<(usize, usize)> {
        (0..)
            .map(|i| self.shape(&format!("{prefix}.{}.weight", 2 * i)))
            .map_while(|s| match s.as_deref() {
                Some([out, inp]) => Some((*inp, *out)),
                _ => None,
            })
            .collect()
    }

    fn under(&self, prefix: &str) -> Vec<(&str, Vec<usize>)> {
        self.tensors
            .iter()
            .filter(|(n, _)| n.starts_with(prefix))
            .map(|(n, t)| (n.as_str(), t.dims().to_vec()))
            .collect()
    }
}

fn list_tensors(tensors: &[(&str, Vec<usize>)]) -> String {
    if tensors.is_empty() {
        return "no tensors".into();
    }
    tensors
        .iter()
        .map(|(n, s)| format!("{n} {s:?}"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The LSTM inside `{owner}.features_extractor.`: its module path and hidden size.
fn find_lstm(state: &StateDict, owner: &str) -> Result<(String, usize), Sb3Error> {
    let prefix = format!("{owner}.features_extractor.");
    let tensors = state.under(&prefix);
    let fail = |reason: String| Sb3Error::Extractor {
        path: state.path.clone(),
        reason,
        tensors: list_tensors(&tensors),
    };
    let Some((first, _)) = tensors
        .iter()
        .find(|(n, _)| n.ends_with(&format!(".{}", LSTM_SUFFIXES[0])))
    else {
        return Err(fail(format!("{owner} has no LSTM weight_ih_l0")));
    };
    let module = first[..first.len() - LSTM_SUFFIXES[0].len() - 1].to_string();
    let expected: BTreeSet<String> = LSTM_SUFFIXES
        .iter()
        .map(|s| format!("{module}.{s}"))
        .collect();
    let found: BTreeSet<String> = tensors.iter().map(|(n, _)| n.to_string()).collect();
    if found != expected {
        let extra: Vec<&String> = found.difference(&expected).collect();
        let missing: Vec<&String> = expected.difference(&found).collect();
        return Err(fail(if extra.is_empty() {
            format!("{missing:?} missing")
        } else {
            format!("tensors beyond one single-layer LSTM: {extra:?}")
        }));
    }
    let entry = OBS_DIM + ACT_DIM;
    match state.shape(&format!("{module}.weight_ih_l0")).as_deref() {
        Some([four_h, input]) if *input == entry && four_h % 4 == 0 && *four_h > 0 => {
            let module = module[prefix.len()..].to_string();
            Ok((module, four_h / 4))
        }
        other => Err(fail(format!(
            "weight_ih_l0 is {other:?}, expected (4H, {entry})"
        ))),
    }
}

/// Infers gaitscope's NetConfig from the state dict, checking everything it can represent.
fn infer_net(
    archive: &Archive,
    state: &StateDict,
    obs_dim: usize,
    choice: ImportEncoder,
) -> Result<(NetConfig, Option<String>), Sb3Error> {
    let path = archive.path.clone();
    let arch = |reason: String| Sb3Error::Architecture {
        path: path.clone(),
        reason,
    };
    let encoder = match (choice, obs_dim) {
        (ImportEncoder::Auto, n) if n == OBS_DIM => EncoderKind::None,
        (ImportEncoder::Auto, _) => EncoderKind::Lstm,
        (ImportEncoder::None, n) if n == OBS_DIM => EncoderKind::None,
        (ImportEncoder::Lstm, n) if n == FOLDED_DIM => EncoderKind::Lstm,
        (choice, n) => {
            return Err(arch(format!(
                "--encoder {} does not fit a {n}-d observation ({OBS_DIM}: none, {FOLDED_DIM}: lstm)",
                match choice {
                    ImportEncoder::None => "none",
                    _ => "lstm",
                }
            )));
        }
    };
    let (lstm_module, z_dim) = match encoder {
        EncoderKind::None => {
            let tensors = state.under("actor.features_extractor.");
            if !tensors.is_empty() {
                return Err(Sb3Error::Extractor {
                    path,
                    reason: "a 29-d policy in gaitscope reads the observation itself".into(),
                    tensors: list_tensors(&tensors),
                });
            }
            (None, 32)
        }
        _ => {
            let (module, hidden) = find_lstm(state, "actor")?;
            (Some(module), hidden)
        }
    };
    let features = match encoder {
        EncoderKind::None => OBS_DIM,
        _ => z_dim + OBS_DIM,
    };
    let actor = state.linear_stack("actor.latent_pi");
    let critic = state.linear_stack("critic.qf0");
    let actor_hidden: Vec<usize> = actor.iter().map(|&(_, out)| out).collect();
    let (critic_hidden, q_out) = match critic.split_last() {
        Some((last, hidden)) => (hidden.iter().map(|&(_, o)| o).collect::<Vec<_>>(), last.1),
        None => {
            return Err(Sb3Error::MissingTensor {
                path,
                name: "critic.qf0.0.weight".into(),
            });
        }
    };
    if q_out != 1 {
        return Err(arch(format!("critic.qf0 ends in {q_out} outputs, not 1")));
    }
    if actor_hidden != critic_hidden {
        return Err(arch(format!(
            "the actor's hidden sizes {actor_hidden:?} differ from the critic's {critic_hidden:?}; gaitscope's models use one list for both"
        )));
    }
    if let Some(&(input, _)) = actor.first()
        && input != features
    {
        return Err(arch(format!(
            "actor.latent_pi.0 reads {input} features; gaitscope's {encoder} model has {features}"
        )));
    }
    if state.shape("critic.qf2.0.weight").is_some() {
        return Err(arch(
            "it has more than two Q-networks (n_critics > 2); gaitscope's SAC has two".into(),
        ));
    }
    let share = archive
        .policy_kwarg("share_features_extractor")
        .and_then(Value::as_bool)
        .unwrap_or(false); // SB3's default for SAC
    let net = NetConfig {
        encoder,
        share_encoder: share && encoder.uses_window(),
        z_dim,
        hidden: actor_hidden,
        ..NetConfig::ant(encoder)
    };
    Ok((net, lstm_module))
}

/// The SB3 name of one of our parameters, and whether its layout is PyTorch's (out, in).
fn sb3_name(ours: &str, lstm_module: Option<&str>) -> Option<String> {
    let (owner, rest) = ours.split_once('.')?;
    if let Some(param) = rest.strip_prefix("encoder.lstm.") {
        return Some(format!(
            "{owner}.features_extractor.{}.{param}_l0",
            lstm_module?
        ));
    }
    let (layer, param) = rest.rsplit_once('.')?;
    let layer = match layer {
        "mean" => "mu".to_string(),
        "log_std" => "log_std".to_string(),
        _ => {
            let (module, index) = layer.split_once('.')?;
            let index: usize = index.parse().ok()?;
            let module = match module {
                "trunk" => "latent_pi".to_string(),
                q => format!("qf{}", q.strip_prefix('q')?),
            };
            format!("{module}.{}", 2 * index)
        }
    };
    Some(format!("{owner}.{layer}.{param}"))
}

/// Converts one SB3 tensor to our layout: 2-D weights transposed, biases as one row.
fn to_ours(path: &Path, name: &str, tensor: &Tensor, ours: &[usize]) -> Result<Tensor, Sb3Error> {
    let found = tensor.dims().to_vec();
    let is_bias = name
        .rsplit('.')
        .next()
        .is_some_and(|p| p.starts_with("bias"));
    let (expected, converted) = match ours {
        [1, n] if is_bias => (vec![*n], tensor.reshape((1, *n))),
        [a, b] if !is_bias => (vec![*b, *a], tensor.t().and_then(|t| t.contiguous())),
        _ => (ours.to_vec(), Ok(tensor.clone())),
    };
    if found != expected {
        return Err(Sb3Error::Shape {
            path: path.to_owned(),
            name: name.to_string(),
            expected,
            found,
        });
    }
    let converted = converted?;
    let values = converted.flatten_all()?.to_vec1::<f32>()?;
    if values.iter().any(|v| !v.is_finite()) {
        return Err(Sb3Error::NonFinite {
            path: path.to_owned(),
            name: name.to_string(),
        });
    }
    Ok(converted)
}

/// log α: `log_ent_coef` (learned coefficient) or the log of a fixed `ent_coef`.
fn log_alpha(archive: &Archive, variables: &BTreeMap<String, Tensor>) -> Result<f32, Sb3Error> {
    let path = archive.path.clone();
    if let Some(t) = variables.get("log_ent_coef") {
        let values = t.flatten_all()?.to_vec1::<f32>()?;
        return match values.as_slice() {
            [v] if v.is_finite() => Ok(*v),
            [_] => Err(Sb3Error::NonFinite {
                path,
                name: "log_ent_coef".into(),
            }),
            _ => Err(Sb3Error::Shape {
                path,
                name: "log_ent_coef".into(),
                expected: vec![1],
                found: t.dims().to_vec(),
            }),
        };
    }
    let fixed = archive.field("ent_coef").and_then(|v| match v {
        Value::Number(n) => n.as_f64(),
        Value::String(s) => s.parse::<f64>().ok(),
        _ => None,
    });
    match fixed {
        Some(v) if v > 0.0 && v.is_finite() => Ok(v.ln() as f32),
        _ => Err(Sb3Error::NotAnArchive {
            path,
            reason: "it holds neither log_ent_coef nor a fixed positive ent_coef".into(),
        }),
    }
}

fn sac_config(archive: &Archive, alpha: f64) -> SacConfig {
    let default = SacConfig::default();
    let num = |key: &str| archive.field(key).and_then(Value::as_f64);
    let count = |key: &str| {
        archive
            .field(key)
            .and_then(Value::as_u64)
            .map(|v| v as usize)
    };
    SacConfig {
        gamma: num("gamma").unwrap_or(default.gamma),
        tau: num("tau").unwrap_or(default.tau),
        learning_rate: num("learning_rate").unwrap_or(default.learning_rate),
        batch_size: count("batch_size").unwrap_or(default.batch_size),
        buffer_size: count("buffer_size").unwrap_or(default.buffer_size),
        learning_starts: count("learning_starts").unwrap_or(default.learning_starts),
        initial_alpha: alpha,
        target_entropy: num("target_entropy"),
        // SB3 trains no auxiliary loss.
        aux: default.aux,
    }
}

/// Builds the gaitscope model from an archive (nothing written but scratch files).
fn build_model(
    archive: &Archive,
    choice: ImportEncoder,
    scratch: &Path,
) -> Result<(SacModel, Provenance, u64), Sb3Error> {
    let obs_dim = check_spaces(archive)?;
    let device = Device::Cpu;
    let state = StateDict {
        path: archive.path.clone(),
        tensors: read_pth(archive, "policy.pth", &archive.policy_pth, scratch)?,
    };
    let variables = match &archive.variables_pth {
        Some(bytes) => read_pth(archive, "pytorch_variables.pth", bytes, scratch)?,
        None => BTreeMap::new(),
    };
    let (net, lstm_module) = infer_net(archive, &state, obs_dim, choice)?;
    let alpha = log_alpha(archive, &variables)?;
    let model = SacModel::new(net.clone(), f64::from(alpha).exp(), 0, &device)?;
    let mut mapping = Vec::new();
    for (ours, var) in model.all_params() {
        if ours == "log_alpha" {
            var.set(&Tensor::new(&[alpha], &device)?)?;
            continue;
        }
        let name =
            sb3_name(ours, lstm_module.as_deref()).ok_or_else(|| Sb3Error::Architecture {
                path: archive.path.clone(),
                reason: format!("gaitscope parameter '{ours}' has no SB3 counterpart"),
            })?;
        mapping.push((name, var));
    }
    // Every name accounted for before any value is read: a renamed tensor shows as both.
    let mut expected: BTreeSet<String> = mapping.iter().map(|(n, _)| n.clone()).collect();
    if net.share_encoder {
        let module = lstm_module.as_deref().unwrap_or_default();
        expected.extend(
            LSTM_SUFFIXES
                .iter()
                .map(|s| format!("critic.features_extractor.{module}.{s}")),
        );
    }
    let present: BTreeSet<String> = state.tensors.keys().cloned().collect();
    if expected != present {
        return Err(Sb3Error::TensorNames {
            path: archive.path.clone(),
            missing: expected.difference(&present).cloned().collect(),
            unexpected: present.difference(&expected).cloned().collect(),
        });
    }
    for (name, var) in mapping {
        let tensor = state.get(&name)?;
        var.set(&to_ours(&archive.path, &name, &tensor, var.dims())?)?;
    }
    // A shared extractor appears under the critic too (the same module): check it is the same.
    if net.share_encoder {
        let module = lstm_module.as_deref().unwrap_or_default();
        for suffix in LSTM_SUFFIXES {
            let actor = state.get(&format!("actor.features_extractor.{module}.{suffix}"))?;
            let name = format!("critic.features_extractor.{module}.{suffix}");
            let critic = state.get(&name)?;
            let same = actor.dims() == critic.dims()
                && actor
                    .ne(&critic)?
                    .sum_all()?
                    .to_dtype(DType::U32)?
                    .to_scalar::<u32>()?
                    == 0;
            if !same {
                return Err(Sb3Error::Architecture {
                    path: archive.path.clone(),
                    reason: format!(
                        "share_features_extractor is set but '{name}' differs from the actor's"
                    ),
                });
            }
        }
    }
    let file = archive
        .path
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_default();
    let provenance = Provenance {
        source: "stable-baselines3".into(),
        file,
        version: archive.version.clone(),
        sha256: archive.sha256.clone(),
    };
    let steps = archive
        .field("num_timesteps")
        .and_then(Value::as_u64)
        .unwrap_or(0);
    Ok((model, provenance, steps))
}

/// Imports `model_zip` into a new checkpoint directory `out`. The directory appears only when
/// the import succeeded: everything is written to a sibling scratch folder and renamed.
pub fn import_sb3(
    model_zip: &Path,
    out: &Path,
    choice: ImportEncoder,
) -> Result<ImportSummary, Sb3Error> {
    if out.exists() {
        return Err(Sb3Error::OutputExists(out.to_owned()));
    }
    let archive = Archive::read(model_zip)?;
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|source| Sb3Error::Write {
        path: parent.clone(),
        source,
    })?;
    let name = out
        .file_name()
        .map(|f| f.to_string_lossy().into_owned())
        .unwrap_or_else(|| "checkpoint".into());
    let staging = parent.join(format!(".{name}.importing-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&staging);
    std::fs::create_dir_all(&staging).map_err(|source| Sb3Error::Write {
        path: staging.clone(),
        source,
    })?;
    let result = (|| {
        let (model, provenance, steps) = build_model(&archive, choice, &staging)?;
        let record = TrainingRecord {
            env: GaitConfig::default(),
            sac: sac_config(&archive, model.alpha()?),
            seed: archive.field("seed").and_then(Value::as_u64).unwrap_or(0),
            steps_done: steps,
            episodes_done: archive
                .field("_episode_num")
                .and_then(Value::as_u64)
                .unwrap_or(0),
            wall_time_s: 0.0,
            imported_from: Some(provenance.clone()),
        };
        let meta = model.save(&staging, &record)?;
        std::fs::rename(&staging, out).map_err(|source| Sb3Error::Write {
            path: out.to_owned(),
            source,
        })?;
        Ok(ImportSummary {
            net: meta.net,
            provenance,
            tensors: meta.tensors.len(),
            alpha: model.alpha()?,
            num_timesteps: steps,
        })
    })();
    if result.is_err() {
        let _ = std::fs::remove_dir_all(&staging);
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_map_onto_sb3s() {
        let cases = [
            ("actor.trunk.0.weight", "actor.latent_pi.0.weight"),
            ("actor.trunk.1.bias", "actor.latent_pi.2.bias"),
            ("actor.mean.weight", "actor.mu.weight"),
            ("actor.log_std.bias", "actor.log_std.bias"),
            ("critic.q0.2.weight", "critic.qf0.4.weight"),
            ("critic_target.q1.0.bias", "critic_target.qf1.0.bias"),
            (
                "critic.encoder.lstm.weight_hh",
                "critic.features_extractor.rnn.weight_hh_l0",
            ),
        ];
        for (ours, theirs) in cases {
            assert_eq!(
                sb3_name(ours, Some("rnn")).as_deref(),
                Some(theirs),
                "{ours}"
            );
        }
    }

    #[test]
    fn numpy_reprs_parse() {
        let v = Value::String("[-1. -1.  1.5e+00 inf]".into());
        assert_eq!(
            parse_numpy_vector(&v),
            Some(vec![-1.0, -1.0, 1.5, f64::INFINITY])
        );
        assert_eq!(parse_numpy_vector(&Value::String("[a b]".into())), None);
    }

    #[test]
    fn weights_are_transposed_and_biases_become_rows() {
        let dev = Device::Cpu;
        let w = Tensor::new(&[[1f32, 2., 3.], [4., 5., 6.]], &dev).unwrap(); // (out 2, in 3)
        let ours = to_ours(Path::new("m.zip"), "l.weight", &w, &[3, 2]).unwrap();
        assert_eq!(
            ours.to_vec2::<f32>().unwrap(),
            [[1., 4.], [2., 5.], [3., 6.]]
        );
        let b = Tensor::new(&[7f32, 8.], &dev).unwrap();
        let ours = to_ours(Path::new("m.zip"), "l.bias", &b, &[1, 2]).unwrap();
        assert_eq!(ours.to_vec2::<f32>().unwrap(), [[7., 8.]]);
        assert!(matches!(
            to_ours(Path::new("m.zip"), "l.weight", &w, &[2, 3]),
            Err(Sb3Error::Shape { .. })
        ));
        let nan = Tensor::new(&[f32::NAN, 0.], &dev).unwrap();
        assert!(matches!(
            to_ours(Path::new("m.zip"), "l.bias", &nan, &[1, 2]),
            Err(Sb3Error::NonFinite { .. })
        ));
    }
}
