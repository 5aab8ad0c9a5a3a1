//! `probe.json`: every probe and the PCA basis fitted on one set of recorded steps, their
//! scores, the Markdown table, and saving next to the checkpoint.

use ndarray::Array2;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::policy::checkpoint::write_atomic;

use super::linear::evaluate_probe;
use super::{
    LinearProbe, PROBE_FILE, PcaBasis, ProbeError, ProbeResult, ProbeStep, split_by_episode,
};

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

/// The most `probe.json` may hold.
const MAX_PROBE_BYTES: u64 = 64 * 1024 * 1024;

impl ProbeFile {
    pub fn load(dir: &Path) -> Result<Self, ProbeError> {
        let path = dir.join(PROBE_FILE);
        // A probe file holds two linear probes and a PCA basis: kilobytes. The bound keeps a
        // symlink to /dev/zero or a FIFO from being read at all.
        let text = crate::files::read_text_capped(&path, MAX_PROBE_BYTES).map_err(|e| {
            ProbeError::Read {
                path: path.clone(),
                reason: e.into(),
            }
        })?;
        serde_json::from_str(&text).map_err(|e| ProbeError::Read {
            path,
            reason: e.into(),
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

/// One row of features per step.
pub(super) fn rows(steps: &[&ProbeStep], f: impl Fn(&ProbeStep) -> Vec<f64>) -> Array2<f64> {
    let data: Vec<Vec<f64>> = steps.iter().map(|s| f(s)).collect();
    let cols = data.first().map_or(0, Vec::len);
    Array2::from_shape_vec((data.len(), cols), data.into_iter().flatten().collect())
        .unwrap_or_else(|_| Array2::zeros((0, cols)))
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
    let pca = PcaBasis::fit(&z_all, 3)?;
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
            "| damaged vs not | {} / {} | the training set's majority class, on test: {} |\n",
            pct(self.damaged_from_z.test.accuracy),
            pct(self.damaged_from_z.test.balanced_accuracy),
            pct(self.damaged_from_z.majority.accuracy)
        );
        for j in &self.joints {
            s += &format!(
                "| {} damaged | {} / {} | the training set's majority class, on test: {} |\n",
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
        reason: e.into(),
    })?;
    write_atomic(&path, &json)?;
    Ok(path)
}

impl crate::lane::Readout for ProbeFile {
    fn joint_damage(&self, z: &[f32]) -> Option<[f64; crate::damage::N_ACTUATORS]> {
        let p = self.joint_damage_probabilities(z);
        (p.len() == crate::damage::N_ACTUATORS).then(|| std::array::from_fn(|i| p[i]))
    }
}
