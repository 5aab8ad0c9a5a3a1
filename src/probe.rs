//! `gaitscope probe`: what does z know about the damage?
//!
//! Rollouts across the three conditions record z, the raw observation and the truth (condition,
//! which joints are effectively damaged, steps since the first trigger). Linear probes
//! (linfa-logistic) are trained on a 70/30 split *by episode* with standardised features; PCA
//! (linfa-reduction) gives the latent's main axes. The fitted probes and PCA basis are saved as
//! `probe.json` next to the checkpoint, where telemetry and the live viewer pick them up.

use linfa::prelude::*;
use linfa_logistic::{LogisticRegression, MultiLogisticRegression};
use linfa_reduction::Pca;
use ndarray::{Array1, Array2, Axis};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::damage::{Condition, ConditionChoice, N_ACTUATORS};
use crate::env::{AntEnv, EnvError};
use crate::plots::{self, BandSeries, ErrorBarSeries, PlotError};
use crate::policy::checkpoint::{CheckpointError, write_atomic};
use crate::policy::{ActionMode, Policy};
use crate::window::ContextWindow;

pub const PROBE_FILE: &str = "probe.json";

#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    #[error(transparent)]
    Checkpoint(#[from] CheckpointError),
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error("policy inference failed: {0}")]
    Policy(#[from] candle_core::Error),
    #[error("{0} has no context encoder, so there is no z to probe")]
    NoLatent(PathBuf),
    #[error("fitting the {what} probe: {reason}")]
    Fit { what: String, reason: String },
    #[error(transparent)]
    Plot(#[from] PlotError),
    #[error("cannot read {path}: {reason}")]
    Read { path: PathBuf, reason: String },
}

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
}

/// Runs `episodes_per_condition` episodes under each condition (deterministic actions) and
/// records every step. Episodes get seeds `seed, seed + 1, …`, conditions interleaved.
pub fn collect(
    policy: &Policy,
    episodes_per_condition: usize,
    max_steps: usize,
    seed: u64,
) -> Result<Vec<ProbeStep>, ProbeError> {
    let net = policy.net().clone();
    let mut steps = Vec::new();
    let mut episode = 0;
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
                });
                window.push(&obs, &decision.action);
                obs = out.obs;
                if out.done() {
                    break;
                }
            }
            episode += 1;
        }
    }
    Ok(steps)
}

/// Episode ids for training and testing: a seeded 70/30 split of whole episodes.
pub fn split_by_episode(
    episodes: &[usize],
    train_fraction: f64,
    seed: u64,
) -> (Vec<usize>, Vec<usize>) {
    let mut ids: Vec<usize> = episodes.to_vec();
    ids.sort_unstable();
    ids.dedup();
    ids.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    let n_train = ((ids.len() as f64) * train_fraction).round() as usize;
    let (train, test) = ids.split_at(n_train.min(ids.len()));
    (train.to_vec(), test.to_vec())
}

/// Per-feature mean and standard deviation, fitted on training rows.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Standardizer {
    pub mean: Vec<f64>,
    pub std: Vec<f64>,
}

impl Standardizer {
    pub fn fit(x: &Array2<f64>) -> Self {
        let mean = x.mean_axis(Axis(0)).map(|m| m.to_vec()).unwrap_or_default();
        let std = x
            .std_axis(Axis(0), 0.0)
            .iter()
            .map(|&s| if s > 1e-12 { s } else { 1.0 })
            .collect();
        Self { mean, std }
    }
    pub fn apply(&self, x: &Array2<f64>) -> Array2<f64> {
        let mut out = x.clone();
        for mut row in out.rows_mut() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (*v - self.mean[j]) / self.std[j];
            }
        }
        out
    }
}

/// Accuracy and balanced accuracy (mean per-class recall) of predictions.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    pub accuracy: f64,
    pub balanced_accuracy: f64,
}

