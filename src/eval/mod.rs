//! `gaitscope eval`: every model × condition on the same evaluation seeds, deterministic
//! actions, a step limit (500 by default); success within it and within the paper's tighter
//! budgets (250/350/500) with Wilson intervals, McNemar's paired test of each encoder against the
//! baseline, and the recovery fraction, all on success within the limit.
//!
//! Episodes run in parallel across cores; within a worker, its episodes step in lockstep so the
//! policy sees one batch per step instead of one call per env.

pub mod seeds;
pub mod stats;
pub mod typical;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::config::GaitConfig;
use crate::damage::{Condition, ConditionChoice, N_ACTUATORS};
use crate::env::EnvError;
use crate::plots::{self, ErrorBarSeries, PlotError};
use crate::policy::checkpoint::{CheckpointError, write_atomic};
use crate::policy::{ActionMode, EncoderKind, OracleView, Policy};
use stats::{McNemar, Rate, mcnemar, recovery_fraction};

/// What an evaluation cell runs under: a damage condition (fatigue as in training), or a
/// scenario (by name; `--scenario`, `--suite ood`). Names are interned for the process's
/// lifetime (a handful per evaluation) so cells stay `Copy` keys.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Case {
    Condition(Condition),
    Scenario(&'static str),
}

impl Case {
    pub fn scenario(name: &str) -> Self {
        Case::Scenario(Box::leak(name.to_string().into_boxed_str()))
    }

    pub fn name(&self) -> &'static str {
        match self {
            Case::Condition(c) => c.name(),
            Case::Scenario(s) => s,
        }
    }
}

impl std::fmt::Display for Case {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Serialize for Case {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Case {
    /// A condition's name, else a scenario's (as [`Serialize`] writes them).
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let name = String::deserialize(deserializer)?;
        Ok(
            match Condition::ALL.into_iter().find(|c| c.name() == name) {
                Some(c) => Case::Condition(c),
                None => Case::scenario(&name),
            },
        )
    }
}

impl From<Condition> for Case {
    fn from(c: Condition) -> Self {
        Case::Condition(c)
    }
}

/// The cases to evaluate: the conditions asked for (all three when none are asked for and no
/// scenario is; healthy alone beside scenarios), then each scenario.
pub fn cases(
    conditions: &[Condition],
    scenarios: &[crate::damage::scenario::Scenario],
) -> Vec<Case> {
    let conditions: &[Condition] = match (conditions.is_empty(), scenarios.is_empty()) {
        (false, _) => conditions,
        (true, true) => &Condition::ALL,
        (true, false) => &[Condition::Healthy],
    };
    conditions
        .iter()
        .map(|&c| Case::from(c))
        .chain(scenarios.iter().map(|s| Case::scenario(&s.name)))
        .collect()
}

/// Scenarios are told apart by name, and every joint and set they name must exist in each
/// model's world: checked before minutes of evaluation.
fn check_scenarios(opts: &EvalOptions, policies: &[Policy]) -> Result<(), EvalError> {
    for (i, s) in opts.scenarios.iter().enumerate() {
        if opts.scenarios[..i].iter().any(|t| t.name == s.name) {
            return Err(EvalError::Options(format!(
                "two scenarios are named '{}': each needs its own name",
                s.name
            )));
        }
        for policy in policies {
            let mut requested = GaitConfig::default();
            requested.damage.scenario = Some(s.clone());
            let world = crate::lane::checkpoint_world(&policy.meta.env, &requested);
            crate::env::AntEnv::new(world, 0)?;
        }
    }
    Ok(())
}

/// An oracle's label when it is told every joint is healthy: `oracle-s0` →
/// `oracle-told-healthy-s0`, so its seeds group as `oracle-told-healthy`.
pub fn told_healthy_label(label: &str) -> String {
    match seeds::split_seed(label) {
        Some((stem, seed)) => format!("{stem}-told-healthy-s{seed}"),
        None => format!("{label}-told-healthy"),
    }
}

/// Evaluation seeds start here: training seeds are small integers and streams derived from them.
pub const EVAL_SEED_BASE: u64 = 1_000_000_000;
/// Success is also reported within these step budgets (the paper's).
pub const SUCCESS_BUDGETS: [usize; 3] = [250, 350, 500];

/// The budgets an evaluation limited to `max_steps` reports success within: the paper's
/// tighter than the limit, then the limit itself, the success every table leads with and every
/// comparison is made on (250, 350, 500 at the paper's 500; 250, 350, 400 at 400; 250, 350,
/// 500, 1000 at 1,000).
pub fn success_budgets(max_steps: usize) -> Vec<usize> {
    let mut budgets: Vec<usize> = SUCCESS_BUDGETS
        .into_iter()
        .filter(|&b| b < max_steps)
        .collect();
    budgets.push(max_steps);
    budgets
}

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error("{model}")]
    Policy {
        model: String,
        #[source]
        source: crate::policy::PolicyError,
    },
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error("cannot write {path}: {reason}")]
    Write {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("invalid evaluation options: {0}")]
    Options(String),
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not an evaluation's eval.json")]
    SavedJson {
        path: PathBuf,
        #[source]
        source: serde_json::Error,
    },
    #[error("{path} cannot be summarised again: {why}")]
    Saved { path: PathBuf, why: String },
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub checkpoints: Vec<PathBuf>,
    /// Oracles to evaluate a second time, told every joint is healthy whatever the damage
    /// ([`crate::policy::OracleView::ToldHealthy`]): what knowing the damage is worth to each
    /// network. Each is its own model, labelled [`told_healthy_label`].
    pub told_healthy: Vec<PathBuf>,
    pub episodes: usize,
    pub seed_base: u64,
    pub conditions: Vec<Case>,
    /// The scenarios of the [`Case::Scenario`] cases, by name.
    pub scenarios: Vec<crate::damage::scenario::Scenario>,
    pub max_steps: usize,
    pub threads: usize,
}

