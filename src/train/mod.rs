//! `gaitscope train`: SAC (Stable-Baselines3 defaults) on the damaged Ant, with an optional
//! context encoder. One readable loop in CleanRL's shape; deviations from SB3 are noted inline.
//!
//! A run folder holds the checkpoint (`model.safetensors`, `checkpoint.json`), the optimiser and
//! RNG state for `--resume` (`train_state.json`, `train_state.safetensors`), the replay buffer
//! (`replay.bin`, so a resumed run continues with the same data; git-ignored, and with
//! `--replay-dir` kept in another folder) and the metrics (`metrics.jsonl`, CleanRL-style names).
//! Each checkpoint lands as one set under the folder's lock ([`run_dir`]). A resume that finds no
//! buffer refills one with the current policy before it updates again: updating from a few
//! hundred fresh transitions wrecked two of our runs.

pub mod adam;
pub mod aux;
pub mod curves;
pub mod fused;
mod metrics;
pub mod replay;
mod resume;
pub mod run_dir;
pub mod sac;
pub mod update_stats;
pub mod warm_start;

use metrics::{EpisodeMetrics, MetricsLog, RecentEpisodes, ResumeMetrics, UpdateMetrics};
pub use resume::{BufferSource, ResumeRecord, RunIdentity, load_learner, read_resumes};
use resume::{TrainState, aux_name, resume_run, save_run, truncate_metrics};
pub use warm_start::WarmStart;

use candle_core::Device;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::config::GaitConfig;
use crate::damage::Condition;
use crate::env::{AntEnv, EnvError};
use crate::policy::checkpoint::{self, CheckpointError};
use crate::policy::{EncoderKind, NetConfig, Privileged, SacConfig, SacModel};
use crate::window::ContextWindow;
use replay::{Batch, ReplayBuffer, Transition};
use run_dir::{RunDir, SaveStage};
use sac::{SacLearner, UpdatePath, UpdateStats};

pub const STATE_FILE: &str = "train_state.json";
pub const OPTIMIZER_FILE: &str = "train_state.safetensors";
pub const REPLAY_FILE: &str = "replay.bin";
pub const METRICS_FILE: &str = "metrics.jsonl";
/// Transitions a buffer-less resume collects before updating (`--refill`'s default).
pub const DEFAULT_REFILL: usize = 50_000;
/// The least `--refill` accepts: below it SAC samples the same few episodes over and over.
pub const MIN_REFILL: usize = 10_000;
/// Largest replay buffer a run may ask for (5M transitions of the Ant: ~1.4 GB).
pub const MAX_BUFFER_SIZE: usize = 5_000_000;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("tensor error: {0}")]
    Tensor(#[from] candle_core::Error),
    #[error("{path}: {reason}")]
    State {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("invalid training options: {0}")]
    Options(String),
    #[error(
        "training diverged at step {step}: {what} is not finite; nothing was saved, the last good checkpoint stands"
    )]
    Diverged { step: u64, what: String },
    #[error(transparent)]
    RunDir(#[from] run_dir::RunDirError),
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{state} keeps this run's replay buffer in {recorded}; a run folder does not choose \
         where the trainer writes: repeat --replay-dir {recorded} to resume with it there, or \
         give another --replay-dir"
    )]
    ReplayDirNotConfirmed { state: PathBuf, recorded: PathBuf },
}

/// What a training run needs; everything else derives from the seed.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub net: NetConfig,
    pub sac: SacConfig,
    pub env: GaitConfig,
    pub seed: u64,
    /// Total env steps (a resumed run stops at the same total).
    pub total_steps: u64,
    pub out: PathBuf,
    /// Save a checkpoint every this many env steps (and always at the end).
    pub checkpoint_every: u64,
    /// Also save the replay buffer with each checkpoint, for an exact `--resume`.
    pub save_replay: bool,
    /// Log update losses every this many env steps.
    pub log_every: u64,
    pub progress_bar: bool,
    /// Fused (the fast path) or candle's autograd; the same algorithm.
    pub update: UpdatePath,
    /// Threads per fused update (1: the training thread alone). The results do not depend on it.
    pub threads: usize,
    /// Where `replay.bin` lives (`None`: the run folder; a resume also finds the folder the
    /// run recorded).
    pub replay_dir: Option<PathBuf>,
    /// A resume without its buffer collects min(buffer size, steps done, this) transitions with
    /// the current policy before the next update (at least [`MIN_REFILL`]).
    pub refill: usize,
    /// A fresh run that starts from this memoryless model's weights ([`warm_start`]: an
    /// encoder model's z and an oracle's privileged inputs at zero weight at first); its
    /// steps before `learning_starts` act with that policy instead of uniform noise.
    pub init_from: Option<PathBuf>,
}

/// One env step as the trainer sees it.
#[derive(Debug, Clone)]
pub struct TaskStep {
    pub obs: Vec<f64>,
    pub reward: f64,
    pub terminated: bool,
    pub truncated: bool,
    pub success: bool,
    pub triggered_joints: usize,
    pub condition: Option<Condition>,
}

/// An environment the trainer can drive: the damaged Ant, or a toy problem in the tests.
pub trait Task {
    fn obs_dim(&self) -> usize;
    fn act_dim(&self) -> usize;
    /// Reseeds, then resets.
    fn reset_with_seed(&mut self, seed: u64) -> Vec<f64>;
    fn reset(&mut self) -> Vec<f64>;
    fn step(&mut self, action: &[f64]) -> Result<TaskStep, TrainError>;
}

/// The damaged Ant as a training task; an oracle's observations carry its privileged inputs.
pub struct AntTask {
    pub env: AntEnv,
    privileged: Privileged,
}

impl AntTask {
    pub fn new(env: AntEnv, privileged: Privileged) -> Self {
        Self { env, privileged }
    }

    /// The model's input after a reset or a step: the observation (and an oracle's scales, as
    /// [`Privileged::input`] builds it for every lane).
    fn input(&self, obs: &crate::env::Observation) -> Vec<f64> {
        let mut v = obs.to_vec();
        v.extend(self.privileged.values(self.env.damage().scale()));
        v
    }
}

