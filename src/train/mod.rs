//! `gaitscope train`: SAC (Stable-Baselines3 defaults) on the damaged Ant, with an optional
//! context encoder. One readable loop in CleanRL's shape; deviations from SB3 are noted inline.
//!
//! A run folder holds the checkpoint (`model.safetensors`, `checkpoint.json`), the optimiser and
//! RNG state for `--resume` (`train_state.json`, `train_state.safetensors`), the replay buffer
//! (`replay.bin`, so a resumed run continues with the same data; git-ignored) and the metrics
//! (`metrics.jsonl`, CleanRL-style names).

pub mod adam;
pub mod curves;
pub mod fused;
pub mod replay;
pub mod sac;

use candle_core::{Device, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, VecDeque};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use crate::config::GaitConfig;
use crate::damage::Condition;
use crate::env::{AntEnv, EnvError};
use crate::policy::checkpoint::{
    self, CheckpointError, TrainingRecord, load_expected_tensors, safetensors_bytes, write_atomic,
};
use crate::policy::{EncoderKind, NetConfig, SacConfig, SacModel};
use crate::window::ContextWindow;
use adam::Adam;
use replay::{Batch, ReplayBuffer, Transition};
use sac::{SacLearner, UpdatePath, UpdateStats};

pub const STATE_FILE: &str = "train_state.json";
pub const OPTIMIZER_FILE: &str = "train_state.safetensors";
pub const REPLAY_FILE: &str = "replay.bin";
pub const METRICS_FILE: &str = "metrics.jsonl";

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error("tensor error: {0}")]
    Tensor(#[from] candle_core::Error),
    #[error("{path}: {reason}")]
    State { path: PathBuf, reason: String },
    #[error("cannot write {path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("invalid training options: {0}")]
    Options(String),
    #[error("training diverged at step {step}: {what} is not finite")]
    Diverged { step: u64, what: &'static str },
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

/// The damaged Ant as a training task.
pub struct AntTask(pub AntEnv);

impl Task for AntTask {
    fn obs_dim(&self) -> usize {
        crate::env::OBS_DIM
    }
    fn act_dim(&self) -> usize {
        crate::env::ACT_DIM
    }
    fn reset_with_seed(&mut self, seed: u64) -> Vec<f64> {
        self.0.reset_with_seed(seed).to_vec()
    }
    fn reset(&mut self) -> Vec<f64> {
        self.0.reset().to_vec()
    }
    fn step(&mut self, action: &[f64]) -> Result<TaskStep, TrainError> {
        let out = self.0.step(action)?;
        Ok(TaskStep {
            obs: out.obs.to_vec(),
            reward: out.reward.total,
            terminated: out.terminated,
            truncated: out.truncated,
            success: out.success,
            triggered_joints: self.0.damage().n_triggered(),
            condition: Some(self.0.condition()),
        })
    }
}

/// Optimiser, RNG and counter state for `--resume`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct TrainState {
    steps_done: u64,
    episodes_done: u64,
    wall_time_s: f64,
    adam_steps: [u64; 3],
    /// Draws warm-up actions and exploration noise.
    action_rng: ChaCha8Rng,
    /// Draws replay samples and the update's reparameterisation noise.
    update_rng: ChaCha8Rng,
    replay_saved: bool,
    /// Ties this state to the weights it was saved with.
    model_crc32: u32,
}

/// How a run ended.
#[derive(Debug, Clone, Serialize)]
pub struct TrainSummary {
    pub steps_done: u64,
    pub episodes_done: u64,
    pub wall_time_s: f64,
    pub interrupted: bool,
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
    train(&mut AntTask(env), opts, resume, stop)
}

/// What a fresh `train_ant` would refuse, found without training or writing anything (the env
/// is built once, so a bad model path or config fails here too).
pub fn check_ant(opts: &TrainOptions) -> Result<(), TrainError> {
    let env = AntEnv::new(opts.env.clone(), opts.seed)?;
    validate_fresh(opts, &AntTask(env))
}

/// The training loop, for any [`Task`].
pub fn train(
    task: &mut impl Task,
    mut opts: TrainOptions,
    resume: bool,
    stop: Arc<AtomicBool>,
) -> Result<TrainSummary, TrainError> {
    let device = Device::Cpu;
    let started = Instant::now();

    // --- setup: fresh or resumed -----------------------------------------------------------
    let (mut learner, mut state, mut replay) = if resume {
        resume_run(&mut opts, &device)?
    } else {
        validate_fresh(&opts, task)?;
        let model = SacModel::new(opts.net.clone(), opts.sac.initial_alpha, opts.seed, &device)?;
        let learner = SacLearner::new(model, opts.sac.clone(), device.clone());
        let state = TrainState {
            steps_done: 0,
            episodes_done: 0,
            wall_time_s: 0.0,
            adam_steps: [0; 3],
            action_rng: ChaCha8Rng::seed_from_u64(opts.seed ^ 0xA5A5_0001),
            update_rng: ChaCha8Rng::seed_from_u64(opts.seed ^ 0xA5A5_0002),
            replay_saved: false,
            model_crc32: 0,
        };
        let net = &opts.net;
        let window_len = if net.encoder.uses_window() {
            net.context_len
        } else {
            0
        };
        let replay = ReplayBuffer::new(opts.sac.buffer_size, net.obs_dim, net.act_dim, window_len);
        std::fs::create_dir_all(&opts.out).map_err(|source| TrainError::Io {
            path: opts.out.clone(),
            source,
        })?;
        truncate_metrics(&opts.out, 0)?;
        (learner, state, replay)
    };
    learner.set_update_path(opts.update)?;
    learner.set_threads(opts.threads)?;
    let net = opts.net.clone();
    let mut metrics = MetricsLog::open(&opts.out)?;
    let progress = progress_bar(&opts, state.steps_done);

    // A resumed run restarts the episode it was in, from a seed derived from the step count.
    let mut obs = task.reset_with_seed(
        opts.seed
            .wrapping_add(state.steps_done.wrapping_mul(0x9E37)),
    );
    let mut window = ContextWindow::with_dims(net.context_len, net.obs_dim, net.act_dim);
    let mut encoder_window = vec![0f32; net.context_len * net.entry_dim()];
    let (mut t_in_episode, mut episode_return) = (0usize, 0.0);
    let mut recent = RecentEpisodes::new(20);
    let mut batch = Batch::default();
    let mut last_stats = UpdateStats::default();
    let start_step = state.steps_done;
    let wall_before = state.wall_time_s;
    let mut interrupted = false;
    let mut learning_started: Option<(u64, Instant)> = None;

    // --- the loop ----------------------------------------------------------------------------
    while state.steps_done < opts.total_steps {
        if stop.load(Ordering::Relaxed) {
            interrupted = true;
            break;
        }
        let global_step = state.steps_done;

        // Act: uniform warm-up, then a squashed-Gaussian sample from the actor.
        let action: Vec<f64> = if global_step < opts.sac.learning_starts as u64 {
            (0..net.act_dim)
                .map(|_| state.action_rng.random_range(-1.0..=1.0))
                .collect()
        } else {
            let obs32: Vec<f32> = obs.iter().map(|&v| v as f32).collect();
            let noise: Vec<f32> = (0..net.act_dim)
                .map(|_| state.action_rng.sample::<f32, _>(StandardNormal))
                .collect();
            let window_arg = if net.encoder.uses_window() {
                encoder_window.copy_from_slice(window.as_slice());
                Some(&encoder_window[..])
            } else {
                None
            };
            learner.explore(&obs32, window_arg, &noise)?
        };

        // Step the env and store the transition.
        let step = task.step(&action)?;
        replay.push(Transition {
            obs: &obs,
            action: &action,
            reward: step.reward,
            next_obs: &step.obs,
            terminated: step.terminated,
            truncated: step.truncated,
            t_in_episode,
        });
        window.push(&obs, &action);
        episode_return += step.reward;
        state.steps_done += 1;

        if step.terminated || step.truncated {
            state.episodes_done += 1;
            recent.push(episode_return, step.success);
            metrics.write(&EpisodeMetrics {
                global_step: state.steps_done,
                episodic_return: episode_return,
                episodic_length: t_in_episode + 1,
                success: step.success,
                triggered_joints: step.triggered_joints,
                condition: step.condition,
            })?;
            obs = task.reset();
            window.clear();
            t_in_episode = 0;
            episode_return = 0.0;
        } else {
            obs = step.obs;
            t_in_episode += 1;
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
                        what,
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
            save_run(&opts, &mut learner, &mut state, &replay)?;
        }
    }

    // --- final checkpoint (also on Ctrl-C) ---------------------------------------------------
    let learning_steps_per_s = learning_started
        .map(|(from, at)| (state.steps_done - from) as f64 / at.elapsed().as_secs_f64().max(1e-9));
    let elapsed = started.elapsed().as_secs_f64();
    state.wall_time_s = wall_before + elapsed;
    save_run(&opts, &mut learner, &mut state, &replay)?;
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
        steps_per_s: (state.steps_done - start_step) as f64 / elapsed.max(1e-9),
        learning_steps_per_s,
    })
}

