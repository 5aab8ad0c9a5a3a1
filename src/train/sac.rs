//! One SAC gradient step, in Stable-Baselines3's order:
//! entropy coefficient → critic (against the target) → actor (against the updated critic) →
//! Polyak update of the target.

use candle_core::{Device, Result, Tensor};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use super::adam::Adam;
use super::aux::AuxHeads;
use super::fused::{AuxTargets, FusedSac};
use super::replay::Batch;
pub use super::update_stats::UpdateStats;
use crate::policy::layers::Grad;
use crate::policy::{AuxKind, PolicyInput, SacConfig, SacModel, squashed_sample};

/// How an update is computed: the same algorithm either way.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum UpdatePath {
    /// Hand-written forward and backward passes over preallocated buffers ([`FusedSac`]).
    #[default]
    Fused,
    /// candle's autograd, op by op: the reference the fused path is tested against.
    Reference,
}

/// The model plus its three optimisers. With the fused path on, the live weights and moments
/// are the fused learner's; [`Self::sync_model`] copies them into `model` and the optimisers.
pub struct SacLearner {
    pub model: SacModel,
    pub config: SacConfig,
    pub target_entropy: f64,
    pub actor_opt: Adam,
    pub critic_opt: Adam,
    pub alpha_opt: Adam,
    /// The encoders' auxiliary heads (`--aux`), trained with the actor and critic losses.
    pub aux: Option<AuxHeads>,
    device: Device,
    fused: Option<FusedSac>,
}

impl SacLearner {
    pub fn new(model: SacModel, config: SacConfig, device: Device) -> Self {
        let lr = config.learning_rate;
        let target_entropy = config.target_entropy.unwrap_or(-(model.net.act_dim as f64));
        Self {
            actor_opt: Adam::new(model.actor_params.vars(), lr),
            critic_opt: Adam::new(model.critic_params.vars(), lr),
            alpha_opt: Adam::new(model.alpha_params.vars(), lr),
            model,
            config,
            target_entropy,
            aux: None,
            device,
            fused: None,
        }
    }

    /// Fresh auxiliary heads as `config.aux` asks (none when it is off), drawn from `seed`.
    pub fn init_aux(&mut self, seed: u64) -> Result<()> {
        self.aux = match self.config.aux.kind {
            AuxKind::None => None,
            AuxKind::Dynamics => {
                if !self.model.net.encoder.uses_window() {
                    candle_core::bail!("--aux dynamics needs an encoder (it shapes z)");
                }
                Some(AuxHeads::new(
                    self.config.aux,
                    &self.model.net,
                    seed,
                    self.config.learning_rate,
                    &self.device,
                )?)
            }
        };
        Ok(())
    }

    /// A transition as it enters the replay buffer: the auxiliary loss's normalisation takes
    /// its change of observation (terminal transitions have no next state to predict).
    pub fn observe(&mut self, obs: &[f64], next_obs: &[f64], terminated: bool) {
        if let Some(aux) = &mut self.aux
            && !terminated
        {
            aux.norm.observe(obs, next_obs);
        }
    }

    /// Switches to `path`, carrying the current weights and optimiser state across.
    pub fn set_update_path(&mut self, path: UpdatePath) -> Result<()> {
        self.sync_model()?;
        self.fused = match path {
            UpdatePath::Reference => None,
            UpdatePath::Fused => Some(FusedSac::new(
                &self.model,
                [&self.actor_opt, &self.critic_opt, &self.alpha_opt],
                &self.config,
                self.target_entropy,
                self.aux.as_ref(),
            )?),
        };
        Ok(())
    }

