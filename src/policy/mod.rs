//! SAC networks with an optional context encoder, and the inference API eval and the viewer use.
//!
//! Features, by encoder (SB3 SAC, the paper's Table 1):
//! - `none`: the observation (29).
//! - `lstm`: LSTM(37 → 32) over the 16-step window, z = final hidden state; features = [z, obs].
//! - `mlp-window`: MLP over the flattened window → 32, tanh; features = [z, obs].
//!
//! The actor is features → MLP [256, 256] ReLU → mean, log-std (clamped to [−20, 2]) → tanh-squashed
//! Gaussian; each critic is [features, action] → MLP [256, 256] → 1. Actor and critics own separate
//! encoders unless `share_encoder` (then, as in SB3, the actor owns it and the critic reads it
//! without gradient).

pub mod checkpoint;
pub(crate) mod gemm;
pub mod layers;
pub mod lstm_kernel;
pub mod pickle_guard;
pub mod sb3;
pub(crate) mod simd;

use candle_core::{D, Device, Result, Tensor, Var};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use layers::{Grad, Linear, Lstm, Mlp, ParamStore};

pub use checkpoint::{CheckpointError, CheckpointMeta};

pub const LOG_STD_MIN: f64 = -20.0;
pub const LOG_STD_MAX: f64 = 2.0;
/// SB3's epsilon in the tanh log-prob correction log(1 − tanh(u)² + ε).
pub const TANH_EPS: f64 = 1e-6;

/// Which feature extractor a model uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum EncoderKind {
    /// Memoryless baseline: the observation only.
    None,
    /// The paper's context encoder.
    Lstm,
    /// The ablation: an MLP over the flattened window.
    MlpWindow,
}

impl EncoderKind {
    pub fn name(self) -> &'static str {
        match self {
            EncoderKind::None => "none",
            EncoderKind::Lstm => "lstm",
            EncoderKind::MlpWindow => "mlp-window",
        }
    }

    pub fn uses_window(self) -> bool {
        self != EncoderKind::None
    }
}

impl std::fmt::Display for EncoderKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Inputs a model reads beside the observation that no deployed robot has: an oracle's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Privileged {
    /// The observation only (every model but an oracle).
    #[default]
    None,
    /// The true torque scale of each actuator, the one the next action is applied with (8
    /// values after the 29 of the observation): the damage oracle, a memoryless measured
    /// ceiling (RMA's expert).
    Damage,
    /// The same truth as the torque each actuator lost, 1 − scale: 0 while a joint is whole.
    /// Equivalent for a network up to its first layer's bias, not for training it: an input
    /// stuck at 1 while healthy trains its weights like a bias, so a death then moves the
    /// network by whatever they drifted to; an input at 0 leaves its weights to what damaged
    /// steps teach them (issue 47: a `damage` oracle learned large weights there and no
    /// damage-specific gait).
    #[serde(rename = "torque-lost")]
    TorqueLost,
}

impl Privileged {
    pub fn name(self) -> &'static str {
        match self {
            Privileged::None => "none",
            Privileged::Damage => "damage",
            Privileged::TorqueLost => "torque-lost",
        }
    }

    /// Values it adds to the observation.
    pub fn dim(self) -> usize {
        match self {
            Privileged::None => 0,
            Privileged::Damage | Privileged::TorqueLost => crate::damage::N_ACTUATORS,
        }
    }

    fn is_none(&self) -> bool {
        *self == Privileged::None
    }

    /// The values it adds for the torque scales `scales` (none for [`Privileged::None`]).
    pub fn values(
        self,
        scales: &[f64; crate::damage::N_ACTUATORS],
    ) -> impl Iterator<Item = f64> + '_ {
        let f: Option<fn(f64) -> f64> = match self {
            Privileged::None => None,
            Privileged::Damage => Some(|s| s),
            Privileged::TorqueLost => Some(|s| 1.0 - s),
        };
        f.into_iter()
            .flat_map(move |f| scales.iter().map(move |&s| f(s)))
    }

    /// The model's input for one env: the observation, then (an oracle's) the true scales as
    /// [`Self::values`] gives them.
    pub fn input(
        self,
        obs: &[f64],
        scales: &[f64; crate::damage::N_ACTUATORS],
        out: &mut Vec<f32>,
    ) {
        out.extend(obs.iter().map(|&v| v as f32));
        out.extend(self.values(scales).map(|v| v as f32));
    }
}

