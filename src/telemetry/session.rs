//! The simulation loop that `record` (headless) and `live` (interactive) share: one lane per
//! model, all lanes in lockstep on the same seeds and the same hand-made damage, every step
//! logged to Rerun.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use rerun::RecordingStream;
use std::path::PathBuf;

use super::{AntLogger, EpisodeMeta, Sink, TelemetryError, open};
use crate::config::{DamageConfig, EnvConfig, GaitConfig};
use crate::damage::JointOverride;
use crate::env::{AntEnv, Observation, StepOutcome};
use crate::policy::{ActionMode, Policy};
use crate::rollout::BuiltinPolicy;
use crate::window::ContextWindow;

/// Who acts in a lane.
pub enum Actor {
    Checkpoint { dir: PathBuf, policy: Box<Policy> },
    Builtin(BuiltinPolicy),
}

impl Actor {
    /// Loads a checkpoint folder.
    pub fn load(dir: &std::path::Path) -> Result<Self, crate::policy::checkpoint::CheckpointError> {
        Ok(Actor::Checkpoint {
            dir: dir.to_path_buf(),
            policy: Box::new(Policy::load(dir, None)?),
        })
    }

    /// The checkpoint folder's name, or the built-in policy's.
    pub fn label(&self) -> String {
        match self {
            Actor::Checkpoint { dir, .. } => crate::eval::model_label(dir),
            Actor::Builtin(p) => format!("{p:?}").to_lowercase(),
        }
    }

    pub fn encoder(&self) -> String {
        match self {
            Actor::Checkpoint { policy, .. } => policy.net().encoder.to_string(),
            Actor::Builtin(_) => "none (built-in policy)".into(),
        }
    }

    pub fn checkpoint_dir(&self) -> Option<&std::path::Path> {
        match self {
            Actor::Checkpoint { dir, .. } => Some(dir),
            Actor::Builtin(_) => None,
        }
    }

    /// The env settings this actor runs under: a checkpoint's own task settings (it was trained
    /// on them) with the requested condition and step limit; a built-in policy takes `requested`.
    fn config(&self, requested: &GaitConfig) -> GaitConfig {
        match self {
            Actor::Checkpoint { policy, .. } => {
                let trained = &policy.meta.env;
                GaitConfig {
                    damage: DamageConfig {
                        condition: requested.damage.condition,
                        ..trained.damage.clone()
                    },
                    env: EnvConfig {
                        max_episode_steps: requested.env.max_episode_steps,
                        ..trained.env.clone()
                    },
                    context: trained.context.clone(),
                }
            }
            Actor::Builtin(_) => requested.clone(),
        }
    }

    fn context_len(&self) -> usize {
        match self {
            Actor::Checkpoint { policy, .. } => policy.net().context_len,
            Actor::Builtin(_) => 1,
        }
    }
}

/// An actor and where its entities go.
pub struct LaneSpec {
    pub actor: Actor,
    /// Entity root (`ant`, or one per model when several run side by side).
    pub root: String,
    /// Where this lane's world is drawn (metres), so side-by-side Ants do not overlap.
    pub world_offset: [f32; 3],
}

/// The world offset of the k-th of several side-by-side models: 12 m apart along x, which clears
/// the floor patch drawn around start and goal.
pub fn side_by_side_offset(k: usize) -> [f32; 3] {
    [12.0 * k as f32, 0.0, 0.0]
}

/// One model driving one Ant.
pub struct Lane {
    actor: Actor,
    root: String,
    env: AntEnv,
    logger: AntLogger,
    window: ContextWindow,
    obs: Observation,
    /// Built-in policies' actions and sampled actions' noise.
    rng: ChaCha8Rng,
    last: Option<StepOutcome>,
    z: Option<Vec<f32>>,
    done: bool,
}

