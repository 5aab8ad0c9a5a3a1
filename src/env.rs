//! The damaged-Ant world: Gymnasium Ant-v4 physics and reward, a goal at (5, 5), and the
//! contact-force fatigue model of [`crate::damage`].
//!
//! Where Gymnasium defines a thing we do exactly what it does, including its quirks:
//! `get_body_com("torso")` is the torso's `xpos`, which after `mj_step` is one substep stale
//! (MuJoCo computes kinematics *before* integrating), and the healthy bonus is paid on every
//! step because Ant-v4 terminates when unhealthy.

use mujoco_rs::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::config::{ConfigError, GaitConfig};
use crate::damage::{
    Condition, ConditionChoice, DamageError, DamageState, DeadOnset, Edit, JointOverride,
    N_ACTUATORS, Push, PushRecord,
};

/// Observation: qpos[2..15] (13), qvel (14), goal − torso_xy (2).
pub const OBS_DIM: usize = 29;
pub const ACT_DIM: usize = N_ACTUATORS;
/// Generalised coordinates of the Ant: free joint (7) + 8 hinges.
pub const NQ: usize = 15;
/// Degrees of freedom of the Ant: free joint (6) + 8 hinges.
pub const NV: usize = 14;

pub type Observation = [f64; OBS_DIM];
/// The Ant's legs, in the order of the model's bodies: front_left_leg, front_right_leg,
/// back_leg, right_back_leg.
pub const N_LEGS: usize = 4;
pub type Action = [f64; ACT_DIM];

/// Gymnasium's `ant.xml`, compiled in so the binary runs from any directory.
pub const BUNDLED_ANT_XML: &str = include_str!("../assets/ant.xml");

type Physics = MjData<Box<MjModel>>;

#[derive(Debug, thiserror::Error)]
pub enum EnvError {
    #[error("cannot read model file {path}: {source}")]
    ModelRead {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("MuJoCo could not load the model {origin}: {reason}")]
    ModelLoad {
        origin: String,
        #[source]
        reason: crate::Cause,
    },
    #[error("model {origin} is not the Ant-v4 model: {reason}")]
    NotAnAnt { origin: String, reason: String },
    #[error("action has {got} values, the Ant has {expected} actuators")]
    ActionLength { expected: usize, got: usize },
    #[error("action[{index}] is {value}; actions must be finite")]
    NonFiniteAction { index: usize, value: f64 },
    #[error("the episode is over (terminated or truncated); call reset before stepping again")]
    EpisodeOver,
    #[error("initial state: {0}")]
    BadState(String),
    #[error(transparent)]
    Damage(#[from] DamageError),
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Scenario(#[from] crate::damage::scenario::ScenarioError),
    #[error("unknown body '{name}' to push (the model's bodies: {known})")]
    NoSuchBody { name: String, known: String },
    #[error(
        "pushes on {body} would add up to {newtons:.0} N at once, more than the {max} N a push \
         may have: a push's cap holds for pushes stacked on one body too",
        max = crate::damage::MAX_PUSH_NEWTONS
    )]
    StackedPushes { body: String, newtons: f64 },
    #[error(
        "{} pushes would act at once; at most {} may",
        crate::damage::MAX_ACTIVE_PUSHES + 1,
        crate::damage::MAX_ACTIVE_PUSHES
    )]
    TooManyPushes,
}

/// One actuator's place in the model: actuator → joint → body.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ActuatorInfo {
    pub actuator: usize,
    pub joint: String,
    pub joint_id: usize,
    /// Body the joint moves; its `cfrc_ext` feeds the actuator's fatigue.
    pub body_id: usize,
    pub body: String,
}

/// The reward of one step, term by term.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RewardTerms {
    /// Torso x velocity (m/s), Ant-v4's forward reward.
    pub forward: f64,
    pub healthy: f64,
    pub ctrl_cost: f64,
    /// forward + healthy − ctrl_cost: the Ant-v4 reward.
    pub native: f64,
    /// Decrease in goal distance this step (m).
    pub progress: f64,
    /// 1 when the torso is inside the success radius after this step.
    pub success: f64,
    /// native_w·native + progress_w·progress + bonus·success.
    pub total: f64,
}

/// What one env step produced.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StepOutcome {
    /// Index of this step in the episode, from 0.
    pub step: usize,
    pub obs: Observation,
    pub reward: RewardTerms,
    pub terminated: bool,
    pub truncated: bool,
    pub success: bool,
    pub healthy: bool,
    /// MuJoCo reported a diverging simulation (bad qpos/qvel/qacc) and reset its state; the
    /// episode is terminated as unhealthy.
    pub unstable: bool,
    pub distance: f64,
    pub commanded_action: Action,
    pub applied_action: Action,
    /// Actuators that triggered on this step.
    pub new_triggers: usize,
    /// How the episode ended with this step, if it did.
    pub ending: Option<Ending>,
}

/// How an episode ended. Ant-v4 terminates when the torso leaves its healthy height band; the
/// early endings seen are the torso *leaping above* it, not flips (a flipped Ant stays inside
/// the band and runs out of time), so the two are named apart.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Ending {
    /// The torso reached the goal's radius.
    Success,
    /// The torso rose above the healthy height band (`healthy_z_range`'s top).
    Leapt,
    /// The torso sank below the band.
    Collapsed,
    /// MuJoCo reported a diverging simulation.
    Unstable,
    /// The step limit, the torso upright.
    Timeout,
    /// The step limit, the torso upside down (its up axis pointing below the horizon).
    TimeoutUpsideDown,
    /// The torso turned upside down, in a world that ends the episode there
    /// (`env.terminate_upside_down`).
    Flipped,
}

impl Ending {
    pub const ALL: [Ending; 7] = [
        Ending::Success,
        Ending::Leapt,
        Ending::Collapsed,
        Ending::Flipped,
        Ending::Unstable,
        Ending::Timeout,
        Ending::TimeoutUpsideDown,
    ];

    /// Its name in every view, table and JSON line.
    pub fn name(self) -> &'static str {
        match self {
            Ending::Success => "success",
            Ending::Leapt => "leapt",
            Ending::Collapsed => "collapsed",
            Ending::Unstable => "unstable simulation",
            Ending::Timeout => "timeout",
            Ending::TimeoutUpsideDown => "timeout upside down",
            Ending::Flipped => "flipped",
        }
    }

    /// What it means, for keys and captions.
    pub fn meaning(self) -> &'static str {
        match self {
            Ending::Success => "the torso reached the goal",
            Ending::Leapt => "the torso leapt above the healthy height band (Ant-v4's termination)",
            Ending::Collapsed => "the torso sank below the healthy height band",
            Ending::Unstable => "MuJoCo reported a diverging simulation",
            Ending::Timeout => "the step limit, upright",
            Ending::TimeoutUpsideDown => "the step limit, the torso upside down",
            Ending::Flipped => "the torso turned upside down, in a world that ends episodes there",
        }
    }

    /// Whether the episode ended early without reaching the goal (a termination, not a timeout).
    pub fn is_fall(self) -> bool {
        matches!(
            self,
            Ending::Leapt | Ending::Collapsed | Ending::Flipped | Ending::Unstable
        )
    }
}