pub fn scores(truth: &[usize], predicted: &[usize]) -> Scores {
    let n = truth.len().max(1) as f64;
    let accuracy = truth.iter().zip(predicted).filter(|(a, b)| a == b).count() as f64 / n;
    let mut classes: Vec<usize> = truth.to_vec();
    classes.sort_unstable();
    classes.dedup();
    let recalls: Vec<f64> = classes
        .iter()
        .map(|&c| {
            let of_class: Vec<usize> = (0..truth.len()).filter(|&i| truth[i] == c).collect();
            of_class.iter().filter(|&&i| predicted[i] == c).count() as f64 / of_class.len() as f64
        })
        .collect();
    let balanced_accuracy = if recalls.is_empty() {
        0.0
    } else {
        recalls.iter().sum::<f64>() / recalls.len() as f64
    };
    Scores {
        accuracy,
        balanced_accuracy,
    }
}

/// A fitted linear probe: standardise, then softmax (or sigmoid for two classes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LinearProbe {
    pub classes: Vec<usize>,
    pub standardizer: Standardizer,
    /// One row of weights per class (a single row for a binary probe: P(class 1)).
    pub weights: Vec<Vec<f64>>,
    pub intercepts: Vec<f64>,
}

impl LinearProbe {
    /// Fits on (x, y); one class only gives a constant probe.
    pub fn fit(what: &str, x: &Array2<f64>, y: &[usize]) -> Result<Self, ProbeError> {
        let standardizer = Standardizer::fit(x);
        let xs = standardizer.apply(x);
        let mut classes: Vec<usize> = y.to_vec();
        classes.sort_unstable();
        classes.dedup();
        let fail = |e: &dyn std::fmt::Display| ProbeError::Fit {
            what: what.to_string(),
            reason: e.to_string(),
        };
        let (weights, intercepts) = match classes.len() {
            0 => {
                return Err(ProbeError::Fit {
                    what: what.into(),
                    reason: "no samples".into(),
                });
            }
            // One class seen: a constant probe (its weights are never used).
            1 => (vec![vec![0.0; x.ncols()]], vec![0.0]),
            2 => {
                let targets: Array1<usize> =
                    y.iter().map(|&c| usize::from(c == classes[1])).collect();
                let ds = Dataset::new(xs, targets);
                let model = LogisticRegression::default()
                    .max_iterations(200)
                    .fit(&ds)
                    .map_err(|e| fail(&e))?;
                // linfa's positive class is its second label; ours is "== classes[1]" (= 1).
                let sign = if model.labels().pos.class == 1 {
                    1.0
                } else {
                    -1.0
                };
                (
                    vec![model.params().iter().map(|w| sign * w).collect()],
                    vec![sign * model.intercept()],
                )
            }
            _ => {
                let ds = Dataset::new(xs, Array1::from(y.to_vec()));
                let model = MultiLogisticRegression::default()
                    .max_iterations(200)
                    .fit(&ds)
                    .map_err(|e| fail(&e))?;
                let order: Vec<usize> = model.classes().to_vec();
                let params = model.params();
                let mut weights = vec![Vec::new(); classes.len()];
                let mut intercepts = vec![0.0; classes.len()];
                for (k, class) in order.iter().enumerate() {
                    let slot = classes.iter().position(|c| c == class).unwrap_or(k);
                    weights[slot] = params.column(k).to_vec();
                    intercepts[slot] = model.intercept()[k];
                }
                (weights, intercepts)
            }
        };
        Ok(Self {
            classes,
            standardizer,
            weights,
            intercepts,
        })
    }