/// One evaluated episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecord {
    pub model: String,
    /// The model this run is a seed of ([`seeds::group_of`] its label).
    pub group: String,
    /// The run's training seed (its checkpoint's).
    pub train_seed: u64,
    pub encoder: EncoderKind,
    pub condition: Case,
    pub episode: usize,
    pub seed: u64,
    pub success: bool,
    /// Ended by termination (a fall, or reaching the goal) rather than the step limit.
    pub terminated: bool,
    /// How it ended ([`crate::env::Ending`]: success, leapt, collapsed, timeout, …).
    pub ending: Option<crate::env::Ending>,
    pub steps: usize,
    /// Steps taken when the goal was reached.
    pub steps_to_success: Option<usize>,
    pub final_distance: f64,
    #[serde(rename = "return")]
    pub episode_return: f64,
    pub triggered_joints: usize,
    pub trigger_steps: [Option<usize>; N_ACTUATORS],
    /// The step from which each actuator ran dead, if the world's draw killed it: which units
    /// a failure had to walk without. (Absent from evaluations saved before worlds killed
    /// actuators: none died there.)
    #[serde(default)]
    pub dead_steps: [Option<usize>; N_ACTUATORS],
    /// What the world's draw killed or was to kill, by name ([`crate::env::AntEnv::drawn_deaths`]):
    /// the same for every model on a seed, so success can be compared per pattern.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub drawn_deaths: Vec<String>,
    /// The first step run under damage ([`crate::damage::DamageState::damage_onset`]): after
    /// the first trigger, or from a scenario's first weakened joint.
    pub damage_onset: Option<usize>,
}

impl EpisodeRecord {
    pub fn success_within(&self, budget: usize) -> bool {
        self.steps_to_success.is_some_and(|s| s <= budget)
    }
}

/// One model under one condition.
#[derive(Debug, Clone, Serialize)]
pub struct CellSummary {
    pub model: String,
    pub encoder: EncoderKind,
    pub condition: Case,
    /// Success within each budget of [`success_budgets`] (the last: the step limit).
    pub success: BTreeMap<usize, Rate>,
    pub mean_final_distance: f64,
    pub mean_return: f64,
    pub mean_steps_to_success: Option<f64>,
}

/// An encoder against the baseline under one condition (paired on seeds).
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub baseline: String,
    pub encoder: String,
    pub condition: Case,
    /// Paired test on success at the step limit: b = baseline only, c = encoder only.
    pub mcnemar: McNemar,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub episodes_per_cell: usize,
    pub max_steps: usize,
    pub seeds: Vec<u64>,
    pub cells: Vec<CellSummary>,
    pub comparisons: Vec<Comparison>,
    /// Per encoder model: RF on success at the step limit against the baseline.
    pub recovery_fraction: BTreeMap<String, RecoveryFraction>,
    /// Runs grouped by model: means over training seeds, paired tests, failure modes.
    pub across_seeds: seeds::AcrossSeeds,
    /// Seconds spent per model.
    pub wall_time_s: BTreeMap<String, f64>,
    /// Runs that resumed with a refilled replay buffer (train_state.json's `resumes`), by label:
    /// their training was interrupted and their buffer rebuilt, which a reader should know.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub refilled_runs: BTreeMap<String, Vec<crate::train::ResumeRecord>>,
    pub episodes: Vec<EpisodeRecord>,
}

/// RF on success at the step limit with the three rates it is computed from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RecoveryFraction {
    pub encoder_severe: f64,
    pub baseline_severe: f64,
    pub baseline_healthy: f64,
    /// `None` when the baseline loses nothing under severe damage.
    pub value: Option<f64>,
}

pub use crate::policy::checkpoint::model_label;

/// Episodes per (model, condition) cell, at most.
pub const MAX_EPISODES: usize = 100_000;

