//! A self-supervised auxiliary loss for the encoders (`train --aux dynamics`): each encoder
//! (the actor's, and the critic's when it has its own) gets a small head
//! [z, o_t, a_t] → 256 → the normalised change of the observation, o_{t+1} − o_t. Its mean
//! squared error × weight joins that network's loss, so z is asked to carry what predicts the
//! dynamics — never a damage label: targets come from the replay buffer's own transitions
//! (terminal ones skipped), normalised by a running mean and std of the change kept here and
//! saved with every checkpoint (`aux.safetensors`). The heads are not needed to act.

use candle_core::{D, DType, Device, Result, Tensor};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::collections::HashMap;

use super::adam::Adam;
use super::replay::Batch;
use crate::policy::layers::{Grad, Mlp, ParamStore};
use crate::policy::{AuxConfig, NetConfig};

/// The heads' file in a run folder, saved with every checkpoint.
pub const AUX_FILE: &str = "aux.safetensors";
/// Width of each head's hidden layer.
pub const AUX_HIDDEN: usize = 256;
/// A change whose spread is below this is divided by it instead (a dimension that barely
/// moves must not blow its target up).
pub const MIN_STD: f64 = 1e-3;
/// The heads' initialisation stream, apart from the policy's (so `--aux none` and the policy
/// weights of an aux run start from the same draw).
const INIT_SALT: u64 = 0xA0C5_D1A6_0000_0001;

/// Running mean and variance (Welford) of o_{t+1} − o_t over non-terminal transitions (kept in
/// train_state.json, in f64).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeltaNorm {
    pub count: f64,
    pub mean: Vec<f64>,
    /// Sum of squared deviations.
    pub m2: Vec<f64>,
}

impl DeltaNorm {
    pub fn new(obs_dim: usize) -> Self {
        Self {
            count: 0.0,
            mean: vec![0.0; obs_dim],
            m2: vec![0.0; obs_dim],
        }
    }

    /// Takes one transition's change into the statistics.
    pub fn observe(&mut self, obs: &[f64], next_obs: &[f64]) {
        self.count += 1.0;
        for (i, (o, n)) in obs.iter().zip(next_obs).enumerate() {
            let x = n - o;
            let d = x - self.mean[i];
            self.mean[i] += d / self.count;
            self.m2[i] += d * (x - self.mean[i]);
        }
    }

    pub fn std(&self) -> Vec<f64> {
        self.m2
            .iter()
            .map(|m2| {
                let var = if self.count > 1.0 {
                    m2 / self.count
                } else {
                    1.0
                };
                var.sqrt().max(MIN_STD)
            })
            .collect()
    }

    /// The normalised change of each row of `batch` (B × obs_dim), and the mask of its
    /// non-terminal rows (B × 1).
    pub fn targets(&self, batch: &Batch, obs_dim: usize) -> (Vec<f32>, Vec<f32>) {
        let std = self.std();
        let targets = (0..batch.size * obs_dim)
            .map(|k| {
                let i = k % obs_dim;
                let delta = f64::from(batch.next_obs[k]) - f64::from(batch.obs[k]);
                ((delta - self.mean[i]) / std[i]) as f32
            })
            .collect();
        let mask = batch.terminated.iter().map(|&t| 1.0 - t).collect();
        (targets, mask)
    }
}

/// What train_state.json keeps of the auxiliary heads.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AuxState {
    pub norm: DeltaNorm,
    /// Adam's step count per head (actor, then critic).
    pub adam_steps: Vec<u64>,
}

/// The auxiliary heads, their optimisers and the normalisation.
pub struct AuxHeads {
    pub config: AuxConfig,
    /// The actor's head's weights (`aux.actor.*`) and the critic's (`aux.critic.*`, empty
    /// without a critic head).
    pub actor_params: ParamStore,
    pub critic_params: ParamStore,
    pub actor: Mlp,
    /// None when the critic reads the actor's encoder (nothing of its own to shape).
    pub critic: Option<Mlp>,
    pub actor_opt: Adam,
    pub critic_opt: Option<Adam>,
    pub norm: DeltaNorm,
}

