//! `gaitscope bench env`: env throughput against bare MuJoCo on the same model.
//!
//! All three loops replay the same pre-drawn random actions, so the only difference between
//! them is the work each does per env step:
//! - bare MuJoCo: write ctrl, `frame_skip` × `mj_step`, `mj_rnePostConstraint`;
//! - env (29-d): the same plus reward, damage, observation and bookkeeping;
//! - env + window (621-d): the same plus pushing the context window and writing the encoder input.

use mujoco_rs::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

use crate::config::GaitConfig;
use crate::env::{ACT_DIM, Action, AntEnv, BUNDLED_ANT_XML, EnvError};
use crate::window::ContextWindow;

#[derive(Debug, Clone, Serialize)]
pub struct EnvBenchReport {
    pub steps_per_run: usize,
    pub runs: usize,
    /// Median env steps per second over the runs.
    pub bare_mujoco_steps_per_s: f64,
    pub env_steps_per_s: f64,
    pub env_window_steps_per_s: f64,
}

impl EnvBenchReport {
    pub fn env_vs_bare(&self) -> f64 {
        self.env_steps_per_s / self.bare_mujoco_steps_per_s
    }
    pub fn window_vs_bare(&self) -> f64 {
        self.env_window_steps_per_s / self.bare_mujoco_steps_per_s
    }
}

impl std::fmt::Display for EnvBenchReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(
            f,
            "env steps/s, median of {} runs of {} steps (one core):",
            self.runs, self.steps_per_run
        )?;
        writeln!(
            f,
            "  bare MuJoCo (5 × mj_step + mj_rnePostConstraint)  {:>9.0}",
            self.bare_mujoco_steps_per_s
        )?;
        writeln!(
            f,
            "  env, 29-d observation                             {:>9.0}  ({:.1} % of bare)",
            self.env_steps_per_s,
            100.0 * self.env_vs_bare()
        )?;
        write!(
            f,
            "  env + context window, 621-d encoder input         {:>9.0}  ({:.1} % of bare)",
            self.env_window_steps_per_s,
            100.0 * self.window_vs_bare()
        )
    }
}

/// Runs the three loops `runs` times each, interleaved so drift in machine load hits all alike.
pub fn bench_env(
    config: &GaitConfig,
    steps: usize,
    runs: usize,
) -> Result<EnvBenchReport, EnvError> {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let actions: Vec<Action> = (0..4096)
        .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..=1.0)))
        .collect();
    let mut bare = BareAnt::new(config)?;
    let mut env = AntEnv::new(config.clone(), 0)?;
    let mut window = ContextWindow::new(config.context.len);
    let mut encoder_input = vec![0.0f32; window.encoder_input_dim()];

    let (mut t_bare, mut t_env, mut t_window) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..runs.max(1) {
        t_bare.push(steps_per_s(steps, || {
            bare.run(&actions, steps);
            Ok(())
        })?);
        t_env.push(steps_per_s(steps, || {
            run_env(&mut env, &actions, steps, None)
        })?);
        t_window.push(steps_per_s(steps, || {
            run_env(
                &mut env,
                &actions,
                steps,
                Some((&mut window, &mut encoder_input)),
            )
        })?);
    }
    Ok(EnvBenchReport {
        steps_per_run: steps,
        runs: runs.max(1),
        bare_mujoco_steps_per_s: median(t_bare),
        env_steps_per_s: median(t_env),
        env_window_steps_per_s: median(t_window),
    })
}