impl Task for AntTask {
    fn obs_dim(&self) -> usize {
        crate::env::OBS_DIM + self.privileged.dim()
    }
    fn act_dim(&self) -> usize {
        crate::env::ACT_DIM
    }
    fn reset_with_seed(&mut self, seed: u64) -> Vec<f64> {
        let obs = self.env.reset_with_seed(seed);
        self.input(&obs)
    }
    fn reset(&mut self) -> Vec<f64> {
        let obs = self.env.reset();
        self.input(&obs)
    }
    fn step(&mut self, action: &[f64]) -> Result<TaskStep, TrainError> {
        let out = self.env.step(action)?;
        Ok(TaskStep {
            obs: self.input(&out.obs),
            reward: out.reward.total,
            terminated: out.terminated,
            truncated: out.truncated,
            success: out.success,
            triggered_joints: self.env.damage().n_triggered(),
            condition: Some(self.env.condition()),
        })
    }
}

/// How a run ended.
#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    pub steps_done: u64,
    pub episodes_done: u64,
    pub wall_time_s: f64,
    pub interrupted: bool,
    /// Whether this invocation saved a checkpoint (not when stopped during a refill).
    pub saved: bool,
    /// Env steps per second over this invocation, warm-up included.
    pub steps_per_s: f64,
    /// Env steps per second once every step also runs a gradient update.
    pub learning_steps_per_s: Option<f64>,
}

/// Trains on the damaged Ant (fresh, or resumed from `opts.out` when `resume`).
pub fn train_ant(
    opts: TrainOptions,
    resume: bool,
    stop: Arc<AtomicBool>,
) -> Result<TrainSummary, TrainError> {
    let mut env_config = opts.env.clone();
    if resume {
        env_config = checkpoint::read_meta(&opts.out)?.env;
    }
    let env = AntEnv::new(env_config, opts.seed)?;
    let privileged = if resume {
        checkpoint::read_meta(&opts.out)?.net.privileged
    } else {
        opts.net.privileged
    };
    train(&mut AntTask::new(env, privileged), opts, resume, stop)
}

/// What a fresh `train_ant` would refuse, found without training or writing anything (the env
/// is built once, so a bad model path or config fails here too).
pub fn check_ant(opts: &TrainOptions) -> Result<(), TrainError> {
    let env = AntEnv::new(opts.env.clone(), opts.seed)?;
    validate_fresh(opts, &AntTask::new(env, opts.net.privileged))?;
    if let Some(from) = &opts.init_from {
        let device = Device::Cpu;
        let model = SacModel::new(opts.net.clone(), opts.sac.initial_alpha, opts.seed, &device)?;
        warm_start::warm_start(&model, from, &opts.env.world, &device)?;
    }
    Ok(())
}

/// The training loop, for any [`Task`].
pub fn train(
    task: &mut impl Task,
    opts: TrainOptions,
    resume: bool,
    stop: Arc<AtomicBool>,
) -> Result<TrainSummary, TrainError> {
    train_with_save_hook(task, opts, resume, stop, &mut |_| Ok(()))
}

