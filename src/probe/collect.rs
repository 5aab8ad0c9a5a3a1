//! Rollouts of an encoder policy across the three conditions, recording z, the raw
//! observation and the truth at every step.

use crate::damage::{Condition, ConditionChoice, N_ACTUATORS};
use crate::env::AntEnv;
use crate::policy::{ActionMode, Policy};
use crate::window::ContextWindow;

use super::ProbeError;

/// One recorded step.
#[derive(Debug, Clone)]
pub struct ProbeStep {
    pub episode: usize,
    pub t: usize,
    pub condition: Condition,
    pub z: Vec<f32>,
    pub obs: Vec<f64>,
    /// Joint i is effectively damaged: triggered and its torque scale below 1.
    pub damaged: [bool; N_ACTUATORS],
    pub fatigue: [f64; N_ACTUATORS],
    pub first_trigger: Option<usize>,
    /// First fatigue-trigger step of each joint so far.
    pub joint_triggers: [Option<usize>; N_ACTUATORS],
    /// Decrease in goal distance this step (m).
    pub progress: f64,
    /// The context window the policy read at this step (T × (obs, action), flattened), on the
    /// steps `collect` was asked to keep it for; empty elsewhere.
    pub window: Vec<f32>,
}

/// Runs `episodes_per_condition` episodes under each condition (deterministic actions) and
/// records every step. Episodes get seeds `seed, seed + 1, …`, conditions interleaved. The
/// window (592 numbers for the Ant) is kept on every `window_every`-th step (0: never).
pub fn collect(
    policy: &Policy,
    episodes_per_condition: usize,
    max_steps: usize,
    seed: u64,
    window_every: usize,
) -> Result<Vec<ProbeStep>, ProbeError> {
    let net = policy.net().clone();
    let mut steps = Vec::new();
    let mut episode = 0;
    let progress = crate::progress::bar(
        (episodes_per_condition * Condition::ALL.len()) as u64,
        "probe episodes",
    );
    for k in 0..episodes_per_condition {
        for condition in Condition::ALL {
            let mut config = policy.meta.env.clone();
            config.damage.condition = ConditionChoice::Fixed(condition);
            config.env.max_episode_steps = max_steps;
            let mut env = AntEnv::new(config, 0)?;
            let episode_seed = seed + (k * Condition::ALL.len() + condition.index()) as u64;
            let mut obs = env.reset_with_seed(episode_seed);
            let mut window = ContextWindow::new(net.context_len);
            loop {
                let decision = policy.act_one(&obs, &window, ActionMode::Deterministic, None)?;
                let out = env.step(&decision.action)?;
                let damage = env.damage();
                steps.push(ProbeStep {
                    episode,
                    t: out.step,
                    condition,
                    z: decision.z.clone().unwrap_or_default(),
                    obs: obs.to_vec(),
                    damaged: std::array::from_fn(|i| {
                        damage.triggered()[i] && damage.scale()[i] < 1.0
                    }),
                    fatigue: *damage.fatigue(),
                    first_trigger: damage.first_trigger_steps().iter().flatten().min().copied(),
                    joint_triggers: damage.first_trigger_steps(),
                    progress: out.reward.progress,
                    window: if window_every > 0 && out.step % window_every == 0 {
                        window.as_slice().to_vec()
                    } else {
                        Vec::new()
                    },
                });
                window.push(&obs, &decision.action);
                obs = out.obs;
                if out.done() {
                    break;
                }
            }
            episode += 1;
            progress.inc(1);
        }
    }
    progress.finish_and_clear();
    Ok(steps)
}
