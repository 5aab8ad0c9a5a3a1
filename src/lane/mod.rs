//! The one stepping core (docs/layout.md): who acts ([`Actor`], which owns the one rule
//! for the world a model runs in), a lane's whole state ([`Lane`]; its [`LaneState`] is the
//! snapshot, the rewind point and the fork) and [`Lane::advance`]: decide → step → window push.
//! Front-ends and sinks call `advance` and read what it left; none steps the sim its own way.
//!
//! Data one way: physics ([`crate::env`]) → damage → policy → lane → sinks → front-ends.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::config::{DamageConfig, EnvConfig, GaitConfig};
use crate::damage::{DamageEvent, Edit, JointState, N_ACTUATORS, PushRecord};
use crate::env::{
    ACT_DIM, Action, AntEnv, EnvError, EnvSnapshot, N_LEGS, Observation, StepOutcome,
};
use crate::policy::{ActionMode, Policy};
use crate::window::ContextWindow;

mod saved;
pub use saved::{
    MAX_STATE_BYTES, STATE_FORMAT, SavedState, SavedWindow, StartState, StateFileError,
};

#[derive(Debug, thiserror::Error)]
pub enum LaneError {
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Policy(#[from] crate::policy::PolicyError),
    #[error("--fork-at {at} is beyond the episodes' step limit ({limit})")]
    ForkBeyondLimit { at: usize, limit: usize },
    #[error("the scripted actions end after {len} steps; step {step} has none")]
    ScriptEnded { step: usize, len: usize },
}

/// Policies that need no checkpoint.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BuiltinPolicy {
    /// Uniform in [−1, 1]⁸ from a seeded RNG.
    Random,
    /// All zeros: the Ant stands still.
    Zero,
}

impl BuiltinPolicy {
    pub fn act(self, rng: &mut impl Rng) -> Action {
        match self {
            BuiltinPolicy::Random => std::array::from_fn(|_| rng.random_range(-1.0..=1.0)),
            BuiltinPolicy::Zero => [0.0; ACT_DIM],
        }
    }
}

/// The RNG a built-in policy acts from in the episode seeded with `seed`: a stream distinct from
/// the env's, so the policy does not shift the env's draws.
pub fn policy_rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed ^ 0x9E37_79B9_7F4A_7C15)
}

/// A per-joint P(damaged) read from a policy's latent z (a fitted probe, probe.json): each
/// step's record carries it, computed once.
pub trait Readout: Send + Sync {
    fn joint_damage(&self, z: &[f32]) -> Option<[f64; N_ACTUATORS]>;
}

/// Who acts in a lane.
#[derive(Clone)]
pub enum Actor {
    /// A checkpoint's policy, and its probe's readout when a viewer shows P(damaged).
    Checkpoint {
        dir: PathBuf,
        policy: Box<Policy>,
        probe: Option<Arc<dyn Readout>>,
    },
    Builtin(BuiltinPolicy),
    /// A fixed action list, step k taking action k (a replay).
    Scripted(Arc<[Action]>),
}

impl Actor {
    /// Loads a checkpoint folder (its policy; see [`Self::with_readout`] for a probe).
    pub fn load(dir: &Path) -> Result<Self, crate::policy::checkpoint::CheckpointError> {
        Ok(Self::from_policy(dir, Policy::load(dir, None)?))
    }

    /// A checkpoint's policy, loaded by the caller.
    pub fn from_policy(dir: &Path, policy: Policy) -> Self {
        Actor::Checkpoint {
            dir: dir.to_path_buf(),
            policy: Box::new(policy),
            probe: None,
        }
    }

    /// Every step's record also carries `readout`'s P(damaged) per joint (a checkpoint's probe).
    pub fn with_readout(self, readout: Arc<dyn Readout>) -> Self {
        match self {
            Actor::Checkpoint { dir, policy, .. } => Actor::Checkpoint {
                dir,
                policy,
                probe: Some(readout),
            },
            other => other,
        }
    }

    /// The probe's P(damaged) per joint for `z`.
    fn probe_readout(&self, z: Option<&[f32]>) -> Option<[f64; N_ACTUATORS]> {
        match self {
            Actor::Checkpoint {
                probe: Some(probe), ..
            } => probe.joint_damage(z?),
            _ => None,
        }
    }