fn steps_per_s(steps: usize, run: impl FnOnce() -> Result<(), EnvError>) -> Result<f64, EnvError> {
    let start = Instant::now();
    run()?;
    Ok(steps as f64 / start.elapsed().as_secs_f64())
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn run_env(
    env: &mut AntEnv,
    actions: &[Action],
    steps: usize,
    mut window: Option<(&mut ContextWindow, &mut Vec<f32>)>,
) -> Result<(), EnvError> {
    let mut obs = env.reset();
    if let Some((w, _)) = window.as_mut() {
        w.clear();
    }
    for t in 0..steps {
        let action = &actions[t % actions.len()];
        if let Some((w, input)) = window.as_mut() {
            w.write_encoder_input(&obs, input);
            std::hint::black_box(&input[..]);
        }
        let out = env.step(action)?;
        if let Some((w, _)) = window.as_mut() {
            w.push(&obs, action);
        }
        obs = out.obs;
        if out.done() {
            obs = env.reset();
            if let Some((w, _)) = window.as_mut() {
                w.clear();
            }
        }
    }
    Ok(())
}

/// The Ant with nothing but MuJoCo: the floor under the env's cost.
struct BareAnt {
    physics: MjData<Box<MjModel>>,
    frame_skip: usize,
    max_steps: usize,
    z_range: [f64; 2],
}

impl BareAnt {
    fn new(config: &GaitConfig) -> Result<Self, EnvError> {
        let model = MjModel::from_xml_string(BUNDLED_ANT_XML).map_err(|e| EnvError::ModelLoad {
            origin: "bundled assets/ant.xml".into(),
            reason: e.into(),
        })?;
        Ok(Self {
            physics: MjData::new(Box::new(model)),
            frame_skip: config.env.frame_skip,
            max_steps: config.env.max_episode_steps,
            z_range: config.env.healthy_z_range,
        })
    }

    fn run(&mut self, actions: &[Action], steps: usize) {
        self.physics.reset();
        self.physics.forward();
        let mut episode_steps = 0;
        for t in 0..steps {
            let action: &[f64; ACT_DIM] = &actions[t % actions.len()];
            self.physics.ctrl_mut().copy_from_slice(action);
            for _ in 0..self.frame_skip {
                self.physics.step();
            }
            self.physics.rne_post_constraint();
            episode_steps += 1;
            // Same episode structure as the env (reset on fall or time limit), minus the noise.
            let z = self.physics.qpos()[2];
            if !(self.z_range[0]..=self.z_range[1]).contains(&z) || episode_steps >= self.max_steps
            {
                self.physics.reset();
                self.physics.forward();
                episode_steps = 0;
            }
        }
    }
}

/// `gaitscope bench train`: training throughput per encoder, against the update alone.
#[derive(Debug, Clone, Serialize)]
pub struct TrainBenchRow {
    pub encoder: crate::policy::EncoderKind,
    /// Threads per update.
    pub threads: usize,
    /// Env steps/s with one update per step (acting, env, replay, update).
    pub train_steps_per_s: f64,
    /// Updates/s with no env: sample a batch, forward and backward passes, optimiser steps.
    pub updates_per_s: f64,
    /// Actor forward passes/s at batch 1 (acting).
    pub act_per_s: f64,
}

/// Measures each encoder: a short real training run (after warm-up), then updates alone.
pub fn bench_train(
    encoders: &[crate::policy::EncoderKind],
    steps: u64,
    update: crate::train::sac::UpdatePath,
    threads: usize,
    scratch: &std::path::Path,
) -> Result<Vec<TrainBenchRow>, crate::train::TrainError> {
    use crate::policy::SacModel;
    use crate::train::replay::{Batch, ReplayBuffer, Transition};
    use crate::train::sac::SacLearner;
    use crate::train::{self, AntTask, Task};
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;

    let mut rows = Vec::new();
    for &encoder in encoders {
        // 1. The real loop: warm-up of 1,000 random steps, then `steps` learning steps.
        let dir = scratch.join(format!("bench-{encoder}"));
        let _ = std::fs::remove_dir_all(&dir);
        let mut opts = train::ant_options(encoder, 1_000 + steps, 0, dir.clone());
        opts.sac.learning_starts = 1_000;
        opts.save_replay = false;
        opts.progress_bar = false;
        opts.checkpoint_every = u64::MAX;
        opts.update = update;
        opts.threads = threads;
        let summary = train::train_ant(opts.clone(), false, Arc::new(AtomicBool::new(false)))?;
        let _ = std::fs::remove_dir_all(&dir);

        // 2. Updates alone, on a buffer of random transitions.
        let net = opts.net.clone();
        let device = candle_core::Device::Cpu;
        let model = SacModel::new(net.clone(), 1.0, 0, &device)?;
        let mut learner = SacLearner::new(model, opts.sac.clone(), device.clone());
        learner.set_update_path(update)?;
        learner.set_threads(threads)?;
        let window_len = if encoder.uses_window() {
            net.context_len
        } else {
            0
        };
        let mut replay = ReplayBuffer::new(5_000, net.obs_dim, net.act_dim, window_len);
        let mut task = AntTask::new(
            AntEnv::new(GaitConfig::default(), 0)?,
            crate::policy::Privileged::None,
        );
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut obs = task.reset_with_seed(0);
        let mut t = 0;
        for _ in 0..5_000 {
            let action: Vec<f64> = (0..net.act_dim)
                .map(|_| rng.random_range(-1.0..=1.0))
                .collect();
            let step = task.step(&action)?;
            replay.push(Transition {
                obs: &obs,
                action: &action,
                reward: step.reward,
                next_obs: &step.obs,
                terminated: step.terminated,
                truncated: step.truncated,
                t_in_episode: t,
            });
            (obs, t) = if step.terminated || step.truncated {
                (task.reset(), 0)
            } else {
                (step.obs, t + 1)
            };
        }
        let mut batch = Batch::default();
        let n_updates = (steps / 2).max(20);
        let start = Instant::now();
        for _ in 0..n_updates {
            replay.sample(opts.sac.batch_size, &mut rng, &mut batch);
            learner.update(&batch, &mut rng)?;
        }
        let updates_per_s = n_updates as f64 / start.elapsed().as_secs_f64();

        // 3. Acting at batch 1.
        let obs32 = vec![0.1f32; net.obs_dim];
        let window = vec![0.1f32; net.context_len * net.entry_dim()];
        let noise = vec![0.0f32; net.act_dim];
        let start = Instant::now();
        let n_act = 2_000;
        for _ in 0..n_act {
            learner.explore(&obs32, encoder.uses_window().then_some(&window[..]), &noise)?;
        }
        let act_per_s = n_act as f64 / start.elapsed().as_secs_f64();
        rows.push(TrainBenchRow {
            encoder,
            train_steps_per_s: summary.learning_steps_per_s.unwrap_or(f64::NAN),
            threads,
            updates_per_s,
            act_per_s,
        });
    }
    Ok(rows)
}

/// `gaitscope bench record`: the cost of telemetry per env step.
#[derive(Debug, Clone, Serialize)]
pub struct RecordBenchReport {
    pub steps: u64,
    pub plain_steps_per_s: f64,
    pub recorded_steps_per_s: f64,
    pub bytes_per_step: f64,
    /// Resident memory before and after the recorded run (MB).
    pub rss_before_mb: f64,
    pub rss_after_mb: f64,
}

impl RecordBenchReport {
    /// Share of a recorded step's time spent on telemetry.
    pub fn telemetry_share(&self) -> f64 {
        1.0 - self.recorded_steps_per_s / self.plain_steps_per_s
    }
}

fn rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Full-length episodes of the zero policy (the Ant stands, episodes run to the limit), first
/// without telemetry, then recorded to a file in `scratch`.
pub fn bench_record(
    episodes: usize,
    scratch: &std::path::Path,
) -> Result<RecordBenchReport, crate::telemetry::RecordError> {
    use crate::rollout::{BuiltinPolicy, run_builtin_episode};
    use crate::telemetry::{Actor, RecordOptions, Sink, record};
    let mut config = GaitConfig::default();
    config.env.max_episode_steps = 500;
    let mut env = AntEnv::new(config.clone(), 0)?;
    let start = Instant::now();
    let mut plain_steps = 0u64;
    for k in 0..episodes {
        plain_steps +=
            run_builtin_episode(&mut env, BuiltinPolicy::Zero, k, k as u64)?.steps as u64;
    }
    let plain_steps_per_s = plain_steps as f64 / start.elapsed().as_secs_f64();
    let path = scratch.join("bench.rrd");
    let rss_before_mb = rss_mb();
    let start = Instant::now();
    let summary = record(
        RecordOptions {
            actors: vec![Actor::Builtin(BuiltinPolicy::Zero)],
            config,
            episodes,
            seed: 0,
            sink: Sink::File(path.clone()),
            start: None,
            attribution: false,
            caption: None,
            fork: None,
        },
        &std::sync::atomic::AtomicBool::new(false),
    )?;
    let recorded_steps_per_s = summary.steps as f64 / start.elapsed().as_secs_f64();
    let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
    let _ = std::fs::remove_file(&path);
    Ok(RecordBenchReport {
        steps: summary.steps,
        plain_steps_per_s,
        recorded_steps_per_s,
        bytes_per_step: bytes as f64 / summary.steps.max(1) as f64,
        rss_before_mb,
        rss_after_mb: rss_mb(),
    })
}

/// One live-loop measurement: how many models, at what speed, and what the loop achieved.
#[derive(Debug, Clone)]
pub struct LiveBenchRow {
    pub models: usize,
    /// Whether the attribution view ran with every step.
    pub attribution: bool,
    pub report: crate::app::SpeedReport,
}

impl std::fmt::Display for LiveBenchRow {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let r = &self.report;
        write!(
            f,
            "{} model(s){} at {}×: {:.1} of {:.0} env steps/s asked for ({:.1} % of real time) over {:.1} s",
            self.models,
            if self.attribution {
                " + attribution"
            } else {
                ""
            },
            r.speed,
            r.steps_per_s(),
            r.target_steps_per_s,
            100.0 * r.keeps_up(),
            r.seconds
        )
    }
}