impl std::fmt::Display for Ending {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl StepOutcome {
    /// How the episode ended at this step, in words ([`Ending::name`]), or `None` while it goes
    /// on.
    pub fn ending(&self) -> Option<&'static str> {
        self.ending.map(Ending::name)
    }

    pub fn done(&self) -> bool {
        self.terminated || self.truncated
    }
}

/// The Ant-v4 goal task with joint fatigue.
pub struct AntEnv {
    config: GaitConfig,
    physics: Physics,
    damage: DamageState,
    actuators: [ActuatorInfo; N_ACTUATORS],
    torso_body: usize,
    feet: [Vec<usize>; N_LEGS],
    leg_names: [String; N_LEGS],
    leg_of_actuator: [usize; N_ACTUATORS],
    ground: Vec<usize>,
    init_qpos: [f64; NQ],
    init_qvel: [f64; NV],
    dt: f64,
    rng: ChaCha8Rng,
    steps: usize,
    prev_distance: f64,
    /// The torso's xy as the last reset or step left MuJoCo's `xpos` (Gymnasium's
    /// `get_body_com` after a step reads the last substep's forward pass); kept so a restored
    /// snapshot measures the next step's progress from the same place.
    last_xy: [f64; 2],
    done: bool,
    unstable_warnings: i32,
    /// This episode's schedule, when the config names a scenario.
    plan: Option<crate::damage::scenario::ScenarioPlan>,
    /// This episode's deaths still to come (a world with dead actuators), by onset.
    dead_plan: Vec<DeadOnset>,
    /// Whether a reset draws the world's deaths (off in the live viewer's manual condition,
    /// where only a hand damages joints); kept across resets.
    world_deaths: bool,
    /// The model's named bodies (id order), what a push may name.
    bodies: Vec<(String, usize)>,
    /// Pushes still to act, and those that acted during the last step.
    pushes: Pushes,
}

/// A push applied and not yet over.
#[derive(Debug, Clone, PartialEq)]
struct ActivePush {
    push: Push,
    body: usize,
    start: usize,
    remaining: usize,
    source: Option<String>,
}

#[derive(Debug, Clone, Default, PartialEq)]
struct Pushes {
    active: Vec<ActivePush>,
    last_step: Vec<PushRecord>,
}

/// Everything that decides an env's future, restorable exactly: MuJoCo's integration state
/// (every input of `mj_step`, the solver's warm start included), the damage state, the RNG and
/// the episode's counters. A few hundred numbers for the Ant.
#[derive(Debug, Clone)]
pub struct EnvSnapshot {
    physics: Box<[f64]>,
    damage: DamageState,
    rng: ChaCha8Rng,
    steps: usize,
    prev_distance: f64,
    last_xy: [f64; 2],
    done: bool,
    plan: Option<crate::damage::scenario::ScenarioPlan>,
    dead_plan: Vec<DeadOnset>,
    pushes: Pushes,
}

impl EnvSnapshot {
    /// Env steps taken in the episode when the snapshot was taken.
    pub fn steps(&self) -> usize {
        self.steps
    }
}

/// An env between two steps, in named numbers (a saved state file's core): what decides the
/// next steps given the actions. MuJoCo's integration state for the Ant is time, qpos, qvel and
/// the solver's warm start (no activations, mocap or user data); the torso position the
/// next step's progress is measured from; damage; pushes still acting. The RNG and a scenario's
/// later edits are not part of it (they shape resets and scenarios, not the physics).
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnvSave {
    pub step: usize,
    pub time: f64,
    pub qpos: Vec<f64>,
    pub qvel: Vec<f64>,
    pub qacc_warmstart: Vec<f64>,
    /// The torso xy the next step's forward velocity and progress start from.
    pub torso_xy: [f64; 2],
    pub goal_distance: f64,
    pub damage: crate::damage::DamageSave,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pushes: Vec<PendingPush>,
    /// Deaths the world drew for this episode that have not happened yet.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dead_plan: Vec<DeadOnset>,
}

/// A push still to act for `remaining` steps.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PendingPush {
    pub push: Push,
    pub start: usize,
    pub remaining: usize,
}

/// `mjSTATE_INTEGRATION`: FULLPHYSICS leaves out the warm start, which changes the solver's
/// result in the last bits.
const SNAPSHOT_STATE: u32 = MjtState::mjSTATE_INTEGRATION as u32;

impl AntEnv {
    /// Loads the model named by the config (or the bundled Ant) and seeds the env's RNG.
    /// The env needs a [`Self::reset`] before the first step.
    pub fn new(config: GaitConfig, seed: u64) -> Result<Self, EnvError> {
        config.validate()?;
        let (model, origin) = load_model(config.env.model_path.as_deref())?;
        let ant =
            AntLayout::inspect(&model).map_err(|reason| EnvError::NotAnAnt { origin, reason })?;
        let physics = MjData::new(Box::new(model));
        let dt = physics.model().opt().timestep * config.env.frame_skip as f64;
        let joint_names = std::array::from_fn(|i| ant.actuators[i].joint.clone());
        let damage = DamageState::new(config.damage.clone(), joint_names);
        let bodies = (1..physics.model().nbody() as usize)
            .filter_map(|b| {
                let name = physics.model().id_to_name(MjtObjBase::mjOBJ_BODY, b)?;
                (!name.is_empty()).then(|| (name.to_string(), b))
            })
            .collect();
        let mut env = Self {
            config,
            physics,
            damage,
            actuators: ant.actuators,
            torso_body: ant.torso_body,
            feet: ant.feet,
            leg_names: ant.leg_names,
            leg_of_actuator: ant.leg_of_actuator,
            ground: ant.ground,
            init_qpos: ant.init_qpos,
            init_qvel: [0.0; NV],
            dt,
            rng: ChaCha8Rng::seed_from_u64(seed),
            steps: 0,
            prev_distance: 0.0,
            last_xy: [0.0; 2],
            done: true,
            unstable_warnings: 0,
            plan: None,
            dead_plan: Vec::new(),
            world_deaths: true,
            bodies,
            pushes: Pushes::default(),
        };
        if let Some(scenario) = &env.config.damage.scenario {
            scenario.check(&env.joint_map())?;
        }
        env.physics.forward();
        env.last_xy = env.xpos_torso_xy();
        env.prev_distance = env.goal_distance();
        Ok(env)
    }