    /// The checkpoint folder's name, or the built-in policy's.
    pub fn label(&self) -> String {
        match self {
            Actor::Checkpoint { dir, .. } => crate::policy::checkpoint::model_label(dir),
            Actor::Builtin(p) => format!("{p:?}").to_lowercase(),
            Actor::Scripted(_) => "replay".into(),
        }
    }

    pub fn encoder(&self) -> String {
        match self {
            Actor::Checkpoint { policy, .. } => policy.net().encoder.to_string(),
            Actor::Builtin(_) => "none (built-in policy)".into(),
            Actor::Scripted(_) => "none (scripted actions)".into(),
        }
    }

    /// Whether the actor has a latent z: a checkpoint with a context encoder.
    pub fn has_z(&self) -> bool {
        self.policy().is_some_and(|p| p.net().encoder.uses_window())
    }

    pub fn checkpoint_dir(&self) -> Option<&Path> {
        match self {
            Actor::Checkpoint { dir, .. } => Some(dir),
            _ => None,
        }
    }

    pub fn policy(&self) -> Option<&Policy> {
        match self {
            Actor::Checkpoint { policy, .. } => Some(policy),
            _ => None,
        }
    }

    /// The world a checkpoint was trained in (none for a built-in policy or a script).
    pub fn trained_world(&self) -> Option<&GaitConfig> {
        self.policy().map(|p| &p.meta.env)
    }

    /// The world this actor runs in — the one rule, for every command: a checkpoint's own task
    /// (model, reward, damage model, context: it was trained on them) with the caller's
    /// condition, scenario and step limit; a built-in policy or a script runs in the requested
    /// world.
    pub fn world(&self, requested: &GaitConfig) -> GaitConfig {
        match self {
            Actor::Checkpoint { policy, .. } => checkpoint_world(&policy.meta.env, requested),
            Actor::Builtin(_) | Actor::Scripted(_) => requested.clone(),
        }
    }

    /// The settings of `requested` that [`Self::world`] does not use (a `--config` given to a
    /// checkpoint command): "env", "damage", "context" where they differ beyond the condition,
    /// scenario and step limit. Callers print them; nothing is dropped silently.
    pub fn unused_settings(&self, requested: &GaitConfig) -> Vec<&'static str> {
        let world = self.world(requested);
        let mut unused = Vec::new();
        if world.world != requested.world {
            unused.push("world");
        }
        if world.env != requested.env {
            unused.push("env");
        }
        if world.damage != requested.damage {
            unused.push("damage");
        }
        if world.context != requested.context {
            unused.push("context");
        }
        unused
    }

    /// Steps of (observation, action) the actor reads.
    pub fn context_len(&self) -> usize {
        match self {
            Actor::Checkpoint { policy, .. } => policy.net().context_len,
            Actor::Builtin(_) | Actor::Scripted(_) => 1,
        }
    }

    /// The action for step `step` from `obs` after `window` (and z, for encoder policies);
    /// `rng` draws a built-in policy's actions and a sampled policy's noise.
    pub fn decide(
        &self,
        step: usize,
        obs: &Observation,
        scales: &[f64; N_ACTUATORS],
        window: &ContextWindow,
        rng: &mut ChaCha8Rng,
        mode: ActionMode,
    ) -> Result<(Vec<f64>, Option<Vec<f32>>), LaneError> {
        match self {
            Actor::Checkpoint { policy, .. } => {
                let noise: Option<Vec<f32>> = (mode == ActionMode::Sampled).then(|| {
                    (0..policy.net().act_dim)
                        .map(|_| rng.sample(StandardNormal))
                        .collect()
                });
                let d = policy.act_one(obs, scales, window, mode, noise.as_deref())?;
                Ok((d.action, d.z))
            }
            Actor::Builtin(p) => Ok((p.act(rng).to_vec(), None)),
            Actor::Scripted(actions) => match actions.get(step) {
                Some(a) => Ok((a.to_vec(), None)),
                None => Err(LaneError::ScriptEnded {
                    step,
                    len: actions.len(),
                }),
            },
        }
    }
}