    /// Class probabilities for one feature vector.
    pub fn probabilities(&self, x: &[f64]) -> Vec<f64> {
        let xs: Vec<f64> = x
            .iter()
            .enumerate()
            .map(|(j, v)| (v - self.standardizer.mean[j]) / self.standardizer.std[j])
            .collect();
        let logit = |k: usize| {
            self.intercepts[k]
                + self.weights[k]
                    .iter()
                    .zip(&xs)
                    .map(|(w, v)| w * v)
                    .sum::<f64>()
        };
        match self.classes.len() {
            1 => vec![1.0],
            2 => {
                let p = 1.0 / (1.0 + (-logit(0)).exp());
                vec![1.0 - p, p]
            }
            n => {
                let logits: Vec<f64> = (0..n).map(logit).collect();
                let max = logits.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let exps: Vec<f64> = logits.iter().map(|l| (l - max).exp()).collect();
                let sum: f64 = exps.iter().sum();
                exps.iter().map(|e| e / sum).collect()
            }
        }
    }

    pub fn predict(&self, x: &[f64]) -> usize {
        let p = self.probabilities(x);
        let best = (0..p.len())
            .max_by(|&a, &b| p[a].total_cmp(&p[b]))
            .unwrap_or(0);
        self.classes[best]
    }
}

/// The saved PCA basis: project with (z − mean) · componentsᵀ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PcaBasis {
    pub mean: Vec<f64>,
    /// Rows are principal axes.
    pub components: Vec<Vec<f64>>,
    /// Share of z's total variance along each axis.
    pub explained_variance_ratio: Vec<f64>,
}

impl PcaBasis {
    pub fn project(&self, z: &[f64]) -> Vec<f64> {
        self.components
            .iter()
            .map(|axis| {
                axis.iter()
                    .zip(z)
                    .zip(&self.mean)
                    .map(|((a, v), m)| a * (v - m))
                    .sum()
            })
            .collect()
    }
}

/// One probe's test result next to its baselines.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeResult {
    pub name: String,
    pub test: Scores,
    /// Always predicting the training set's most common class.
    pub majority: Scores,
}

/// `probe.json`: the fitted probes and basis, and how they scored.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeFile {
    pub checkpoint_steps: u64,
    pub steps_recorded: usize,
    pub episodes: usize,
    pub train_episodes: Vec<usize>,
    pub test_episodes: Vec<usize>,
    /// 3-way condition from z, from the raw observation, and chance (1/3).
    pub condition_from_z: ProbeResult,
    pub condition_from_obs: ProbeResult,
    pub chance: f64,
    /// Any joint effectively damaged, from z.
    pub damaged_from_z: ProbeResult,
    /// Per joint (actuator order), from z.
    pub joints: Vec<ProbeResult>,
    pub joint_names: Vec<String>,
    pub condition_probe: LinearProbe,
    pub joint_probes: Vec<LinearProbe>,
    pub pca: PcaBasis,
}