impl Lane {
    fn new(
        spec: LaneSpec,
        rec: &RecordingStream,
        config: &GaitConfig,
        seed: u64,
    ) -> Result<Self, RecordError> {
        let env = AntEnv::new(spec.actor.config(config), seed)?;
        let probe = match spec.actor.checkpoint_dir() {
            Some(dir) if dir.join(crate::probe::PROBE_FILE).exists() => {
                Some(crate::probe::ProbeFile::load(dir)?)
            }
            _ => None,
        };
        let logger = AntLogger::new(rec.clone(), &spec.root, &env, probe)
            .with_world_offset(spec.world_offset);
        let window = ContextWindow::new(spec.actor.context_len());
        let obs = env.observation();
        Ok(Self {
            actor: spec.actor,
            root: spec.root,
            env,
            logger,
            window,
            obs,
            rng: crate::rollout::policy_rng(seed),
            last: None,
            z: None,
            done: true,
        })
    }

    fn decide(&mut self, mode: ActionMode) -> Result<(Vec<f64>, Option<Vec<f32>>), RecordError> {
        match &self.actor {
            Actor::Checkpoint { policy, .. } => {
                let noise: Option<Vec<f32>> = (mode == ActionMode::Sampled).then(|| {
                    (0..policy.net().act_dim)
                        .map(|_| self.rng.sample(StandardNormal))
                        .collect()
                });
                let d = policy.act_one(&self.obs, &self.window, mode, noise.as_deref())?;
                Ok((d.action, d.z))
            }
            Actor::Builtin(p) => Ok((p.act(&mut self.rng).to_vec(), None)),
        }
    }

    pub fn actor(&self) -> &Actor {
        &self.actor
    }
    pub fn root(&self) -> &str {
        &self.root
    }
    pub fn env(&self) -> &AntEnv {
        &self.env
    }
    /// The outcome of this episode's latest step (none right after a reset).
    pub fn last(&self) -> Option<&StepOutcome> {
        self.last.as_ref()
    }
    /// The latent the policy produced for the latest step (encoder policies).
    pub fn z(&self) -> Option<&[f32]> {
        self.z.as_deref()
    }
    pub fn probe(&self) -> Option<&crate::probe::ProbeFile> {
        self.logger.probe()
    }
    pub fn is_done(&self) -> bool {
        self.done
    }
}

/// Models in lockstep, logged to one recording stream.
pub struct Session {
    rec: RecordingStream,
    lanes: Vec<Lane>,
    /// Requested settings (condition, step limit); each lane derives its own from them.
    config: GaitConfig,
    /// Settings changed since the lanes' envs were built: rebuilt at the next episode.
    config_changed: bool,
    fatigue_triggers: bool,
    mode: ActionMode,
    global_step: u64,
    episodes_started: u64,
    seed: u64,
}

