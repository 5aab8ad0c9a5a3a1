//! Why did z move? Integrated gradients (Sundararajan et al., 2017) of a policy's latent z, or
//! of its deterministic action, with respect to its input window (16 steps × 37 features: 29
//! observation + 8 action, oldest first) — and, for the action, the current observation —
//! from an all-zero baseline (the window at reset).
//!
//! The path integral is a midpoint Riemann sum over `steps` points α = (k + ½)/steps, one
//! batched forward and one backward per output dimension through candle's autograd (the
//! encoders' reference path). Completeness — Σ attribution = output − baseline output — holds
//! up to the sum's error, which the caller can read from [`Attribution::completeness_error`].

use candle_core::{D, Device, Tensor, Var};
use serde::Serialize;

use crate::damage::N_ACTUATORS;
use crate::env::ActuatorInfo;
use crate::policy::layers::Grad;
use crate::policy::{Policy, PolicyInput};

/// Interpolation points to start from.
pub const DEFAULT_IG_STEPS: usize = 64;
/// Without a fixed count, the points double until completeness holds, up to this many.
pub const MAX_IG_STEPS: usize = 8_192;

/// What is explained.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Target {
    /// Each dimension of the encoder's latent z (the window alone decides it).
    Z,
    /// Each dimension of the deterministic action tanh(μ) (window and current observation).
    Action,
}

#[derive(Debug, thiserror::Error)]
pub enum ExplainError {
    #[error("{0}")]
    Input(String),
    #[error("attribution failed: {0}")]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error("--step {step} is beyond the episode, which ended after {steps} steps")]
    StepBeyondEpisode { step: usize, steps: usize },
    #[error(
        "--step {step}: the episode ended after {steps} steps, with no decision left to explain"
    )]
    NoDecisionLeft { step: usize, steps: usize },
}

/// One step's attribution.
#[derive(Debug, Clone, Serialize)]
pub struct Attribution {
    pub target: Target,
    /// Interpolation points used.
    pub steps: usize,
    /// The explained output at the input, and at the all-zero baseline.
    pub output: Vec<f64>,
    pub baseline_output: Vec<f64>,
    /// output dims × window steps × entry features (zeros for slots the window has not
    /// filled yet).
    pub attribution: Vec<Vec<Vec<f64>>>,
    /// For the action: output dims × observation features (the current observation's share).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub obs_attribution: Option<Vec<Vec<f64>>>,
}

impl Attribution {
    /// |Σ attribution − (output − baseline output)| per output dimension.
    pub fn completeness_error(&self) -> Vec<f64> {
        (0..self.output.len())
            .map(|d| {
                let window: f64 = self.attribution[d].iter().flatten().sum();
                let obs: f64 = self
                    .obs_attribution
                    .as_ref()
                    .map_or(0.0, |o| o[d].iter().sum());
                (window + obs - (self.output[d] - self.baseline_output[d])).abs()
            })
            .collect()
    }

    /// Whether completeness holds in every output dimension: within 1 % of the output's change
    /// or 1e-3, whichever is larger.
    pub fn is_complete(&self) -> bool {
        self.completeness_error()
            .iter()
            .zip(self.output.iter().zip(&self.baseline_output))
            .all(|(err, (o, b))| *err <= (0.01 * (o - b).abs()).max(1e-3))
    }

    /// Per window slot (oldest first): the attribution summed over features and output dims.
    pub fn per_slot(&self) -> Vec<f64> {
        let slots = self.attribution.first().map_or(0, Vec::len);
        (0..slots)
            .map(|t| {
                self.attribution
                    .iter()
                    .map(|d| d[t].iter().sum::<f64>())
                    .sum()
            })
            .collect()
    }

    /// Per feature group, summed over slots and output dims (absolute values, so opposite
    /// signs in different slots do not cancel): see [`feature_groups`].
    pub fn per_group(&self, groups: &[FeatureGroup]) -> Vec<(String, f64)> {
        groups
            .iter()
            .map(|g| {
                let total = self
                    .attribution
                    .iter()
                    .flat_map(|d| d.iter())
                    .map(|entry| g.features.iter().map(|&f| entry[f].abs()).sum::<f64>())
                    .sum();
                (g.name.clone(), total)
            })
            .collect()
    }
}