impl ProbeFile {
    pub fn load(dir: &Path) -> Result<Self, ProbeError> {
        let path = dir.join(PROBE_FILE);
        let text = std::fs::read_to_string(&path).map_err(|e| ProbeError::Read {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        serde_json::from_str(&text).map_err(|e| ProbeError::Read {
            path,
            reason: e.to_string(),
        })
    }

    /// P(joint damaged | z) from each joint's probe, in actuator order: the live readout.
    pub fn joint_damage_probabilities(&self, z: &[f32]) -> Vec<f64> {
        let z: Vec<f64> = z.iter().map(|&v| f64::from(v)).collect();
        self.joint_probes
            .iter()
            .map(|p| p.probabilities(&z).last().copied().unwrap_or(0.0))
            .collect()
    }

    /// Mean per-joint test accuracy.
    pub fn mean_joint_accuracy(&self) -> f64 {
        self.joints.iter().map(|j| j.test.accuracy).sum::<f64>() / self.joints.len().max(1) as f64
    }
}

fn rows(steps: &[&ProbeStep], f: impl Fn(&ProbeStep) -> Vec<f64>) -> Array2<f64> {
    let data: Vec<Vec<f64>> = steps.iter().map(|s| f(s)).collect();
    let cols = data.first().map_or(0, Vec::len);
    Array2::from_shape_vec((data.len(), cols), data.into_iter().flatten().collect())
        .unwrap_or_else(|_| Array2::zeros((0, cols)))
}

fn evaluate_probe(
    name: &str,
    train_x: &Array2<f64>,
    train_y: &[usize],
    test_x: &Array2<f64>,
    test_y: &[usize],
) -> Result<(ProbeResult, LinearProbe), ProbeError> {
    let probe = LinearProbe::fit(name, train_x, train_y)?;
    let predicted: Vec<usize> = test_x
        .rows()
        .into_iter()
        .map(|r| probe.predict(r.as_slice().unwrap_or(&r.to_vec())))
        .collect();
    let mut counts = std::collections::BTreeMap::new();
    for &c in train_y {
        *counts.entry(c).or_insert(0usize) += 1;
    }
    let majority_class = counts
        .iter()
        .max_by_key(|(_, n)| **n)
        .map_or(0, |(c, _)| *c);
    let result = ProbeResult {
        name: name.to_string(),
        test: scores(test_y, &predicted),
        majority: scores(test_y, &vec![majority_class; test_y.len()]),
    };
    Ok((result, probe))
}

/// Fits every probe and the PCA basis on recorded steps.
pub fn fit_probes(
    steps: &[ProbeStep],
    joint_names: &[String],
    checkpoint_steps: u64,
    seed: u64,
) -> Result<ProbeFile, ProbeError> {
    let episodes: Vec<usize> = steps.iter().map(|s| s.episode).collect();
    let (train_ids, test_ids) = split_by_episode(&episodes, 0.7, seed);
    let train: Vec<&ProbeStep> = steps
        .iter()
        .filter(|s| train_ids.contains(&s.episode))
        .collect();
    let test: Vec<&ProbeStep> = steps
        .iter()
        .filter(|s| test_ids.contains(&s.episode))
        .collect();
    let z_of = |s: &ProbeStep| s.z.iter().map(|&v| v as f64).collect::<Vec<f64>>();
    let (ztr, zte) = (rows(&train, z_of), rows(&test, z_of));
    let (otr, ote) = (
        rows(&train, |s| s.obs.clone()),
        rows(&test, |s| s.obs.clone()),
    );
    let cond = |v: &[&ProbeStep]| v.iter().map(|s| s.condition.index()).collect::<Vec<_>>();
    let (condition_from_z, condition_probe) =
        evaluate_probe("condition (z)", &ztr, &cond(&train), &zte, &cond(&test))?;
    let (condition_from_obs, _) = evaluate_probe(
        "condition (raw obs)",
        &otr,
        &cond(&train),
        &ote,
        &cond(&test),
    )?;
    let any = |v: &[&ProbeStep]| {
        v.iter()
            .map(|s| usize::from(s.damaged.iter().any(|&d| d)))
            .collect::<Vec<_>>()
    };
    let (damaged_from_z, _) = evaluate_probe("damaged (z)", &ztr, &any(&train), &zte, &any(&test))?;
    let mut joints = Vec::new();
    let mut joint_probes = Vec::new();
    for (i, name) in joint_names.iter().enumerate() {
        let lab = |v: &[&ProbeStep]| {
            v.iter()
                .map(|s| usize::from(s.damaged[i]))
                .collect::<Vec<_>>()
        };
        let (result, probe) = evaluate_probe(name, &ztr, &lab(&train), &zte, &lab(&test))?;
        joints.push(result);
        joint_probes.push(probe);
    }
    let all: Vec<&ProbeStep> = steps.iter().collect();
    let z_all = rows(&all, z_of);
    let pca_model = Pca::params(3.min(z_all.ncols()))
        .fit(&DatasetBase::from(z_all.clone()))
        .map_err(|e| ProbeError::Fit {
            what: "PCA".into(),
            reason: e.to_string(),
        })?;
    let mut pca = PcaBasis {
        mean: pca_model.mean().to_vec(),
        components: pca_model
            .components()
            .rows()
            .into_iter()
            .map(|r| r.to_vec())
            .collect(),
        explained_variance_ratio: Vec::new(),
    };
    // Share of z's total variance along each axis, measured directly: linfa's own ratio is
    // relative to the kept axes only.
    let total: f64 = z_all.var_axis(Axis(0), 0.0).sum();
    let projected: Vec<Vec<f64>> = z_all
        .rows()
        .into_iter()
        .map(|r| pca.project(&r.to_vec()))
        .collect();
    pca.explained_variance_ratio = (0..pca.components.len())
        .map(|k| {
            projected.iter().map(|p| p[k] * p[k]).sum::<f64>()
                / projected.len().max(1) as f64
                / total.max(1e-12)
        })
        .collect();
    Ok(ProbeFile {
        checkpoint_steps,
        steps_recorded: steps.len(),
        episodes: train_ids.len() + test_ids.len(),
        train_episodes: train_ids,
        test_episodes: test_ids,
        condition_from_z,
        condition_from_obs,
        chance: 1.0 / 3.0,
        damaged_from_z,
        joints,
        joint_names: joint_names.to_vec(),
        condition_probe,
        joint_probes,
        pca,
    })
}

impl ProbeFile {
    pub fn markdown(&self) -> String {
        let pct = |v: f64| format!("{:.1} %", 100.0 * v);
        let mut s = format!(
            "**Linear probes** ({} steps, {} episodes, 70/30 split by episode; test accuracy / balanced accuracy)\n\n| probe | from z | baseline |\n|---|---:|---:|\n",
            self.steps_recorded, self.episodes
        );
        s += &format!(
            "| condition, 3-way | {} / {} | raw obs {} / {}; chance {} |\n",
            pct(self.condition_from_z.test.accuracy),
            pct(self.condition_from_z.test.balanced_accuracy),
            pct(self.condition_from_obs.test.accuracy),
            pct(self.condition_from_obs.test.balanced_accuracy),
            pct(self.chance)
        );
        s += &format!(
            "| damaged vs not | {} / {} | majority {} |\n",
            pct(self.damaged_from_z.test.accuracy),
            pct(self.damaged_from_z.test.balanced_accuracy),
            pct(self.damaged_from_z.majority.accuracy)
        );
        for j in &self.joints {
            s += &format!(
                "| {} damaged | {} / {} | majority {} |\n",
                j.name,
                pct(j.test.accuracy),
                pct(j.test.balanced_accuracy),
                pct(j.majority.accuracy)
            );
        }
        s += &format!(
            "\nMean per-joint accuracy {}. PCA of z: explained variance ratio {:?}\n",
            pct(self.mean_joint_accuracy()),
            self.pca
                .explained_variance_ratio
                .iter()
                .map(|v| format!("{:.3}", v))
                .collect::<Vec<_>>()
        );
        s
    }
}

/// Writes `probe.json` next to the checkpoint.
pub fn save(file: &ProbeFile, checkpoint: &Path) -> Result<PathBuf, ProbeError> {
    let path = checkpoint.join(PROBE_FILE);
    let json = serde_json::to_vec_pretty(file).map_err(|e| ProbeError::Fit {
        what: "probe.json".into(),
        reason: e.to_string(),
    })?;
    write_atomic(&path, &json)?;
    Ok(path)
}

/// Steps aligned to each episode's first trigger: (offset, value) for offsets in `range`.
fn aligned(
    steps: &[ProbeStep],
    range: std::ops::RangeInclusive<i64>,
    value: impl Fn(&ProbeStep, &[&ProbeStep]) -> f64,
) -> Vec<Vec<f64>> {
    let mut by_episode: std::collections::BTreeMap<usize, Vec<&ProbeStep>> = Default::default();
    for s in steps {
        by_episode.entry(s.episode).or_default().push(s);
    }
    let width = (range.end() - range.start() + 1) as usize;
    let mut curves = Vec::new();
    for episode in by_episode.values() {
        let Some(onset) = episode.last().and_then(|s| s.first_trigger) else {
            continue;
        };
        if episode[0].condition == Condition::Healthy {
            continue; // a trigger changes nothing under the healthy condition
        }
        let mut curve = vec![f64::NAN; width];
        for s in episode {
            let offset = s.t as i64 - onset as i64;
            if range.contains(&offset) {
                curve[(offset - range.start()) as usize] = value(s, episode);
            }
        }
        curves.push(curve);
    }
    curves
}

/// Mean and ±1 standard deviation over curves, ignoring missing points.
fn band(label: &str, xs: &[f64], curves: &[Vec<f64>]) -> BandSeries {
    let (mut mean, mut low, mut high) = (Vec::new(), Vec::new(), Vec::new());
    for k in 0..xs.len() {
        let v: Vec<f64> = curves
            .iter()
            .map(|c| c[k])
            .filter(|v| v.is_finite())
            .collect();
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt();
        mean.push(m);
        low.push(m - sd);
        high.push(m + sd);
    }
    BandSeries {
        label: format!("{label} (n = {})", curves.len()),
        x: xs.to_vec(),
        mean,
        low,
        high,
    }
}

/// The figures: PCA scatter, onset alignment, fatigue asymmetry.
pub fn figures(
    file: &ProbeFile,
    encoder: &[ProbeStep],
    baseline: Option<&[ProbeStep]>,
    out: &Path,
) -> Result<Vec<PathBuf>, ProbeError> {
    std::fs::create_dir_all(out).map_err(|e| ProbeError::Read {
        path: out.to_owned(),
        reason: e.to_string(),
    })?;
    let mut written = Vec::new();

    // PCA of z, coloured by number of damaged joints.
    let mut classes: Vec<(String, Vec<(f64, f64)>)> = (0..=N_ACTUATORS)
        .map(|n| (format!("{n} damaged"), Vec::new()))
        .collect();
    for s in encoder {
        let p = file
            .pca
            .project(&s.z.iter().map(|&v| v as f64).collect::<Vec<_>>());
        classes[s.damaged.iter().filter(|&&d| d).count()]
            .1
            .push((p[0], p.get(1).copied().unwrap_or(0.0)));
    }
    classes.retain(|(_, p)| !p.is_empty());
    let ev = &file.pca.explained_variance_ratio;
    let path = out.join("pca_z.png");
    plots::scatter(
        &path,
        "PCA of z, coloured by number of damaged joints",
        (
            &format!("PC1 ({:.0} %)", 100.0 * ev.first().unwrap_or(&0.0)),
            &format!("PC2 ({:.0} %)", 100.0 * ev.get(1).unwrap_or(&0.0)),
        ),
        &classes,
    )?;
    written.push(path);

    // Onset: latent shift and progress rate around the first trigger.
    let range = -20i64..=60;
    let xs: Vec<f64> = range.clone().map(|v| v as f64).collect();
    let shift = aligned(encoder, range.clone(), |s, episode| {
        let onset = episode.last().and_then(|e| e.first_trigger).unwrap_or(0);
        let pre: Vec<&&ProbeStep> = episode.iter().filter(|e| e.t < onset).collect();
        let dim = s.z.len();
        let mean: Vec<f64> = (0..dim)
            .map(|j| pre.iter().map(|e| e.z[j] as f64).sum::<f64>() / pre.len().max(1) as f64)
            .collect();
        s.z.iter()
            .zip(&mean)
            .map(|(&v, m)| (v as f64 - m).powi(2))
            .sum::<f64>()
            .sqrt()
    });
    let path = out.join("onset_latent_shift.png");
    plots::bands(
        &path,
        // Spelled out: plotters draws the combining macron of "z̄" as a separate glyph.
        "Latent shift at damage onset: distance of z from its pre-onset mean",
        "steps since first trigger",
        "‖z − mean z before onset‖",
        &[band("encoder", &xs, &shift)],
        Some(0.0),
    )?;
    written.push(path);
    let dt = 0.05;
    let mut progress = vec![band(
        "encoder",
        &xs,
        &aligned(encoder, range.clone(), |s, _| s.progress / dt),
    )];
    if let Some(base) = baseline {
        progress.push(band(
            "baseline",
            &xs,
            &aligned(base, range.clone(), |s, _| s.progress / dt),
        ));
    }
    let path = out.join("onset_progress.png");
    plots::bands(
        &path,
        "Goal-progress rate at damage onset",
        "steps since first trigger",
        "progress (m/s)",
        &progress,
        Some(0.0),
    )?;
    written.push(path);

    // Fatigue asymmetry: one episode's fatigue per joint, and mean first-trigger step per joint.
    if let Some(first) = encoder.first() {
        let ep: Vec<&ProbeStep> = encoder
            .iter()
            .filter(|s| s.episode == first.episode)
            .collect();
        let series: Vec<BandSeries> = (0..N_ACTUATORS)
            .map(|i| {
                let y: Vec<f64> = ep.iter().map(|s| s.fatigue[i]).collect();
                BandSeries {
                    label: file.joint_names[i].clone(),
                    x: ep.iter().map(|s| s.t as f64).collect(),
                    mean: y.clone(),
                    low: y.clone(),
                    high: y,
                }
            })
            .collect();
        let path = out.join("fatigue_episode.png");
        plots::bands(
            &path,
            &format!("Fatigue per joint over one episode ({})", first.condition),
            "step",
            "fatigue",
            &series,
            None,
        )?;
        written.push(path);
    }
    // The last step of each episode holds its complete trigger record.
    let mut last_of_episode: std::collections::BTreeMap<usize, &ProbeStep> = Default::default();
    for s in encoder {
        last_of_episode.insert(s.episode, s);
    }
    let trigger_steps: Vec<Vec<f64>> = (0..N_ACTUATORS)
        .map(|i| {
            last_of_episode
                .values()
                .filter_map(|s| s.joint_triggers[i].map(|t| t as f64))
                .collect()
        })
        .collect();
    let order: Vec<usize> = {
        let mut o: Vec<usize> = (0..N_ACTUATORS).collect();
        o.sort_by_key(|&i| {
            (
                !file.joint_names[i].starts_with("hip"),
                file.joint_names[i].clone(),
            )
        });
        o
    };
    let names: Vec<&str> = order
        .iter()
        .map(|&i| file.joint_names[i].as_str())
        .collect();
    let points: Vec<(f64, f64, f64)> = order
        .iter()
        .map(|&i| {
            let v = &trigger_steps[i];
            let n = v.len().max(1) as f64;
            let m = v.iter().sum::<f64>() / n;
            let se = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt() / n.sqrt();
            (m, m - 1.96 * se, m + 1.96 * se)
        })
        .collect();
    let max = points
        .iter()
        .map(|p| p.2)
        .filter(|v| v.is_finite())
        .fold(10.0f64, f64::max);
    let path = out.join("trigger_step_by_joint.png");
    plots::error_bars(
        &path,
        "Mean first-trigger step per joint (hips vs ankles)",
        "step",
        &names,
        &[ErrorBarSeries {
            label: "encoder policy".into(),
            points,
        }],
        (0.0, max * 1.1),
    )?;
    written.push(path);
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_never_puts_an_episode_on_both_sides() {
        let episodes: Vec<usize> = (0..50).flat_map(|e| std::iter::repeat_n(e, 7)).collect();
        let (train, test) = split_by_episode(&episodes, 0.7, 3);
        assert_eq!((train.len(), test.len()), (35, 15));
        assert!(train.iter().all(|e| !test.contains(e)));
        let mut all: Vec<usize> = train.iter().chain(&test).copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..50).collect::<Vec<_>>());
    }