    /// Threads each fused update may use (see [`FusedSac::set_threads`]); the reference path
    /// keeps candle's own setting.
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        match &mut self.fused {
            Some(fused) => fused.set_threads(threads),
            None => Ok(()),
        }
    }

    /// Makes `model` and the optimisers current (the fused path keeps its own copy while it
    /// trains); a no-op on the reference path.
    pub fn sync_model(&mut self) -> Result<()> {
        if let Some(fused) = &self.fused {
            fused.write_back(
                &self.model,
                [
                    &mut self.actor_opt,
                    &mut self.critic_opt,
                    &mut self.alpha_opt,
                ],
                self.aux.as_mut(),
            )?;
        }
        Ok(())
    }

    /// An exploration action (squashed-Gaussian sample) for one observation, from the live
    /// weights; `noise` is act_dim standard normals.
    pub fn explore(
        &mut self,
        obs: &[f32],
        window: Option<&[f32]>,
        noise: &[f32],
    ) -> Result<Vec<f64>> {
        if let Some(fused) = &mut self.fused {
            return Ok(fused.act(obs, window, noise));
        }
        let net = &self.model.net;
        let decision = self
            .model
            .actor
            .decide(
                net,
                &self.device,
                obs,
                window,
                crate::policy::ActionMode::Sampled,
                Some(noise),
            )
            // The training loop's own inputs: a mismatch here is a bug, reported as candle's.
            .map_err(candle_core::Error::wrap)?;
        Ok(decision
            .into_iter()
            .next()
            .map(|d| d.action)
            .unwrap_or_default())
    }

    /// The fused learner's gradients of the last update, by parameter name (tests).
    pub fn fused_gradients(&self) -> Option<NamedGradients> {
        self.fused.as_ref().map(FusedSac::gradients)
    }

    fn inputs(&self, batch: &Batch) -> Result<(PolicyInput, PolicyInput)> {
        let net = &self.model.net;
        let windows = net.encoder.uses_window();
        let now = PolicyInput::from_slices(
            net,
            &batch.obs,
            windows.then_some(&batch.window[..]),
            &self.device,
        )?;
        let next = PolicyInput::from_slices(
            net,
            &batch.next_obs,
            windows.then_some(&batch.next_window[..]),
            &self.device,
        )?;
        Ok((now, next))
    }

    fn noise(&self, b: usize, rng: &mut ChaCha8Rng) -> Result<Tensor> {
        let act = self.model.net.act_dim;
        let values: Vec<f32> = (0..b * act)
            .map(|_| rng.sample::<f32, _>(StandardNormal))
            .collect();
        Tensor::from_vec(values, (b, act), &self.device)
    }

    /// One gradient step on `batch`; `rng` draws the reparameterisation noise.
    pub fn update(&mut self, batch: &Batch, rng: &mut ChaCha8Rng) -> Result<UpdateStats> {
        match &mut self.fused {
            Some(fused) => match &self.aux {
                Some(aux) => {
                    let (targets, mask) = aux.norm.targets(batch, self.model.net.obs_dim);
                    let targets = AuxTargets {
                        targets: &targets,
                        mask: &mask,
                    };
                    fused.update(batch, rng, Some(targets))
                }
                None => fused.update(batch, rng, None),
            },
            None => Ok(self.reference_update(batch, rng)?.0),
        }
    }

    /// The update with candle's autograd; also returns every parameter's gradient by name.
    pub fn reference_update(
        &mut self,
        batch: &Batch,
        rng: &mut ChaCha8Rng,
    ) -> Result<(UpdateStats, NamedGradients)> {
        let b = batch.size;
        let (input, next_input) = self.inputs(batch)?;
        let model = &self.model;

        // --- entropy coefficient -------------------------------------------------------------
        let actor_out = model.actor.forward(&input, Grad::Track)?;
        let (action_pi, log_prob_pi) = squashed_sample(&actor_out, &self.noise(b, rng)?)?;
        let alpha = model.alpha()?;
        let alpha_loss = (model
            .log_alpha
            .as_tensor()
            .broadcast_mul(&(log_prob_pi.detach() + self.target_entropy)?)?
            .mean_all()?
            * -1.0)?;
        let alpha_grads = alpha_loss.backward()?;
        self.alpha_opt.step(&alpha_grads)?;
        let mut gradients = named_gradients(&self.model.alpha_params, &alpha_grads)?;

        // --- critic ----------------------------------------------------------------------------
        let target_q = {
            let next_out = model.actor.forward(&next_input, Grad::Frozen)?;
            let (next_action, next_log_prob) = squashed_sample(&next_out, &self.noise(b, rng)?)?;
            let next_features =
                model
                    .critic_target
                    .features(&next_input, &model.actor.encoder, Grad::Frozen)?;
            let [q1, q2] =
                model
                    .critic_target
                    .q_values(&next_features, &next_action, Grad::Frozen)?;
            let next_q = (q1.minimum(&q2)? - (next_log_prob * alpha)?)?;
            let rewards = Tensor::from_slice(&batch.rewards, (b, 1), &self.device)?;
            let not_done =
                Tensor::from_slice(&batch.terminated, (b, 1), &self.device)?.affine(-1.0, 1.0)?;
            // Bootstrap cut on termination only: a truncated episode still has a future.
            (rewards + (not_done * next_q)?.affine(self.config.gamma, 0.0)?)?.detach()
        };
        let actions = Tensor::from_slice(&batch.actions, (b, model.net.act_dim), &self.device)?;
        let features = model
            .critic
            .features(&input, &model.actor.encoder, Grad::Track)?;
        let [q1, q2] = model.critic.q_values(&features, &actions, Grad::Track)?;
        let qf1_loss = (&q1 - &target_q)?.sqr()?.mean_all()?;
        let qf2_loss = (&q2 - &target_q)?.sqr()?.mean_all()?;
        let mut critic_loss = ((&qf1_loss + &qf2_loss)? * 0.5)?;
        // The critic's auxiliary head reads z, the first z_dim features of its own encoder.
        let mut aux_critic_loss = None;
        if let Some(aux) = &self.aux
            && let Some(head) = &aux.critic
        {
            let z = features.narrow(1, 0, model.net.z_dim)?;
            let (loss, value) = aux.loss(head, &z, batch, &self.device)?;
            critic_loss = (critic_loss + loss)?;
            aux_critic_loss = Some(value);
        }
        let critic_grads = critic_loss.backward()?;
        self.critic_opt.step(&critic_grads)?;
        gradients.extend(named_gradients(&self.model.critic_params, &critic_grads)?);
        if let Some(aux) = &mut self.aux
            && let Some(opt) = &mut aux.critic_opt
        {
            opt.step(&critic_grads)?;
            gradients.extend(named_gradients(&aux.critic_params, &critic_grads)?);
        }

        // --- actor -------------------------------------------------------------------------------
        // The critic (just updated) is frozen: gradients reach the action, not its weights.
        let model = &self.model;
        let features_pi = model
            .critic
            .features(&input, &model.actor.encoder, Grad::Frozen)?
            .detach();
        let [q1_pi, q2_pi] = model
            .critic
            .q_values(&features_pi, &action_pi, Grad::Frozen)?;
        let min_q_pi = q1_pi.minimum(&q2_pi)?;
        let actor_loss = ((log_prob_pi * alpha)? - min_q_pi)?.mean_all()?;
        let (mut actor_total, mut aux_loss) = (actor_loss.clone(), None);
        if let (Some(aux), Some(z)) = (&self.aux, &actor_out.z) {
            let (loss, value) = aux.loss(&aux.actor, z, batch, &self.device)?;
            actor_total = (actor_total + loss)?;
            aux_loss = Some(value);
        }
        let actor_grads = actor_total.backward()?;
        self.actor_opt.step(&actor_grads)?;
        gradients.extend(named_gradients(&self.model.actor_params, &actor_grads)?);
        if let Some(aux) = &mut self.aux {
            // Only the actor's head: the critic's took no part in this loss.
            aux.actor_opt.step(&actor_grads)?;
            gradients.extend(named_gradients(&aux.actor_params, &actor_grads)?);
        }

        // --- target critic -------------------------------------------------------------------
        polyak_update(self.model.target_pairs(), self.config.tau)?;

        let scalar = |t: &Tensor| -> Result<f64> { Ok(t.to_scalar::<f32>()? as f64) };
        let stats = UpdateStats {
            qf1_loss: scalar(&qf1_loss)?,
            qf2_loss: scalar(&qf2_loss)?,
            qf1_values: scalar(&q1.mean_all()?)?,
            qf2_values: scalar(&q2.mean_all()?)?,
            actor_loss: scalar(&actor_loss)?,
            alpha,
            alpha_loss: scalar(&alpha_loss)?,
            aux_loss,
            aux_critic_loss,
        };
        Ok((stats, gradients))
    }
}