/// A named set of window-entry features (indices into the 37).
#[derive(Debug, Clone, Serialize)]
pub struct FeatureGroup {
    pub name: String,
    pub features: Vec<usize>,
}

/// The Ant's window entry in groups: each actuated joint's position, velocity and action
/// (`hip_1`, …, by the model's actuators), the torso (height, orientation, velocities), the goal
/// vector. Observation layout: qpos[2..15] (0–12), qvel (13–26), goal vector (27–28); then the
/// action (29–36, actuator order).
pub fn feature_groups(actuators: &[ActuatorInfo; N_ACTUATORS]) -> Vec<FeatureGroup> {
    let mut groups: Vec<FeatureGroup> = actuators
        .iter()
        .map(|a| {
            // Hinge joints follow the free root joint: qpos index 7 + (id − 1) → obs 5 + (id − 1),
            // qvel index 6 + (id − 1) → obs 19 + (id − 1).
            let k = a.joint_id.saturating_sub(1);
            FeatureGroup {
                name: a.joint.clone(),
                features: vec![5 + k, 19 + k, 29 + a.actuator],
            }
        })
        .collect();
    groups.push(FeatureGroup {
        name: "torso".into(),
        features: (0..5).chain(13..19).collect(),
    });
    groups.push(FeatureGroup {
        name: "goal".into(),
        features: vec![27, 28],
    });
    groups
}

/// Integrated gradients of `target` for one decision: `window` is context_len × entry (the
/// policy's own window, zero-padded where unfilled), `obs` the current observation.
pub fn integrated_gradients(
    policy: &Policy,
    window: &[f32],
    obs: &[f32],
    target: Target,
    steps: usize,
) -> Result<Attribution, ExplainError> {
    let net = policy.net();
    let (t_len, entry, obs_dim) = (net.context_len, net.entry_dim(), net.obs_dim);
    if steps == 0 || steps > 10_000 {
        return Err(ExplainError::Input(format!(
            "--ig-steps {steps} must lie in 1..=10000"
        )));
    }
    let uses_window = net.encoder.uses_window();
    if target == Target::Z && !uses_window {
        return Err(ExplainError::Input(format!(
            "a '{}' model has no latent z to explain; try --target action",
            net.encoder
        )));
    }
    if (uses_window && window.len() != t_len * entry) || obs.len() != obs_dim {
        return Err(ExplainError::Input(format!(
            "window of {} and observation of {} values, expected {} and {obs_dim}",
            window.len(),
            obs.len(),
            t_len * entry
        )));
    }
    let device = Device::Cpu;
    let window_var = uses_window
        .then(|| Var::from_vec(path_points(window, steps), (steps, t_len, entry), &device))
        .transpose()?;
    let obs_var = Var::from_vec(path_points(obs, steps), (steps, obs_dim), &device)?;
    let input = PolicyInput {
        window: window_var.as_ref().map(|v| v.as_tensor().clone()),
        obs: obs_var.as_tensor().clone(),
    };
    let outputs = forward(policy, &input, target)?;
    // The output at the input and at the baseline, by the same forward.
    let at = |x_window: Vec<f32>, x_obs: Vec<f32>| -> Result<Vec<f64>, ExplainError> {
        let input = PolicyInput {
            window: uses_window
                .then(|| Tensor::from_vec(x_window, (1, t_len, entry), &device))
                .transpose()?,
            obs: Tensor::from_vec(x_obs, (1, obs_dim), &device)?,
        };
        Ok(forward(policy, &input, target)?
            .flatten_all()?
            .to_vec1::<f32>()?
            .into_iter()
            .map(f64::from)
            .collect())
    };
    let window_len = if uses_window { t_len * entry } else { 0 };
    let output = at(window.to_vec(), obs.to_vec())?;
    let baseline_output = at(vec![0.0; window_len], vec![0.0; obs_dim])?;
    let dims = output.len();
    let mut attribution = Vec::with_capacity(dims);
    let mut obs_attribution = Vec::with_capacity(dims);
    for d in 0..dims {
        let grads = outputs.narrow(D::Minus1, d, 1)?.sum_all()?.backward()?;
        let mean_grad = |var: &Var, x: &[f32]| mean_gradient_times_input(&grads, var, x, steps);
        attribution.push(match &window_var {
            Some(var) => mean_grad(var, window)?
                .chunks(entry)
                .map(<[f64]>::to_vec)
                .collect(),
            None => Vec::new(),
        });
        if target == Target::Action {
            obs_attribution.push(mean_grad(&obs_var, obs)?);
        }
    }
    Ok(Attribution {
        target,
        steps,
        output,
        baseline_output,
        attribution,
        obs_attribution: (target == Target::Action).then_some(obs_attribution),
    })
}