fn validate_fresh(opts: &TrainOptions, task: &impl Task) -> Result<(), TrainError> {
    let bad = |m: String| Err(TrainError::Options(m));
    if (opts.net.obs_dim, opts.net.act_dim) != (task.obs_dim(), task.act_dim()) {
        return bad(format!(
            "net dims {}/{} do not match the task's {}/{}",
            opts.net.obs_dim,
            opts.net.act_dim,
            task.obs_dim(),
            task.act_dim()
        ));
    }
    if opts.total_steps == 0 || opts.checkpoint_every == 0 || opts.log_every == 0 {
        return bad(
            "--steps, the checkpoint interval and the log interval must be at least 1".into(),
        );
    }
    if opts.sac.batch_size == 0 || opts.sac.buffer_size == 0 {
        return bad("batch size and buffer size must be at least 1".into());
    }
    if opts.net.context_len == 0 || opts.net.z_dim == 0 || opts.net.hidden.contains(&0) {
        return bad("context length, z size and hidden sizes must be at least 1".into());
    }
    if checkpoint::read_meta(&opts.out).is_ok() {
        return bad(format!(
            "{} already holds a checkpoint; use --resume {} to continue it, or another --out",
            opts.out.display(),
            opts.out.display()
        ));
    }
    Ok(())
}