/// Runs the evaluation (no files written; see [`write_outputs`]).
pub fn evaluate(opts: &EvalOptions) -> Result<EvalReport, EvalError> {
    if opts.checkpoints.is_empty()
        || opts.episodes == 0
        || opts.conditions.is_empty()
        || opts.max_steps == 0
    {
        return Err(EvalError::Options(
            "need at least one checkpoint, episode, condition and step".into(),
        ));
    }
    if opts.episodes > MAX_EPISODES || opts.max_steps > crate::config::MAX_EPISODE_STEPS {
        return Err(EvalError::Options(format!(
            "--episodes must lie in 1..={MAX_EPISODES} and --max-steps in 1..={} (got {} and {})",
            crate::config::MAX_EPISODE_STEPS,
            opts.episodes,
            opts.max_steps
        )));
    }
    let seeds: Vec<u64> = (0..opts.episodes as u64)
        .map(|i| opts.seed_base + i)
        .collect();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.threads.max(1))
        .build()
        .map_err(|e| EvalError::Options(format!("thread pool: {e}")))?;
    // Every checkpoint loads, and every scenario fits every model, before any episode runs.
    let mut models: Vec<(&PathBuf, OracleView)> = opts
        .checkpoints
        .iter()
        .map(|dir| (dir, OracleView::Truth))
        .collect();
    models.extend(
        opts.told_healthy
            .iter()
            .map(|dir| (dir, OracleView::ToldHealthy)),
    );
    let policies = models
        .iter()
        .map(|&(dir, view)| {
            Policy::load(dir, None)?
                .with_oracle_view(view)
                .map_err(|source| EvalError::Policy {
                    model: format!("--told-healthy {}", dir.display()),
                    source,
                })
        })
        .collect::<Result<Vec<_>, EvalError>>()?;
    check_scenarios(opts, &policies)?;
    let mut labels = Vec::new();
    let mut runs: Vec<(String, u64, PathBuf)> = Vec::new();
    let mut episodes = Vec::new();
    let mut wall_time_s = BTreeMap::new();
    let mut refilled_runs = BTreeMap::new();
    let progress = crate::progress::bar(
        (models.len() * opts.conditions.len() * seeds.len()) as u64,
        "eval episodes",
    );
    for (&(dir, view), policy) in models.iter().zip(policies) {
        let actor = crate::lane::Actor::from_policy(dir, policy.clone());
        let mut label = match view {
            OracleView::Truth => model_label(dir),
            OracleView::ToldHealthy => told_healthy_label(&model_label(dir)),
        };
        while labels.contains(&label) {
            label.push('\'');
        }
        labels.push(label.clone());
        let (group, train_seed) = (seeds::group_of(&label), policy.meta.seed);
        if let Some((_, _, other)) = runs
            .iter()
            .find(|(g, s, _)| *g == group && *s == train_seed)
        {
            return Err(EvalError::Options(format!(
                "{} and {} are both training seed {train_seed} of '{group}': a group needs one run \
                 per seed to pair it with the baseline's",
                other.display(),
                dir.display()
            )));
        }
        runs.push((group, train_seed, dir.clone()));
        let started = Instant::now();
        for &condition in &opts.conditions {
            let mut requested = GaitConfig::default();
            match condition {
                Case::Condition(c) => requested.damage.condition = ConditionChoice::Fixed(c),
                Case::Scenario(name) => {
                    // A scenario whose fatigue rule names no condition runs under severe.
                    requested.damage.condition = ConditionChoice::Fixed(Condition::Severe);
                    requested.damage.scenario = Some(
                        opts.scenarios
                            .iter()
                            .find(|s| s.name == name)
                            .cloned()
                            .ok_or_else(|| EvalError::Options(format!("no scenario '{name}'")))?,
                    );
                }
            }
            requested.env.max_episode_steps = opts.max_steps;
            // The checkpoint's own world with this case and limit (the lane core's one rule).
            let config = actor.world(&requested);
            let chunk = seeds.len().div_ceil(opts.threads.max(1) * 2).max(1);
            let batches: Vec<Result<Vec<EpisodeRecord>, EvalError>> = pool.install(|| {
                seeds
                    .par_chunks(chunk)
                    .enumerate()
                    .map(|(c, chunk_seeds)| {
                        let run = run_lockstep(
                            &actor,
                            &label,
                            &config,
                            condition,
                            chunk_seeds,
                            c * chunk,
                        );
                        progress.inc(chunk_seeds.len() as u64);
                        run
                    })
                    .collect()
            });
            for batch in batches {
                episodes.extend(batch?);
            }
        }
        // A run folder without train_state.json (an import) has no resumes to report.
        let refills: Vec<crate::train::ResumeRecord> = crate::train::read_resumes(dir)
            .unwrap_or_default()
            .into_iter()
            .filter(|r| r.buffer == crate::train::BufferSource::Refilled)
            .collect();
        if !refills.is_empty() {
            refilled_runs.insert(label.clone(), refills);
        }
        wall_time_s.insert(label, started.elapsed().as_secs_f64());
    }
    progress.finish_and_clear();
    let mut report = summarize(episodes, opts, seeds, wall_time_s);
    report.refilled_runs = refilled_runs;
    Ok(report)
}

/// The most an `eval.json` read back by [`rescore`] may weigh: 100,000 episodes at a few
/// hundred bytes each.
pub const MAX_EVAL_JSON_BYTES: u64 = 256 << 20;

/// What [`rescore`] reads of a saved `eval.json`: the episodes and what they were run under.
#[derive(Deserialize)]
struct SavedEval {
    max_steps: usize,
    seeds: Vec<u64>,
    #[serde(default)]
    wall_time_s: BTreeMap<String, f64>,
    #[serde(default)]
    refilled_runs: BTreeMap<String, Vec<crate::train::ResumeRecord>>,
    episodes: Vec<EpisodeRecord>,
}

/// A saved evaluation (`eval.json`) summarised again by this version's tables, from its
/// episodes alone: no model runs. The cases keep the order they first appear in.
pub fn rescore(path: &Path) -> Result<EvalReport, EvalError> {
    let bad = |why: String| EvalError::Saved {
        path: path.to_path_buf(),
        why,
    };
    let bytes =
        crate::files::read_capped(path, MAX_EVAL_JSON_BYTES).map_err(|e| EvalError::Read {
            path: path.to_path_buf(),
            source: e,
        })?;
    let saved: SavedEval =
        serde_json::from_slice(&bytes).map_err(|source| EvalError::SavedJson {
            path: path.to_path_buf(),
            source,
        })?;
    if saved.episodes.is_empty() || saved.seeds.is_empty() {
        return Err(bad("no episodes".into()));
    }
    if !(1..=crate::config::MAX_EPISODE_STEPS).contains(&saved.max_steps) {
        return Err(bad(format!("max_steps {} out of range", saved.max_steps)));
    }
    let mut conditions: Vec<Case> = Vec::new();
    for e in &saved.episodes {
        if e.steps > saved.max_steps || e.steps_to_success.is_some_and(|s| s > saved.max_steps) {
            return Err(bad(format!(
                "episode {} of {} ran {} steps, beyond its max_steps {}",
                e.episode, e.model, e.steps, saved.max_steps
            )));
        }
        if !saved.seeds.contains(&e.seed) {
            return Err(bad(format!(
                "episode seed {} is not among its seeds",
                e.seed
            )));
        }
        if !conditions.contains(&e.condition) {
            conditions.push(e.condition);
        }
    }
    let opts = EvalOptions {
        checkpoints: Vec::new(),
        told_healthy: Vec::new(),
        episodes: saved.seeds.len(),
        seed_base: saved.seeds[0],
        conditions,
        scenarios: Vec::new(),
        max_steps: saved.max_steps,
        threads: 1,
    };
    let mut report = summarize(saved.episodes, &opts, saved.seeds, saved.wall_time_s);
    report.refilled_runs = saved.refilled_runs;
    Ok(report)
}

