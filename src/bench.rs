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
            reason: e.to_string(),
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