/// The decision at step `step` of the episode `actor` plays from `seed` in its world (the lane
/// core: [`crate::lane::Actor::world`]), explained; with the window's feature groups.
/// `ig_steps`: a fixed number of interpolation points, or `None` to start at
/// [`DEFAULT_IG_STEPS`] and double until completeness holds (ReLU kinks along the path make
/// the sum's error fall only as 1/steps; real observations can need a few hundred).
pub fn explain_step(
    actor: &crate::lane::Actor,
    requested: &crate::config::GaitConfig,
    seed: u64,
    step: usize,
    target: Target,
    ig_steps: Option<usize>,
) -> Result<Explained, ExplainError> {
    let Some(policy) = actor.policy() else {
        return Err(ExplainError::Input(
            "explain needs a checkpoint's policy".into(),
        ));
    };
    let mut lane = crate::lane::Lane::new(actor, requested, seed)?;
    lane.run_while(
        actor,
        crate::policy::ActionMode::Deterministic,
        |lane| lane.steps() < step,
        |_| Ok::<(), ExplainError>(()),
    )?;
    if lane.steps() < step {
        return Err(ExplainError::StepBeyondEpisode {
            step,
            steps: lane.steps(),
        });
    }
    if lane.is_done() {
        return Err(ExplainError::NoDecisionLeft {
            step,
            steps: lane.steps(),
        });
    }
    let obs: Vec<f32> = lane.obs().iter().map(|&v| v as f32).collect();
    let window = lane.window().as_slice();
    let mut steps = ig_steps.unwrap_or(DEFAULT_IG_STEPS);
    let attribution = loop {
        let a = integrated_gradients(policy, window, &obs, target, steps)?;
        if ig_steps.is_some() || a.is_complete() || steps >= MAX_IG_STEPS {
            break a;
        }
        steps *= 2;
    };
    let damage = lane.env().damage();
    let torque = (0..N_ACTUATORS)
        .map(|i| {
            let t = crate::palette::Torque::of(damage.scale()[i], damage.joint_state(i));
            (damage.joint_names()[i].clone(), t.describe())
        })
        .collect();
    Ok(Explained {
        attribution,
        groups: feature_groups(lane.env().actuators()),
        window_filled: lane.window().filled(),
        window_len: actor.context_len(),
        condition: damage.condition(),
        torque,
        damage_onset: damage.damage_onset(),
    })
}

/// One decision explained, with what a reader needs beside the numbers: how full the window
/// was, and the damage at that step.
#[derive(Debug, Clone)]
pub struct Explained {
    pub attribution: Attribution,
    pub groups: Vec<FeatureGroup>,
    /// Steps the window held at this decision (0 at step 0: a reset zero-pads it all).
    pub window_filled: usize,
    pub window_len: usize,
    pub condition: crate::damage::Condition,
    /// Each joint's torque at this step, in the views' words ("full torque", "scale 0.10").
    pub torque: Vec<(String, String)>,
    /// The first step run under damage, if any came by this step.
    pub damage_onset: Option<usize>,
}