    /// Reseeds the RNG, then resets (Gymnasium's `reset(seed=...)`).
    pub fn reset_with_seed(&mut self, seed: u64) -> Observation {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
        self.reset()
    }

    /// Starts an episode: draws the condition (if random), then qpos = init + U(−c, c) and
    /// qvel = init + c·N(0, 1) with c the reset noise scale.
    pub fn reset(&mut self) -> Observation {
        let condition = match self.config.damage.condition {
            ConditionChoice::Random => {
                Condition::ALL[self.rng.random_range(0..Condition::ALL.len())]
            }
            ConditionChoice::Fixed(c) => c,
        };
        let c = self.config.env.reset_noise_scale;
        let qpos: [f64; NQ] =
            std::array::from_fn(|i| self.init_qpos[i] + self.rng.random_range(-c..=c));
        let qvel: [f64; NV] = std::array::from_fn(|i| {
            let n: f64 = self.rng.sample(StandardNormal);
            self.init_qvel[i] + c * n
        });
        self.start_episode(&qpos, &qvel, condition)
    }

    /// Starts an episode from a given state (no noise), as the replay command does.
    pub fn reset_to_state(
        &mut self,
        qpos: &[f64],
        qvel: &[f64],
        condition: Condition,
    ) -> Result<Observation, EnvError> {
        check_state_vector("qpos", qpos, NQ)?;
        check_state_vector("qvel", qvel, NV)?;
        Ok(self.start_episode(qpos, qvel, condition))
    }

    fn start_episode(&mut self, qpos: &[f64], qvel: &[f64], condition: Condition) -> Observation {
        // Gymnasium: mj_resetData, then set_state (qpos, qvel, mj_forward).
        self.physics.reset();
        self.physics.qpos_mut().copy_from_slice(qpos);
        self.physics.qvel_mut().copy_from_slice(qvel);
        self.physics.forward();
        // A scenario: its fatigue rule, and this episode's draws (from the episode's RNG, after
        // the reset noise, so the start state is the same with or without it).
        let mut condition = condition;
        self.plan = None;
        if !self.config.damage.fatigue {
            self.damage.set_fatigue_triggers(false);
        }
        // A scenario whose rule is off damages the Ant alone: neither fatigue nor the world's
        // deaths act beside it.
        let mut scenario_alone = false;
        if let Some(scenario) = self.config.damage.scenario.clone() {
            use crate::damage::scenario::FatigueRule;
            match scenario.fatigue {
                FatigueRule::Off => {
                    self.damage.set_fatigue_triggers(false);
                    scenario_alone = true;
                }
                FatigueRule::On => self.damage.set_fatigue_triggers(true),
                FatigueRule::OnWith(c) => {
                    self.damage.set_fatigue_triggers(true);
                    condition = c;
                }
            }
            let seed: u64 = self.rng.random();
            // Checked against this model at construction, so planning cannot fail here.
            self.plan = scenario.plan(seed, &self.joint_map()).ok();
        }
        // The world's deaths: drawn after the scenario's (the paper's world draws nothing, so
        // its episodes are as before).
        self.dead_plan = match &self.config.damage.dead {
            Some(dead) => {
                // Drawn either way, so the episode's later draws do not depend on it.
                let seed: u64 = self.rng.random();
                if self.world_deaths && !scenario_alone {
                    dead.plan(condition, seed, &self.leg_actuators())
                } else {
                    Vec::new()
                }
            }
            None => Vec::new(),
        };
        self.damage.reset(condition);
        self.pushes = Pushes::default();
        self.steps = 0;
        self.done = false;
        self.kill_due();
        self.unstable_warnings = self.divergence_warnings();
        self.last_xy = self.xpos_torso_xy();
        self.prev_distance = self.goal_distance();
        self.observation()
    }

    /// The state to [`Self::restore`] later (a rewind) or into another env of the same config
    /// (a fork).
    pub fn snapshot(&self) -> EnvSnapshot {
        EnvSnapshot {
            physics: self.physics.state(SNAPSHOT_STATE),
            damage: self.damage.clone(),
            rng: self.rng.clone(),
            steps: self.steps,
            prev_distance: self.prev_distance,
            last_xy: self.last_xy,
            done: self.done,
            plan: self.plan.clone(),
            dead_plan: self.dead_plan.clone(),
            pushes: self.pushes.clone(),
        }
    }

    /// Puts the env back into `snapshot`'s state: stepping on from here repeats, bit for bit,
    /// what followed the snapshot (given the same actions).
    pub fn restore(&mut self, snapshot: &EnvSnapshot) -> Result<(), EnvError> {
        self.physics
            .set_state(&snapshot.physics, SNAPSHOT_STATE)
            .map_err(|e| EnvError::BadState(format!("restoring a snapshot: {e:?}")))?;
        // Derived quantities (body poses, contacts) for whoever draws the restored state; the
        // next mj_step recomputes them from the state anyway.
        self.physics.forward();
        self.physics.rne_post_constraint();
        self.damage = snapshot.damage.clone();
        self.rng = snapshot.rng.clone();
        self.steps = snapshot.steps;
        self.prev_distance = snapshot.prev_distance;
        self.last_xy = snapshot.last_xy;
        self.done = snapshot.done;
        self.plan = snapshot.plan.clone();
        self.dead_plan = snapshot.dead_plan.clone();
        self.pushes = snapshot.pushes.clone();
        // Only warnings raised by later steps count as divergence.
        self.unstable_warnings = self.divergence_warnings();
        Ok(())
    }

    /// The state between steps, to start another episode from (see [`EnvSave`]).
    pub fn save(&self) -> EnvSave {
        EnvSave {
            step: self.steps,
            time: self.physics.time(),
            qpos: self.physics.qpos().to_vec(),
            qvel: self.physics.qvel().to_vec(),
            qacc_warmstart: self.physics.qacc_warmstart().to_vec(),
            torso_xy: self.last_xy,
            goal_distance: self.prev_distance,
            damage: self.damage.save(),
            pushes: self
                .pushes
                .active
                .iter()
                .map(|p| PendingPush {
                    push: p.push.clone(),
                    start: p.start,
                    remaining: p.remaining,
                })
                .collect(),
            dead_plan: self.dead_plan.clone(),
        }
    }

