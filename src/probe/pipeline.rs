//! `gaitscope probe` from start to end: load every checkpoint first (a bad one fails before
//! minutes of rollouts), collect episodes through the lane core, fit the probes the live
//! readout uses (probe.json), draw the figures, cross-validate, write the report.

use std::path::{Path, PathBuf};

use super::{
    OnsetAttribution, ProbeError, ProbeReport, collect, figures, fit_probes, onset_attribution,
    onset_figure, probe_cv, save,
};
use crate::damage::Condition;
use crate::lane::Actor;
use crate::policy::{EncoderKind, Policy};

/// What to probe and how.
#[derive(Debug, Clone)]
pub struct ProbeOptions {
    /// Encoder checkpoints whose z is probed.
    pub checkpoints: Vec<PathBuf>,
    /// A memoryless checkpoint for the progress-at-onset comparison.
    pub baseline: Option<PathBuf>,
    /// Episodes per condition.
    pub episodes: usize,
    pub max_steps: usize,
    pub seed: u64,
    /// Keep the raw window on every this-many-th step (the window probe).
    pub window_every: usize,
    /// Cross-validation folds, grouped by episode.
    pub folds: usize,
    /// Write each checkpoint's probe.json.
    pub save: bool,
    /// Folder for the figures and the report.
    pub out: PathBuf,
}

impl ProbeOptions {
    /// Counts that make no probe: refused before anything loads.
    pub fn check(&self) -> Result<(), ProbeError> {
        let bad = |reason: String| Err(ProbeError::Options(reason));
        if self.episodes == 0 || self.max_steps == 0 || self.window_every == 0 {
            return bad("--episodes, --max-steps and --window-every must be at least 1".into());
        }
        let episodes = self.episodes * Condition::ALL.len();
        if self.folds < 2 || self.folds > episodes {
            return bad(format!(
                "--folds must be between 2 and the number of episodes ({episodes})"
            ));
        }
        if self.checkpoints.is_empty() {
            return bad("at least one --checkpoint to probe".into());
        }
        Ok(())
    }
}

/// What a probe run produced.
#[derive(Debug)]
pub struct ProbeRun {
    /// Per checkpoint: its label and its probe.json in words (markdown).
    pub probes: Vec<(String, String)>,
    /// The cross-validated report (also written as probe-cv.json and probe-cv.md).
    pub report: ProbeReport,
    /// Where z looks around the first trigger, per checkpoint (onset-attribution.json).
    pub onset: Vec<OnsetAttribution>,
    /// Every file written, in order.
    pub written: Vec<PathBuf>,
}

/// Runs the whole probe (see the module doc).
pub fn run(opts: &ProbeOptions) -> Result<ProbeRun, ProbeError> {
    opts.check()?;
    let mut actors = Vec::new();
    for dir in &opts.checkpoints {
        let policy = Policy::load(dir, None)?;
        if !policy.net().encoder.uses_window() {
            return Err(ProbeError::NoLatent(dir.clone()));
        }
        actors.push(Actor::from_policy(dir, policy));
    }
    let baseline = match &opts.baseline {
        Some(dir) => {
            let base = Actor::from_policy(dir, Policy::load(dir, Some(EncoderKind::None))?);
            Some(collect(&base, opts.episodes, opts.max_steps, opts.seed, 0)?)
        }
        None => None,
    };
    let mut run = ProbeRun {
        probes: Vec::new(),
        report: ProbeReport { runs: Vec::new() },
        onset: Vec::new(),
        written: Vec::new(),
    };
    for (dir, actor) in opts.checkpoints.iter().zip(&actors) {
        let label = crate::policy::checkpoint::model_label(dir);
        let steps = collect(
            actor,
            opts.episodes,
            opts.max_steps,
            opts.seed,
            opts.window_every,
        )?;
        let policy = actor.policy().ok_or(ProbeError::NoLatent(dir.clone()))?;
        let joint_names = joint_names(&policy.meta.env)?;
        let file = fit_probes(&steps, &joint_names, policy.meta.steps_done, opts.seed)?;
        run.probes.push((label.clone(), file.markdown()));
        if opts.save {
            run.written.push(save(&file, dir)?);
        }
        let figures_dir = if opts.checkpoints.len() > 1 {
            opts.out.join(&label)
        } else {
            opts.out.clone()
        };
        run.written.extend(figures(
            &file,
            &label,
            &steps,
            baseline.as_deref(),
            &figures_dir,
        )?);
        let cv = probe_cv(
            &label,
            &steps,
            &joint_names,
            opts.window_every,
            opts.folds,
            opts.seed,
        )?;
        run.report.runs.push(cv);
        run.onset.push(onset_attribution(
            actor,
            &label,
            opts.episodes,
            opts.max_steps,
            opts.seed,
        )?);
    }
    run.written.extend(write_report(&run.report, &opts.out)?);
    run.written.extend(write_onset(&run.onset, &opts.out)?);
    Ok(run)
}

/// The actuated joints' names of a checkpoint's model, in actuator order.
fn joint_names(world: &crate::config::GaitConfig) -> Result<Vec<String>, ProbeError> {
    Ok(crate::env::AntEnv::new(world.clone(), 0)?
        .actuators()
        .iter()
        .map(|a| a.joint.clone())
        .collect())
}

/// onset-attribution.json, onset-attribution.md and one probe_onset_attribution-MODEL.png per
/// model (its seeds pooled) under `out`.
fn write_onset(runs: &[OnsetAttribution], out: &Path) -> Result<Vec<PathBuf>, ProbeError> {
    let json = serde_json::to_vec_pretty(runs).map_err(|e| ProbeError::Fit {
        what: "onset-attribution.json".into(),
        reason: e.into(),
    })?;
    let json_path = out.join("onset-attribution.json");
    crate::policy::checkpoint::write_atomic(&json_path, &json)?;
    let mut written = vec![json_path];
    let mut groups: Vec<(String, Vec<OnsetAttribution>)> = Vec::new();
    for run in runs {
        let g = crate::eval::seeds::group_of(&run.label);
        match groups.iter_mut().find(|(name, _)| *name == g) {
            Some((_, rs)) => rs.push(run.clone()),
            None => groups.push((g, vec![run.clone()])),
        }
    }
    let mut md = String::new();
    for (group, rs) in &groups {
        let png = out.join(format!("probe_onset_attribution-{group}.png"));
        md += &format!("### {group}\n\n{}\n", onset_figure(rs, &png)?);
        written.push(png);
    }
    let md_path = out.join("onset-attribution.md");
    crate::policy::checkpoint::write_atomic(&md_path, md.as_bytes())?;
    written.push(md_path);
    Ok(written)
}

/// probe-cv.json, probe-cv.md and probe_latency.png under `out`.
fn write_report(report: &ProbeReport, out: &Path) -> Result<Vec<PathBuf>, ProbeError> {
    let write = |path: PathBuf, bytes: &[u8]| -> Result<PathBuf, ProbeError> {
        crate::policy::checkpoint::write_atomic(&path, bytes)?;
        Ok(path)
    };
    let json = serde_json::to_vec_pretty(report).map_err(|e| ProbeError::Fit {
        what: "probe-cv.json".into(),
        reason: e.into(),
    })?;
    let json = write(out.join("probe-cv.json"), &json)?;
    let md = write(out.join("probe-cv.md"), report.markdown().as_bytes())?;
    let latency = out.join("probe_latency.png");
    report.latency_figure(&latency)?;
    Ok(vec![json, md, latency])
}
