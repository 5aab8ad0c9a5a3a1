//! Training curves from `metrics.jsonl` (the paper's Figure 3): return, success rate, critic and
//! actor loss, α, and triggered joints per episode, for one or more runs.

use serde::Deserialize;
use std::path::{Path, PathBuf};

use crate::plots::{LinePanel, PlotError, line_panels};

/// Episodes averaged per point of the return / success / triggers curves.
pub const EPISODE_WINDOW: usize = 20;

/// One line of `metrics.jsonl`: an episode summary or an update's losses (CleanRL's names).
#[derive(Debug, Deserialize)]
struct MetricsLine {
    global_step: u64,
    #[serde(rename = "charts/episodic_return")]
    episodic_return: Option<f64>,
    #[serde(rename = "charts/success")]
    success: Option<bool>,
    #[serde(rename = "charts/triggered_joints")]
    triggered_joints: Option<f64>,
    #[serde(rename = "losses/qf1")]
    qf1: Option<f64>,
    #[serde(rename = "losses/qf2")]
    qf2: Option<f64>,
    #[serde(rename = "losses/actor_loss")]
    actor_loss: Option<f64>,
    #[serde(rename = "losses/alpha")]
    alpha: Option<f64>,
}

/// A run's metrics, by env step.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunMetrics {
    /// (step, return, success, triggered joints) per finished episode.
    pub episodes: Vec<(u64, f64, bool, f64)>,
    /// (step, mean critic loss, actor loss, α) per logged update.
    pub updates: Vec<(u64, f64, f64, f64)>,
}

#[derive(Debug, thiserror::Error)]
pub enum CurvesError {
    #[error("reading {path}: {reason}")]
    Read { path: PathBuf, reason: String },
    #[error("{path} line {line}: {reason}")]
    Line {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{0} has no finished episodes yet")]
    Empty(PathBuf),
    #[error(transparent)]
    Plot(#[from] PlotError),
}

impl RunMetrics {
    /// Reads `metrics.jsonl` from a run folder (or the file itself). A cut-off last line (a run
    /// killed mid-write) is skipped; any other malformed line is an error naming it.
    pub fn read(run: &Path) -> Result<Self, CurvesError> {
        let path = if run.is_dir() {
            run.join(super::METRICS_FILE)
        } else {
            run.to_path_buf()
        };
        let text = std::fs::read_to_string(&path).map_err(|e| CurvesError::Read {
            path: path.clone(),
            reason: e.to_string(),
        })?;
        let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
        let mut metrics = RunMetrics::default();
        for (i, line) in lines.iter().enumerate() {
            let parsed: MetricsLine = match serde_json::from_str(line) {
                Ok(m) => m,
                Err(_) if i + 1 == lines.len() && !text.ends_with('\n') => break,
                Err(e) => {
                    return Err(CurvesError::Line {
                        path: path.clone(),
                        line: i + 1,
                        reason: e.to_string(),
                    });
                }
            };
            let step = parsed.global_step;
            // A run resumed from an earlier checkpoint appends from there: what was logged past
            // that point belongs to the abandoned continuation.
            metrics.episodes.retain(|e| e.0 <= step);
            metrics.updates.retain(|u| u.0 <= step);
            if let (Some(r), Some(s)) = (parsed.episodic_return, parsed.success) {
                let triggered = parsed.triggered_joints.unwrap_or(f64::NAN);
                metrics.episodes.push((step, r, s, triggered));
            }
            if let (Some(q1), Some(q2), Some(a), Some(alpha)) =
                (parsed.qf1, parsed.qf2, parsed.actor_loss, parsed.alpha)
            {
                metrics.updates.push((step, 0.5 * (q1 + q2), a, alpha));
            }
        }
        if metrics.episodes.is_empty() {
            return Err(CurvesError::Empty(path));
        }
        Ok(metrics)
    }
}

/// Trailing mean over `window` values, one point per value (shorter at the start).
pub fn rolling_mean(values: &[f64], window: usize) -> Vec<f64> {
    let window = window.max(1);
    let mut sum = 0.0;
    values
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            sum += v;
            if i >= window {
                sum -= values[i - window];
            }
            sum / (i + 1).min(window) as f64
        })
        .collect()
}