/// [`train`] with a hook at every stage of every checkpoint save: the fault-injection tests
/// end a save there, as a kill would.
pub fn train_with_save_hook(
    task: &mut impl Task,
    mut opts: TrainOptions,
    resume: bool,
    stop: Arc<AtomicBool>,
    save_hook: &mut dyn FnMut(SaveStage) -> std::io::Result<()>,
) -> Result<TrainSummary, TrainError> {
    let device = Device::Cpu;
    let started = Instant::now();

    // --- setup: fresh or resumed -----------------------------------------------------------
    let (run, mut learner, mut state, mut replay, resumed) = if resume {
        let r = resume_run(&mut opts, &device)?;
        (r.run, r.learner, r.state, r.replay, Some(r.record))
    } else {
        validate_fresh(&opts, task)?;
        // Built (and warm-started) before the run folder exists, so a refused source leaves
        // nothing behind.
        let model = SacModel::new(opts.net.clone(), opts.sac.initial_alpha, opts.seed, &device)?;
        let warm = match &opts.init_from {
            Some(from) => Some(warm_start::warm_start(
                &model,
                from,
                &opts.env.world,
                &device,
            )?),
            None => None,
        };
        let replay_dir = opts.replay_dir.clone().unwrap_or_else(|| opts.out.clone());
        let run = RunDir::lock(&opts.out, &replay_dir)?;
        // A fresh run that was killed during its first save may have left staged files.
        run.recover()?;
        if checkpoint::read_meta(&opts.out).is_ok() {
            return Err(already_a_run(&opts.out));
        }
        let mut learner = SacLearner::new(model, opts.sac.clone(), device.clone());
        learner.init_aux(opts.seed)?;
        let state = TrainState {
            steps_done: 0,
            episodes_done: 0,
            wall_time_s: 0.0,
            adam_steps: [0; 3],
            action_rng: ChaCha8Rng::seed_from_u64(opts.seed ^ 0xA5A5_0001),
            update_rng: ChaCha8Rng::seed_from_u64(opts.seed ^ 0xA5A5_0002),
            replay_saved: false,
            model_crc32: 0,
            optimizer_crc32: None,
            replay_crc32: None,
            aux_crc32: None,
            aux: None,
            replay_dir: (replay_dir != opts.out).then_some(replay_dir),
            resumes: Vec::new(),
            warm_start: warm,
        };
        let replay = new_replay(&opts);
        truncate_metrics(&opts.out, 0)?;
        (run, learner, state, replay, None)
    };
    learner.set_update_path(opts.update)?;
    learner.set_threads(opts.threads)?;
    let net = opts.net.clone();
    let mut metrics = MetricsLog::open(&opts.out)?;

    // A resumed run restarts the episode it was in, from a seed derived from the step count.
    let mut episode = Episode::new(
        &net,
        task.reset_with_seed(
            opts.seed
                .wrapping_add(state.steps_done.wrapping_mul(0x9E37)),
        ),
    );
    let start_step = state.steps_done;
    let wall_before = state.wall_time_s;

    // --- refill: a resume without its buffer collects one before it updates again ------------
    if let Some(mut record) = resumed {
        if record.buffer == BufferSource::Refilled {
            let target = record.refill_transitions;
            record.refill_transitions = 0;
            let bar = refill_bar(&opts, target);
            log::info!(
                "refilling the replay buffer: {} transitions from the current policy before updates resume (step {})",
                target - replay.len(),
                state.steps_done
            );
            while replay.len() < target {
                if stop.load(Ordering::Relaxed) {
                    log::warn!(
                        "interrupted during the refill: nothing saved; the checkpoint of step {} stands",
                        state.steps_done
                    );
                    return Ok(TrainSummary {
                        steps_done: state.steps_done,
                        episodes_done: state.episodes_done,
                        wall_time_s: state.wall_time_s,
                        interrupted: true,
                        saved: false,
                        steps_per_s: 0.0,
                        learning_steps_per_s: None,
                    });
                }
                let warm_up = uniform_warm_up(&state, &opts);
                let (_, ended) = collect_step(
                    task,
                    &mut learner,
                    &net,
                    warm_up,
                    &mut state.action_rng,
                    &mut episode,
                    &mut replay,
                )?;
                record.refill_transitions += 1;
                record.refill_episodes += u64::from(ended.is_some());
                if let Some(bar) = &bar {
                    bar.set_position(replay.len() as u64);
                }
            }
            record.refill_episodes += u64::from(episode.t > 0);
            if let Some(bar) = bar {
                bar.finish_and_clear();
            }
        }
        metrics.write(&ResumeMetrics {
            global_step: state.steps_done,
            resume: record.clone(),
        })?;
        state.resumes.push(record);
    }

    let progress = progress_bar(&opts, state.steps_done);
    let mut recent = RecentEpisodes::new(20);
    let mut batch = Batch::default();
    let mut last_stats = UpdateStats::default();
    let mut interrupted = false;
    let mut learning_started: Option<(u64, Instant)> = None;

    // --- the loop ----------------------------------------------------------------------------
    while state.steps_done < opts.total_steps {
        if stop.load(Ordering::Relaxed) {
            interrupted = true;
            break;
        }

        // Act (uniform warm-up, then a squashed-Gaussian sample), step, store the transition.
        let warm_up = uniform_warm_up(&state, &opts);
        let (step, ended) = collect_step(
            task,
            &mut learner,
            &net,
            warm_up,
            &mut state.action_rng,
            &mut episode,
            &mut replay,
        )?;
        state.steps_done += 1;
        if let Some(end) = ended {
            state.episodes_done += 1;
            recent.push(end.episodic_return, step.success);
            metrics.write(&EpisodeMetrics {
                global_step: state.steps_done,
                episodic_return: end.episodic_return,
                episodic_length: end.length,
                success: step.success,
                triggered_joints: step.triggered_joints,
                condition: step.condition,
            })?;
        }

        // Learn: one gradient step per env step once warm-up is over.
        let warmed_up = state.steps_done > opts.sac.learning_starts as u64
            && replay.len()
                >= opts
                    .sac
                    .learning_starts
                    .max(opts.sac.batch_size.min(replay.capacity()));
        if warmed_up {
            learning_started.get_or_insert_with(|| (state.steps_done, Instant::now()));
            replay.sample(opts.sac.batch_size, &mut state.update_rng, &mut batch);
            last_stats = learner.update(&batch, &mut state.update_rng)?;
            for (what, v) in [
                ("critic loss", last_stats.qf1_loss),
                ("actor loss", last_stats.actor_loss),
            ] {
                if !v.is_finite() {
                    return Err(TrainError::Diverged {
                        step: state.steps_done,
                        what: what.to_string(),
                    });
                }
            }
        }

        let elapsed = started.elapsed().as_secs_f64();
        let sps = (state.steps_done - start_step) as f64 / elapsed.max(1e-9);
        if state.steps_done.is_multiple_of(opts.log_every)
            && state.steps_done > opts.sac.learning_starts as u64
        {
            metrics.write(&UpdateMetrics {
                global_step: state.steps_done,
                stats: last_stats,
                sps,
            })?;
        }
        if let Some(bar) = &progress {
            bar.set_position(state.steps_done);
            if state.steps_done.is_multiple_of(100) {
                bar.set_message(recent.describe(sps));
            }
        }
        if state.steps_done.is_multiple_of(opts.checkpoint_every)
            && state.steps_done < opts.total_steps
        {
            state.wall_time_s = wall_before + elapsed;
            save_run(&run, &opts, &mut learner, &mut state, &replay, save_hook)?;
        }
    }

    // --- final checkpoint (also on Ctrl-C) ---------------------------------------------------
    let learning_steps_per_s = learning_started
        .map(|(from, at)| (state.steps_done - from) as f64 / at.elapsed().as_secs_f64().max(1e-9));
    let elapsed = started.elapsed().as_secs_f64();
    state.wall_time_s = wall_before + elapsed;
    save_run(&run, &opts, &mut learner, &mut state, &replay, save_hook)?;
    if let Some(bar) = progress {
        bar.finish_with_message(
            recent.describe((state.steps_done - start_step) as f64 / elapsed.max(1e-9)),
        );
    }
    Ok(TrainSummary {
        steps_done: state.steps_done,
        episodes_done: state.episodes_done,
        wall_time_s: state.wall_time_s,
        interrupted,
        saved: true,
        steps_per_s: (state.steps_done - start_step) as f64 / elapsed.max(1e-9),
        learning_steps_per_s,
    })
}

/// The episode the trainer is in: the observation, the context window, the running return.
struct Episode {
    obs: Vec<f64>,
    window: ContextWindow,
    encoder_window: Vec<f32>,
    t: usize,
    episodic_return: f64,
}

/// How an episode ended, for the metrics.
struct EpisodeEnd {
    episodic_return: f64,
    length: usize,
}