/// Interpolation points for [`z_shift_attribution`] beside a running sim: 32 keep completeness
/// within 0.1 % of the shift on the bundled LSTM and cost 0.7 ms a step (docs/debugger.md).
pub const SHIFT_POINTS: usize = 32;

/// What moved z away from where a reset leaves it: integrated gradients of the scalar
/// ‖z(x) − z(0)‖ (z(0): the latent of the all-zero window a reset starts with) over the same
/// path, one backward pass. By completeness the attributions add up to ‖z − z(0)‖: the live
/// view's heatmap, cheap enough to run beside the sim.
#[derive(Debug, Clone, Serialize)]
pub struct ShiftAttribution {
    pub steps: usize,
    /// ‖z − z(0)‖ at the input.
    pub shift: f64,
    /// Window slots (oldest first) × entry features.
    pub attribution: Vec<Vec<f64>>,
}

impl ShiftAttribution {
    /// |Σ attribution − shift|.
    pub fn completeness_error(&self) -> f64 {
        (self.attribution.iter().flatten().sum::<f64>() - self.shift).abs()
    }

    /// Slots × groups: each group's features summed (signed) per slot.
    pub fn by_group(&self, groups: &[FeatureGroup]) -> Vec<Vec<f64>> {
        self.attribution
            .iter()
            .map(|slot| {
                groups
                    .iter()
                    .map(|g| g.features.iter().map(|&f| slot[f]).sum())
                    .collect()
            })
            .collect()
    }
}

/// See [`ShiftAttribution`]; `window` is context_len × entry, as the policy reads it.
pub fn z_shift_attribution(
    policy: &Policy,
    window: &[f32],
    steps: usize,
) -> Result<ShiftAttribution, ExplainError> {
    let net = policy.net();
    let (t_len, entry, obs_dim) = (net.context_len, net.entry_dim(), net.obs_dim);
    if !net.encoder.uses_window() {
        return Err(ExplainError::Input(format!(
            "a '{}' model has no latent z to explain",
            net.encoder
        )));
    }
    if steps == 0 || steps > 10_000 || window.len() != t_len * entry {
        return Err(ExplainError::Input(format!(
            "{steps} points and a window of {} values (expected 1..=10000 and {})",
            window.len(),
            t_len * entry
        )));
    }
    let device = Device::Cpu;
    // z(0) first, as a constant; then the path, α = (k + ½)/steps.
    let zero = PolicyInput {
        window: Some(Tensor::zeros(
            (1, t_len, entry),
            candle_core::DType::F32,
            &device,
        )?),
        obs: Tensor::zeros((1, obs_dim), candle_core::DType::F32, &device)?,
    };
    let z0 = forward(policy, &zero, Target::Z)?;
    let var = Var::from_vec(path_points(window, steps), (steps, t_len, entry), &device)?;
    let input = PolicyInput {
        window: Some(var.as_tensor().clone()),
        obs: Tensor::zeros((steps, obs_dim), candle_core::DType::F32, &device)?,
    };
    let z = forward(policy, &input, Target::Z)?;
    // ‖·‖ with a floor inside the root: near α = 0 the shift vanishes and its gradient is
    // undefined; the floor (1e-12) changes the value by < 1e-6.
    let norm = z
        .broadcast_sub(&z0)?
        .sqr()?
        .sum(D::Minus1)?
        .affine(1.0, 1e-12)?
        .sqrt()?;
    let grads = norm.sum_all()?.backward()?;
    let flat = mean_gradient_times_input(&grads, &var, window, steps)?;
    // The shift at the input itself.
    let at = PolicyInput {
        window: Some(Tensor::from_vec(
            window.to_vec(),
            (1, t_len, entry),
            &device,
        )?),
        obs: Tensor::zeros((1, obs_dim), candle_core::DType::F32, &device)?,
    };
    let shift = f64::from(
        forward(policy, &at, Target::Z)?
            .sub(&z0)?
            .sqr()?
            .sum_all()?
            .sqrt()?
            .to_scalar::<f32>()?,
    );
    Ok(ShiftAttribution {
        steps,
        shift,
        attribution: flat.chunks(entry).map(<[f64]>::to_vec).collect(),
    })
}