impl std::fmt::Display for Privileged {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Shapes of a model; stored in `checkpoint.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetConfig {
    pub encoder: EncoderKind,
    /// The actor's and critics' input: the env's observation plus [`Self::privileged`]'s.
    pub obs_dim: usize,
    pub act_dim: usize,
    /// Window length k (ignored by `none`).
    pub context_len: usize,
    pub z_dim: usize,
    /// Hidden sizes of the actor and critic MLPs.
    pub hidden: Vec<usize>,
    /// Hidden sizes of the `mlp-window` encoder.
    pub window_mlp_hidden: Vec<usize>,
    pub share_encoder: bool,
    /// An oracle's privileged inputs (absent from checkpoint.json for every other model).
    #[serde(default, skip_serializing_if = "Privileged::is_none")]
    pub privileged: Privileged,
}

impl NetConfig {
    /// The paper's model for the Ant.
    pub fn ant(encoder: EncoderKind) -> Self {
        Self {
            encoder,
            obs_dim: crate::env::OBS_DIM,
            act_dim: crate::env::ACT_DIM,
            context_len: 16,
            z_dim: 32,
            hidden: vec![256, 256],
            window_mlp_hidden: vec![64],
            share_encoder: false,
            privileged: Privileged::None,
        }
    }

    /// The paper's memoryless model given `privileged` inputs too (an oracle).
    pub fn ant_oracle(privileged: Privileged) -> Self {
        Self {
            obs_dim: crate::env::OBS_DIM + privileged.dim(),
            privileged,
            ..Self::ant(EncoderKind::None)
        }
    }

    /// Why this shape cannot be a gaitscope model of the Ant's task, if it cannot: privileged
    /// inputs only for the memoryless model (an oracle needs no memory), and an observation of
    /// exactly the task's size plus theirs.
    pub fn check_inputs(&self) -> std::result::Result<(), String> {
        if self.privileged != Privileged::None && self.encoder != EncoderKind::None {
            return Err(format!(
                "privileged inputs ({}) are for the memoryless oracle (encoder none), not encoder {}",
                self.privileged, self.encoder
            ));
        }
        let want = crate::env::OBS_DIM + self.privileged.dim();
        if self.obs_dim != want {
            return Err(format!(
                "obs_dim {} does not fit the task: {} observation values + {} privileged ({}) = {want}",
                self.obs_dim,
                crate::env::OBS_DIM,
                self.privileged.dim(),
                self.privileged
            ));
        }
        Ok(())
    }

    pub fn entry_dim(&self) -> usize {
        self.obs_dim + self.act_dim
    }

    pub fn features_dim(&self) -> usize {
        match self.encoder {
            EncoderKind::None => self.obs_dim,
            _ => self.z_dim + self.obs_dim,
        }
    }
}

/// SAC hyperparameters (Stable-Baselines3 defaults, the paper's Table 1); stored in
/// `checkpoint.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SacConfig {
    pub gamma: f64,
    /// Polyak coefficient of the target critic.
    pub tau: f64,
    pub learning_rate: f64,
    pub batch_size: usize,
    pub buffer_size: usize,
    /// Uniformly random actions (and no updates) for this many env steps.
    pub learning_starts: usize,
    pub initial_alpha: f64,
    /// Target entropy; `None` means −act_dim (−8 for the Ant).
    pub target_entropy: Option<f64>,
    /// A self-supervised auxiliary loss for the encoders (`--aux`); absent from
    /// checkpoint.json when off, so runs without it are written as before.
    #[serde(skip_serializing_if = "AuxConfig::is_off")]
    pub aux: AuxConfig,
}

/// Which auxiliary loss the encoders get (train/aux.rs), and its weight.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AuxConfig {
    pub kind: AuxKind,
    pub weight: f64,
}