/// Writes weights, optimiser state, RNGs and (optionally) the replay buffer.
fn save_run(
    opts: &TrainOptions,
    learner: &mut SacLearner,
    state: &mut TrainState,
    replay: &ReplayBuffer,
) -> Result<(), TrainError> {
    let record = TrainingRecord {
        env: opts.env.clone(),
        sac: opts.sac.clone(),
        seed: opts.seed,
        steps_done: state.steps_done,
        episodes_done: state.episodes_done,
        wall_time_s: state.wall_time_s,
        imported_from: None,
    };
    learner.sync_model()?;
    // Optimiser state and replay first, JSON state last: a crash in between leaves the previous
    // train_state.json, whose CRC no longer matches the new weights, and resume says so.
    let optimizers = [&learner.actor_opt, &learner.critic_opt, &learner.alpha_opt];
    let tensors = optimizer_tensors(&optimizers)?;
    write_atomic(
        &opts.out.join(OPTIMIZER_FILE),
        &safetensors_bytes(tensors.iter().map(|(n, t)| (n.as_str(), t)))?,
    )?;
    if opts.save_replay {
        let path = opts.out.join(REPLAY_FILE);
        let mut bytes = Vec::new();
        replay
            .write_to(&mut bytes)
            .map_err(|source| TrainError::Io {
                path: path.clone(),
                source,
            })?;
        write_atomic(&path, &bytes)?;
    }
    let meta = learner.model.save(&opts.out, &record)?;
    state.adam_steps = [
        learner.actor_opt.t,
        learner.critic_opt.t,
        learner.alpha_opt.t,
    ];
    state.replay_saved = opts.save_replay;
    state.model_crc32 = meta.model_crc32;
    let path = opts.out.join(STATE_FILE);
    let json = serde_json::to_vec_pretty(state).map_err(|e| TrainError::State {
        path: path.clone(),
        reason: e.to_string(),
    })?;
    write_atomic(&path, &json)?;
    Ok(())
}