impl Session {
    /// Builds the lanes; call [`Self::start_episode`] before stepping.
    pub fn new(
        rec: RecordingStream,
        specs: Vec<LaneSpec>,
        config: GaitConfig,
    ) -> Result<Self, RecordError> {
        let lanes = specs
            .into_iter()
            .map(|spec| Lane::new(spec, &rec, &config, 0))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            rec,
            lanes,
            config,
            config_changed: false,
            fatigue_triggers: true,
            mode: ActionMode::Deterministic,
            global_step: 0,
            episodes_started: 0,
            seed: 0,
        })
    }

    /// Deterministic (evaluation) or sampled actions, from the next step on.
    pub fn set_action_mode(&mut self, mode: ActionMode) {
        self.mode = mode;
    }

    /// New requested settings, in force from the next episode.
    pub fn set_config(&mut self, config: GaitConfig) {
        self.config = config;
        self.config_changed = true;
    }

    /// Whether fatigue triggers joints, from the next episode (off: only a person damages joints).
    pub fn set_fatigue_triggers(&mut self, on: bool) {
        self.fatigue_triggers = on;
    }

    /// Replaces the models (e.g. another checkpoint picked in the panel); start an episode next.
    /// The recording and its timelines go on.
    pub fn replace_lanes(&mut self, specs: Vec<LaneSpec>) -> Result<(), RecordError> {
        // The layout follows the models: one 3-D view each.
        let roots: Vec<String> = specs.iter().map(|s| s.root.clone()).collect();
        super::default_blueprint(&roots)
            .send(
                &self.rec,
                rerun::blueprint::BlueprintActivation {
                    make_active: true,
                    make_default: true,
                },
            )
            .map_err(TelemetryError::from)?;
        self.lanes = specs
            .into_iter()
            .map(|spec| Lane::new(spec, &self.rec, &self.config, self.seed))
            .collect::<Result<Vec<_>, _>>()?;
        self.config_changed = false;
        Ok(())
    }

    /// Takes the models out, leaving no lanes until [`Self::replace_lanes`].
    pub fn take_actors(&mut self) -> Vec<Actor> {
        self.lanes.drain(..).map(|l| l.actor).collect()
    }

    /// Resets every lane with `seed` and logs the episode's metadata.
    pub fn start_episode(&mut self, seed: u64) -> Result<(), RecordError> {
        if self.config_changed {
            for lane in &mut self.lanes {
                lane.env = AntEnv::new(lane.actor.config(&self.config), seed)?;
            }
            self.config_changed = false;
        }
        self.seed = seed;
        let episode = self.episodes_started;
        self.episodes_started += 1;
        for lane in &mut self.lanes {
            lane.env.set_fatigue_triggers(self.fatigue_triggers);
            lane.obs = lane.env.reset_with_seed(seed);
            lane.window.clear();
            lane.rng = crate::rollout::policy_rng(seed);
            lane.last = None;
            lane.z = None;
            lane.done = false;
            lane.logger.set_time(self.global_step, episode);
            let meta = episode_meta(self.fatigue_triggers, seed, &lane.actor, &lane.env);
            lane.logger.log_episode(&meta, &lane.env, None)?;
        }
        Ok(())
    }

    /// One env step for every lane still running. Returns whether every lane's episode is over.
    pub fn step(&mut self) -> Result<bool, RecordError> {
        if self.is_over() {
            return Ok(true);
        }
        self.global_step += 1;
        let episode = self.episodes_started.saturating_sub(1);
        let mut ended = Vec::new();
        for i in 0..self.lanes.len() {
            if self.lanes[i].done {
                continue;
            }
            let (action, z) = self.lanes[i].decide(self.mode)?;
            let lane = &mut self.lanes[i];
            let out = lane.env.step(&action)?;
            lane.window.push(&lane.obs, &action);
            lane.logger.set_time(self.global_step, episode);
            lane.logger.log_step(&lane.env, &out, z.as_deref())?;
            lane.obs = out.obs;
            lane.z = z;
            if out.done() {
                lane.done = true;
                let meta = episode_meta(self.fatigue_triggers, self.seed, &lane.actor, &lane.env);
                lane.logger.log_episode(&meta, &lane.env, Some(&out))?;
                ended.push(i);
            }
            self.lanes[i].last = Some(out);
        }
        // A lane that ended while others run waits for them: its series stop here.
        if !self.is_over() {
            for i in ended {
                let logger = &mut self.lanes[i].logger;
                logger.set_time(self.global_step + 1, episode);
                logger.log_series_gap()?;
            }
        }
        Ok(self.is_over())
    }

    /// Whether every lane's episode has ended (true before the first episode too).
    pub fn is_over(&self) -> bool {
        self.lanes.iter().all(|l| l.done)
    }

    /// The same hand-made change to every lane; it applies from the next step and is logged
    /// as an event with it.
    pub fn apply_override(
        &mut self,
        actuator: usize,
        change: JointOverride,
    ) -> Result<(), RecordError> {
        for lane in &mut self.lanes {
            lane.env.apply_override(actuator, change)?;
        }
        Ok(())
    }

    pub fn lanes(&self) -> &[Lane] {
        &self.lanes
    }
    /// Env steps since the recording started (the `step` timeline).
    pub fn global_step(&self) -> u64 {
        self.global_step
    }
    pub fn episodes_started(&self) -> u64 {
        self.episodes_started
    }
    /// The current episode's seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }
    pub fn config(&self) -> &GaitConfig {
        &self.config
    }
    pub fn recording(&self) -> &RecordingStream {
        &self.rec
    }

    /// Waits up to `timeout` for everything logged so far to reach the sinks.
    pub fn flush_within(&self, timeout: std::time::Duration) -> Result<(), TelemetryError> {
        match self.rec.flush_with_timeout(timeout) {
            Ok(()) => Ok(()),
            Err(rerun::sink::SinkFlushError::Timeout) => Err(TelemetryError::FlushTimeout(timeout)),
            Err(e) => Err(TelemetryError::Flush(e.to_string())),
        }
    }

    /// Blocks until everything logged so far has reached the sinks.
    pub fn flush(&self) -> Result<(), TelemetryError> {
        self.rec
            .flush_blocking()
            .map_err(|e| TelemetryError::Flush(e.to_string()))
    }
}