    /// Starts an episode from a saved state: stepping on with the same actions repeats what
    /// followed it. Every number is checked first; on an error the env is left as it was.
    pub fn start_from_save(&mut self, saved: &EnvSave) -> Result<Observation, EnvError> {
        check_state_vector("qpos", &saved.qpos, NQ)?;
        check_state_vector("qvel", &saved.qvel, NV)?;
        check_state_vector("qacc_warmstart", &saved.qacc_warmstart, NV)?;
        check_state_vector(
            "time, torso_xy, goal_distance",
            &[
                saved.time,
                saved.torso_xy[0],
                saved.torso_xy[1],
                saved.goal_distance,
            ],
            4,
        )?;
        if saved.step >= self.config.env.max_episode_steps {
            return Err(EnvError::BadState(format!(
                "the state is at step {}, at or past this episode's step limit {}",
                saved.step, self.config.env.max_episode_steps
            )));
        }
        let mut damage = self.damage.clone();
        damage.restore_save(&saved.damage)?;
        for d in &saved.dead_plan {
            if d.actuator >= N_ACTUATORS || !(d.scale.is_finite() && (0.0..=1.0).contains(&d.scale))
            {
                return Err(EnvError::BadState(format!(
                    "a pending death names actuator {} at scale {} (actuators 0..{N_ACTUATORS}, scales in [0, 1])",
                    d.actuator, d.scale
                )));
            }
            if d.step < saved.step {
                return Err(EnvError::BadState(format!(
                    "a pending death at step {} lies before the state's step {}",
                    d.step, saved.step
                )));
            }
        }
        if saved.dead_plan.windows(2).any(|w| w[0].step > w[1].step) {
            return Err(EnvError::BadState(
                "the pending deaths are not in step order".into(),
            ));
        }
        let mut active = Vec::with_capacity(saved.pushes.len());
        // Each push was checked as it was read (a `Push` always is); its progress is not.
        for p in &saved.pushes {
            if !(1..=p.push.steps).contains(&p.remaining) {
                return Err(EnvError::BadState(format!(
                    "a pending push has {} steps left of its {}",
                    p.remaining, p.push.steps
                )));
            }
            active.push(ActivePush {
                body: self.body_id(&p.push.body)?,
                push: p.push.clone(),
                start: p.start,
                remaining: p.remaining,
                source: None,
            });
        }
        // Gymnasium's set_state (mj_resetData, state, mj_forward), with the warm start and time.
        self.physics.reset();
        self.physics.qpos_mut().copy_from_slice(&saved.qpos);
        self.physics.qvel_mut().copy_from_slice(&saved.qvel);
        self.physics
            .qacc_warmstart_mut()
            .copy_from_slice(&saved.qacc_warmstart);
        self.physics.set_time(saved.time);
        self.physics.forward();
        self.physics.rne_post_constraint();
        self.damage = damage;
        self.plan = None;
        self.dead_plan = saved.dead_plan.clone();
        self.pushes = Pushes {
            active,
            last_step: Vec::new(),
        };
        self.steps = saved.step;
        self.done = false;
        self.unstable_warnings = self.divergence_warnings();
        self.last_xy = saved.torso_xy;
        self.prev_distance = saved.goal_distance;
        Ok(self.observation())
    }

    /// Advances one env step (frame_skip physics steps) with `action` in [−1, 1]⁸.
    /// Values outside are clipped; a wrong length or a non-finite value is an error.
    pub fn step(&mut self, action: &[f64]) -> Result<StepOutcome, EnvError> {
        if self.done {
            return Err(EnvError::EpisodeOver);
        }
        let commanded = validate_action(action)?;
        if let Some(plan) = &self.plan {
            let name = plan.name.clone();
            for (actuator, change) in plan.changes_before(self.steps) {
                self.damage
                    .apply_change(self.steps, actuator, change, Some(&name))?;
            }
            for push in plan.pushes_before(self.steps) {
                self.start_push(push, Some(&name))?;
            }
        }
        let applied = self.damage.applied_action(&commanded);
        let xy_before = self.last_xy;

        self.physics.ctrl_mut().copy_from_slice(&applied);
        // Pushes act through every substep of this env step, then the force is gone again (so
        // a snapshot never holds one: the active list is the state).
        for p in &self.pushes.active {
            let f = &mut self.physics.xfrc_applied_mut()[p.body];
            for (f, push) in f.iter_mut().zip(p.push.force) {
                *f += push;
            }
        }
        for _ in 0..self.config.env.frame_skip {
            self.physics.step();
        }
        self.end_push_step();
        // cfrc_ext is only filled on request; it depends on the final state alone, so once per
        // env step gives the same fatigue as once per substep (and is what Gymnasium does).
        self.physics.rne_post_constraint();

        let warnings = self.divergence_warnings();
        let unstable = warnings != self.unstable_warnings;
        self.unstable_warnings = warnings;

        let env = &self.config.env;
        let xy_after = self.xpos_torso_xy();
        self.last_xy = xy_after;
        let forward = (xy_after[0] - xy_before[0]) / self.dt;
        let healthy = !unstable && self.is_healthy();
        let ctrl_cost = env.ctrl_cost_weight * applied.iter().map(|a| a * a).sum::<f64>();
        let native = forward + env.healthy_reward - ctrl_cost;
        let distance = self.goal_distance();
        let progress = self.prev_distance - distance;
        self.prev_distance = distance;
        let success = distance < env.success_radius;
        let success_term = if success { 1.0 } else { 0.0 };
        let total = env.native_reward_weight * native
            + env.progress_weight * progress
            + env.success_bonus * success_term;

        let contact_norms = self.actuator_contact_norms();
        let step = self.steps;
        let new_triggers = self.damage.accumulate(step, &commanded, &contact_norms);

        self.steps += 1;
        let terminated = !healthy || success;
        let truncated = self.steps >= env.max_episode_steps;
        self.done = terminated || truncated;
        let ending = if success {
            Some(Ending::Success)
        } else if unstable {
            Some(Ending::Unstable)
        } else if terminated {
            let z = self.physics.qpos()[2];
            // A flip is named only where the world ends episodes for it; anything else inside
            // the band (a non-finite state MuJoCo did not flag) stays a collapse, as before.
            let [lo, hi] = env.healthy_z_range;
            let flipped = env.terminate_upside_down && self.torso_upside_down();
            Some(if z > hi {
                Ending::Leapt
            } else if z >= lo && flipped {
                Ending::Flipped
            } else {
                Ending::Collapsed
            })
        } else if truncated {
            Some(if self.torso_upside_down() {
                Ending::TimeoutUpsideDown
            } else {
                Ending::Timeout
            })
        } else {
            None
        };
        let outcome = StepOutcome {
            step,
            obs: self.observation(),
            reward: RewardTerms {
                forward,
                healthy: env.healthy_reward,
                ctrl_cost,
                native,
                progress,
                success: success_term,
                total,
            },
            terminated,
            truncated,
            success,
            healthy,
            unstable,
            distance,
            commanded_action: commanded,
            applied_action: applied,
            new_triggers,
            ending,
        };
        // Deaths due at the next step happen now, so the scales after a step (what the oracle
        // reads, what the viewer colours) are those the next action is applied with.
        if !self.done {
            self.kill_due();
        }
        Ok(outcome)
    }