impl Episode {
    fn new(net: &NetConfig, obs: Vec<f64>) -> Self {
        Self {
            obs,
            window: ContextWindow::with_dims(net.context_len, net.obs_dim, net.act_dim),
            encoder_window: vec![0f32; net.context_len * net.entry_dim()],
            t: 0,
            episodic_return: 0.0,
        }
    }
}

/// One step of data collection, shared by training and the refill: act (uniform in warm-up, else
/// a sample from the actor), step the task, store the transition, reset at an episode's end.
fn collect_step(
    task: &mut impl Task,
    learner: &mut SacLearner,
    net: &NetConfig,
    warm_up: bool,
    rng: &mut ChaCha8Rng,
    ep: &mut Episode,
    replay: &mut ReplayBuffer,
) -> Result<(TaskStep, Option<EpisodeEnd>), TrainError> {
    let action: Vec<f64> = if warm_up {
        (0..net.act_dim)
            .map(|_| rng.random_range(-1.0..=1.0))
            .collect()
    } else {
        let obs32: Vec<f32> = ep.obs.iter().map(|&v| v as f32).collect();
        let noise: Vec<f32> = (0..net.act_dim)
            .map(|_| rng.sample::<f32, _>(StandardNormal))
            .collect();
        let window_arg = if net.encoder.uses_window() {
            ep.encoder_window.copy_from_slice(ep.window.as_slice());
            Some(&ep.encoder_window[..])
        } else {
            None
        };
        learner.explore(&obs32, window_arg, &noise)?
    };
    let mut step = task.step(&action)?;
    learner.observe(&ep.obs, &step.obs, step.terminated);
    replay.push(Transition {
        obs: &ep.obs,
        action: &action,
        reward: step.reward,
        next_obs: &step.obs,
        terminated: step.terminated,
        truncated: step.truncated,
        t_in_episode: ep.t,
    });
    ep.window.push(&ep.obs, &action);
    ep.episodic_return += step.reward;
    if step.terminated || step.truncated {
        let end = EpisodeEnd {
            episodic_return: ep.episodic_return,
            length: ep.t + 1,
        };
        ep.obs = task.reset();
        ep.window.clear();
        ep.t = 0;
        ep.episodic_return = 0.0;
        Ok((step, Some(end)))
    } else {
        ep.obs = std::mem::take(&mut step.obs);
        ep.t += 1;
        Ok((step, None))
    }
}

fn new_replay(opts: &TrainOptions) -> ReplayBuffer {
    let net = &opts.net;
    let window_len = if net.encoder.uses_window() {
        net.context_len
    } else {
        0
    };
    ReplayBuffer::new(opts.sac.buffer_size, net.obs_dim, net.act_dim, window_len)
}

fn already_a_run(dir: &Path) -> TrainError {
    TrainError::Options(format!(
        "{} already holds a checkpoint; use --resume {} to continue it, or another --out",
        dir.display(),
        dir.display()
    ))
}

fn validate_fresh(opts: &TrainOptions, task: &impl Task) -> Result<(), TrainError> {
    if (opts.net.obs_dim, opts.net.act_dim) != (task.obs_dim(), task.act_dim()) {
        return Err(TrainError::Options(format!(
            "net dims {}/{} do not match the task's {}/{}",
            opts.net.obs_dim,
            opts.net.act_dim,
            task.obs_dim(),
            task.act_dim()
        )));
    }
    validate_options(opts)?;
    if checkpoint::read_meta(&opts.out).is_ok() {
        return Err(already_a_run(&opts.out));
    }
    Ok(())
}

/// The ranges every run must be in, fresh or resumed (a hand-edited `checkpoint.json` included).
fn validate_options(opts: &TrainOptions) -> Result<(), TrainError> {
    let bad = |m: String| Err(TrainError::Options(m));
    if opts.total_steps == 0 || opts.checkpoint_every == 0 || opts.log_every == 0 {
        return bad(
            "--steps, the checkpoint interval and the log interval must be at least 1".into(),
        );
    }
    let sac = &opts.sac;
    if sac.batch_size == 0 || sac.buffer_size == 0 {
        return bad("batch size and buffer size must be at least 1".into());
    }
    if sac.buffer_size > MAX_BUFFER_SIZE {
        return bad(format!(
            "buffer size {} is above the limit of {MAX_BUFFER_SIZE} transitions",
            sac.buffer_size
        ));
    }
    if sac.batch_size > 65_536 {
        return bad(format!("batch size {} is above 65536", sac.batch_size));
    }
    // The numbers SAC's updates multiply by: a discount outside [0, 1) or a rate past 1 is
    // a run that diverges, not a choice (a hand-edited checkpoint.json resumed with gamma −1).
    let ranges = [
        ("gamma", sac.gamma, 0.0, 1.0, "[0, 1)"),
        ("tau", sac.tau, f64::MIN_POSITIVE, 1.0, "(0, 1]"),
        (
            "learning rate",
            sac.learning_rate,
            f64::MIN_POSITIVE,
            1.0,
            "(0, 1]",
        ),
        (
            "initial alpha",
            sac.initial_alpha,
            f64::MIN_POSITIVE,
            1e6,
            "(0, 1e6]",
        ),
    ];
    for (name, value, low, high, says) in ranges {
        let inside = value >= low && value <= high && !(name == "gamma" && value == 1.0);
        if !inside {
            return bad(format!("SAC {name} must lie in {says}, got {value}"));
        }
    }
    if let Some(t) = sac.target_entropy
        && !(t.is_finite() && t.abs() <= 1e6)
    {
        return bad(format!("SAC target entropy must lie within ±1e6, got {t}"));
    }
    let net = &opts.net;
    if net.privileged != Privileged::None {
        net.check_inputs().map_err(TrainError::Options)?;
    }
    if net.context_len == 0 || net.z_dim == 0 || net.hidden.contains(&0) {
        return bad("context length, z size and hidden sizes must be at least 1".into());
    }
    if net.context_len > 1024 || net.z_dim > 4096 || net.hidden.iter().any(|&h| h > 65_536) {
        return bad(format!(
            "network too large: context length {} (at most 1024), z size {} (at most 4096), hidden {:?} (each at most 65536)",
            net.context_len, net.z_dim, net.hidden
        ));
    }
    if opts.refill < MIN_REFILL {
        return bad(format!(
            "--refill {} is below {MIN_REFILL}: a resumed run would update from a near-empty buffer",
            opts.refill
        ));
    }
    if !sac.aux.is_off() {
        if !net.encoder.uses_window() {
            return bad(format!(
                "--aux {} needs an encoder to shape (--encoder lstm or mlp-window), not --encoder none",
                aux_name(sac.aux.kind)
            ));
        }
        if !(sac.aux.weight.is_finite() && sac.aux.weight > 0.0 && sac.aux.weight <= 1e3) {
            return bad(format!(
                "--aux-weight {} must be a number in (0, 1000]",
                sac.aux.weight
            ));
        }
    }
    Ok(())
}