/// One step of a lane, owned: what every sink reads. Sinks that draw geometry read the env
/// beside it ([`Lane::env`]), which is in the state after this step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepRecord {
    /// The observation the actor decided from.
    pub obs_before: Observation,
    /// The env's side: step index, observation after, reward terms, endings, distance,
    /// commanded and applied action.
    pub outcome: StepOutcome,
    /// The policy's latent for this step (encoder policies).
    pub z: Option<Vec<f32>>,
    /// The actor's probe (probe.json), P(damaged) per joint from this step's z: computed here,
    /// once; every view shows this value.
    pub probe: Option<[f64; N_ACTUATORS]>,
    /// The damage state after the step.
    pub fatigue: [f64; N_ACTUATORS],
    pub triggered: [bool; N_ACTUATORS],
    pub scales: [f64; N_ACTUATORS],
    pub joint_states: [JointState; N_ACTUATORS],
    pub torso_xy: [f64; 2],
    /// Per leg (the model's body order), whether its foot touches the floor.
    pub contacts: [bool; N_LEGS],
    pub qpos: Vec<f64>,
    pub qvel: Vec<f64>,
    /// The damage events that belong to this step: its triggers, and the edits (by hand, by a
    /// scenario, by a fork) that took effect with it.
    pub events: Vec<DamageEvent>,
    /// The pushes that acted during this step (one that starts here is an event too).
    pub pushes: Vec<PushRecord>,
}

impl StepRecord {
    fn capture(
        env: &AntEnv,
        obs_before: Observation,
        outcome: StepOutcome,
        z: Option<Vec<f32>>,
        probe: Option<[f64; N_ACTUATORS]>,
    ) -> Self {
        let damage = env.damage();
        let events = damage.events();
        // Events are kept in step order; this step's are the tail with its step.
        let first = events
            .iter()
            .rposition(|e| e.step < outcome.step)
            .map_or(0, |k| k + 1);
        let events = events[first..]
            .iter()
            .filter(|e| e.step == outcome.step)
            .cloned()
            .collect();
        Self {
            obs_before,
            z,
            probe,
            fatigue: *damage.fatigue(),
            triggered: *damage.triggered(),
            scales: *damage.scale(),
            joint_states: std::array::from_fn(|i| damage.joint_state(i)),
            torso_xy: env.torso_xy(),
            contacts: env.foot_contacts(),
            qpos: env.qpos().to_vec(),
            qvel: env.qvel().to_vec(),
            events,
            pushes: env.last_pushes().to_vec(),
            outcome,
        }
    }

    /// Env step index in the episode, from 0.
    pub fn step(&self) -> usize {
        self.outcome.step
    }

    /// Whether the episode ended with this step.
    pub fn done(&self) -> bool {
        self.outcome.done()
    }

    /// Joints whose torque is reduced now (triggered by fatigue or failed by hand).
    pub fn damaged(&self) -> [bool; N_ACTUATORS] {
        std::array::from_fn(|i| self.triggered[i] && self.scales[i] < 1.0)
    }
}

/// The world of a checkpoint trained in `trained` (see [`Actor::world`]), for callers that
/// hold a bare [`Policy`] (eval's batched lanes).
pub fn checkpoint_world(trained: &GaitConfig, requested: &GaitConfig) -> GaitConfig {
    GaitConfig {
        world: trained.world.clone(),
        damage: DamageConfig {
            condition: requested.damage.condition,
            scenario: requested.damage.scenario.clone(),
            ..trained.damage.clone()
        },
        env: EnvConfig {
            max_episode_steps: requested.env.max_episode_steps,
            ..trained.env.clone()
        },
        context: trained.context.clone(),
    }
}

/// A counterfactual lane: the main lane's exact state before step `at`, with `edits` applied.
#[derive(Debug, Clone, PartialEq)]
pub struct Fork {
    pub at: usize,
    pub edits: Vec<Edit>,
}

/// A fork whose step never came: the episode ended first, or started after it (from a saved
/// state). The one such error of every front-end (rollout, record, video, live).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ForkBeyondEpisode {
    pub at: usize,
    pub steps: usize,
    /// The step the episode started at.
    pub first_step: usize,
}