/// The path's points, one copy of `x` per midpoint α = (k + ½)/steps (the baseline is zero).
fn path_points(x: &[f32], steps: usize) -> Vec<f32> {
    (0..steps)
        .flat_map(|k| {
            let a = (k as f32 + 0.5) / steps as f32;
            x.iter().map(move |&v| a * v)
        })
        .collect()
}

/// Each feature's integrated gradient: `var`'s gradient averaged over the path's points, times
/// the input (minus the zero baseline).
fn mean_gradient_times_input(
    grads: &candle_core::backprop::GradStore,
    var: &Var,
    x: &[f32],
    steps: usize,
) -> Result<Vec<f64>, ExplainError> {
    let len = x.len();
    let g = match grads.get(var) {
        Some(g) => g.flatten_all()?.to_vec1::<f32>()?,
        None => vec![0.0; steps * len],
    };
    Ok((0..len)
        .map(|i| {
            let sum: f64 = (0..steps).map(|k| f64::from(g[k * len + i])).sum();
            sum / steps as f64 * f64::from(x[i])
        })
        .collect())
}

/// z or tanh(μ) for a batch, weights frozen (gradients reach the inputs only).
fn forward(policy: &Policy, input: &PolicyInput, target: Target) -> candle_core::Result<Tensor> {
    match target {
        Target::Z => match policy.actor.encoder.forward(input, Grad::Frozen)?.1 {
            Some(z) => Ok(z),
            None => candle_core::bail!("this encoder has no z"),
        },
        Target::Action => policy.actor.forward(input, Grad::Frozen)?.mean.tanh(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::policy::{EncoderKind, NetConfig, SacModel};

    fn policy(kind: EncoderKind) -> Policy {
        let net = NetConfig {
            hidden: vec![32, 32],
            z_dim: 4,
            context_len: 6,
            window_mlp_hidden: vec![16],
            ..NetConfig::ant(kind)
        };
        let model = SacModel::new(net, 1.0, 3, &Device::Cpu).unwrap();
        let record = crate::policy::checkpoint::TrainingRecord {
            env: crate::GaitConfig::default(),
            sac: crate::policy::SacConfig::default(),
            seed: 3,
            steps_done: 0,
            episodes_done: 0,
            wall_time_s: 0.0,
            imported_from: None,
        };
        let dir = tempfile::tempdir().unwrap();
        model.save(dir.path(), &record).unwrap();
        Policy::load(dir.path(), None).unwrap()
    }

    fn inputs(net: &NetConfig, filled: usize) -> (Vec<f32>, Vec<f32>) {
        let entry = net.entry_dim();
        let mut window = vec![0f32; net.context_len * entry];
        // The newest `filled` slots hold data (the window is zero-padded at the old end).
        for t in net.context_len - filled..net.context_len {
            for f in 0..entry {
                window[t * entry + f] = ((t * 31 + f * 7) % 17) as f32 / 8.0 - 1.0;
            }
        }
        let obs = (0..net.obs_dim).map(|i| (i as f32 * 0.37).sin()).collect();
        (window, obs)
    }

    #[test]
    fn attributions_are_complete_and_empty_slots_carry_nothing() {
        for kind in [EncoderKind::Lstm, EncoderKind::MlpWindow] {
            let p = policy(kind);
            let (window, obs) = inputs(p.net(), 4);
            for target in [Target::Z, Target::Action] {
                let a = integrated_gradients(&p, &window, &obs, target, 64).unwrap();
                for (d, err) in a.completeness_error().iter().enumerate() {
                    let delta = (a.output[d] - a.baseline_output[d]).abs();
                    assert!(
                        *err <= (0.01 * delta).max(1e-3),
                        "{kind} {target:?} dim {d}: error {err}, output change {delta}"
                    );
                }
                // Slots 0 and 1 were never filled: exactly zero (input − baseline is 0 there).
                for d in &a.attribution {
                    assert!(d[..2].iter().flatten().all(|&v| v == 0.0));
                    assert!(d[2..].iter().flatten().any(|&v| v != 0.0));
                }
            }
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        // With one interpolation point at α = ½ the attribution is ∂f/∂x(x/2) · x: check the
        // gradient part against central differences of the forward pass.
        let p = policy(EncoderKind::Lstm);
        let (window, obs) = inputs(p.net(), 6);
        let a = integrated_gradients(&p, &window, &obs, Target::Z, 1).unwrap();
        let half: Vec<f32> = window.iter().map(|v| v * 0.5).collect();
        let f = |w: &[f32]| -> f64 {
            let input = PolicyInput {
                window: Some(Tensor::from_vec(w.to_vec(), (1, 6, 37), &Device::Cpu).unwrap()),
                obs: Tensor::from_vec(obs.clone(), (1, 29), &Device::Cpu).unwrap(),
            };
            f64::from(
                forward(&p, &input, Target::Z)
                    .unwrap()
                    .to_vec2::<f32>()
                    .unwrap()[0][1],
            )
        };
        let eps = 1e-2f32;
        for i in [3usize, 40, 100, 200] {
            let (mut up, mut down) = (half.clone(), half.clone());
            up[i] += eps;
            down[i] -= eps;
            let numeric = (f(&up) - f(&down)) / (2.0 * f64::from(eps));
            let analytic = a.attribution[1][i / 37][i % 37] / f64::from(window[i]);
            assert!(
                (numeric - analytic).abs() <= 1e-3 + 1e-2 * numeric.abs(),
                "feature {i}: {analytic} vs {numeric}"
            );
        }
    }

    #[test]
    fn the_z_shift_attribution_adds_up_to_the_shift() {
        for kind in [EncoderKind::Lstm, EncoderKind::MlpWindow] {
            let p = policy(kind);
            let (window, _) = inputs(p.net(), 4);
            let a = z_shift_attribution(&p, &window, 64).unwrap();
            assert!(a.shift > 0.0);
            assert!(
                a.completeness_error() <= (0.01 * a.shift).max(1e-3),
                "{kind}: error {} of a shift {}",
                a.completeness_error(),
                a.shift
            );
            assert!(a.attribution[..2].iter().flatten().all(|&v| v == 0.0));
            // The shift, computed by hand from the per-dimension z.
            let z = |w: &[f32]| {
                integrated_gradients(&p, w, &[0.0; 29], Target::Z, 1)
                    .unwrap()
                    .output
            };
            let (zx, z0) = (z(&window), z(&vec![0.0; window.len()]));
            let by_hand = zx
                .iter()
                .zip(&z0)
                .map(|(a, b)| (a - b) * (a - b))
                .sum::<f64>()
                .sqrt();
            assert!((a.shift - by_hand).abs() < 1e-5, "{} vs {by_hand}", a.shift);
            let env = crate::env::AntEnv::new(crate::GaitConfig::default(), 0).unwrap();
            let grouped = a.by_group(&feature_groups(env.actuators()));
            assert_eq!((grouped.len(), grouped[0].len()), (6, 10));
            let total: f64 = grouped.iter().flatten().sum();
            assert!((total - a.attribution.iter().flatten().sum::<f64>()).abs() < 1e-9);
        }
    }

    #[test]
    fn groups_cover_every_feature_once() {
        let env = crate::env::AntEnv::new(crate::GaitConfig::default(), 0).unwrap();
        let groups = feature_groups(env.actuators());
        let mut seen: Vec<usize> = groups.iter().flat_map(|g| g.features.clone()).collect();
        seen.sort_unstable();
        assert_eq!(seen, (0..37).collect::<Vec<_>>());
        let hip_4 = groups.iter().find(|g| g.name == "hip_4").unwrap();
        // hip_4 is actuator 0 and the 7th hinge (qpos 13 → obs 11, qvel 12 → obs 25).
        assert_eq!(hip_4.features, vec![11, 25, 29]);
    }
}