impl Default for AuxConfig {
    fn default() -> Self {
        Self {
            kind: AuxKind::None,
            weight: 1.0,
        }
    }
}

impl AuxConfig {
    pub fn is_off(&self) -> bool {
        self.kind == AuxKind::None
    }
}

/// The auxiliary losses there are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AuxKind {
    /// None: today's SAC.
    #[default]
    None,
    /// Predict the normalised change of the observation from [z, o_t, a_t].
    Dynamics,
}

impl Default for SacConfig {
    fn default() -> Self {
        Self {
            gamma: 0.99,
            tau: 0.005,
            learning_rate: 3e-4,
            batch_size: 256,
            buffer_size: 300_000,
            learning_starts: 100,
            initial_alpha: 1.0,
            target_entropy: None,
            aux: AuxConfig::default(),
        }
    }
}

/// A batch of policy inputs: the window `(B, k, obs+act)` (absent for `none`) and obs `(B, obs)`.
#[derive(Debug, Clone)]
pub struct PolicyInput {
    pub window: Option<Tensor>,
    pub obs: Tensor,
}

/// Why a policy could not decide: input that does not fit its network, or candle failing.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    #[error("observation batch of {len} values is not a multiple of {obs_dim}")]
    ObservationBatch { len: usize, obs_dim: usize },
    #[error("observation value {index} is {value}; observations must be finite")]
    NonFinite { index: usize, value: f32 },
    #[error("window has {len} values, expected {batch} × {context_len} × {entry_dim}")]
    WindowSize {
        len: usize,
        batch: usize,
        context_len: usize,
        entry_dim: usize,
    },
    #[error("encoder {0} needs a context window")]
    NoWindow(EncoderKind),
    #[error("sampled actions need {batch} × {act_dim} noise values")]
    Noise { batch: usize, act_dim: usize },
    #[error("the policy returned no decision")]
    NoDecision,
    #[error(
        "only an oracle (a model trained with --privileged damage) can be told the damage; this one reads the observation alone"
    )]
    NotAnOracle,
    #[error("policy inference failed")]
    Candle(#[from] candle_core::Error),
}

impl PolicyInput {
    /// Builds a batch from flat host buffers: `obs` is B × obs_dim, `window` B × k × entry.
    pub fn from_slices(
        net: &NetConfig,
        obs: &[f32],
        window: Option<&[f32]>,
        device: &Device,
    ) -> Result<Self> {
        let b = obs.len() / net.obs_dim;
        let obs = Tensor::from_slice(obs, (b, net.obs_dim), device)?;
        let window = match (net.encoder.uses_window(), window) {
            (true, Some(w)) => Some(Tensor::from_slice(
                w,
                (b, net.context_len, net.entry_dim()),
                device,
            )?),
            (true, None) => candle_core::bail!("encoder {} needs a context window", net.encoder),
            (false, _) => None,
        };
        Ok(Self { window, obs })
    }

    pub fn batch_size(&self) -> usize {
        self.obs.dims()[0]
    }
}

/// Maps (window, obs) to features, exposing z.
#[derive(Debug, Clone)]
pub enum Encoder {
    None,
    Lstm(Lstm),
    MlpWindow(Mlp),
}

impl Encoder {
    pub fn new(
        net: &NetConfig,
        store: &mut ParamStore,
        name: &str,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        Ok(match net.encoder {
            EncoderKind::None => Encoder::None,
            EncoderKind::Lstm => Encoder::Lstm(Lstm::new(
                store,
                &format!("{name}.lstm"),
                net.entry_dim(),
                net.z_dim,
                rng,
                device,
            )?),
            EncoderKind::MlpWindow => {
                let mut dims = vec![net.context_len * net.entry_dim()];
                dims.extend(&net.window_mlp_hidden);
                dims.push(net.z_dim);
                Encoder::MlpWindow(Mlp::new(
                    store,
                    &format!("{name}.mlp"),
                    &dims,
                    false,
                    rng,
                    device,
                )?)
            }
        })
    }