    #[test]
    fn balanced_accuracy_averages_per_class_recall() {
        // Class 0: 3 of 4 right; class 1: 0 of 1 right → accuracy 3/5, balanced (0.75 + 0)/2.
        let s = scores(&[0, 0, 0, 0, 1], &[0, 0, 0, 1, 0]);
        assert!((s.accuracy - 0.6).abs() < 1e-12);
        assert!((s.balanced_accuracy - 0.375).abs() < 1e-12);
    }

    fn synthetic(n: usize, shuffle_labels: bool) -> (Array2<f64>, Vec<usize>) {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        use rand::Rng;
        let x = Array2::from_shape_fn((n, 4), |_| rng.random_range(-1.0..1.0));
        // Three classes cut by linear functions of the features.
        let mut y: Vec<usize> = x
            .rows()
            .into_iter()
            .map(|r| {
                if r[0] + 0.5 * r[1] > 0.3 {
                    2
                } else if r[2] - r[3] > 0.0 {
                    1
                } else {
                    0
                }
            })
            .collect();
        if shuffle_labels {
            y.shuffle(&mut rng);
        }
        (x, y)
    }

    #[test]
    fn probe_learns_a_linear_label_and_not_a_shuffled_one() {
        let (x, y) = synthetic(1200, false);
        let (tr, te) = (
            x.slice(ndarray::s![..800, ..]).to_owned(),
            x.slice(ndarray::s![800.., ..]).to_owned(),
        );
        let (result, _) = evaluate_probe("linear", &tr, &y[..800], &te, &y[800..]).unwrap();
        assert!(result.test.accuracy > 0.95, "{:?}", result.test);
        let (x, y) = synthetic(1200, true);
        let (tr, te) = (
            x.slice(ndarray::s![..800, ..]).to_owned(),
            x.slice(ndarray::s![800.., ..]).to_owned(),
        );
        let (result, _) = evaluate_probe("shuffled", &tr, &y[..800], &te, &y[800..]).unwrap();
        // Shuffled labels carry no signal: no better than always guessing the majority class.
        assert!(
            result.test.accuracy < result.majority.accuracy + 0.05,
            "{:?} vs {:?}",
            result.test,
            result.majority
        );
        assert!(result.test.balanced_accuracy < 0.40, "{:?}", result.test);
    }