    /// Whether the torso's up axis points below the horizon: its world z component,
    /// 1 − 2(x² + y²) of the free joint's quaternion (w, x, y, z) = qpos[3..7], is negative.
    pub fn torso_upside_down(&self) -> bool {
        let q = &self.physics.qpos()[3..7];
        1.0 - 2.0 * (q[1] * q[1] + q[2] * q[2]) < 0.0
    }

    /// Kills the actuators whose onset is the coming step (`self.steps`).
    fn kill_due(&mut self) {
        while let Some(d) = self.dead_plan.first().copied() {
            if d.step > self.steps {
                break;
            }
            self.dead_plan.remove(0);
            // Drawn (or checked, from a saved state) in range, so this cannot fail.
            let killed = self.damage.kill(self.steps, d.actuator, d.scale);
            debug_assert!(killed.is_ok(), "{killed:?}");
        }
    }

    /// The deaths this episode has still to come (a world with dead actuators).
    pub fn pending_deaths(&self) -> &[DeadOnset] {
        &self.dead_plan
    }

    /// The (hip, ankle) actuator pair of each leg that has exactly two (the Ant's four), in
    /// [`Self::leg_names`]' order: what can die as a whole leg.
    pub fn leg_actuators(&self) -> Vec<[usize; 2]> {
        (0..N_LEGS)
            .filter_map(|leg| <[usize; 2]>::try_from(self.actuators_of_leg(leg)).ok())
            .collect()
    }

    /// The actuators whose joints move leg `leg` (an index into [`Self::leg_names`]).
    fn actuators_of_leg(&self, leg: usize) -> Vec<usize> {
        (0..N_ACTUATORS)
            .filter(|&a| self.leg_of_actuator[a] == leg)
            .collect()
    }

    /// Changes a joint by hand; it takes effect on the next step and is logged as an event.
    pub fn apply_override(
        &mut self,
        actuator: usize,
        change: JointOverride,
    ) -> Result<(), EnvError> {
        Ok(self.damage.apply_override(self.steps, actuator, change)?)
    }

    /// Applies an edit (joints' damage, or a push); it takes effect on the next step.
    pub fn apply_edit(&mut self, edit: &Edit) -> Result<(), EnvError> {
        match edit {
            Edit::Joint(e) => Ok(self.damage.apply_edit(self.steps, e)?),
            Edit::Push(p) => self.start_push(p.clone(), None),
        }
    }

    /// Checks that `edit` names a joint or body of this model, changing nothing.
    pub fn check_edit(&self, edit: &Edit) -> Result<(), EnvError> {
        match edit {
            Edit::Joint(e) => self
                .damage
                .resolve(&e.target)
                .map(|_| ())
                .map_err(Into::into),
            Edit::Push(p) => self.body_id(&p.body).map(|_| ()),
        }
    }

    /// The model's named bodies, what a push may name.
    pub fn body_names(&self) -> Vec<&str> {
        self.bodies.iter().map(|(n, _)| n.as_str()).collect()
    }

    fn body_id(&self, name: &str) -> Result<usize, EnvError> {
        self.bodies
            .iter()
            .find(|(n, _)| n == name)
            .map(|&(_, b)| b)
            .ok_or_else(|| EnvError::NoSuchBody {
                name: name.to_string(),
                known: self.body_names().join(", "),
            })
    }

    /// A push acting from the next step on, for its number of steps. The force on one body
    /// from every push acting at once is held to one push's cap (1,000 × 1,000 N stacked on the
    /// torso was accepted before), and so is the number of pushes at once.
    fn start_push(&mut self, push: Push, source: Option<&str>) -> Result<(), EnvError> {
        use crate::damage::{MAX_ACTIVE_PUSHES, MAX_PUSH_NEWTONS};
        let body = self.body_id(&push.body)?;
        if self.pushes.active.len() >= MAX_ACTIVE_PUSHES {
            return Err(EnvError::TooManyPushes);
        }
        let mut total = push.force;
        for p in self.pushes.active.iter().filter(|p| p.body == body) {
            for (t, f) in total.iter_mut().zip(p.push.force) {
                *t += f;
            }
        }
        let newtons = total.iter().map(|f| f * f).sum::<f64>().sqrt();
        if newtons > MAX_PUSH_NEWTONS {
            return Err(EnvError::StackedPushes {
                body: push.body.clone(),
                newtons,
            });
        }
        self.pushes.active.push(ActivePush {
            body,
            start: self.steps,
            remaining: push.steps,
            source: source.map(str::to_string),
            push,
        });
        Ok(())
    }

    /// After a step's physics: the pushes that acted are recorded (at their body's centre of
    /// mass now), the applied forces cleared, and spent pushes dropped.
    fn end_push_step(&mut self) {
        self.pushes.last_step.clear();
        for p in &mut self.pushes.active {
            self.physics.xfrc_applied_mut()[p.body] = [0.0; 6];
            self.pushes.last_step.push(PushRecord {
                push: p.push.clone(),
                start: p.start,
                point: self.physics.xipos()[p.body],
                source: p.source.clone(),
            });
            p.remaining -= 1;
        }
        self.pushes.active.retain(|p| p.remaining > 0);
    }

    /// The pushes that acted during the last step.
    pub fn last_pushes(&self) -> &[PushRecord] {
        &self.pushes.last_step
    }

    /// The current observation (what the last reset or step returned).
    pub fn observation(&self) -> Observation {
        let qpos = self.physics.qpos();
        let qvel = self.physics.qvel();
        let xy = self.torso_xy();
        let goal = self.config.env.goal;
        let mut obs = [0.0; OBS_DIM];
        obs[..NQ - 2].copy_from_slice(&qpos[2..NQ]);
        obs[NQ - 2..NQ - 2 + NV].copy_from_slice(qvel);
        obs[OBS_DIM - 2] = goal[0] - xy[0];
        obs[OBS_DIM - 1] = goal[1] - xy[1];
        obs
    }

    /// Torso position in the plane: the torso body's `xpos` (Gymnasium's `get_body_com`).
    /// Per leg ([`N_LEGS`], model order), whether its foot touches the floor: a contact in
    /// MuJoCo's list (of the last step's final collision pass) between a foot geom and a geom of
    /// the world body.
    pub fn foot_contacts(&self) -> [bool; N_LEGS] {
        let mut touching = [false; N_LEGS];
        for contact in self.physics.contact() {
            let [a, b] = contact.geom.map(|g| g as usize);
            for (leg, feet) in self.feet.iter().enumerate() {
                let foot_on_ground = (feet.contains(&a) && self.ground.contains(&b))
                    || (feet.contains(&b) && self.ground.contains(&a));
                touching[leg] |= foot_on_ground;
            }
        }
        touching
    }