    /// Returns (features, z).
    pub fn forward(&self, input: &PolicyInput, grad: Grad) -> Result<(Tensor, Option<Tensor>)> {
        let z = match (self, &input.window) {
            (Encoder::None, _) => return Ok((input.obs.clone(), None)),
            (Encoder::Lstm(lstm), Some(w)) => lstm.forward(w, grad)?,
            (Encoder::MlpWindow(mlp), Some(w)) => {
                let b = w.dims()[0];
                mlp.forward(&w.reshape((b, ()))?, grad)?.tanh()?
            }
            (_, None) => candle_core::bail!("this encoder needs a context window"),
        };
        let features = Tensor::cat(&[&z, &input.obs], D::Minus1)?;
        Ok((features, Some(z)))
    }
}

/// Output of the actor for a batch.
#[derive(Debug, Clone)]
pub struct ActorOutput {
    pub mean: Tensor,
    /// Clamped to [LOG_STD_MIN, LOG_STD_MAX].
    pub log_std: Tensor,
    pub z: Option<Tensor>,
}

#[derive(Debug, Clone)]
pub struct Actor {
    pub encoder: Encoder,
    trunk: Mlp,
    mean: Linear,
    log_std: Linear,
}

impl Actor {
    pub fn new(
        net: &NetConfig,
        store: &mut ParamStore,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        let encoder = Encoder::new(net, store, "actor.encoder", rng, device)?;
        let mut dims = vec![net.features_dim()];
        dims.extend(&net.hidden);
        let last = *dims.last().unwrap_or(&net.features_dim());
        Ok(Self {
            encoder,
            trunk: Mlp::new(store, "actor.trunk", &dims, true, rng, device)?,
            mean: Linear::new(store, "actor.mean", last, net.act_dim, rng, device)?,
            log_std: Linear::new(store, "actor.log_std", last, net.act_dim, rng, device)?,
        })
    }

    pub fn forward(&self, input: &PolicyInput, grad: Grad) -> Result<ActorOutput> {
        let (features, z) = self.encoder.forward(input, grad)?;
        let h = self.trunk.forward(&features, grad)?;
        let mean = self.mean.forward(&h, grad)?;
        let log_std = self
            .log_std
            .forward(&h, grad)?
            .clamp(LOG_STD_MIN, LOG_STD_MAX)?;
        Ok(ActorOutput { mean, log_std, z })
    }

