//! Rollouts of an encoder policy across the three conditions, recording z, the raw
//! observation and the truth at every step.

use crate::config::GaitConfig;
use crate::damage::{Condition, ConditionChoice, N_ACTUATORS};
use crate::lane::{Actor, Lane};
use crate::policy::ActionMode;

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
    /// The episode's damage onset so far: the first fatigue trigger, or the first death the
    /// world drew (`DamageState::first_onset_steps`).
    pub first_trigger: Option<usize>,
    /// Each joint's onset so far (its fatigue trigger or its death).
    pub joint_triggers: [Option<usize>; N_ACTUATORS],
    /// Decrease in goal distance this step (m).
    pub progress: f64,
    /// The context window the policy read at this step (T × (obs, action), flattened), on the
    /// steps `collect` was asked to keep it for; empty elsewhere.
    pub window: Vec<f32>,
}

/// Probe episode `k` under `condition`: the world asked for (the actor's own world, see
/// `lane::Actor::world`, under this condition and step limit) and its seed — `seed, seed + 1,
/// …`, conditions interleaved. `collect` and `onset` draw the same episodes through it.
pub fn probe_episode(
    seed: u64,
    k: usize,
    condition: Condition,
    max_steps: usize,
) -> (GaitConfig, u64) {
    let mut requested = GaitConfig::default();
    requested.damage.condition = ConditionChoice::Fixed(condition);
    requested.env.max_episode_steps = max_steps;
    let episode_seed = seed + (k * Condition::ALL.len() + condition.index()) as u64;
    (requested, episode_seed)
}

/// Runs `episodes_per_condition` episodes under each condition (deterministic actions) and
/// records every step. Episodes get seeds `seed, seed + 1, …`, conditions interleaved. The
/// window (592 numbers for the Ant) is kept on every `window_every`-th step (0: never).
pub fn collect(
    actor: &Actor,
    episodes_per_condition: usize,
    max_steps: usize,
    seed: u64,
    window_every: usize,
) -> Result<Vec<ProbeStep>, ProbeError> {
    let mut steps = Vec::new();
    let mut episode = 0;
    let progress = crate::progress::bar(
        (episodes_per_condition * Condition::ALL.len()) as u64,
        "probe episodes",
    );
    for k in 0..episodes_per_condition {
        for condition in Condition::ALL {
            let (requested, episode_seed) = probe_episode(seed, k, condition, max_steps);
            let mut lane = Lane::new(actor, &requested, episode_seed)?;
            // The window a step's decision read (taken before it), and each joint's first
            // trigger so far (from the steps' own events).
            let window = std::cell::RefCell::new(Vec::new());
            let mut joint_triggers = [None; crate::damage::N_ACTUATORS];
            lane.run_while(
                actor,
                ActionMode::Deterministic,
                |lane| {
                    if window_every > 0 && lane.steps() % window_every == 0 {
                        *window.borrow_mut() = lane.window().as_slice().to_vec();
                    }
                    true
                },
                |record| {
                    for e in &record.events {
                        if e.kind.is_onset() {
                            joint_triggers[e.actuator].get_or_insert(e.step);
                        }
                    }
                    steps.push(ProbeStep {
                        episode,
                        t: record.step(),
                        condition,
                        z: record.z.clone().unwrap_or_default(),
                        // The observation the actor decided from, before the step.
                        obs: record.obs_before.to_vec(),
                        damaged: record.damaged(),
                        fatigue: record.fatigue,
                        first_trigger: joint_triggers.iter().flatten().min().copied(),
                        joint_triggers,
                        progress: record.outcome.reward.progress,
                        window: window.take(),
                    });
                    Ok::<(), ProbeError>(())
                },
            )?;
            episode += 1;
            progress.inc(1);
        }
    }
    progress.finish_and_clear();
    Ok(steps)
}