    /// The legs' body names, in [`Self::foot_contacts`]'s order.
    pub fn leg_names(&self) -> &[String; N_LEGS] {
        &self.leg_names
    }

    /// Joint and leg names, for resolving scenario targets.
    pub fn joint_map(&self) -> crate::damage::scenario::JointMap {
        crate::damage::scenario::JointMap {
            joints: self.damage.joint_names().to_vec(),
            legs: self.leg_names.to_vec(),
            leg_of: self.leg_of_actuator.to_vec(),
            bodies: self.body_names().iter().map(|n| n.to_string()).collect(),
        }
    }

    /// This episode's scenario schedule, if any.
    pub fn scenario_plan(&self) -> Option<&crate::damage::scenario::ScenarioPlan> {
        self.plan.as_ref()
    }

    /// What the world's draw kills this episode, died already or still to come, in words: a
    /// leg's name where all its actuators die at one step (the world's `leg` unit), else the
    /// joints', in actuator order. Empty when nothing dies. An episode that ends before a death
    /// still names it: models compared on the same seeds are compared on the same draws.
    pub fn drawn_deaths(&self) -> Vec<String> {
        let mut step = self.damage.dead_steps();
        for d in &self.dead_plan {
            step[d.actuator].get_or_insert(d.step);
        }
        let mut names = Vec::new();
        let mut named = [false; N_ACTUATORS];
        for (leg, leg_name) in self.leg_names.iter().enumerate() {
            let of_leg = self.actuators_of_leg(leg);
            let first = of_leg.first().and_then(|&a| step[a]);
            if first.is_some() && of_leg.iter().all(|&a| step[a] == first) {
                names.push(leg_name.clone());
                of_leg.iter().for_each(|&a| named[a] = true);
            }
        }
        for a in 0..N_ACTUATORS {
            if step[a].is_some() && !named[a] {
                names.push(self.damage.joint_names()[a].clone());
            }
        }
        names
    }

    /// The leg (index into [`Self::leg_names`]) each actuator's joint moves.
    pub fn leg_of_actuator(&self) -> &[usize; N_ACTUATORS] {
        &self.leg_of_actuator
    }

    /// The torso's xy (Gymnasium's `get_body_com("torso")[:2]`) after the last reset or step.
    pub fn torso_xy(&self) -> [f64; 2] {
        self.last_xy
    }

    fn xpos_torso_xy(&self) -> [f64; 2] {
        let p = self.physics.xpos()[self.torso_body];
        [p[0], p[1]]
    }

    pub fn goal_distance(&self) -> f64 {
        let xy = self.torso_xy();
        let goal = self.config.env.goal;
        (goal[0] - xy[0]).hypot(goal[1] - xy[1])
    }

    /// Healthy: torso z within the healthy range and the whole state (qpos, qvel) finite — and,
    /// in a world with `env.terminate_upside_down`, the torso not upside down.
    pub fn is_healthy(&self) -> bool {
        let qpos = self.physics.qpos();
        let [lo, hi] = self.config.env.healthy_z_range;
        let finite = qpos
            .iter()
            .chain(self.physics.qvel())
            .all(|v| v.is_finite());
        finite
            && (lo..=hi).contains(&qpos[2])
            && !(self.config.env.terminate_upside_down && self.torso_upside_down())
    }

    /// ‖cfrc_ext‖₂ (full 6-vector) of the body each actuator drives.
    pub fn actuator_contact_norms(&self) -> [f64; N_ACTUATORS] {
        let cfrc = self.physics.cfrc_ext();
        std::array::from_fn(|i| {
            cfrc[self.actuators[i].body_id]
                .iter()
                .map(|v| v * v)
                .sum::<f64>()
                .sqrt()
        })
    }

    /// How many times MuJoCo has found the state diverging and reset it.
    fn divergence_warnings(&self) -> i32 {
        let w = self.physics.warning();
        [
            MjtWarning::mjWARN_BADQPOS,
            MjtWarning::mjWARN_BADQVEL,
            MjtWarning::mjWARN_BADQACC,
        ]
        .iter()
        .map(|&k| w[k as usize].number)
        .sum()
    }

    pub fn config(&self) -> &GaitConfig {
        &self.config
    }
    pub fn damage(&self) -> &DamageState {
        &self.damage
    }
    pub fn actuators(&self) -> &[ActuatorInfo; N_ACTUATORS] {
        &self.actuators
    }
    /// MuJoCo's state, read-only (telemetry draws the Ant from it).
    pub fn physics(&self) -> &MjData<Box<MjModel>> {
        &self.physics
    }
    pub fn qpos(&self) -> &[f64] {
        self.physics.qpos()
    }
    pub fn qvel(&self) -> &[f64] {
        self.physics.qvel()
    }
    pub fn torso_body(&self) -> usize {
        self.torso_body
    }
    /// Env steps taken in this episode.
    pub fn steps(&self) -> usize {
        self.steps
    }
    /// Seconds per env step (frame_skip × timestep).
    pub fn dt(&self) -> f64 {
        self.dt
    }
    /// True once the episode has terminated or been truncated.
    pub fn is_done(&self) -> bool {
        self.done
    }
    pub fn condition(&self) -> Condition {
        self.damage.condition()
    }
    /// Whether fatigue triggers joints (see [`DamageState::set_fatigue_triggers`]).
    pub fn set_fatigue_triggers(&mut self, on: bool) {
        self.damage.set_fatigue_triggers(on);
    }
    /// Whether the next resets draw the world's deaths (see [`Self::pending_deaths`]).
    pub fn set_world_deaths(&mut self, on: bool) {
        self.world_deaths = on;
    }
}

/// Keeps MuJoCo's warnings on the console instead of also appending them to `MUJOCO_LOG.TXT` in
/// the working directory.
///
/// # Safety
/// Changes MuJoCo's global log configuration: call it before any other thread uses MuJoCo.
pub unsafe fn keep_mujoco_logs_on_console() {
    // SAFETY: forwarded to the caller.
    unsafe { set_log_config(log_config().with_logto_file(false)) }
}

fn load_model(path: Option<&Path>) -> Result<(MjModel, String), EnvError> {
    match path {
        None => {
            let origin = "bundled assets/ant.xml".to_string();
            let model =
                MjModel::from_xml_string(BUNDLED_ANT_XML).map_err(|e| EnvError::ModelLoad {
                    origin: origin.clone(),
                    reason: e.into(),
                })?;
            Ok((model, origin))
        }
        Some(path) => {
            // Read first so a missing or unreadable file gets the OS's reason, not MuJoCo's.
            std::fs::File::open(path).map_err(|source| EnvError::ModelRead {
                path: path.to_owned(),
                source,
            })?;
            let origin = path.display().to_string();
            let model = MjModel::from_xml(path).map_err(|e| EnvError::ModelLoad {
                origin: origin.clone(),
                reason: e.into(),
            })?;
            Ok((model, origin))
        }
    }
}