impl std::fmt::Display for ForkBeyondEpisode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.at < self.first_step {
            write!(
                f,
                "--fork-at {} comes before step {}, where this episode starts (its saved state's \
                 step): fork at {} or later",
                self.at, self.first_step, self.first_step
            )
        } else {
            write!(
                f,
                "--fork-at {} is beyond the episode, which ended after {} steps",
                self.at, self.steps
            )
        }
    }
}

impl std::error::Error for ForkBeyondEpisode {}

impl Fork {
    /// The one fork rule: a fork branches off `lane` while its episode runs, before step `at`.
    pub fn due(&self, lane: &Lane) -> bool {
        !lane.is_done() && lane.steps() == self.at
    }

    /// What to say when `lane`'s episode ended without the fork coming due.
    pub fn beyond(&self, lane: &Lane) -> ForkBeyondEpisode {
        ForkBeyondEpisode {
            at: self.at,
            steps: lane.steps(),
            first_step: lane.first_step(),
        }
    }

    /// Checked once, before any step, for every front-end: every edit names a joint (or a
    /// push a body) of this world's model, and step `at` lies inside its step limit.
    pub fn validate(&self, world: &GaitConfig) -> Result<(), LaneError> {
        let env = AntEnv::new(world.clone(), 0)?;
        for edit in &self.edits {
            env.check_edit(edit)?;
        }
        let limit = world.env.max_episode_steps;
        if self.at >= limit {
            return Err(LaneError::ForkBeyondLimit { at: self.at, limit });
        }
        Ok(())
    }
}

/// A lane's whole state: cloning it is a snapshot; restoring it and stepping the same actions
/// repeats every bit.
#[derive(Debug, Clone)]
pub struct LaneState {
    env: EnvSnapshot,
    run: Run,
}

/// Everything of a lane besides the physics: the same in the live lane and in its snapshot.
#[derive(Debug, Clone)]
struct Run {
    window: ContextWindow,
    obs: Observation,
    rng: ChaCha8Rng,
    last: Option<StepRecord>,
    done: bool,
    /// The step this episode started at: 0, or a saved state's step.
    first_step: usize,
}

impl LaneState {
    /// Env steps of the episode at the snapshot.
    pub fn steps(&self) -> usize {
        self.env.steps()
    }
}

/// One episode being stepped: the env in the actor's world, the context window, the current
/// observation, the actor's RNG, the latest step.
pub struct Lane {
    env: AntEnv,
    run: Run,
}

impl Lane {
    /// A lane for `actor` in its world (see [`Actor::world`]), reset with `seed`.
    pub fn new(actor: &Actor, requested: &GaitConfig, seed: u64) -> Result<Self, LaneError> {
        let mut lane = Self::unstarted(actor, requested, seed)?;
        lane.reset(seed);
        Ok(lane)
    }

    /// A lane in `actor`'s world that has not started an episode: done until [`Self::reset`].
    pub fn unstarted(actor: &Actor, requested: &GaitConfig, seed: u64) -> Result<Self, LaneError> {
        let env = AntEnv::new(actor.world(requested), seed)?;
        let run = Run {
            window: ContextWindow::new(actor.context_len()),
            obs: env.observation(),
            rng: policy_rng(seed),
            last: None,
            done: true,
            first_step: 0,
        };
        Ok(Self { env, run })
    }

    /// A new episode from `seed` (the actor's RNG re-seeded from it too, so an episode is
    /// reproducible on its own).
    /// The step this episode started at: 0, or its saved state's step.
    pub fn first_step(&self) -> usize {
        self.run.first_step
    }

    pub fn reset(&mut self, seed: u64) {
        self.run.obs = self.env.reset_with_seed(seed);
        self.run.window.clear();
        self.run.rng = policy_rng(seed);
        self.run.last = None;
        self.run.done = false;
        self.run.first_step = 0;
    }

    /// A new episode from a given state (`rollout --init-state`).
    pub fn reset_to_state(
        &mut self,
        qpos: &[f64],
        qvel: &[f64],
        condition: crate::damage::Condition,
    ) -> Result<(), LaneError> {
        self.run.obs = self.env.reset_to_state(qpos, qvel, condition)?;
        self.run.window.clear();
        self.run.last = None;
        self.run.done = false;
        self.run.first_step = 0;
        Ok(())
    }