    /// Actions (and z) for a batch of host inputs, without recording gradients.
    pub fn decide(
        &self,
        net: &NetConfig,
        device: &Device,
        obs: &[f32],
        window: Option<&[f32]>,
        mode: ActionMode,
        noise: Option<&[f32]>,
    ) -> std::result::Result<Vec<Decision>, PolicyError> {
        if obs.is_empty() || !obs.len().is_multiple_of(net.obs_dim) {
            return Err(PolicyError::ObservationBatch {
                len: obs.len(),
                obs_dim: net.obs_dim,
            });
        }
        if let Some((index, &value)) = obs.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(PolicyError::NonFinite { index, value });
        }
        let b = obs.len() / net.obs_dim;
        match window {
            Some(w) if w.len() != b * net.context_len * net.entry_dim() => {
                return Err(PolicyError::WindowSize {
                    len: w.len(),
                    batch: b,
                    context_len: net.context_len,
                    entry_dim: net.entry_dim(),
                });
            }
            None if net.encoder.uses_window() => return Err(PolicyError::NoWindow(net.encoder)),
            _ => {}
        }
        let noise_error = PolicyError::Noise {
            batch: b,
            act_dim: net.act_dim,
        };
        // Rows go through in blocks of 2 to DECIDE_BLOCK rows: candle's CPU matmul rounds a
        // product differently for a single row, and again past 64 rows (the window-MLP's
        // 592-wide input: measured on the bundled encoders, tests/batch_invariance.rs), and a
        // lane must decide the same bits alone (live, record, rollout) as in eval's lockstep
        // of any size. Larger batches are cut into blocks; a lone row goes as itself twice.
        if b > DECIDE_BLOCK {
            if let Some(e) = noise
                && e.len() != b * net.act_dim
            {
                return Err(noise_error);
            }
            let mut out = Vec::with_capacity(b);
            for start in (0..b).step_by(DECIDE_BLOCK) {
                let rows = DECIDE_BLOCK.min(b - start);
                let cut = |v: &[f32], per: usize| v[start * per..(start + rows) * per].to_vec();
                let w = window.map(|w| cut(w, net.context_len * net.entry_dim()));
                let e = noise.map(|e| cut(e, net.act_dim));
                out.extend(self.decide(
                    net,
                    device,
                    &cut(obs, net.obs_dim),
                    w.as_deref(),
                    mode,
                    e.as_deref(),
                )?);
            }
            return Ok(out);
        }
        let twice = |v: &[f32]| [v, v].concat();
        let (obs_in, window_in, noise_in);
        let (obs, window, noise, rows) = if b == 1 {
            obs_in = twice(obs);
            window_in = window.map(twice);
            noise_in = noise.map(twice);
            (&obs_in[..], window_in.as_deref(), noise_in.as_deref(), 2)
        } else {
            (obs, window, noise, b)
        };
        let input = PolicyInput::from_slices(net, obs, window, device)?;
        let out = self.forward(&input, Grad::Frozen)?;
        let action = match (mode, noise) {
            (ActionMode::Deterministic, _) => out.mean.tanh()?,
            (ActionMode::Sampled, Some(noise)) if noise.len() == rows * net.act_dim => {
                squashed_sample(
                    &out,
                    &Tensor::from_slice(noise, (rows, net.act_dim), device)?,
                )?
                .0
            }
            (ActionMode::Sampled, _) => return Err(noise_error),
        };
        let mut actions = action.to_vec2::<f32>()?;
        let mut zs: Vec<Option<Vec<f32>>> = match &out.z {
            Some(z) => z.to_vec2::<f32>()?.into_iter().map(Some).collect(),
            None => vec![None; rows],
        };
        actions.truncate(b);
        zs.truncate(b);
        Ok(actions
            .into_iter()
            .zip(zs)
            .map(|(a, z)| Decision {
                action: a.into_iter().map(f64::from).collect(),
                z,
            })
            .collect())
    }
}

/// The most rows one forward pass decides (see [`Actor::decide`]): every row's bits are the
/// same in any block of 2 to this many rows.
pub const DECIDE_BLOCK: usize = 64;

/// Squashed-Gaussian sample: a = tanh(μ + σ·ε) and its log-probability (B, 1), with the tanh
/// correction. `noise` is ε ~ N(0, 1) of the same shape as μ, drawn by the caller (seeded).
pub fn squashed_sample(out: &ActorOutput, noise: &Tensor) -> Result<(Tensor, Tensor)> {
    let std = out.log_std.exp()?;
    let u = (&out.mean + (std * noise)?)?;
    let action = u.tanh()?;
    // log N(u; μ, σ) = −ε²/2 − log σ − log(2π)/2, with (u − μ)/σ = ε exactly.
    let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    let gaussian = ((noise.sqr()? * -0.5)? - &out.log_std)?.affine(1.0, -half_log_2pi)?;
    let correction = (action.sqr()?.affine(-1.0, 1.0 + TANH_EPS))?.log()?;
    let log_prob = (gaussian - correction)?.sum_keepdim(D::Minus1)?;
    Ok((action, log_prob))
}

/// Twin Q-networks with one encoder (SB3's ContinuousCritic).
#[derive(Debug, Clone)]
pub struct Critic {
    /// `None` when the encoder is shared with (and owned by) the actor.
    pub encoder: Option<Encoder>,
    q: [Mlp; 2],
}