fn episode_meta(fatigue_triggers: bool, seed: u64, actor: &Actor, env: &AntEnv) -> EpisodeMeta {
    let condition = env.condition();
    EpisodeMeta {
        checkpoint: actor.label(),
        encoder: actor.encoder(),
        condition: if fatigue_triggers {
            condition.to_string()
        } else {
            format!("manual (no fatigue triggers; fail now → {condition} scale)")
        },
        seed,
    }
}

/// What `gaitscope record` does.
pub struct RecordOptions {
    pub actors: Vec<Actor>,
    pub config: GaitConfig,
    pub episodes: usize,
    pub seed: u64,
    pub sink: Sink,
}

/// Outcome of a recording.
pub struct RecordSummary {
    pub steps: u64,
    pub episodes: usize,
    pub interrupted: bool,
    pub storage: Option<rerun::sink::MemorySinkStorage>,
}

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    Telemetry(#[from] TelemetryError),
    #[error(transparent)]
    Env(#[from] crate::env::EnvError),
    #[error(transparent)]
    Probe(#[from] crate::probe::ProbeError),
    #[error("policy inference failed: {0}")]
    Policy(#[from] candle_core::Error),
}

/// Entity roots for several models: `ant` alone, else each model's label (made unique).
pub fn model_roots(actors: &[Actor]) -> Vec<String> {
    let mut roots: Vec<String> = Vec::new();
    for actor in actors {
        let mut root = if actors.len() == 1 {
            "ant".to_string()
        } else {
            actor.label()
        };
        while roots.contains(&root) {
            root.push('_');
        }
        roots.push(root);
    }
    roots
}

/// Runs `episodes` episodes per actor, all actors in lockstep on the same seeds (episode k uses
/// seed + k), logging every step. Stops early, with everything flushed, when `stop` is set.
pub fn record(
    opts: RecordOptions,
    stop: &std::sync::atomic::AtomicBool,
) -> Result<RecordSummary, RecordError> {
    let roots = model_roots(&opts.actors);
    let recording_id = format!(
        "gaitscope-{}-seed{}-{}",
        roots.join("-"),
        opts.seed,
        opts.episodes
    );
    let (rec, storage) = open(&opts.sink, &recording_id, &roots)?;
    let specs = opts
        .actors
        .into_iter()
        .zip(roots)
        .enumerate()
        .map(|(k, (actor, root))| LaneSpec {
            actor,
            root,
            world_offset: side_by_side_offset(k),
        })
        .collect();
    let mut session = Session::new(rec, specs, opts.config)?;
    let mut episodes_done = 0;
    let mut interrupted = false;
    'episodes: for k in 0..opts.episodes {
        session.start_episode(opts.seed.wrapping_add(k as u64))?;
        while !session.is_over() {
            if stop.load(std::sync::atomic::Ordering::Relaxed) {
                interrupted = true;
                break 'episodes;
            }
            session.step()?;
        }
        episodes_done += 1;
    }
    session.flush()?;
    Ok(RecordSummary {
        steps: session.global_step(),
        episodes: episodes_done,
        interrupted,
        storage,
    })
}