/// Runs one episode per seed, all stepping together, one batched policy call per step.
pub fn run_lockstep(
    actor: &crate::lane::Actor,
    label: &str,
    config: &GaitConfig,
    condition: Case,
    seeds: &[u64],
    first_episode: usize,
) -> Result<Vec<EpisodeRecord>, EvalError> {
    use crate::lane::{Lane, advance_lockstep};
    let Some(policy) = actor.policy() else {
        return Err(EvalError::Options(format!("{label} is not a checkpoint")));
    };
    let net = policy.net().clone();
    let mut lanes = seeds
        .iter()
        .map(|&s| Lane::new(actor, config, s))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| lane_error(label, e))?;
    let mut records: Vec<Option<EpisodeRecord>> = vec![None; seeds.len()];
    let mut returns = vec![0.0; seeds.len()];
    while lanes.iter().any(|l| !l.is_done()) {
        advance_lockstep(actor, &mut lanes, ActionMode::Deterministic)
            .map_err(|e| lane_error(label, e))?;
        for (i, lane) in lanes.iter().enumerate() {
            let (Some(out), None) = (lane.outcome(), &records[i]) else {
                continue;
            };
            returns[i] += out.reward.total;
            if out.done() {
                let damage = lane.env().damage();
                records[i] = Some(EpisodeRecord {
                    model: label.to_string(),
                    group: seeds::group_of(label),
                    train_seed: policy.meta.seed,
                    encoder: net.encoder,
                    condition,
                    episode: first_episode + i,
                    seed: seeds[i],
                    success: out.success,
                    terminated: out.terminated,
                    ending: out.ending,
                    steps: out.step + 1,
                    steps_to_success: out.success.then_some(out.step + 1),
                    final_distance: out.distance,
                    episode_return: returns[i],
                    triggered_joints: damage.n_triggered(),
                    trigger_steps: damage.first_trigger_steps(),
                    dead_steps: damage.dead_steps(),
                    drawn_deaths: lane.env().drawn_deaths(),
                    damage_onset: damage.damage_onset(),
                });
            }
        }
    }
    Ok(records.into_iter().flatten().collect())
}

/// A lane error in eval's words: inference failures name the model.
fn lane_error(label: &str, e: crate::lane::LaneError) -> EvalError {
    match e {
        crate::lane::LaneError::Policy(source) => EvalError::Policy {
            model: label.to_string(),
            source,
        },
        crate::lane::LaneError::Env(e) => EvalError::Env(e),
        other => EvalError::Lane(other),
    }
}

/// One model's episodes under one condition, in eval-seed order (the order pairs are made in).
pub(crate) fn episodes_of<'a>(
    episodes: &'a [EpisodeRecord],
    model: &str,
    condition: Case,
) -> Vec<&'a EpisodeRecord> {
    let mut v: Vec<&EpisodeRecord> = episodes
        .iter()
        .filter(|e| e.model == model && e.condition == condition)
        .collect();
    v.sort_by_key(|e| e.seed);
    v
}

fn summarize(
    episodes: Vec<EpisodeRecord>,
    opts: &EvalOptions,
    seeds: Vec<u64>,
    wall_time_s: BTreeMap<String, f64>,
) -> EvalReport {
    let mut models: Vec<(String, EncoderKind)> = Vec::new();
    for e in &episodes {
        if !models.iter().any(|(m, _)| m == &e.model) {
            models.push((e.model.clone(), e.encoder));
        }
    }
    let cell = |model: &str, condition: Case| episodes_of(&episodes, model, condition);
    let mean = |v: &[f64]| {
        if v.is_empty() {
            f64::NAN
        } else {
            v.iter().sum::<f64>() / v.len() as f64
        }
    };
    let mut cells = Vec::new();
    for (model, encoder) in &models {
        for &condition in &opts.conditions {
            let eps = cell(model, condition);
            let success = success_budgets(opts.max_steps)
                .into_iter()
                .map(|b| {
                    (
                        b,
                        Rate::new(
                            eps.iter().filter(|e| e.success_within(b)).count(),
                            eps.len(),
                        ),
                    )
                })
                .collect();
            let to_success: Vec<f64> = eps
                .iter()
                .filter_map(|e| e.steps_to_success.map(|s| s as f64))
                .collect();
            cells.push(CellSummary {
                model: model.clone(),
                encoder: *encoder,
                condition,
                success,
                mean_final_distance: mean(
                    &eps.iter().map(|e| e.final_distance).collect::<Vec<_>>(),
                ),
                mean_return: mean(&eps.iter().map(|e| e.episode_return).collect::<Vec<_>>()),
                mean_steps_to_success: (!to_success.is_empty()).then(|| mean(&to_success)),
            });
        }
    }
    // Each encoder run against the baseline run of its own training seed (seed s against seed
    // s, as across seeds), or the first baseline run when none has that seed.
    let train_seed = |model: &str| {
        episodes
            .iter()
            .find(|e| e.model == model)
            .map(|e| e.train_seed)
    };
    let baselines: Vec<&String> = models
        .iter()
        .filter(|(_, k)| *k == EncoderKind::None)
        .map(|(m, _)| m)
        .collect();
    let baseline_for = |model: &str| {
        baselines
            .iter()
            .find(|b| train_seed(b) == train_seed(model))
            .or(baselines.first())
            .map(|b| b.as_str())
    };
    let mut comparisons = Vec::new();
    let mut rf = BTreeMap::new();
    let rate = |model: &str, c: Case| {
        cells
            .iter()
            .find(|x| x.model == model && x.condition == c)
            .map(|x| x.success[&opts.max_steps].rate)
    };
    for (model, _) in models.iter().filter(|(_, k)| *k != EncoderKind::None) {
        if let Some(base) = baseline_for(model) {
            for &condition in &opts.conditions {
                let (b, e) = (cell(base, condition), cell(model, condition));
                let pairs = b.iter().zip(&e).map(|(x, y)| {
                    (
                        x.success_within(opts.max_steps),
                        y.success_within(opts.max_steps),
                    )
                });
                comparisons.push(Comparison {
                    baseline: base.to_string(),
                    encoder: model.clone(),
                    condition,
                    mcnemar: mcnemar(pairs),
                });
            }
            if let (Some(es), Some(bs), Some(bh)) = (
                rate(model, Case::Condition(Condition::Severe)),
                rate(base, Case::Condition(Condition::Severe)),
                rate(base, Case::Condition(Condition::Healthy)),
            ) {
                let value = recovery_fraction(es, bs, bh);
                rf.insert(
                    model.clone(),
                    RecoveryFraction {
                        encoder_severe: es,
                        baseline_severe: bs,
                        baseline_healthy: bh,
                        value,
                    },
                );
            }
        }
    }
    EvalReport {
        across_seeds: seeds::across_seeds(&episodes, &opts.conditions, opts.max_steps),
        episodes_per_cell: opts.episodes,
        max_steps: opts.max_steps,
        seeds,
        cells,
        comparisons,
        recovery_fraction: rf,
        wall_time_s,
        refilled_runs: BTreeMap::new(),
        episodes,
    }
}