/// Whether this step acts uniformly at random: before `learning_starts`, unless the run was
/// warm-started, whose policy already walks and fills the buffer with its own actions.
fn uniform_warm_up(state: &TrainState, opts: &TrainOptions) -> bool {
    state.steps_done < opts.sac.learning_starts as u64 && state.warm_start.is_none()
}

fn progress_bar(opts: &TrainOptions, position: u64) -> Option<indicatif::ProgressBar> {
    if !opts.progress_bar {
        return None;
    }
    let bar = indicatif::ProgressBar::new(opts.total_steps).with_position(position);
    let style = indicatif::ProgressStyle::with_template(
        "{bar:30} {pos}/{len} [{elapsed_precise} < {eta_precise}] {msg}",
    )
    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style);
    Some(bar)
}

fn refill_bar(opts: &TrainOptions, target: usize) -> Option<indicatif::ProgressBar> {
    if !opts.progress_bar {
        return None;
    }
    let bar = indicatif::ProgressBar::new(target as u64);
    let style = indicatif::ProgressStyle::with_template(
        "refill {bar:30} {pos}/{len} [{elapsed_precise} < {eta_precise}]",
    )
    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style);
    Some(bar)
}

/// The paper's training defaults for the Ant.
pub fn ant_options(
    encoder: EncoderKind,
    total_steps: u64,
    seed: u64,
    out: PathBuf,
) -> TrainOptions {
    TrainOptions {
        net: NetConfig::ant(encoder),
        sac: SacConfig::default(),
        env: GaitConfig::default(),
        seed,
        total_steps,
        out,
        checkpoint_every: 10_000,
        save_replay: true,
        log_every: 1_000,
        progress_bar: true,
        update: UpdatePath::Fused,
        threads: 1,
        replay_dir: None,
        refill: DEFAULT_REFILL,
        init_from: None,
    }
}

#[cfg(test)]
mod tests {
    use super::resume::restore_replay;
    use super::*;
    use crate::policy::checkpoint::TrainingRecord;
    use std::collections::BTreeMap;

    #[test]
    fn a_resume_may_only_repeat_what_the_run_is() {
        let dir = tempfile::tempdir().unwrap();
        let net = NetConfig {
            hidden: vec![8],
            z_dim: 2,
            ..NetConfig::ant(EncoderKind::Lstm)
        };
        let sac = SacConfig {
            aux: crate::policy::AuxConfig {
                kind: crate::policy::AuxKind::Dynamics,
                weight: 0.5,
            },
            ..SacConfig::default()
        };
        let record = TrainingRecord {
            env: GaitConfig::default(),
            sac,
            seed: 1,
            steps_done: 0,
            episodes_done: 0,
            wall_time_s: 0.0,
            imported_from: None,
        };
        SacModel::new(net, 1.0, 1, &Device::Cpu)
            .unwrap()
            .save(dir.path(), &record)
            .unwrap();
        let id = |encoder, aux, aux_weight| RunIdentity {
            encoder,
            aux,
            aux_weight,
        };
        use crate::policy::AuxKind::{Dynamics, None as Off};
        // Silence and repetition pass; any difference is named.
        assert!(id(None, None, None).check_against(dir.path()).is_ok());
        let same = id(Some(EncoderKind::Lstm), Some(Dynamics), Some(0.5));
        assert_eq!(same.check_against(dir.path()).unwrap().sac.aux.weight, 0.5);
        for (other, words) in [
            (
                id(Some(EncoderKind::None), None, None),
                "'lstm' run; --encoder none",
            ),
            (id(None, Some(Off), None), "cannot change on resume"),
            (id(None, None, Some(1.0)), "cannot change on resume"),
        ] {
            let e = other.check_against(dir.path()).unwrap_err().to_string();
            assert!(e.contains(words), "{e}");
        }
        // A fresh run: the weight needs the loss.
        assert!(id(None, None, Some(2.0)).fresh_aux().is_err());
        let aux = id(None, Some(Dynamics), Some(2.0)).fresh_aux().unwrap();
        assert_eq!((aux.kind, aux.weight), (Dynamics, 2.0));
        assert!(id(None, None, None).fresh_aux().unwrap().is_off());
    }

    /// Observe s ~ U(−1, 1), act, earn −(a − s/2)²; eight steps an episode.
    struct Toy {
        rng: ChaCha8Rng,
        s: f64,
        t: usize,
    }

    impl Toy {
        fn new() -> Self {
            Self {
                rng: ChaCha8Rng::seed_from_u64(0),
                s: 0.0,
                t: 0,
            }
        }
    }

    impl Task for Toy {
        fn obs_dim(&self) -> usize {
            1
        }
        fn act_dim(&self) -> usize {
            1
        }
        fn reset_with_seed(&mut self, seed: u64) -> Vec<f64> {
            self.rng = ChaCha8Rng::seed_from_u64(seed);
            self.reset()
        }
        fn reset(&mut self) -> Vec<f64> {
            self.t = 0;
            self.s = self.rng.random_range(-1.0..1.0);
            vec![self.s]
        }
        fn step(&mut self, action: &[f64]) -> Result<TaskStep, TrainError> {
            let reward = -(action[0] - self.s / 2.0).powi(2);
            self.t += 1;
            self.s = self.rng.random_range(-1.0..1.0);
            Ok(TaskStep {
                obs: vec![self.s],
                reward,
                terminated: false,
                truncated: self.t >= 8,
                success: false,
                triggered_joints: 0,
                condition: None,
            })
        }
    }