impl Critic {
    pub fn new(
        net: &NetConfig,
        prefix: &str,
        own_encoder: bool,
        store: &mut ParamStore,
        rng: &mut ChaCha8Rng,
        device: &Device,
    ) -> Result<Self> {
        let encoder = if own_encoder {
            Some(Encoder::new(
                net,
                store,
                &format!("{prefix}.encoder"),
                rng,
                device,
            )?)
        } else {
            None
        };
        let mut dims = vec![net.features_dim() + net.act_dim];
        dims.extend(&net.hidden);
        dims.push(1);
        let q0 = Mlp::new(store, &format!("{prefix}.q0"), &dims, false, rng, device)?;
        let q1 = Mlp::new(store, &format!("{prefix}.q1"), &dims, false, rng, device)?;
        Ok(Self {
            encoder,
            q: [q0, q1],
        })
    }

    /// Features for the Q-networks: own encoder, or the actor's (shared, read without gradient).
    pub fn features(&self, input: &PolicyInput, shared: &Encoder, grad: Grad) -> Result<Tensor> {
        match &self.encoder {
            Some(enc) => Ok(enc.forward(input, grad)?.0),
            None => Ok(shared.forward(input, Grad::Frozen)?.0.detach()),
        }
    }

    /// Both Q values, each (B, 1), from precomputed features.
    pub fn q_values(&self, features: &Tensor, action: &Tensor, grad: Grad) -> Result<[Tensor; 2]> {
        let x = Tensor::cat(&[features, action], D::Minus1)?;
        Ok([self.q[0].forward(&x, grad)?, self.q[1].forward(&x, grad)?])
    }
}

/// Actor, critic, target critic and log α: everything a SAC checkpoint holds.
#[derive(Debug, Clone)]
pub struct SacModel {
    pub net: NetConfig,
    pub actor: Actor,
    pub critic: Critic,
    pub critic_target: Critic,
    pub log_alpha: Var,
    /// Parameters by owner, in a fixed order (the checkpoint's tensor order).
    pub actor_params: ParamStore,
    pub critic_params: ParamStore,
    pub target_params: ParamStore,
    pub alpha_params: ParamStore,
}

impl SacModel {
    /// Fresh weights from `seed`; the target critic starts as a copy of the critic.
    pub fn new(net: NetConfig, initial_alpha: f64, seed: u64, device: &Device) -> Result<Self> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut actor_params = ParamStore::new();
        let actor = Actor::new(&net, &mut actor_params, &mut rng, device)?;
        let own = !net.share_encoder || !net.encoder.uses_window();
        let mut critic_params = ParamStore::new();
        let critic = Critic::new(&net, "critic", own, &mut critic_params, &mut rng, device)?;
        // The target always owns an encoder: with sharing it tracks the actor's (as in SB3).
        let mut target_params = ParamStore::new();
        let critic_target = Critic::new(
            &net,
            "critic_target",
            true,
            &mut target_params,
            &mut rng,
            device,
        )?;
        let mut alpha_params = ParamStore::new();
        let log_alpha = alpha_params.push(
            "log_alpha".into(),
            Tensor::new(&[initial_alpha.ln() as f32], device)?,
        )?;
        let model = Self {
            net,
            actor,
            critic,
            critic_target,
            log_alpha,
            actor_params,
            critic_params,
            target_params,
            alpha_params,
        };
        for (dst, src) in model.target_pairs() {
            dst.set(src.as_tensor())?;
        }
        Ok(model)
    }

    /// (target, source) parameter pairs for the Polyak update, in the target's order. The target
    /// was built like the critic (encoder, q0, q1), so with an own encoder the sources are the
    /// critic's parameters in order; with a shared one the actor's encoder comes first.
    pub fn target_pairs(&self) -> impl Iterator<Item = (&Var, &Var)> {
        let shared_encoder = self.actor_params.iter().filter(|(name, _)| {
            self.critic.encoder.is_none() && name.starts_with("actor.encoder.")
        });
        let sources = shared_encoder
            .chain(self.critic_params.iter())
            .map(|(_, v)| v);
        self.target_params.vars().zip(sources)
    }

    /// Every parameter, named, in checkpoint order.
    pub fn all_params(&self) -> impl Iterator<Item = (&str, &Var)> {
        self.actor_params
            .iter()
            .chain(self.critic_params.iter())
            .chain(self.target_params.iter())
            .chain(self.alpha_params.iter())
    }

    pub fn alpha(&self) -> Result<f64> {
        Ok(self.log_alpha.as_tensor().exp()?.to_vec1::<f32>()?[0] as f64)
    }
}

