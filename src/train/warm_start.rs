//! `train --init-from DIR`: a fresh run whose networks start as a trained memoryless model's —
//! the same weights; for an oracle its privileged inputs' first-layer rows at zero, for an
//! encoder model (lstm, mlp-window) its z's first-layer rows at zero and its encoders fresh — so
//! at its first step it acts exactly as that model, whatever it is told or remembers.
//!
//! Why (issue 47): three oracles trained from scratch learned a gait per damage pattern from a
//! fraction of the data each and never matched the baseline under damage. An oracle and a
//! baseline both started from the same trained baseline and trained on for the same steps ask
//! the narrower question the calibration needs: what the true damage is worth to a policy that
//! already walks — and an encoder model started the same way asks what its memory is worth.
//! Everything else is a fresh run: its own seed, step count, Adam state and replay buffer,
//! which its policy (not uniform noise) fills for `learning_starts` steps before the first
//! update.

use std::path::{Path, PathBuf};

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use super::TrainError;
use crate::policy::{EncoderKind, Privileged, SacModel};

/// Where a warm-started run's weights came from (recorded in its `train_state.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WarmStart {
    /// The model's folder, as given.
    pub from: PathBuf,
    /// Its step count and the CRC-32 of its `model.safetensors` when it was read.
    pub steps_done: u64,
    pub model_crc32: u32,
}

/// Sets every weight of `model` (fresh) to the memoryless checkpoint in `from`'s, in the world
/// `world`: equal shapes are copied; a first layer that reads inputs the source did not have
/// gets zero rows for them — an oracle's privileged inputs (after the observation's columns, in
/// the actor's input and in the critics' before the action), an encoder model's z (before the
/// observation) — and an encoder model's encoders keep their fresh weights. Anything else that
/// differs is refused.
pub fn warm_start(
    model: &SacModel,
    from: &Path,
    world: &crate::config::WorldName,
    device: &Device,
) -> Result<WarmStart, TrainError> {
    let bad = |why: String| TrainError::Options(format!("--init-from {}: {why}", from.display()));
    let (source, meta) = SacModel::load(from, Some(EncoderKind::None), device)?;
    if meta.env.world != *world {
        return Err(bad(format!(
            "the model was trained in world '{}', this run is in '{world}' (give --world {})",
            meta.env.world, meta.env.world
        )));
    }
    let (have, want) = (source.net.privileged, model.net.privileged);
    // Where the new inputs' rows go in a first layer, and how many there are.
    let (insert_at, added) = match (have, want) {
        (h, w) if h != w && h != Privileged::None => {
            return Err(bad(format!(
                "the model reads privileged inputs '{h}', this run '{w}': only a model without \
                 them can start one with them"
            )));
        }
        (_, w) if w != Privileged::None && model.net.encoder != EncoderKind::None => {
            return Err(bad(format!(
                "privileged inputs are for the memoryless oracle, not encoder {}",
                model.net.encoder
            )));
        }
        (h, w) if h == w && model.net.encoder == EncoderKind::None => (0, 0),
        // An encoder model: its features are [z, observation], so z's rows come first.
        (h, w) if h == w => (0, model.net.z_dim),
        (_, w) => (crate::env::OBS_DIM, w.dim()),
    };
    if source.net.hidden != model.net.hidden || source.net.act_dim != model.net.act_dim {
        return Err(bad(format!(
            "its hidden layers {:?} and {} actions differ from this run's {:?} and {}",
            source.net.hidden, source.net.act_dim, model.net.hidden, model.net.act_dim
        )));
    }
    let stores = [
        (&model.actor_params, &source.actor_params),
        (&model.critic_params, &source.critic_params),
        (&model.target_params, &source.target_params),
        (&model.alpha_params, &source.alpha_params),
    ];
    for (to, src) in stores {
        // An encoder model's encoders are its own: the source has none to give.
        let fresh = |name: &str| {
            model.net.encoder != EncoderKind::None && name.split('.').nth(1) == Some("encoder")
        };
        let mut src_params = src.iter();
        for (name, var) in to.iter().filter(|(name, _)| !fresh(name)) {
            let Some((src_name, src_var)) = src_params.next() else {
                return Err(bad("its parameters do not pair with this run's".into()));
            };
            if name != src_name {
                return Err(bad(format!(
                    "parameter {src_name} where this run has {name}"
                )));
            }
            let value = src_var.as_tensor();
            let (dims, src_dims) = (var.dims().to_vec(), value.dims().to_vec());
            if dims == src_dims {
                var.set(value)?;
            } else if added > 0
                && dims.len() == 2
                && src_dims.len() == 2
                && dims[1] == src_dims[1]
                && dims[0] == src_dims[0] + added
                && src_dims[0] >= insert_at
            {
                let zeros = Tensor::zeros((added, dims[1]), DType::F32, device)?;
                let rest = src_dims[0] - insert_at;
                let mut rows = vec![zeros];
                if insert_at > 0 {
                    rows.insert(0, value.narrow(0, 0, insert_at)?);
                }
                if rest > 0 {
                    rows.push(value.narrow(0, insert_at, rest)?);
                }
                var.set(&Tensor::cat(&rows, 0)?)?;
            } else {
                return Err(bad(format!(
                    "{name} is {dims:?} here and {src_dims:?} there"
                )));
            }
        }
        if src_params.next().is_some() {
            return Err(bad("its parameters do not pair with this run's".into()));
        }
    }
    // An encoder model's target encoder was a copy of its critic's (or, shared, the actor's)
    // when the model was built; neither was touched, so the target still trails its critic.
    Ok(WarmStart {
        from: from.to_path_buf(),
        steps_done: meta.steps_done,
        model_crc32: meta.model_crc32,
    })
}