    /// One env step — the only place in gaitscope where a lane steps: the actor decides, the
    /// env steps, the window takes the pair. Returns the step's record (also kept as
    /// [`Self::last`]).
    pub fn advance(&mut self, actor: &Actor, mode: ActionMode) -> Result<&StepRecord, LaneError> {
        let (action, z) = actor.decide(
            self.env.steps(),
            &self.run.obs,
            self.env.damage().scale(),
            &self.run.window,
            &mut self.run.rng,
            mode,
        )?;
        self.apply(actor, &action, z)
    }

    /// The step half of [`Self::advance`], for an action decided elsewhere (a batch).
    fn apply(
        &mut self,
        actor: &Actor,
        action: &[f64],
        z: Option<Vec<f32>>,
    ) -> Result<&StepRecord, LaneError> {
        let out = self.env.step(action)?;
        self.run.window.push(&self.run.obs, action);
        let obs_before = std::mem::replace(&mut self.run.obs, out.obs);
        self.run.done = out.done();
        let probe = actor.probe_readout(z.as_deref());
        let record = StepRecord::capture(&self.env, obs_before, out, z, probe);
        Ok(self.run.last.insert(record))
    }

    /// The lane's state now (a snapshot, a rewind point).
    pub fn state(&self) -> LaneState {
        LaneState {
            env: self.env.snapshot(),
            run: self.run.clone(),
        }
    }

    /// Back to a state this lane (or one in the same world) had.
    pub fn restore(&mut self, state: &LaneState) -> Result<(), LaneError> {
        self.env.restore(&state.env)?;
        self.run = state.run.clone();
        Ok(())
    }

    /// A second lane from this one's exact state, `edits` applied before its next step.
    pub fn fork(&self, edits: &[Edit]) -> Result<Lane, LaneError> {
        let mut env = AntEnv::new(self.env.config().clone(), 0)?;
        env.restore(&self.env.snapshot())?;
        for edit in edits {
            env.apply_edit(edit)?;
        }
        Ok(Lane {
            env,
            run: self.run.clone(),
        })
    }

    /// A damage edit (a joint's scale, a failure, a heal, a push), from the next step on; it is
    /// logged as an event with that step.
    pub fn apply_edit(&mut self, edit: &Edit) -> Result<(), LaneError> {
        Ok(self.env.apply_edit(edit)?)
    }

    /// A hand-made change to one actuator (the panel's and page's controls), from the next step.
    pub fn apply_override(
        &mut self,
        actuator: usize,
        change: crate::damage::JointOverride,
    ) -> Result<(), LaneError> {
        Ok(self.env.apply_override(actuator, change)?)
    }

    /// Whether the world damages joints by itself — fatigue reaching τ triggers a joint, and
    /// in a world with dead actuators its deaths come — or only a hand does (the live viewer's
    /// manual condition); kept across resets.
    pub fn set_world_damage(&mut self, on: bool) {
        self.env.set_fatigue_triggers(on);
        self.env.set_world_deaths(on);
    }

    /// Steps the episode on while `go_on` (asked before each step) says so, to its end at most,
    /// each step's record to `each`: the one run-to-end loop (rollout, probe, onset, explain).
    pub fn run_while<E: From<LaneError>>(
        &mut self,
        actor: &Actor,
        mode: ActionMode,
        mut go_on: impl FnMut(&Lane) -> bool,
        mut each: impl FnMut(&StepRecord) -> Result<(), E>,
    ) -> Result<(), E> {
        while !self.is_done() && go_on(self) {
            let record = self.advance(actor, mode)?;
            each(record)?;
        }
        Ok(())
    }

    /// [`Self::run_while`] to the episode's end.
    pub fn run_to_end<E: From<LaneError>>(
        &mut self,
        actor: &Actor,
        mode: ActionMode,
        each: impl FnMut(&StepRecord) -> Result<(), E>,
    ) -> Result<(), E> {
        self.run_while(actor, mode, |_| true, each)
    }