impl EvalReport {
    /// The paper's Table 2 (success@500 by condition: at the step limit) and Table 3 (time
    /// budgets, distances).
    pub fn markdown(&self) -> String {
        let mut models: Vec<&str> = Vec::new();
        for c in &self.cells {
            if !models.contains(&c.model.as_str()) {
                models.push(&c.model);
            }
        }
        let conditions: Vec<Case> = {
            let mut v = Vec::new();
            for c in &self.cells {
                if !v.contains(&c.condition) {
                    v.push(c.condition);
                }
            }
            v
        };
        let get = |m: &str, c: Case| self.cells.iter().find(|x| x.model == m && x.condition == c);
        let mut s = format!(
            "**Success@{} by damage condition or scenario** ({} episodes per cell, same seeds for every model; 95 % Wilson intervals)\n\n| model |",
            self.max_steps, self.episodes_per_cell
        );
        for c in &conditions {
            s += &format!(" {c} |");
        }
        s += "\n|---|";
        s += &"---|".repeat(conditions.len());
        s += "\n";
        for m in &models {
            s += &format!("| {m} |");
            for &c in &conditions {
                let cell = get(m, c)
                    .map(|x| x.success[&self.max_steps].percent_with_interval())
                    .unwrap_or_default();
                s += &format!(" {cell} |");
            }
            s += "\n";
        }
        let budgets = success_budgets(self.max_steps);
        s += "\n**Time to goal and distance**\n\n| model | condition |";
        for b in &budgets {
            s += &format!(" success@{b} |");
        }
        s += " mean final distance (m) | mean return | mean steps to success |\n|---|---|";
        s += &"---:|".repeat(budgets.len() + 3);
        s += "\n";
        for m in &models {
            for &c in &conditions {
                if let Some(x) = get(m, c) {
                    s += &format!("| {m} | {c} |");
                    for b in &budgets {
                        s += &format!(
                            " {:.0} % ± {:.0} |",
                            100.0 * x.success[b].rate,
                            100.0 * x.success[b].standard_error
                        );
                    }
                    s += &format!(
                        " {:.2} | {:.1} | {} |\n",
                        x.mean_final_distance,
                        x.mean_return,
                        x.mean_steps_to_success
                            .map_or("–".into(), |v| format!("{v:.0}"))
                    );
                }
            }
        }
        if let Some(table) = self.deaths_table(&models) {
            s += &table;
        }
        if !self.comparisons.is_empty() {
            s += &format!(
                "\n**Encoder vs baseline, per run** (McNemar on paired success@{}; each encoder \
                 run against the baseline run of its training seed; b = baseline only, c = \
                 encoder only)\n\n| encoder | baseline | condition | b | c | χ² | p (χ²) | p \
                 (exact) |\n|---|---|---|---:|---:|---:|---:|---:|\n",
                self.max_steps
            );
            for cmp in &self.comparisons {
                let m = cmp.mcnemar;
                s += &format!(
                    "| {} | {} | {} | {} | {} | {:.2} | {:.3} | {:.3} |\n",
                    cmp.encoder, cmp.baseline, cmp.condition, m.b, m.c, m.chi2, m.p_chi2, m.p_exact
                );
            }
            for (model, rf) in &self.recovery_fraction {
                let baseline = self
                    .comparisons
                    .iter()
                    .find(|c| c.encoder == *model)
                    .map_or("the baseline", |c| c.baseline.as_str());
                let pct = |r: f64| format!("{:.0} %", 100.0 * r);
                let (es, bs, bh) = (
                    pct(rf.encoder_severe),
                    pct(rf.baseline_severe),
                    pct(rf.baseline_healthy),
                );
                s += &match rf.value {
                    Some(v) => format!(
                        "\nRecovery fraction of {model} (against {baseline}): {v:.2} = (encoder \
                         severe {es} − baseline severe {bs}) / (baseline healthy {bh} − baseline \
                         severe {bs})\n"
                    ),
                    None => format!(
                        "\nRecovery fraction of {model} (against {baseline}): undefined, the \
                         baseline loses nothing under severe damage (healthy {bh}, severe {bs}; \
                         encoder severe {es})\n"
                    ),
                };
            }
        }
        s += "\n";
        for (label, refills) in &self.refilled_runs {
            let what: Vec<String> = refills
                .iter()
                .map(|r| {
                    format!(
                        "at step {} ({} transitions from the policy of that step)",
                        r.step, r.refill_transitions
                    )
                })
                .collect();
            s += &format!(
                "Note: {label} resumed with a refilled replay buffer {}.\n",
                what.join(", ")
            );
        }
        if !self.refilled_runs.is_empty() {
            s += "\n";
        }
        s += &self.across_seeds.markdown();
        s
    }