/// How the policy picks an action.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ActionMode {
    /// tanh(mean): evaluation.
    Deterministic,
    /// A squashed-Gaussian sample: exploration.
    Sampled,
}

/// One decision for one env.
#[derive(Debug, Clone, PartialEq)]
pub struct Decision {
    pub action: Vec<f64>,
    /// The context latent, for encoder policies.
    pub z: Option<Vec<f32>>,
}

/// What an oracle is told about the damage. Always the truth, except in the ablation that asks
/// what the telling is worth to the trained network: the same episodes with every scale held at
/// 1, as if nothing had happened. An oracle that does as well told nothing has not learned to
/// use what it reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OracleView {
    /// The true torque scale of every actuator.
    #[default]
    Truth,
    /// Every scale 1, whatever the damage.
    ToldHealthy,
}

/// A trained actor, ready to act: what eval, record and the live viewer load.
#[derive(Debug, Clone)]
pub struct Policy {
    pub meta: CheckpointMeta,
    pub actor: Actor,
    device: Device,
    oracle_view: OracleView,
}

impl Policy {
    pub fn new(meta: CheckpointMeta, actor: Actor, device: Device) -> Self {
        Self {
            meta,
            actor,
            device,
            oracle_view: OracleView::Truth,
        }
    }

    /// The same oracle, told `view` instead of the truth; refused for a model without
    /// privileged inputs (there is nothing to tell it).
    pub fn with_oracle_view(mut self, view: OracleView) -> std::result::Result<Self, PolicyError> {
        if view != OracleView::Truth && self.meta.net.privileged == Privileged::None {
            return Err(PolicyError::NotAnOracle);
        }
        self.oracle_view = view;
        Ok(self)
    }

    pub fn oracle_view(&self) -> OracleView {
        self.oracle_view
    }

    /// The network's input for one env, appended to `out`: the observation, then (an oracle's)
    /// the torque scales as its [`OracleView`] tells them.
    pub fn model_input(
        &self,
        obs: &[f64],
        scales: &[f64; crate::damage::N_ACTUATORS],
        out: &mut Vec<f32>,
    ) {
        let told = match self.oracle_view {
            OracleView::Truth => scales,
            OracleView::ToldHealthy => &[1.0; crate::damage::N_ACTUATORS],
        };
        self.meta.net.privileged.input(obs, told, out);
    }

    pub fn net(&self) -> &NetConfig {
        &self.meta.net
    }

    /// Decides for a batch: `obs` is B × obs_dim, `window` B × k × entry (encoder policies).
    /// `noise` (B × act_dim standard normals) is required for [`ActionMode::Sampled`].
    pub fn act_batch(
        &self,
        obs: &[f32],
        window: Option<&[f32]>,
        mode: ActionMode,
        noise: Option<&[f32]>,
    ) -> std::result::Result<Vec<Decision>, PolicyError> {
        self.actor
            .decide(&self.meta.net, &self.device, obs, window, mode, noise)
    }

    /// One decision for a single env, from its observation, the true torque scales (read by an
    /// oracle alone) and the context window (ignored by the memoryless models).
    pub fn act_one(
        &self,
        obs: &[f64],
        scales: &[f64; crate::damage::N_ACTUATORS],
        window: &crate::window::ContextWindow,
        mode: ActionMode,
        noise: Option<&[f32]>,
    ) -> std::result::Result<Decision, PolicyError> {
        let mut input = Vec::with_capacity(self.meta.net.obs_dim);
        self.model_input(obs, scales, &mut input);
        let obs = input;
        let window = self
            .meta
            .net
            .encoder
            .uses_window()
            .then(|| window.as_slice());
        self.act_batch(&obs, window, mode, noise)?
            .pop()
            .ok_or(PolicyError::NoDecision)
    }
}