/// The live loop, headless (telemetry to a scratch .rrd, no panel): at 1× and 8× real time, the
/// checkpoint alone and side by side with `compare`, without and with the attribution view,
/// `seconds` each.
pub fn bench_live(
    checkpoint: &Path,
    compare: &Path,
    seconds: f64,
) -> Result<Vec<LiveBenchRow>, crate::app::LiveError> {
    use crate::app::{LiveCondition, LiveSetup, SimHandle};
    use crate::telemetry::{Sink, open};
    let scratch = std::env::temp_dir().join(format!("gaitscope-bench-live-{}", std::process::id()));
    let mut rows = Vec::new();
    for (second, speed, attribution) in [None, Some(compare.to_path_buf())]
        .into_iter()
        .flat_map(|c| [1.0, 8.0].map(|s| (c.clone(), s)))
        .flat_map(|(c, s)| [false, true].map(|a| (c.clone(), s, a)))
    {
        {
            let sink = Sink::File(scratch.join("live.rrd"));
            let (rec, _) = open(
                &sink,
                "gaitscope-bench-live",
                &["ant".into(), "compare".into()],
            )?;
            let setup = LiveSetup {
                checkpoint: checkpoint.to_path_buf(),
                compare: second.clone(),
                condition: LiveCondition::Severe,
                seed: 0,
                speed,
                step_limit: 500,
                mode: crate::policy::ActionMode::Deterministic,
                paused: false,
                breakpoints: Vec::new(),
                start: None,
                attribution,
                fork: None,
                config: crate::GaitConfig::default(),
            };
            let sim = SimHandle::spawn(rec, setup)?;
            std::thread::sleep(std::time::Duration::from_secs_f64(seconds));
            let report = sim.shutdown()?;
            if let Some(r) = report.speeds.into_iter().find(|r| r.speed == speed) {
                rows.push(LiveBenchRow {
                    models: 1 + usize::from(second.is_some()),
                    attribution,
                    report: r,
                });
            }
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
    Ok(rows)
}