    pub fn env(&self) -> &AntEnv {
        &self.env
    }
    pub fn obs(&self) -> &Observation {
        &self.run.obs
    }
    pub fn window(&self) -> &ContextWindow {
        &self.run.window
    }
    /// The latest step's record (none right after a reset).
    pub fn last(&self) -> Option<&StepRecord> {
        self.run.last.as_ref()
    }
    /// The latest step's outcome (none right after a reset).
    pub fn outcome(&self) -> Option<&StepOutcome> {
        self.run.last.as_ref().map(|r| &r.outcome)
    }
    /// How this lane's episode has ended so far (`ending` none while it runs), as `record` and
    /// `video` print it.
    pub fn ending(&self, label: String, episode: usize, seed: u64) -> LaneEnding {
        let out = self.outcome();
        LaneEnding {
            label,
            episode,
            seed,
            ending: out.and_then(|o| o.ending),
            steps: self.steps(),
            distance: out.map_or(self.env.goal_distance(), |o| o.distance),
        }
    }
    /// The latent the policy produced for the latest step (encoder policies).
    pub fn z(&self) -> Option<&[f32]> {
        self.run.last.as_ref()?.z.as_deref()
    }
    pub fn is_done(&self) -> bool {
        self.run.done
    }
    pub fn steps(&self) -> usize {
        self.env.steps()
    }
}

/// Advances every lane of `lanes` that is still running by one step: a checkpoint's
/// deterministic actions come from one batched policy call (eval's lockstep, bit-identical to
/// deciding lane by lane), anything else lane by lane.
pub fn advance_lockstep(
    actor: &Actor,
    lanes: &mut [Lane],
    mode: ActionMode,
) -> Result<(), LaneError> {
    let active: Vec<usize> = (0..lanes.len()).filter(|&i| !lanes[i].run.done).collect();
    if active.is_empty() {
        return Ok(());
    }
    match (actor.policy(), mode) {
        (Some(policy), ActionMode::Deterministic) => {
            let uses_window = policy.net().encoder.uses_window();
            let (mut obs, mut windows) = (Vec::new(), Vec::new());
            for &i in &active {
                let lane = &lanes[i];
                policy.model_input(&lane.run.obs, lane.env.damage().scale(), &mut obs);
                if uses_window {
                    windows.extend_from_slice(lanes[i].run.window.as_slice());
                }
            }
            let decisions =
                policy.act_batch(&obs, uses_window.then_some(&windows[..]), mode, None)?;
            for (&i, d) in active.iter().zip(decisions) {
                lanes[i].apply(actor, &d.action, d.z)?;
            }
        }
        _ => {
            for &i in &active {
                lanes[i].advance(actor, mode)?;
            }
        }
    }
    Ok(())
}

/// How one lane's episode ended.
#[derive(Debug, Clone, PartialEq)]
pub struct LaneEnding {
    /// The lane's model (with "(fork)" for a fork lane).
    pub label: String,
    /// Counted from 1.
    pub episode: usize,
    pub seed: u64,
    pub ending: Option<crate::env::Ending>,
    pub steps: usize,
    /// Goal distance at the end (m).
    pub distance: f64,
}