    /// Success per pattern of the world's deaths (which legs or joints its draw killed), for
    /// worlds with dead actuators: one row per pattern, one column per model. `None` when no
    /// episode drew a death.
    fn deaths_table(&self, models: &[&str]) -> Option<String> {
        if self.episodes.iter().all(|e| e.drawn_deaths.is_empty()) {
            return None;
        }
        // (deaths, pattern) → model → (successes, episodes), in one pass: rows sort fewer
        // deaths first, then by name.
        type PerModel<'a> = BTreeMap<&'a str, (usize, usize)>;
        let mut counts: BTreeMap<(usize, String), PerModel> = BTreeMap::new();
        for e in &self.episodes {
            let pattern = match e.drawn_deaths.is_empty() {
                true => "nothing".to_string(),
                false => e.drawn_deaths.join(" + "),
            };
            let cell = counts
                .entry((e.drawn_deaths.len(), pattern))
                .or_default()
                .entry(e.model.as_str())
                .or_default();
            cell.0 += usize::from(e.success);
            cell.1 += 1;
        }
        let mut s = format!(
            "\n**Success@{} by what the world killed** (episodes grouped by the deaths drawn for \
             their seed, the same for every model; an episode that ended before a death counts \
             under it; 95 % Wilson intervals)\n\n| killed | episodes |",
            self.max_steps
        );
        for m in models {
            s += &format!(" {m} |");
        }
        s += "\n|---|---:|";
        s += &"---:|".repeat(models.len());
        s += "\n";
        for ((_, name), by_model) in &counts {
            let rates: Vec<Rate> = models
                .iter()
                .map(|m| {
                    let (successes, n) = by_model.get(m).copied().unwrap_or_default();
                    Rate::new(successes, n)
                })
                .collect();
            let n = rates.first().map_or(0, |r| r.n);
            s += &format!("| {name} | {n} |");
            for r in &rates {
                // Seeds draw the deaths, so every model has the same count; say so if not.
                let other_n = if r.n == n {
                    String::new()
                } else {
                    format!(" (n = {})", r.n)
                };
                s += &format!(" {}{other_n} |", r.percent_with_interval());
            }
            s += "\n";
        }
        Some(s)
    }
}

/// Writes `eval.json` and the figures into `out`, each atomically.
pub fn write_outputs(report: &EvalReport, out: &Path) -> Result<Vec<PathBuf>, EvalError> {
    std::fs::create_dir_all(out).map_err(|e| EvalError::Write {
        path: out.to_owned(),
        reason: e.into(),
    })?;
    let json_path = out.join("eval.json");
    let json = serde_json::to_vec_pretty(report).map_err(|e| EvalError::Write {
        path: json_path.clone(),
        reason: e.into(),
    })?;
    write_atomic(&json_path, &json)?;
    let mut models: Vec<&str> = Vec::new();
    let mut conditions: Vec<Case> = Vec::new();
    for c in &report.cells {
        if !models.contains(&c.model.as_str()) {
            models.push(&c.model);
        }
        if !conditions.contains(&c.condition) {
            conditions.push(c.condition);
        }
    }
    let names: Vec<&str> = conditions.iter().map(|c| c.name()).collect();
    // One colour per model (the runs of its seeds side by side), one legend entry per model.
    let groups: Vec<String> = models.iter().map(|m| seeds::group_of(m)).collect();
    let keys: Vec<&str> = groups.iter().map(String::as_str).collect();
    let colours = plots::colour_slots(&keys, &plots::MODEL_COLOURS);
    // (legend entry, colour) per run: the first run of each model names it.
    let styles: Vec<(Option<String>, usize)> = (0..models.len())
        .map(|k| {
            let runs = keys.iter().filter(|g| **g == keys[k]).count();
            let first = keys.iter().position(|g| *g == keys[k]) == Some(k);
            let legend = first.then(|| match runs {
                1 => models[k].to_string(),
                n => format!("{} ({n} runs)", keys[k]),
            });
            (legend, colours[k])
        })
        .collect();
    let get = |m: &str, c: Case| {
        report
            .cells
            .iter()
            .find(|x| x.model == m && x.condition == c)
    };
    let success: Vec<ErrorBarSeries> = models
        .iter()
        .enumerate()
        .map(|(k, m)| ErrorBarSeries {
            label: styles[k].0.clone().unwrap_or_default(),
            colour: styles[k].1,
            in_legend: styles[k].0.is_some(),
            dots: Vec::new(),
            points: conditions
                .iter()
                .filter_map(|&c| get(m, c))
                .map(|x| {
                    let r = x.success[&report.max_steps];
                    (100.0 * r.rate, 100.0 * r.wilson_low, 100.0 * r.wilson_high)
                })
                .collect(),
        })
        .collect();
    let success_path = out.join("success_by_condition.png");
    plots::error_bars(
        &success_path,
        &format!(
            "Success@{} by damage condition or scenario (95 % Wilson)",
            report.max_steps
        ),
        "success (%)",
        &names,
        &success,
        (0.0, 100.0),
    )?;
    let distance: Vec<ErrorBarSeries> = models
        .iter()
        .enumerate()
        .map(|(k, m)| ErrorBarSeries {
            label: styles[k].0.clone().unwrap_or_default(),
            colour: styles[k].1,
            in_legend: styles[k].0.is_some(),
            dots: Vec::new(),
            points: conditions
                .iter()
                .map(|&c| {
                    let d: Vec<f64> = report
                        .episodes
                        .iter()
                        .filter(|e| e.model == *m && e.condition == c)
                        .map(|e| e.final_distance)
                        .collect();
                    let n = d.len().max(1) as f64;
                    let mean = d.iter().sum::<f64>() / n;
                    let se = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>()
                        / (n - 1.0).max(1.0)
                        / n)
                        .sqrt();
                    (mean, mean - 1.96 * se, mean + 1.96 * se)
                })
                .collect(),
        })
        .collect();
    let max_d = distance
        .iter()
        .flat_map(|s| s.points.iter().map(|p| p.2))
        .fold(1.0f64, f64::max);
    let distance_path = out.join("final_distance_by_condition.png");
    plots::error_bars(
        &distance_path,
        "Final distance to goal by damage condition or scenario (mean ± 95 % CI)",
        "distance (m)",
        &names,
        &distance,
        (0.0, max_d * 1.05),
    )?;
    let mut written = vec![json_path, success_path, distance_path];
    if report.across_seeds.has_several_seeds() {
        written.extend(across_seeds_figures(
            &report.across_seeds,
            &conditions,
            out,
        )?);
    }
    Ok(written)
}