fn optimizer_tensors(optimizers: &[&Adam; 3]) -> Result<Vec<(String, Tensor)>, TrainError> {
    let mut out = Vec::new();
    for (group, opt) in ["actor", "critic", "alpha"].iter().zip(optimizers) {
        for (i, (m, v)) in opt.moments().enumerate() {
            out.push((
                format!("{group}.{i:03}.m"),
                Tensor::from_slice(m, m.len(), &Device::Cpu)?,
            ));
            out.push((
                format!("{group}.{i:03}.v"),
                Tensor::from_slice(v, v.len(), &Device::Cpu)?,
            ));
        }
    }
    Ok(out)
}

fn resume_run(
    opts: &mut TrainOptions,
    device: &Device,
) -> Result<(SacLearner, TrainState, ReplayBuffer), TrainError> {
    let dir = opts.out.clone();
    let (learner, state, meta) = load_run(&dir, Some(opts.net.encoder), device)?;
    // The run's own settings win over the command line's, except the total step count.
    opts.net = meta.net.clone();
    opts.sac = meta.sac.clone();
    opts.env = meta.env.clone();
    opts.seed = meta.seed;
    let net = &opts.net;
    let window_len = if net.encoder.uses_window() {
        net.context_len
    } else {
        0
    };
    let mut replay = ReplayBuffer::new(opts.sac.buffer_size, net.obs_dim, net.act_dim, window_len);
    let path = dir.join(REPLAY_FILE);
    if state.replay_saved && path.exists() {
        let file = std::fs::File::open(&path).map_err(|e| TrainError::State {
            path: path.clone(),
            reason: format!("cannot open: {e}"),
        })?;
        replay
            .read_from(&mut std::io::BufReader::new(file))
            .map_err(|reason| TrainError::State { path, reason })?;
    } else if state.replay_saved {
        // replay.bin is git-ignored, so a fresh checkout resumes without it: the buffer refills
        // from the current policy and updates wait until it holds `learning_starts` transitions.
        eprintln!(
            "note: {} is missing; resuming with an empty replay buffer",
            path.display()
        );
    }
    truncate_metrics(&dir, state.steps_done)?;
    Ok((learner, state, replay))
}

/// A run's learner as it was saved: weights, and the optimisers' moments and step counts.
pub fn load_learner(dir: &Path, device: &Device) -> Result<SacLearner, TrainError> {
    Ok(load_run(dir, None, device)?.0)
}

fn load_run(
    dir: &Path,
    encoder: Option<EncoderKind>,
    device: &Device,
) -> Result<(SacLearner, TrainState, checkpoint::CheckpointMeta), TrainError> {
    let (model, meta) = SacModel::load(dir, encoder, device)?;
    let state_path = dir.join(STATE_FILE);
    let text = std::fs::read_to_string(&state_path).map_err(|e| TrainError::State {
        path: state_path.clone(),
        reason: format!("cannot read ({e}); was this folder written by `gaitscope train`?"),
    })?;
    let state: TrainState = serde_json::from_str(&text).map_err(|e| TrainError::State {
        path: state_path.clone(),
        reason: e.to_string(),
    })?;
    if state.model_crc32 != meta.model_crc32 || state.steps_done != meta.steps_done {
        return Err(TrainError::State {
            path: state_path,
            reason: "does not belong to the weights next to it (interrupted save?)".into(),
        });
    }
    let mut learner = SacLearner::new(model, meta.sac.clone(), device.clone());
    let opt_path = dir.join(OPTIMIZER_FILE);
    let bytes = std::fs::read(&opt_path).map_err(|source| CheckpointError::Read {
        path: opt_path.clone(),
        source,
    })?;
    let expected: BTreeMap<String, Vec<usize>> =
        optimizer_tensors(&[&learner.actor_opt, &learner.critic_opt, &learner.alpha_opt])?
            .into_iter()
            .map(|(n, t)| (n, t.dims().to_vec()))
            .collect();
    let tensors =
        load_expected_tensors(dir, &opt_path, &bytes, &expected, meta.net.encoder, device)?;
    for ((group, opt), t) in ["actor", "critic", "alpha"]
        .iter()
        .zip([
            &mut learner.actor_opt,
            &mut learner.critic_opt,
            &mut learner.alpha_opt,
        ])
        .zip(state.adam_steps)
    {
        let moments = (0..opt.len())
            .map(|i| {
                let get = |s: &str| tensors[&format!("{group}.{i:03}.{s}")].to_vec1::<f32>();
                Ok((get("m")?, get("v")?))
            })
            .collect::<Result<Vec<_>, candle_core::Error>>()?;
        opt.set_moments(t, moments)
            .map_err(|reason| TrainError::State {
                path: opt_path.clone(),
                reason,
            })?;
    }
    Ok((learner, state, meta))
}