    fn options(out: PathBuf, total_steps: u64) -> TrainOptions {
        TrainOptions {
            net: NetConfig {
                encoder: EncoderKind::None,
                obs_dim: 1,
                act_dim: 1,
                context_len: 4,
                z_dim: 4,
                hidden: vec![8, 8],
                window_mlp_hidden: vec![8],
                share_encoder: false,
                privileged: Privileged::None,
            },
            sac: SacConfig {
                batch_size: 16,
                buffer_size: 20_000,
                learning_starts: 50,
                ..SacConfig::default()
            },
            env: GaitConfig::default(),
            seed: 3,
            total_steps,
            out,
            checkpoint_every: 100,
            save_replay: true,
            log_every: 50,
            progress_bar: false,
            update: UpdatePath::Fused,
            threads: 1,
            replay_dir: None,
            refill: MIN_REFILL,
            init_from: None,
        }
    }

    /// Trains the toy task with `opts`, never stopped.
    fn train_toy(opts: TrainOptions, resume: bool) -> Result<TrainSummary, TrainError> {
        train(
            &mut Toy::new(),
            opts,
            resume,
            Arc::new(AtomicBool::new(false)),
        )
    }

    fn run(out: &Path, total: u64, resume: bool) -> Result<TrainSummary, TrainError> {
        train_toy(options(out.to_owned(), total), resume)
    }

    fn state_of(dir: &Path) -> TrainState {
        serde_json::from_str(&std::fs::read_to_string(dir.join(STATE_FILE)).unwrap()).unwrap()
    }