    #[test]
    fn binary_probe_and_constant_labels() {
        let (x, y) = synthetic(600, false);
        let yb: Vec<usize> = y.iter().map(|&c| usize::from(c == 2)).collect();
        let probe = LinearProbe::fit("binary", &x, &yb).unwrap();
        let acc = x
            .rows()
            .into_iter()
            .zip(&yb)
            .filter(|(r, t)| probe.predict(&r.to_vec()) == **t)
            .count() as f64
            / 600.0;
        assert!(acc > 0.95, "{acc}");
        let constant = LinearProbe::fit("constant", &x, &vec![1; 600]).unwrap();
        assert_eq!(constant.predict(&[0.0; 4]), 1);
    }

    #[test]
    fn pca_projection_is_centered_dot_product() {
        let basis = PcaBasis {
            mean: vec![1.0, 2.0],
            components: vec![vec![0.6, 0.8], vec![-0.8, 0.6]],
            explained_variance_ratio: vec![0.9, 0.1],
        };
        let p = basis.project(&[2.0, 4.0]);
        // (1, 2) · (0.6, 0.8) = 2.2; (1, 2) · (−0.8, 0.6) = 0.4
        assert!((p[0] - 2.2).abs() < 1e-12 && (p[1] - 0.4).abs() < 1e-12);
    }
}