/// Success at the step limit per model and condition: the mean over seeds, its bootstrap interval and each
/// seed's rate; and the failure modes as stacked bars.
fn across_seeds_figures(
    seeds: &seeds::AcrossSeeds,
    conditions: &[Case],
    out: &Path,
) -> Result<Vec<PathBuf>, EvalError> {
    let mut groups: Vec<&str> = Vec::new();
    for g in &seeds.groups {
        if !groups.contains(&g.group.as_str()) {
            groups.push(&g.group);
        }
    }
    let get = |g: &str, c: Case| {
        seeds
            .groups
            .iter()
            .find(|x| x.group == g && x.condition == c)
    };
    // A model and its seed count, as both figures name it.
    let group_label = |g: &str| {
        let n_seeds = conditions
            .iter()
            .find_map(|&c| get(g, c))
            .map_or(0, |c| c.runs.len());
        format!("{g} ({n_seeds} seeds)")
    };
    let colours = plots::colour_slots(&groups, &plots::MODEL_COLOURS);
    let series: Vec<ErrorBarSeries> = groups
        .iter()
        .zip(colours)
        .map(|(&g, colour)| {
            let cells: Vec<&seeds::GroupCell> =
                conditions.iter().filter_map(|&c| get(g, c)).collect();
            ErrorBarSeries {
                label: group_label(g),
                colour,
                in_legend: true,
                points: cells
                    .iter()
                    .map(|c| {
                        let i = c.success[&seeds.budget];
                        (100.0 * i.mean, 100.0 * i.low, 100.0 * i.high)
                    })
                    .collect(),
                dots: cells
                    .iter()
                    .map(|c| {
                        c.runs
                            .iter()
                            .map(|r| 100.0 * r.success[&seeds.budget].rate)
                            .collect()
                    })
                    .collect(),
            }
        })
        .collect();
    let names: Vec<&str> = conditions.iter().map(|c| c.name()).collect();
    let success_path = out.join("success_across_seeds.png");
    plots::error_bars(
        &success_path,
        &format!(
            "Success@{} across seeds (95 % bootstrap; ○ one seed)",
            seeds.budget
        ),
        "success (%)",
        &names,
        &series,
        (0.0, 100.0),
    )?;
    // One panel per model, its conditions as bars.
    let panels: Vec<plots::BarPanel> = groups
        .iter()
        .map(|&g| plots::BarPanel {
            title: group_label(g),
            bars: conditions
                .iter()
                .filter_map(|&c| get(g, c))
                .map(|cell| {
                    let f = cell.failure_modes;
                    let n = f.total().max(1) as f64;
                    plots::StackedBar {
                        label: cell.condition.to_string(),
                        segments: [
                            f.success,
                            f.timed_out,
                            f.terminated_after_damage,
                            f.terminated_before_damage,
                        ]
                        .iter()
                        .map(|&k| 100.0 * k as f64 / n)
                        .collect(),
                    }
                })
                .collect(),
        })
        .collect();
    let modes_path = out.join("failure_modes.png");
    plots::stacked_bars(
        &modes_path,
        "How episodes end, per model and condition (all seeds)",
        "episodes (%)",
        &[
            "success",
            "timed out",
            "ended early after damage",
            "ended early before damage",
        ],
        &panels,
    )?;
    Ok(vec![success_path, modes_path])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report_with(rf: RecoveryFraction) -> EvalReport {
        EvalReport {
            episodes_per_cell: 100,
            max_steps: 500,
            seeds: Vec::new(),
            cells: Vec::new(),
            comparisons: vec![Comparison {
                baseline: "baseline".into(),
                encoder: "encoder".into(),
                condition: Case::Condition(Condition::Severe),
                mcnemar: mcnemar(std::iter::empty()),
            }],
            recovery_fraction: BTreeMap::from([("encoder".to_string(), rf)]),
            wall_time_s: BTreeMap::new(),
            across_seeds: seeds::across_seeds(&[], &[], 500),
            refilled_runs: BTreeMap::new(),
            episodes: Vec::new(),
        }
    }

    fn episode(model: &str, seed: u64, killed: &[&str], success: bool) -> EpisodeRecord {
        EpisodeRecord {
            model: model.into(),
            group: model.into(),
            train_seed: 0,
            encoder: EncoderKind::None,
            condition: Case::Condition(Condition::Mild),
            episode: seed as usize,
            seed,
            success,
            terminated: success,
            ending: None,
            steps: 100,
            steps_to_success: success.then_some(100),
            final_distance: 0.0,
            episode_return: 0.0,
            triggered_joints: 0,
            trigger_steps: [None; N_ACTUATORS],
            dead_steps: [None; N_ACTUATORS],
            drawn_deaths: killed.iter().map(|k| k.to_string()).collect(),
            damage_onset: None,
        }
    }

    #[test]
    fn success_by_what_died_counts_each_pattern_per_model() {
        let mut report = report_with(RecoveryFraction {
            encoder_severe: 0.0,
            baseline_severe: 0.0,
            baseline_healthy: 0.0,
            value: None,
        });
        // Seeds 0–3 kill nothing, 4–7 the back leg, 8–9 the back leg and hip_1: oracle
        // 4/4, 1/4, 0/2; baseline 2/4, 3/4, 2/2.
        let killed = |seed: u64| match seed {
            0..4 => vec![],
            4..8 => vec!["back_leg"],
            _ => vec!["back_leg", "hip_1"],
        };
        let wins = [
            ("oracle", [1, 1, 1, 1, 1, 0, 0, 0, 0, 0]),
            ("baseline", [1, 0, 1, 0, 1, 1, 0, 1, 1, 1]),
        ];
        for (model, won) in wins {
            for seed in 0..10u64 {
                report
                    .episodes
                    .push(episode(model, seed, &killed(seed), won[seed as usize] == 1));
            }
        }
        let table = report.deaths_table(&["oracle", "baseline"]).unwrap();
        let rows: Vec<&str> = table.lines().filter(|l| l.starts_with("| ")).collect();
        let rate = |k, n| Rate::new(k, n).percent_with_interval();
        assert_eq!(rows[0], "| killed | episodes | oracle | baseline |");
        assert_eq!(
            rows[1],
            format!("| nothing | 4 | {} | {} |", rate(4, 4), rate(2, 4))
        );
        assert_eq!(
            rows[2],
            format!("| back_leg | 4 | {} | {} |", rate(1, 4), rate(3, 4))
        );
        assert_eq!(
            rows[3],
            format!("| back_leg + hip_1 | 2 | {} | {} |", rate(0, 2), rate(2, 2))
        );
        assert_eq!(rows.len(), 4);
        // Shown in the report's markdown; absent where nothing died.
        assert!(report.markdown().contains("by what the world killed"));
        report
            .episodes
            .iter_mut()
            .for_each(|e| e.drawn_deaths.clear());
        assert!(report.deaths_table(&["oracle"]).is_none());
        assert!(!report.markdown().contains("by what the world killed"));
    }

    #[test]
    fn every_table_reports_success_within_the_step_limit() {
        // A 1,000-step evaluation where the encoder reaches the goal in 400, 700 and 900 steps
        // (and fails once) and the baseline in 300 (and fails three times), under one condition.
        let mut episodes = Vec::new();
        for (seed, (enc, base)) in [(400, 300), (700, 0), (900, 0), (0, 0)].iter().enumerate() {
            for (model, encoder, steps) in [
                ("encoder", EncoderKind::Lstm, *enc),
                ("baseline", EncoderKind::None, *base),
            ] {
                let mut e = episode(model, seed as u64, &[], steps > 0);
                e.encoder = encoder;
                e.condition = Case::Condition(Condition::Severe);
                e.steps_to_success = (steps > 0).then_some(steps);
                episodes.push(e);
            }
        }
        let opts = EvalOptions {
            checkpoints: Vec::new(),
            told_healthy: Vec::new(),
            episodes: 4,
            seed_base: 0,
            conditions: vec![Case::Condition(Condition::Severe)],
            scenarios: Vec::new(),
            max_steps: 1000,
            threads: 1,
        };
        let report = summarize(episodes, &opts, (0..4).collect(), BTreeMap::new());
        let enc = &report.cells[0];
        assert_eq!(enc.model, "encoder");
        let rates: Vec<(usize, usize)> =
            enc.success.iter().map(|(b, r)| (*b, r.successes)).collect();
        assert_eq!(rates, [(250, 0), (350, 0), (500, 1), (1000, 3)]);
        let md = report.markdown();
        // The headline table: success within 1,000 steps (3 of 4 and 1 of 4).
        let rate = |k| Rate::new(k, 4).percent_with_interval();
        assert!(md.contains("**Success@1000 by damage condition"), "{md}");
        assert!(md.contains(&format!("| encoder | {} |", rate(3))), "{md}");
        assert!(md.contains(&format!("| baseline | {} |", rate(1))), "{md}");
        assert!(
            md.contains(
                "| model | condition | success@250 | success@350 | success@500 | success@1000 |"
            ),
            "{md}"
        );
        // McNemar at 1,000: the encoder alone succeeds on seeds 1 and 2 (c = 2), the baseline
        // alone never (b = 0); at 500 it would be b = 0, c = 0.
        let m = report.comparisons[0].mcnemar;
        assert_eq!((m.b, m.c), (0, 2));
        assert!(md.contains("McNemar on paired success@1000"), "{md}");
        // The across-seed block compares on the same budget.
        let group = &report.across_seeds.groups[0];
        assert_eq!(group.runs[0].success[&1000].successes, 3);
        assert!(success_budgets(400) == [250, 350, 400] && success_budgets(500) == SUCCESS_BUDGETS);
    }

    #[test]
    fn recovery_fraction_line_shows_its_terms() {
        // The paper's numbers: (86 − 70) / (83 − 70) = 1.23.
        let md = report_with(RecoveryFraction {
            encoder_severe: 0.86,
            baseline_severe: 0.70,
            baseline_healthy: 0.83,
            value: recovery_fraction(0.86, 0.70, 0.83),
        })
        .markdown();
        assert!(
            md.contains("Recovery fraction of encoder (against baseline): 1.23 = (encoder severe 86 % − baseline severe 70 %) / (baseline healthy 83 % − baseline severe 70 %)"),
            "{md}"
        );
        // A baseline that gains under severe damage leaves nothing to recover.
        let md = report_with(RecoveryFraction {
            encoder_severe: 0.66,
            baseline_severe: 0.82,
            baseline_healthy: 0.54,
            value: recovery_fraction(0.66, 0.82, 0.54),
        })
        .markdown();
        assert!(
            md.contains("undefined, the baseline loses nothing under severe damage (healthy 54 %, severe 82 %; encoder severe 66 %)"),
            "{md}"
        );
    }
}