/// What the env needs to know about the model, checked once at load.
struct AntLayout {
    actuators: [ActuatorInfo; N_ACTUATORS],
    torso_body: usize,
    init_qpos: [f64; NQ],
    /// Per leg (the torso's child bodies, in model order): the geoms of its last body, the foot.
    feet: [Vec<usize>; N_LEGS],
    leg_names: [String; N_LEGS],
    /// The leg each actuator's joint moves.
    leg_of_actuator: [usize; N_ACTUATORS],
    /// Geoms of the world body (the floor).
    ground: Vec<usize>,
}

impl AntLayout {
    fn inspect(model: &MjModel) -> Result<Self, String> {
        let (nq, nv, nu) = (
            model.nq() as usize,
            model.nv() as usize,
            model.nu() as usize,
        );
        if (nq, nv, nu) != (NQ, NV, N_ACTUATORS) {
            return Err(format!(
                "expected nq={NQ}, nv={NV}, nu={N_ACTUATORS}, found nq={nq}, nv={nv}, nu={nu}"
            ));
        }
        let torso_body = model
            .name_to_id(MjtObjBase::mjOBJ_BODY, "torso")
            .ok_or("no body named 'torso'")?;
        let trnid = model.actuator_trnid();
        let jnt_bodyid = model.jnt_bodyid();
        let njnt = model.njnt() as usize;
        let mut actuators = Vec::with_capacity(N_ACTUATORS);
        for (i, trn) in trnid.iter().enumerate() {
            // Look the driven joint and its body up by index, as the damage model specifies.
            let joint_id = usize::try_from(trn[0])
                .ok()
                .filter(|&j| j < njnt)
                .ok_or_else(|| format!("actuator {i} does not drive a joint"))?;
            let body_id = jnt_bodyid[joint_id] as usize;
            let joint = model
                .id_to_name(MjtObjBase::mjOBJ_JOINT, joint_id)
                .filter(|n| !n.is_empty())
                .ok_or_else(|| format!("joint {joint_id} (actuator {i}) has no name"))?
                .to_string();
            let body = model
                .id_to_name(MjtObjBase::mjOBJ_BODY, body_id)
                .filter(|n| !n.is_empty())
                .map_or_else(|| format!("body{body_id}"), str::to_string);
            actuators.push(ActuatorInfo {
                actuator: i,
                joint,
                joint_id,
                body_id,
                body,
            });
        }
        let actuators: [ActuatorInfo; N_ACTUATORS] = actuators
            .try_into()
            .map_err(|_| "actuator count changed while reading".to_string())?;
        // Gymnasium's init_qpos is the model's qpos0 (torso at 0.75 m, upright, joints at 0).
        let mut init_qpos = [0.0; NQ];
        init_qpos.copy_from_slice(model.qpos0());
        let parent = model.body_parentid();
        let legs: Vec<usize> = (0..parent.len())
            .filter(|&b| parent[b] as usize == torso_body && b != torso_body)
            .collect();
        if legs.len() != N_LEGS {
            return Err(format!(
                "expected {N_LEGS} legs (bodies under the torso), found {}",
                legs.len()
            ));
        }
        let geom_body = model.geom_bodyid();
        let mut feet: [Vec<usize>; N_LEGS] = Default::default();
        let mut leg_names: [String; N_LEGS] = Default::default();
        for (k, &leg) in legs.iter().enumerate() {
            // Down the leg's chain to its last body.
            let mut foot = leg;
            while let Some(child) =
                (0..parent.len()).find(|&b| b != foot && parent[b] as usize == foot)
            {
                foot = child;
            }
            feet[k] = (0..geom_body.len())
                .filter(|&g| geom_body[g] as usize == foot)
                .collect();
            if feet[k].is_empty() {
                return Err(format!(
                    "leg {k}'s last body has no geom to touch the floor"
                ));
            }
            leg_names[k] = model
                .id_to_name(MjtObjBase::mjOBJ_BODY, leg)
                .filter(|n| !n.is_empty())
                .map_or_else(|| format!("leg{k}"), str::to_string);
        }
        let ground = (0..geom_body.len())
            .filter(|&g| geom_body[g] == 0)
            .collect();
        let mut leg_of_actuator = [0; N_ACTUATORS];
        for (i, a) in actuators.iter().enumerate() {
            // Up from the joint's body to the torso's child it hangs from.
            let mut b = a.body_id;
            while b != 0 && parent[b] as usize != torso_body {
                b = parent[b] as usize;
            }
            leg_of_actuator[i] = legs
                .iter()
                .position(|&l| l == b)
                .ok_or_else(|| format!("actuator {i}'s joint is on no leg"))?;
        }
        Ok(Self {
            actuators,
            torso_body,
            init_qpos,
            feet,
            leg_names,
            leg_of_actuator,
            ground,
        })
    }
}

fn validate_action(action: &[f64]) -> Result<Action, EnvError> {
    if action.len() != ACT_DIM {
        return Err(EnvError::ActionLength {
            expected: ACT_DIM,
            got: action.len(),
        });
    }
    let mut clipped = [0.0; ACT_DIM];
    for (i, (&a, out)) in action.iter().zip(&mut clipped).enumerate() {
        if !a.is_finite() {
            return Err(EnvError::NonFiniteAction { index: i, value: a });
        }
        *out = a.clamp(-1.0, 1.0);
    }
    Ok(clipped)
}