/// Drops metric lines logged after `steps_done` (work lost since the last checkpoint).
fn truncate_metrics(dir: &Path, steps_done: u64) -> Result<(), TrainError> {
    let path = dir.join(METRICS_FILE);
    let Ok(text) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    let kept: String = text
        .lines()
        .filter(|line| {
            serde_json::from_str::<serde_json::Value>(line)
                .ok()
                .and_then(|v| v["global_step"].as_u64())
                .is_some_and(|s| s <= steps_done)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    write_atomic(&path, kept.as_bytes()).map_err(TrainError::from)
}

#[derive(Serialize)]
struct EpisodeMetrics {
    global_step: u64,
    #[serde(rename = "charts/episodic_return")]
    episodic_return: f64,
    #[serde(rename = "charts/episodic_length")]
    episodic_length: usize,
    #[serde(rename = "charts/success")]
    success: bool,
    #[serde(rename = "charts/triggered_joints")]
    triggered_joints: usize,
    #[serde(rename = "charts/condition", skip_serializing_if = "Option::is_none")]
    condition: Option<Condition>,
}

#[derive(Serialize)]
struct UpdateMetrics {
    global_step: u64,
    #[serde(flatten)]
    stats: UpdateStats,
    #[serde(rename = "charts/SPS")]
    sps: f64,
}

/// Appends JSON lines to `metrics.jsonl`.
struct MetricsLog {
    path: PathBuf,
    file: std::io::BufWriter<std::fs::File>,
}

impl MetricsLog {
    fn open(dir: &Path) -> Result<Self, TrainError> {
        let path = dir.join(METRICS_FILE);
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|source| TrainError::Io {
                path: path.clone(),
                source,
            })?;
        Ok(Self {
            path,
            file: std::io::BufWriter::new(file),
        })
    }

    fn write(&mut self, record: &impl Serialize) -> Result<(), TrainError> {
        let io = |source| TrainError::Io {
            path: self.path.clone(),
            source,
        };
        serde_json::to_writer(&mut self.file, record).map_err(|e| io(e.into()))?;
        self.file.write_all(b"\n").map_err(io)?;
        self.file.flush().map_err(io)
    }
}

/// Rolling return and success rate for the progress bar.
struct RecentEpisodes {
    capacity: usize,
    episodes: VecDeque<(f64, bool)>,
}

impl RecentEpisodes {
    fn new(capacity: usize) -> Self {
        Self {
            capacity,
            episodes: VecDeque::new(),
        }
    }
    fn push(&mut self, ret: f64, success: bool) {
        if self.episodes.len() == self.capacity {
            self.episodes.pop_front();
        }
        self.episodes.push_back((ret, success));
    }
    fn describe(&self, sps: f64) -> String {
        let n = self.episodes.len().max(1) as f64;
        let ret = self.episodes.iter().map(|e| e.0).sum::<f64>() / n;
        let success = self.episodes.iter().filter(|e| e.1).count() as f64 / n;
        format!(
            "{sps:.0} steps/s  return {ret:.1}  success {:.0} % (last {})",
            100.0 * success,
            self.episodes.len()
        )
    }
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
    }
}