impl std::fmt::Display for LaneEnding {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let ending = self.ending.map_or("not ended", crate::env::Ending::name);
        write!(
            f,
            "{}: {ending} after {} steps, {:.2} m from the goal (episode {}, seed {})",
            self.label, self.steps, self.distance, self.episode, self.seed
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::damage::{Condition, ConditionChoice};
    use crate::policy::{EncoderKind, NetConfig, SacConfig, SacModel};

    fn severe(max_steps: usize) -> GaitConfig {
        let mut c = GaitConfig::default();
        c.damage.condition = ConditionChoice::Fixed(Condition::Severe);
        c.env.max_episode_steps = max_steps;
        c
    }

    /// An untrained LSTM checkpoint trained "in" a world with threshold 10 and window 8.
    fn checkpoint(dir: &Path) -> Actor {
        let mut trained = GaitConfig::default();
        trained.damage.threshold = 10.0;
        trained.context.len = 8;
        let net = NetConfig {
            hidden: vec![16, 16],
            z_dim: 4,
            context_len: 8,
            ..NetConfig::ant(EncoderKind::Lstm)
        };
        let model = SacModel::new(net, 1.0, 5, &candle_core::Device::Cpu).unwrap();
        let record = crate::policy::checkpoint::TrainingRecord {
            env: trained,
            sac: SacConfig::default(),
            seed: 5,
            steps_done: 0,
            episodes_done: 0,
            wall_time_s: 0.0,
            imported_from: None,
        };
        model.save(dir, &record).unwrap();
        Actor::load(dir).unwrap()
    }

    #[test]
    fn a_checkpoint_runs_in_its_own_world_with_the_callers_condition_and_limit() {
        let tmp = tempfile::tempdir().unwrap();
        let actor = checkpoint(tmp.path());
        let world = actor.world(&severe(123));
        assert_eq!(world.damage.threshold, 10.0, "the trained threshold");
        assert_eq!(world.context.len, 8, "the trained window");
        assert_eq!(world.env.max_episode_steps, 123, "the caller's limit");
        assert_eq!(
            world.damage.condition,
            ConditionChoice::Fixed(Condition::Severe)
        );
        // A built-in policy takes the requested world as it is.
        let random = Actor::Builtin(BuiltinPolicy::Random);
        assert_eq!(random.world(&severe(7)), severe(7));
        assert!(random.unused_settings(&severe(7)).is_empty());
        // What the checkpoint's world does not take from a request is named.
        assert_eq!(actor.unused_settings(&severe(123)), ["damage", "context"]);
        let mut asked = actor.world(&severe(123));
        assert!(actor.unused_settings(&asked).is_empty());
        asked.env.frame_skip = 2;
        assert_eq!(actor.unused_settings(&asked), ["env"]);
        // The lane is built in that world.
        let lane = Lane::new(&actor, &severe(123), 1).unwrap();
        assert_eq!(lane.env().config().damage.threshold, 10.0);
        assert_eq!(lane.window().len(), 8);
    }

    #[test]
    fn restoring_a_state_and_stepping_again_repeats_every_bit() {
        let tmp = tempfile::tempdir().unwrap();
        for actor in [
            checkpoint(tmp.path()),
            Actor::Builtin(BuiltinPolicy::Random),
        ] {
            for mode in [ActionMode::Deterministic, ActionMode::Sampled] {
                let mut lane = Lane::new(&actor, &severe(200), 4).unwrap();
                for _ in 0..20 {
                    lane.advance(&actor, mode).unwrap();
                }
                let at = lane.state();
                type Trace = Vec<(Vec<f64>, [f64; 8], Option<Vec<f32>>)>;
                let run = |lane: &mut Lane| -> Trace {
                    (0..30)
                        .map_while(|_| {
                            let r = lane.advance(&actor, mode).ok()?;
                            Some((
                                r.outcome.obs.to_vec(),
                                r.outcome.applied_action,
                                r.z.clone(),
                            ))
                        })
                        .collect()
                };
                let first = run(&mut lane);
                lane.restore(&at).unwrap();
                assert_eq!(lane.steps(), 20);
                assert_eq!(run(&mut lane), first, "{} {mode:?}", actor.label());
                // A fork with no edits is the same lane.
                lane.restore(&at).unwrap();
                let mut fork = lane.fork(&[]).unwrap();
                assert_eq!(run(&mut fork), first);
            }
        }
    }

    #[test]
    fn lockstep_batches_decide_as_lane_by_lane() {
        // A batch of 3 takes another matmul path than a batch of 1, so z may differ in the last
        // bit; over a few steps the two agree to float precision.
        let tmp = tempfile::tempdir().unwrap();
        let actor = checkpoint(tmp.path());
        let seeds = [3u64, 4, 5];
        let lanes = || -> Vec<Lane> {
            seeds
                .iter()
                .map(|&s| Lane::new(&actor, &severe(60), s).unwrap())
                .collect()
        };
        let (mut batched, mut single) = (lanes(), lanes());
        for _ in 0..10 {
            advance_lockstep(&actor, &mut batched, ActionMode::Deterministic).unwrap();
            for lane in &mut single {
                lane.advance(&actor, ActionMode::Deterministic).unwrap();
            }
            for (a, b) in batched.iter().zip(&single) {
                let (za, zb) = (a.z().unwrap(), b.z().unwrap());
                assert!(
                    za.iter().zip(zb).all(|(x, y)| (x - y).abs() < 1e-5),
                    "{za:?} {zb:?}"
                );
                let (oa, ob) = (a.outcome().unwrap(), b.outcome().unwrap());
                assert!(
                    oa.obs
                        .iter()
                        .zip(&ob.obs)
                        .all(|(x, y)| (x - y).abs() < 1e-4)
                );
            }
        }
        // Lanes that ended are left alone.
        let mut ended = lanes();
        ended[1].run.done = true;
        let before = ended[1].steps();
        advance_lockstep(&actor, &mut ended, ActionMode::Deterministic).unwrap();
        assert_eq!(ended[1].steps(), before);
        assert_eq!(ended[0].steps(), 1);
    }

    #[test]
    fn a_fork_is_validated_against_the_world_before_any_step() {
        let world = severe(100);
        let edit = |s: &str| crate::damage::Edit::parse_list(s).unwrap();
        assert!(
            Fork {
                at: 10,
                edits: edit("fail:ankle_3")
            }
            .validate(&world)
            .is_ok()
        );
        assert!(matches!(
            Fork {
                at: 100,
                edits: edit("fail:ankle_3")
            }
            .validate(&world),
            Err(LaneError::ForkBeyondLimit {
                at: 100,
                limit: 100
            })
        ));
        let err = Fork {
            at: 10,
            edits: edit("fail:knee_9"),
        }
        .validate(&world)
        .unwrap_err()
        .to_string();
        assert!(err.contains("knee_9"), "{err}");
    }

    #[test]
    fn a_scripted_lane_steps_as_the_bare_env_and_its_records_carry_the_step() {
        let world = severe(400);
        let actions: Vec<Action> = (0..120)
            .map(|t| std::array::from_fn(|i| ((t * 5 + i * 3) % 11) as f64 / 5.0 - 1.0))
            .collect();
        let actor = Actor::Scripted(actions.clone().into());
        let mut lane = Lane::new(&actor, &world, 9).unwrap();
        // The independent reference: the env stepped by hand with the same actions.
        let mut env = AntEnv::new(world, 9).unwrap();
        let mut obs = env.reset_with_seed(9);
        let mut triggers = 0;
        for action in &actions {
            let record = lane.advance(&actor, ActionMode::Deterministic).unwrap();
            let out = env.step(action).unwrap();
            assert_eq!(record.obs_before, obs);
            assert_eq!(record.outcome, out);
            assert_eq!(record.fatigue, *env.damage().fatigue());
            assert_eq!(record.scales, *env.damage().scale());
            assert_eq!(record.qpos, env.qpos());
            assert_eq!(record.contacts, env.foot_contacts());
            // This step's triggers, and only them, are in its record.
            assert_eq!(record.events.len(), out.new_triggers);
            assert!(record.events.iter().all(|e| e.step == out.step));
            triggers += record.events.len();
            obs = out.obs;
            if out.done() {
                break;
            }
        }
        assert_eq!(triggers, env.damage().events().len());
        assert!(
            triggers > 0,
            "a severe episode of 120 steps triggers a joint"
        );
        if !lane.is_done() {
            assert!(matches!(
                lane.advance(&actor, ActionMode::Deterministic),
                Err(LaneError::ScriptEnded {
                    step: 120,
                    len: 120
                })
            ));
        }
    }

    #[test]
    fn a_forks_edits_are_in_its_first_record() {
        let actor = Actor::Builtin(BuiltinPolicy::Random);
        let mut lane = Lane::new(&actor, &severe(100), 2).unwrap();
        for _ in 0..5 {
            lane.advance(&actor, ActionMode::Deterministic).unwrap();
        }
        let edits = crate::damage::Edit::parse_list("fail:hip_1").unwrap();
        let mut fork = lane.fork(&edits).unwrap();
        let first = fork.advance(&actor, ActionMode::Deterministic).unwrap();
        assert_eq!(first.step(), 5);
        let failed = first
            .events
            .iter()
            .find(|e| e.joint == "hip_1" && e.step == 5)
            .unwrap_or_else(|| panic!("{:?}", first.events));
        assert!(first.scales[failed.actuator] < 1.0);
        let next = fork.advance(&actor, ActionMode::Deterministic).unwrap();
        assert!(next.events.iter().all(|e| e.joint != "hip_1"));
    }
}