/// Draws the six panels for `runs` (label, metrics) into `out`.
pub fn figure(runs: &[(String, RunMetrics)], out: &Path) -> Result<(), CurvesError> {
    let episode_line = |m: &RunMetrics, value: fn(&(u64, f64, bool, f64)) -> f64| {
        let values: Vec<f64> = m.episodes.iter().map(value).collect();
        m.episodes
            .iter()
            .zip(rolling_mean(&values, EPISODE_WINDOW))
            .map(|(e, v)| (e.0 as f64, v))
            .collect::<Vec<_>>()
    };
    let update_line = |m: &RunMetrics, value: fn(&(u64, f64, f64, f64)) -> f64| {
        m.updates
            .iter()
            .map(|u| (u.0 as f64, value(u)))
            .collect::<Vec<_>>()
    };
    let panel = |title: &str, y: &str, line: &dyn Fn(&RunMetrics) -> Vec<(f64, f64)>| LinePanel {
        title: title.to_string(),
        y_label: y.to_string(),
        lines: runs.iter().map(|(l, m)| (l.clone(), line(m))).collect(),
        y_range: None,
    };
    let w = EPISODE_WINDOW;
    let panels = [
        panel(
            &format!("Episodic return ({w}-episode mean)"),
            "return",
            &|m| episode_line(m, |e| e.1),
        ),
        LinePanel {
            y_range: Some((0.0, 1.0)),
            ..panel(
                &format!("Success rate ({w}-episode mean)"),
                "success",
                &|m| episode_line(m, |e| f64::from(u8::from(e.2))),
            )
        },
        panel("Critic loss (mean of Q1, Q2)", "MSE", &|m| {
            update_line(m, |u| u.1)
        }),
        panel("Actor loss", "loss", &|m| update_line(m, |u| u.2)),
        panel("Entropy coefficient α", "α", &|m| update_line(m, |u| u.3)),
        panel(
            &format!("Triggered joints per episode ({w}-episode mean)"),
            "joints",
            &|m| episode_line(m, |e| e.3),
        ),
    ];
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| CurvesError::Read {
            path: dir.to_path_buf(),
            reason: e.to_string(),
        })?;
    }
    line_panels(out, "env steps", 2, &panels)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rolling_mean_is_a_trailing_average() {
        assert_eq!(
            rolling_mean(&[1.0, 2.0, 3.0, 4.0, 5.0], 2),
            vec![1.0, 1.5, 2.5, 3.5, 4.5]
        );
        assert_eq!(rolling_mean(&[2.0, 4.0], 10), vec![2.0, 3.0]);
    }

    #[test]
    fn metrics_lines_are_read_and_a_cut_off_tail_is_skipped() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        let text = concat!(
            r#"{"global_step":1000,"charts/episodic_return":10.0,"charts/episodic_length":1000,"charts/success":false,"charts/triggered_joints":8,"charts/condition":"mild"}"#,
            "\n",
            r#"{"global_step":1000,"losses/qf1":1.0,"losses/qf2":3.0,"losses/qf1_values":1,"losses/qf2_values":1,"losses/actor_loss":-2.0,"losses/alpha":0.5,"losses/alpha_loss":0,"charts/SPS":1}"#,
            "\n",
            r#"{"global_step":1500,"charts/episodic_return":20.0,"charts/success":true,"charts/triggered_joints":2}"#,
            "\n",
            r#"{"global_step":2000,"charts/episo"#
        );
        std::fs::write(&path, text).unwrap();
        let m = RunMetrics::read(dir.path()).unwrap();
        assert_eq!(
            m.episodes,
            vec![(1000, 10.0, false, 8.0), (1500, 20.0, true, 2.0)]
        );
        assert_eq!(m.updates, vec![(1000, 2.0, -2.0, 0.5)]);
        // Resumed from step 1200: the episode logged at 1500 was abandoned.
        let first_three: Vec<&str> = text.lines().take(3).collect();
        let resumed = format!(
            "{}\n{}\n",
            first_three.join("\n"),
            r#"{"global_step":1300,"charts/episodic_return":5.0,"charts/success":false}"#
        );
        std::fs::write(&path, resumed).unwrap();
        let m = RunMetrics::read(dir.path()).unwrap();
        let steps: Vec<u64> = m.episodes.iter().map(|e| e.0).collect();
        assert_eq!(steps, vec![1000, 1300]);
        assert!(m.episodes[1].3.is_nan(), "no trigger count was logged");
        // A broken line in the middle is an error that names it.
        std::fs::write(&path, format!("{{oops\n{text}\n")).unwrap();
        let e = RunMetrics::read(dir.path()).unwrap_err().to_string();
        assert!(e.contains("line 1"), "{e}");
        let e = RunMetrics::read(&dir.path().join("absent"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("absent"), "{e}");
    }
}