    /// Every file of a run folder, by name.
    fn snapshot(dir: &Path) -> BTreeMap<String, Vec<u8>> {
        std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .map(|p| {
                let name = p.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read(&p).unwrap())
            })
            .collect()
    }

    #[test]
    fn a_warm_started_run_fills_its_buffer_with_the_source_policy_not_noise() {
        let tmp = tempfile::tempdir().unwrap();
        let source = tmp.path().join("source");
        let mut learnt = options(source.clone(), 1500);
        learnt.sac.learning_rate = 3e-3;
        train_toy(learnt, false).unwrap();
        // 200 steps and no update, warm-started or not: how far the buffer's actions lie
        // from the toy's best a = s/2 (uniform noise: about 0.5 on average).
        let miss = |init_from: Option<PathBuf>, name: &str| {
            let out = tmp.path().join(name);
            let mut opts = options(out.clone(), 200);
            opts.sac.learning_starts = 200;
            opts.init_from = init_from;
            train_toy(opts.clone(), false).unwrap();
            let state = state_of(&out);
            assert_eq!(
                state.adam_steps, [0; 3],
                "{name}: no update before learning_starts"
            );
            let mut replay = new_replay(&opts);
            restore_replay(&out.join(REPLAY_FILE), state.replay_crc32, &mut replay).unwrap();
            let mut batch = Batch::default();
            replay.sample(512, &mut ChaCha8Rng::seed_from_u64(9), &mut batch);
            let total: f32 = batch
                .actions
                .iter()
                .zip(&batch.obs)
                .map(|(a, s)| (a - s / 2.0).abs())
                .sum();
            (total / 512.0, state.warm_start)
        };
        let (warm, record) = miss(Some(source.clone()), "warm");
        let (cold, none) = miss(None, "cold");
        assert!(warm < 0.25 && cold > 0.4, "warm {warm}, cold {cold}");
        assert_eq!(record.map(|w| w.from), Some(source));
        assert!(none.is_none());
    }

    #[test]
    fn a_resume_without_its_buffer_refills_before_any_update() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        run(&out, 300, false).unwrap();
        let before = state_of(&out);
        // One update per step after warm-up: the gap is the warm-up, and stays so.
        let gap = before.steps_done - before.adam_steps[1];
        std::fs::remove_file(out.join(REPLAY_FILE)).unwrap();
        run(&out, 400, true).unwrap();
        let after = state_of(&out);
        assert_eq!(after.steps_done, 400);
        assert_eq!(
            after.steps_done - after.adam_steps[1],
            gap,
            "the refill's steps must not update"
        );
        // The buffer was refilled to min(buffer 20000, steps 300, refill 10000) = 300.
        assert_eq!(
            after.resumes,
            vec![ResumeRecord {
                step: 300,
                buffer: BufferSource::Refilled,
                restored_transitions: 0,
                refill_transitions: 300,
                refill_episodes: 38,
            }]
        );
        // The buffer holds the refill and the 100 new steps.
        let mut replay = new_replay(&options(out.clone(), 0));
        restore_replay(&out.join(REPLAY_FILE), after.replay_crc32, &mut replay).unwrap();
        assert_eq!(replay.len(), 400);
        let metrics = std::fs::read_to_string(out.join(METRICS_FILE)).unwrap();
        let resume_line = metrics
            .lines()
            .find(|l| l.contains("\"resume\""))
            .expect("metrics.jsonl records the resume");
        let v: serde_json::Value = serde_json::from_str(resume_line).unwrap();
        assert_eq!(v["global_step"], 300);
        assert_eq!(v["resume"]["buffer"], "refilled");
        assert_eq!(v["resume"]["refill_transitions"], 300);

        // With its buffer, a resume restores it and refills nothing.
        run(&out, 500, true).unwrap();
        let last = state_of(&out).resumes.pop().unwrap();
        assert_eq!(last.buffer, BufferSource::Restored);
        assert_eq!(
            (last.restored_transitions, last.refill_transitions),
            (400, 0)
        );
    }

    #[test]
    fn a_kill_at_any_stage_of_a_save_resumes_one_consistent_generation() {
        // Five files a save: weights, optimiser, replay, train state, checkpoint.json.
        let n = 5;
        let stages: Vec<SaveStage> = (0..n)
            .map(SaveStage::Staged)
            .chain([SaveStage::ManifestWritten])
            .chain((0..n).map(SaveStage::Renamed))
            .chain([SaveStage::Done])
            .collect();
        for (k, &kill_at) in stages.iter().enumerate() {
            let tmp = tempfile::tempdir().unwrap();
            let out = tmp.path().join("run");
            run(&out, 200, false).unwrap();
            let mut seen = Vec::new();
            let killed = train_with_save_hook(
                &mut Toy::new(),
                options(out.clone(), 300),
                true,
                Arc::new(AtomicBool::new(false)),
                &mut |stage| {
                    seen.push(stage);
                    if stage == kill_at {
                        Err(std::io::Error::other("killed"))
                    } else {
                        Ok(())
                    }
                },
            );
            assert!(killed.is_err(), "{kill_at:?}");
            assert_eq!(seen.len(), k + 1, "the hook saw every stage up to the kill");
            // The next resume settles the folder and finds everything belonging together: its
            // weights, optimiser and buffer all from one step.
            run(&out, 300, true).unwrap_or_else(|e| panic!("resume after {kill_at:?}: {e}"));
            let state = state_of(&out);
            assert_eq!(state.steps_done, 300);
            let resumed_from = state.resumes.last().unwrap();
            let expected_step = if k < n { 200 } else { 300 };
            assert_eq!(resumed_from.step, expected_step, "killed at {kill_at:?}");
            assert_eq!(resumed_from.buffer, BufferSource::Restored, "{kill_at:?}");
            assert_eq!(resumed_from.restored_transitions as u64, expected_step);
            load_learner(&out, &Device::Cpu).unwrap();
            assert!(!out.join(run_dir::PENDING_FILE).exists());
            assert!(
                snapshot(&out).keys().all(|name| !name.ends_with(".tmp")),
                "nothing staged is left: {:?}",
                snapshot(&out).keys()
            );
        }
    }

    #[test]
    fn non_finite_weights_or_buffer_never_replace_the_last_good_checkpoint() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        run(&out, 200, false).unwrap();
        let good = snapshot(&out);

        // A NaN weight: the save refuses, and every file is as it was.
        let opts = options(out.clone(), 200);
        let mut resumed = resume_run(&mut opts.clone(), &Device::Cpu).unwrap();
        let (_, var) = resumed.learner.model.all_params().next().unwrap();
        let poisoned = (var.as_tensor() * f64::NAN).unwrap();
        var.set(&poisoned).unwrap();
        let err = save_run(
            &resumed.run,
            &opts,
            &mut resumed.learner,
            &mut resumed.state,
            &resumed.replay,
            &mut |_| Ok(()),
        )
        .unwrap_err();
        assert!(matches!(err, TrainError::Diverged { .. }), "{err}");
        assert!(err.to_string().contains("last good checkpoint stands"));
        drop(resumed);
        let mut now = snapshot(&out);
        now.remove(run_dir::LOCK_FILE);
        let mut expected = good.clone();
        expected.remove(run_dir::LOCK_FILE);
        // resume_run rewrites metrics.jsonl (same lines) and nothing else.
        assert_eq!(now, expected);

        // A NaN in replay.bin: without a checksum to go by (older runs) the finite check
        // refuses it...
        let path = out.join(REPLAY_FILE);
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[56..60].copy_from_slice(&f32::NAN.to_le_bytes());
        std::fs::write(&path, &bytes).unwrap();
        let mut replay = new_replay(&opts);
        let err = restore_replay(&path, None, &mut replay)
            .unwrap_err()
            .to_string();
        assert!(err.contains("NaN"), "{err}");
        // ... and with one it is set aside, never read, and the resume refills instead.
        run(&out, 300, true).unwrap();
        assert!(out.join("replay.bin.mismatched").exists());
        let state = state_of(&out);
        assert_eq!(state.steps_done, 300);
        let resume = state.resumes.last().unwrap();
        assert_eq!(
            (
                resume.buffer,
                resume.restored_transitions,
                resume.refill_transitions
            ),
            (BufferSource::Refilled, 0, 200)
        );
    }

    /// replay.bin is read only when it is a regular file of exactly the size this run's buffer
    /// saves to: a FIFO is refused at once (opening it would block), a symlink to /dev/zero
    /// and a sparse file of gigabytes are judged by their size before a byte is read (set
    /// aside when a checksum says the run saved another buffer; refused for a run without one).
    #[test]
    fn a_replay_file_is_judged_by_its_kind_and_size_before_it_is_read() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        run(&out, 200, false).unwrap();
        let opts = options(out.clone(), 0);
        let path = out.join(REPLAY_FILE);
        let mut replay = new_replay(&opts);
        assert_eq!(
            std::fs::metadata(&path).unwrap().len(),
            replay.file_len(),
            "the saved buffer is exactly file_len bytes"
        );
        let good = std::fs::read(&path).unwrap();

        // A FIFO: refused without blocking.
        std::fs::remove_file(&path).unwrap();
        crate::files::mkfifo(&path);
        let started = Instant::now();
        let err = restore_replay(&path, Some(1), &mut replay).unwrap_err();
        assert!(err.to_string().contains("not a regular file"), "{err}");
        assert!(started.elapsed().as_secs() < 5);
        std::fs::remove_file(&path).unwrap();

        // A symlink to /dev/zero: a device, refused.
        std::os::unix::fs::symlink("/dev/zero", &path).unwrap();
        let err = restore_replay(&path, None, &mut replay).unwrap_err();
        assert!(err.to_string().contains("not a regular file"), "{err}");
        std::fs::remove_file(&path).unwrap();

        // A sparse 2 GiB file: without a checksum refused by its size, with one set aside;
        // neither reads it (the process would need 2 GiB to).
        let sparse = std::fs::File::create(&path).unwrap();
        sparse.set_len(2 << 30).unwrap();
        drop(sparse);
        let err = restore_replay(&path, None, &mut replay).unwrap_err();
        let text = err.to_string();
        assert!(
            text.contains("2147483648 bytes") && text.contains(&replay.file_len().to_string()),
            "{text}"
        );
        restore_replay(&path, Some(7), &mut replay).unwrap();
        assert!(!path.exists() && out.join("replay.bin.mismatched").exists());
        assert!(replay.is_empty(), "nothing was read into the buffer");

        // The real buffer still reads.
        std::fs::write(&path, &good).unwrap();
        restore_replay(&path, Some(crc32fast::hash(&good)), &mut replay).unwrap();
        assert_eq!(replay.len(), 200);
    }

    /// train_state.json may name a replay folder elsewhere (`--replay-dir`), but a resume writes
    /// there only when the command line names it again: an edited state file cannot send the
    /// trainer's writes to /etc.
    #[test]
    fn a_recorded_replay_dir_is_used_only_when_the_command_line_repeats_it() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        let elsewhere = tmp.path().join("cache");
        let run_in = |total: u64, resume: bool| {
            let mut opts = options(out.clone(), total);
            opts.replay_dir = Some(elsewhere.clone());
            train_toy(opts, resume)
        };
        run_in(200, false).unwrap();
        assert!(elsewhere.join(REPLAY_FILE).exists());
        assert_eq!(state_of(&out).replay_dir, Some(elsewhere.clone()));

        // Resumed without --replay-dir: refused, naming the flag to give; nothing written.
        let before = snapshot(&out);
        let err = run(&out, 300, true).unwrap_err();
        assert!(
            matches!(&err, TrainError::ReplayDirNotConfirmed { recorded, .. } if *recorded == elsewhere),
            "{err}"
        );
        assert!(err.to_string().contains("repeat --replay-dir"), "{err}");
        let mut after = snapshot(&out);
        after.remove(run_dir::LOCK_FILE);
        let mut expected = before.clone();
        expected.remove(run_dir::LOCK_FILE);
        assert_eq!(after, expected);

        // A state file edited to point at another folder: refused the same way.
        let state_path = out.join(STATE_FILE);
        let text = std::fs::read_to_string(&state_path).unwrap();
        let hostile = tmp.path().join("etc");
        std::fs::write(
            &state_path,
            text.replace(
                &serde_json::to_string(&elsewhere).unwrap(),
                &serde_json::to_string(&hostile).unwrap(),
            ),
        )
        .unwrap();
        assert!(matches!(
            run(&out, 300, true),
            Err(TrainError::ReplayDirNotConfirmed { .. })
        ));
        assert!(
            !hostile.exists(),
            "nothing was created where the file pointed"
        );
        std::fs::write(&state_path, text).unwrap();

        // Repeated on the command line, the resume restores the buffer there.
        run_in(300, true).unwrap();
        let resume = state_of(&out).resumes.pop().unwrap();
        assert_eq!(resume.buffer, BufferSource::Restored);
    }

    #[test]
    fn metrics_lines_follow_a_file_replaced_under_the_trainer() {
        // What `git stash` does to a tracked metrics.jsonl: a new file takes the name.
        let dir = tempfile::tempdir().unwrap();
        let mut log = MetricsLog::open(dir.path()).unwrap();
        let line = |step: u64| serde_json::json!({ "global_step": step });
        log.write(&line(1)).unwrap();
        let path = dir.path().join(METRICS_FILE);
        let replacement = dir.path().join("replacement");
        std::fs::write(&replacement, "{\"global_step\":0}\n").unwrap();
        std::fs::rename(&replacement, &path).unwrap();
        log.write(&line(2)).unwrap();
        assert_eq!(
            std::fs::read_to_string(&path).unwrap(),
            "{\"global_step\":0}\n{\"global_step\":2}\n"
        );
        // A folder that went away is an error naming the file, not a silent loss.
        drop(dir);
        let e = log.write(&line(3)).unwrap_err().to_string();
        assert!(e.contains(METRICS_FILE), "{e}");
    }

    #[test]
    fn a_second_trainer_on_one_folder_is_refused_and_readers_still_read() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        run(&out, 100, false).unwrap();
        let holder = RunDir::lock(&out, &out).unwrap();
        let err = run(&out, 200, true).unwrap_err().to_string();
        assert!(
            err.contains(&format!("pid {}", std::process::id())),
            "{err}"
        );
        load_learner(&out, &Device::Cpu).expect("readers take no lock");
        drop(holder);
        run(&out, 200, true).unwrap();
    }

    #[test]
    fn a_resume_checks_hand_edited_settings_like_a_fresh_run() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("run");
        run(&out, 100, false).unwrap();
        let meta_path = out.join(checkpoint::META_FILE);
        let original = std::fs::read_to_string(&meta_path).unwrap();
        for (size, says) in [
            (0u64, "at least 1"),
            (1_000_000_000_000_000, "above the limit"),
        ] {
            let mut meta: serde_json::Value = serde_json::from_str(&original).unwrap();
            meta["sac"]["buffer_size"] = size.into();
            std::fs::write(&meta_path, meta.to_string()).unwrap();
            let err = run(&out, 200, true).unwrap_err().to_string();
            assert!(
                err.contains("checkpoint.json") && err.contains(says),
                "{err}"
            );
        }
        std::fs::write(&meta_path, &original).unwrap();
        run(&out, 200, true).unwrap();
    }

    #[test]
    fn an_optimiser_file_from_another_run_is_refused() {
        let tmp = tempfile::tempdir().unwrap();
        let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
        run(&a, 100, false).unwrap();
        let mut other = options(b.clone(), 150);
        other.seed = 9;
        train_toy(other, false).unwrap();
        std::fs::copy(b.join(OPTIMIZER_FILE), a.join(OPTIMIZER_FILE)).unwrap();
        let err = run(&a, 200, true).unwrap_err().to_string();
        assert!(err.contains("belongs to another run"), "{err}");
    }
}