fn check_state_vector(name: &str, values: &[f64], expected: usize) -> Result<(), EnvError> {
    if values.len() != expected {
        return Err(EnvError::BadState(format!(
            "{name} has {} values, the Ant needs {expected}",
            values.len()
        )));
    }
    if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(EnvError::BadState(format!(
            "{name}[{i}] is {v}; the state must be finite"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::damage::JointOverride;

    fn actions(n: usize, seed: u64) -> Vec<Action> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..=1.0)))
            .collect()
    }

    fn run(env: &mut AntEnv, actions: &[Action]) -> Vec<StepOutcome> {
        actions.iter().map_while(|a| env.step(a).ok()).collect()
    }

    /// An episode's ending in words: a timeout at the step limit, a fall when the torso leaves
    /// the healthy range, nothing while it goes on.
    #[test]
    fn endings_name_how_an_episode_stopped() {
        let mut config = GaitConfig::default();
        config.env.max_episode_steps = 5;
        let mut env = AntEnv::new(config, 0).unwrap();
        env.reset_with_seed(1);
        let outs = run(&mut env, &[[0.0; N_ACTUATORS]; 5]);
        assert!(outs[..4].iter().all(|o| o.ending().is_none()));
        assert_eq!(outs[4].ending(), Some("timeout"));
        // The same step with the torso forced out of the healthy z range: a fall.
        let mut config = GaitConfig::default();
        config.env.healthy_z_range = [0.9, 1.0];
        let mut env = AntEnv::new(config, 0).unwrap();
        env.reset_with_seed(1);
        let out = env.step(&[0.0; N_ACTUATORS]).unwrap();
        assert!(out.terminated && !out.success);
        assert_eq!(out.ending(), Some("collapsed"));
        // Above the band: a leap, Ant-v4's usual early ending.
        let mut config = GaitConfig::default();
        config.env.healthy_z_range = [0.0, 0.3];
        let mut env = AntEnv::new(config, 0).unwrap();
        env.reset_with_seed(1);
        let out = env.step(&[0.0; N_ACTUATORS]).unwrap();
        assert_eq!(out.ending, Some(Ending::Leapt));
        // Upside down at the limit: the torso's quaternion turned half a turn about x.
        let mut config = GaitConfig::default();
        config.env.max_episode_steps = 1;
        config.env.healthy_z_range = [-10.0, 10.0];
        let mut env = AntEnv::new(config, 0).unwrap();
        env.reset_with_seed(1);
        let mut qpos = env.qpos().to_vec();
        qpos[2] = 1.0;
        qpos[3..7].copy_from_slice(&[0.0, 1.0, 0.0, 0.0]);
        let qvel = vec![0.0; env.qvel().len()];
        env.reset_to_state(&qpos, &qvel, crate::damage::Condition::Healthy)
            .unwrap();
        assert!(env.torso_upside_down());
        let out = env.step(&[0.0; N_ACTUATORS]).unwrap();
        assert_eq!(out.ending, Some(Ending::TimeoutUpsideDown));
        assert_eq!(out.ending(), Some("timeout upside down"));
    }

    /// A world with `env.terminate_upside_down` ends the episode on the step the torso is upside
    /// down (unhealthy: no healthy bonus is earned after it); Ant-v4's rule (the default) lets
    /// the same state go on, and an upright torso goes on in both.
    #[test]
    fn turning_upside_down_ends_the_episode_only_where_the_world_says_so() {
        let flipped_step = |terminate: bool, quaternion: [f64; 4]| {
            let mut config = GaitConfig::default();
            config.env.terminate_upside_down = terminate;
            let mut env = AntEnv::new(config, 0).unwrap();
            env.reset_with_seed(1);
            let mut qpos = env.qpos().to_vec();
            qpos[2] = 0.5;
            qpos[3..7].copy_from_slice(&quaternion);
            let qvel = vec![0.0; env.qvel().len()];
            env.reset_to_state(&qpos, &qvel, crate::damage::Condition::Healthy)
                .unwrap();
            env.step(&[0.0; N_ACTUATORS]).unwrap()
        };
        // Half a turn about x: up axis (0, 0, −1).
        let out = flipped_step(true, [0.0, 1.0, 0.0, 0.0]);
        assert!(out.terminated && !out.healthy && !out.success);
        assert_eq!(out.ending, Some(Ending::Flipped));
        assert!(Ending::Flipped.is_fall());
        let out = flipped_step(false, [0.0, 1.0, 0.0, 0.0]);
        assert!(!out.terminated && out.healthy && out.ending.is_none());
        // Tilted 60° about y (up axis z = cos 60° = 0.5 > 0): still upright, goes on.
        let (s, c) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
        let out = flipped_step(true, [c, 0.0, s, 0.0]);
        assert!(!out.terminated && out.ending.is_none());
    }

    /// Foot contacts against MuJoCo's contact list read here by geom name, on stepped states
    /// where both touching and lifted feet occur.
    #[test]
    fn foot_contacts_match_mujoco_contacts_by_geom_name() {
        let mut env = AntEnv::new(GaitConfig::default(), 0).unwrap();
        env.reset_with_seed(2);
        assert_eq!(
            env.leg_names(),
            &[
                "front_left_leg",
                "front_right_leg",
                "back_leg",
                "right_back_leg"
            ]
        );
        let model = env.physics().model();
        let id = |name: &str| model.name_to_id(MjtObjBase::mjOBJ_GEOM, name).unwrap();
        let feet = [
            "left_ankle_geom",
            "right_ankle_geom",
            "third_ankle_geom",
            "fourth_ankle_geom",
        ]
        .map(id);
        let floor = id("floor");
        let (mut seen_on, mut seen_off) = (0, 0);
        for action in actions(300, 3) {
            if env.step(&action).is_err() {
                env.reset();
                continue;
            }
            let expected: [bool; N_LEGS] = std::array::from_fn(|leg| {
                env.physics().contact().iter().any(|c| {
                    let g = c.geom.map(|g| g as usize);
                    g == [feet[leg], floor] || g == [floor, feet[leg]]
                })
            });
            let got = env.foot_contacts();
            assert_eq!(got, expected);
            seen_on += got.iter().filter(|&&c| c).count();
            seen_off += got.iter().filter(|&&c| !c).count();
        }
        assert!(
            seen_on > 50 && seen_off > 50,
            "{seen_on} on, {seen_off} off"
        );
    }

    /// Rewind: restoring a snapshot and stepping the same actions repeats every outcome bit for
    /// bit (obs, rewards, fatigue triggers, flags), in the same env and in a second env (a fork).
    #[test]
    fn a_restored_snapshot_replays_bit_for_bit() {
        let mut config = GaitConfig::default();
        config.damage.condition = ConditionChoice::Fixed(Condition::Severe);
        let mut env = AntEnv::new(config.clone(), 0).unwrap();
        env.reset_with_seed(5);
        run(&mut env, &actions(40, 1));
        // A hand override in the history: the snapshot carries overrides too.
        env.apply_override(2, JointOverride::SetScale(0.3)).unwrap();
        let snapshot = env.snapshot();
        assert_eq!(snapshot.steps(), 40);
        let later = actions(150, 2);
        let first = run(&mut env, &later);
        assert!(first.len() > 20, "the episode should run on");
        assert!(
            first.iter().any(|o| o.new_triggers > 0),
            "a trigger after the snapshot"
        );
        env.restore(&snapshot).unwrap();
        assert_eq!(env.steps(), 40);
        let again = run(&mut env, &later);
        assert_eq!(first, again);
        let mut fork = AntEnv::new(config, 99).unwrap();
        fork.reset_with_seed(77);
        fork.restore(&snapshot).unwrap();
        assert_eq!(run(&mut fork, &later), first);
        assert_eq!(fork.damage().events(), env.damage().events());
    }
}