/// Gradients by parameter name, flattened.
pub type NamedGradients = Vec<(String, Vec<f32>)>;

/// Each parameter of `store` that has a gradient in `grads`.
fn named_gradients(
    store: &crate::policy::layers::ParamStore,
    grads: &candle_core::backprop::GradStore,
) -> Result<NamedGradients> {
    let mut out = Vec::new();
    for (name, var) in store.iter() {
        if let Some(g) = grads.get(var) {
            out.push((name.to_string(), g.flatten_all()?.to_vec1::<f32>()?));
        }
    }
    Ok(out)
}

/// target ← τ·source + (1 − τ)·target, for each pair.
pub fn polyak_update<'a>(
    pairs: impl Iterator<Item = (&'a candle_core::Var, &'a candle_core::Var)>,
    tau: f64,
) -> Result<()> {
    let tau = tau as f32;
    for (target, source) in pairs {
        let src = source.flatten_all()?.to_vec1::<f32>()?;
        let mut dst = target.flatten_all()?.to_vec1::<f32>()?;
        for (d, s) in dst.iter_mut().zip(&src) {
            *d = tau * s + (1.0 - tau) * *d;
        }
        target.set(&Tensor::from_vec(dst, target.shape(), target.device())?)?;
    }
    Ok(())
}