impl AuxHeads {
    /// Fresh heads for a network of shape `net` (which must have an encoder).
    pub fn new(
        config: AuxConfig,
        net: &NetConfig,
        seed: u64,
        lr: f64,
        device: &Device,
    ) -> Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ INIT_SALT);
        let dims = [
            net.z_dim + net.obs_dim + net.act_dim,
            AUX_HIDDEN,
            net.obs_dim,
        ];
        let mut actor_store = ParamStore::new();
        let actor = Mlp::new(
            &mut actor_store,
            "aux.actor",
            &dims,
            false,
            &mut rng,
            device,
        )?;
        let mut critic_store = ParamStore::new();
        let critic = if net.share_encoder {
            None
        } else {
            Some(Mlp::new(
                &mut critic_store,
                "aux.critic",
                &dims,
                false,
                &mut rng,
                device,
            )?)
        };
        let actor_opt = Adam::new(actor_store.vars(), lr);
        let critic_opt = critic.as_ref().map(|_| Adam::new(critic_store.vars(), lr));
        Ok(Self {
            config,
            actor_params: actor_store,
            critic_params: critic_store,
            actor,
            critic,
            actor_opt,
            critic_opt,
            norm: DeltaNorm::new(net.obs_dim),
        })
    }

    /// The weighted loss of `head` for latents `z` of `batch` (the mean over non-terminal rows
    /// and observation dimensions), and its unweighted value.
    pub fn loss(
        &self,
        head: &Mlp,
        z: &Tensor,
        batch: &Batch,
        device: &Device,
    ) -> Result<(Tensor, f64)> {
        let b = batch.size;
        let obs_dim = self.norm.mean.len();
        let act_dim = batch.actions.len() / b.max(1);
        let obs = Tensor::from_slice(&batch.obs, (b, obs_dim), device)?;
        let actions = Tensor::from_slice(&batch.actions, (b, act_dim), device)?;
        let x = Tensor::cat(&[z, &obs, &actions], D::Minus1)?;
        let prediction = head.forward(&x, Grad::Track)?;
        let (targets, mask) = self.norm.targets(batch, obs_dim);
        let targets = Tensor::from_vec(targets, (b, obs_dim), device)?;
        let rows = mask.iter().sum::<f32>().max(1.0);
        let mask = Tensor::from_vec(mask, (b, 1), device)?;
        let squared = (prediction - targets)?.sqr()?.broadcast_mul(&mask)?;
        let loss = (squared.sum_all()? / f64::from(rows * obs_dim as f32))?;
        let value = f64::from(loss.to_scalar::<f32>()?);
        Ok(((loss * self.config.weight)?, value))
    }

    /// Both heads' weights, actor's first.
    pub fn params(&self) -> impl Iterator<Item = (&str, &candle_core::Var)> {
        self.actor_params.iter().chain(self.critic_params.iter())
    }

    fn optimizers(&self) -> Vec<(&'static str, &Adam)> {
        let mut opts = vec![("actor", &self.actor_opt)];
        if let Some(opt) = &self.critic_opt {
            opts.push(("critic", opt));
        }
        opts
    }

    /// What train_state.json keeps of the heads: the normalisation and the Adam step counts.
    pub fn state(&self) -> AuxState {
        AuxState {
            norm: self.norm.clone(),
            adam_steps: self.optimizers().iter().map(|(_, o)| o.t).collect(),
        }
    }

    /// The heads' tensors (aux.safetensors): weights and Adam moments.
    pub fn tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let cpu = Device::Cpu;
        let mut out = Vec::new();
        for (name, var) in self.params() {
            out.push((name.to_string(), var.as_tensor().to_device(&cpu)?));
        }
        for (group, opt) in self.optimizers() {
            for (i, (m, v)) in opt.moments().enumerate() {
                out.push((
                    format!("adam.{group}.{i:03}.m"),
                    Tensor::from_slice(m, m.len(), &cpu)?,
                ));
                out.push((
                    format!("adam.{group}.{i:03}.v"),
                    Tensor::from_slice(v, v.len(), &cpu)?,
                ));
            }
        }
        Ok(out)
    }

    /// Whether every weight, moment and statistic is a finite number.
    pub fn is_finite(&self) -> Result<bool> {
        for (_, t) in self.tensors()? {
            if t.flatten_all()?
                .to_vec1::<f32>()?
                .iter()
                .any(|v| !v.is_finite())
            {
                return Ok(false);
            }
        }
        let n = &self.norm;
        Ok(n.count.is_finite() && n.mean.iter().chain(&n.m2).all(|v| v.is_finite()))
    }

    /// Puts back what [`Self::tensors`] and [`Self::state`] saved; every tensor must be there
    /// with its shape.
    pub fn restore(
        &mut self,
        saved: &HashMap<String, Tensor>,
        state: &AuxState,
    ) -> std::result::Result<(), String> {
        if state.norm.mean.len() != self.norm.mean.len()
            || state.norm.m2.len() != self.norm.m2.len()
        {
            return Err(format!(
                "the normalisation has {} dimensions, the observation {}",
                state.norm.mean.len(),
                self.norm.mean.len()
            ));
        }
        if state.adam_steps.len() != self.optimizers().len() {
            return Err(format!(
                "{} Adam step counts for {} heads",
                state.adam_steps.len(),
                self.optimizers().len()
            ));
        }
        let expected = self.tensors().map_err(|e| e.to_string())?;
        for (name, t) in &expected {
            match saved.get(name) {
                Some(s) if s.dims() == t.dims() => {}
                Some(s) => {
                    return Err(format!(
                        "tensor '{name}' has shape {:?}, expected {:?}",
                        s.dims(),
                        t.dims()
                    ));
                }
                None => return Err(format!("tensor '{name}' is missing")),
            }
        }
        let f32s = |name: &str| -> std::result::Result<Vec<f32>, String> {
            saved[name]
                .to_dtype(DType::F32)
                .and_then(|t| t.flatten_all()?.to_vec1::<f32>())
                .map_err(|e| e.to_string())
        };
        for (name, var) in self.params() {
            Tensor::from_vec(f32s(name)?, var.shape(), var.device())
                .and_then(|t| var.set(&t))
                .map_err(|e| e.to_string())?;
        }
        let restore_opt =
            |group: &str, opt: &mut Adam, t: u64| -> std::result::Result<(), String> {
                let moments = (0..opt.len())
                    .map(|i| {
                        Ok((
                            f32s(&format!("adam.{group}.{i:03}.m"))?,
                            f32s(&format!("adam.{group}.{i:03}.v"))?,
                        ))
                    })
                    .collect::<std::result::Result<Vec<_>, String>>()?;
                opt.set_moments(t, moments)
            };
        restore_opt("actor", &mut self.actor_opt, state.adam_steps[0])?;
        if let Some(opt) = &mut self.critic_opt {
            restore_opt("critic", opt, state.adam_steps[1])?;
        }
        self.norm = state.norm.clone();
        Ok(())
    }
}
