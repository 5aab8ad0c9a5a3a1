//! Training curves from `metrics.jsonl` (the paper's Figure 3): return, success rate, critic and
//! actor loss, α, and triggered joints per episode, for one or more runs; with `train --aux`, the
//! auxiliary dynamics loss of each encoder too.

use serde::Deserialize;
use std::path::{Path, PathBuf};

use crate::plots::{
    Line, LinePanel, MODEL_COLOURS, PlotError, SeriesLabelPosition, colour_slots, line_panels,
};

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
    #[serde(rename = "losses/aux")]
    aux: Option<f64>,
    #[serde(rename = "losses/aux_critic")]
    aux_critic: Option<f64>,
}

/// A run's metrics, by env step.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunMetrics {
    /// (step, return, success, triggered joints) per finished episode.
    pub episodes: Vec<(u64, f64, bool, f64)>,
    /// (step, mean critic loss, actor loss, α) per logged update.
    pub updates: Vec<(u64, f64, f64, f64)>,
    /// (step, the actor's encoder's auxiliary loss, the critic's) per logged update of a run
    /// trained with `--aux` (unweighted; NaN where a network has no encoder of its own).
    pub aux: Vec<(u64, f64, f64)>,
    /// The steps its checkpoint (`checkpoint.json` beside the metrics) says were trained, if
    /// there is one: a log that stops well before it lost its tail.
    pub steps_done: Option<u64>,
}

#[derive(Debug, thiserror::Error)]
pub enum CurvesError {
    #[error("reading {path}: {reason}")]
    Read {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("{path} line {line}: {reason}")]
    Line {
        path: PathBuf,
        line: usize,
        #[source]
        reason: crate::Cause,
    },
    #[error("{0} has no finished episodes yet")]
    Empty(PathBuf),
    #[error(transparent)]
    Plot(#[from] PlotError),
}

/// The most a run's `metrics.jsonl` may hold: a million-step run writes a few MB.
pub(crate) const MAX_METRICS_BYTES: u64 = 1024 * 1024 * 1024;

impl RunMetrics {
    /// Reads `metrics.jsonl` from a run folder (or the file itself). A cut-off last line (a run
    /// killed mid-write) is skipped; any other malformed line is an error naming it.
    pub fn read(run: &Path) -> Result<Self, CurvesError> {
        let path = if run.is_dir() {
            run.join(super::METRICS_FILE)
        } else {
            run.to_path_buf()
        };
        let text = crate::files::read_text_capped(&path, MAX_METRICS_BYTES).map_err(|e| {
            CurvesError::Read {
                path: path.clone(),
                reason: e.into(),
            }
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
                        reason: e.into(),
                    });
                }
            };
            let step = parsed.global_step;
            // A run resumed from an earlier checkpoint appends from there: what was logged past
            // that point belongs to the abandoned continuation.
            metrics.episodes.retain(|e| e.0 <= step);
            metrics.updates.retain(|u| u.0 <= step);
            metrics.aux.retain(|u| u.0 <= step);
            if let (Some(r), Some(s)) = (parsed.episodic_return, parsed.success) {
                let triggered = parsed.triggered_joints.unwrap_or(f64::NAN);
                metrics.episodes.push((step, r, s, triggered));
            }
            if let (Some(q1), Some(q2), Some(a), Some(alpha)) =
                (parsed.qf1, parsed.qf2, parsed.actor_loss, parsed.alpha)
            {
                metrics.updates.push((step, 0.5 * (q1 + q2), a, alpha));
            }
            if parsed.aux.is_some() || parsed.aux_critic.is_some() {
                let or_nan = |v: Option<f64>| v.unwrap_or(f64::NAN);
                metrics
                    .aux
                    .push((step, or_nan(parsed.aux), or_nan(parsed.aux_critic)));
            }
        }
        if metrics.episodes.is_empty() {
            return Err(CurvesError::Empty(path));
        }
        // Unreadable or absent: curves are drawn from a bare metrics file too.
        metrics.steps_done = path
            .parent()
            .and_then(|dir| std::fs::read(dir.join(crate::policy::checkpoint::META_FILE)).ok())
            .and_then(|bytes| serde_json::from_slice::<serde_json::Value>(&bytes).ok())
            .and_then(|meta| meta["steps_done"].as_u64());
        Ok(metrics)
    }

    /// Stretches of steps with no log lines, as (last logged update, next logged update or the
    /// checkpoint's step count): where consecutive update lines, or the last one and the
    /// checkpoint, are more than twice the run's logging interval (its smallest spacing) apart.
    /// Training logs an update line every interval without fail, so such a stretch means lines
    /// were lost (e.g. the file was replaced under the trainer); the weights trained on.
    pub fn gaps(&self) -> Vec<(u64, u64)> {
        let steps: Vec<u64> = self.updates.iter().map(|u| u.0).collect();
        let Some(interval) = steps
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]))
            .filter(|&d| d > 0)
            .min()
        else {
            return Vec::new();
        };
        let ends = steps.iter().copied().chain(self.steps_done);
        steps
            .iter()
            .copied()
            .zip(ends.skip(1))
            .filter(|&(a, b)| b > a.saturating_add(2 * interval))
            .collect()
    }

    /// The label of a run with gaps names them: "encoder-lstm-s2 (no log 233k–408k)".
    pub fn label(&self, name: &str) -> String {
        match self.gap_list() {
            Some(list) => format!("{name} (no log {list})"),
            None => name.to_string(),
        }
    }

    /// The gaps as "233k–408k, 423k–500k"; `None` without gaps.
    fn gap_list(&self) -> Option<String> {
        let gaps = self.gaps();
        if gaps.is_empty() {
            return None;
        }
        let k = |s: u64| format!("{}k", s / 1000);
        let list: Vec<String> = gaps
            .iter()
            .map(|&(a, b)| format!("{}–{}", k(a), k(b)))
            .collect();
        Some(list.join(", "))
    }
}

/// `points` (step, value) with a NaN point inside each gap, so a drawn line breaks there.
fn broken_at(points: Vec<(f64, f64)>, gaps: &[(u64, u64)]) -> Vec<(f64, f64)> {
    let mut out = Vec::with_capacity(points.len() + gaps.len());
    let mut gaps = gaps.iter().peekable();
    for p in points {
        while let Some(&&(a, b)) = gaps.peek() {
            if p.0 <= a as f64 {
                break;
            }
            if out.last().is_some_and(|q: &(f64, f64)| q.0 <= a as f64) {
                out.push((0.5 * (a + b) as f64, f64::NAN));
            }
            gaps.next();
        }
        out.push(p);
    }
    out
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

/// One run to draw: its model group (runs of one group share a colour), its own label and
/// its metrics.
#[derive(Debug, Clone)]
pub struct CurveRun {
    pub group: String,
    pub label: String,
    pub metrics: RunMetrics,
}

/// One run's line of one metric, and the stretches its log lost.
struct Curve {
    points: Vec<(f64, f64)>,
    gaps: Vec<(u64, u64)>,
}

/// Points on which a group's mean over seeds is drawn.
const MEAN_POINTS: usize = 250;

/// Draws the panels for `runs` into `out`: a run alone in its group as one line; a group
/// of several runs (training seeds of one model) as a thin pale line per seed under a bold
/// line of their mean, drawn where every seed has logged.
pub fn figure(runs: &[CurveRun], out: &Path) -> Result<(), CurvesError> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| CurvesError::Read {
            path: dir.to_path_buf(),
            reason: e.into(),
        })?;
    }
    line_panels(out, "env steps", 2, &panels(runs))?;
    Ok(())
}

fn episode_line(m: &RunMetrics, value: fn(&(u64, f64, bool, f64)) -> f64) -> Vec<(f64, f64)> {
    let values: Vec<f64> = m.episodes.iter().map(value).collect();
    m.episodes
        .iter()
        .zip(rolling_mean(&values, EPISODE_WINDOW))
        .map(|(e, v)| (e.0 as f64, v))
        .collect()
}

fn update_line(m: &RunMetrics, value: fn(&(u64, f64, f64, f64)) -> f64) -> Vec<(f64, f64)> {
    m.updates.iter().map(|u| (u.0 as f64, value(u))).collect()
}

/// The panels: return, success, critic loss, actor loss, α, triggered joints; then, where some
/// run trained with `--aux`, its encoders' auxiliary losses (only the runs that have them).
fn panels(runs: &[CurveRun]) -> Vec<LinePanel> {
    let mut groups: Vec<(&str, Vec<&CurveRun>)> = Vec::new();
    for run in runs {
        match groups.iter_mut().find(|(g, _)| *g == run.group) {
            Some((_, members)) => members.push(run),
            None => groups.push((&run.group, vec![run])),
        }
    }
    let keys: Vec<&str> = groups.iter().map(|(g, _)| *g).collect();
    let colours = colour_slots(&keys, &MODEL_COLOURS);
    let lines = |metric: &dyn Fn(&RunMetrics) -> Vec<(f64, f64)>| {
        let mut lines = Vec::new();
        for ((group, members), &colour) in groups.iter().zip(&colours) {
            let curves: Vec<Curve> = members
                .iter()
                .map(|r| Curve {
                    points: metric(&r.metrics),
                    gaps: r.metrics.gaps(),
                })
                .collect();
            if let [only] = members.as_slice() {
                lines.push(Line {
                    name: only.metrics.label(&only.label),
                    colour,
                    points: broken_at(curves[0].points.clone(), &curves[0].gaps),
                    faint: false,
                });
                continue;
            }
            // The mean breaks wherever one seed has no log: the legend says whose and where,
            // by the run's name past its group's ("s2"), or its whole name for seed 0.
            let unlogged: Vec<String> = members
                .iter()
                .filter_map(|r| {
                    let list = r.metrics.gap_list()?;
                    let who = r
                        .label
                        .strip_prefix(*group)
                        .map(|s| s.trim_start_matches('-'))
                        .filter(|s| !s.is_empty())
                        .unwrap_or(&r.label);
                    Some(format!("{who} no log {list}"))
                })
                .collect();
            let name = if unlogged.is_empty() {
                format!("{group} (mean of {} seeds)", members.len())
            } else {
                format!(
                    "{group} (mean of {} seeds; {})",
                    members.len(),
                    unlogged.join("; ")
                )
            };
            for curve in &curves {
                lines.push(Line {
                    name: name.clone(),
                    colour,
                    points: broken_at(curve.points.clone(), &curve.gaps),
                    faint: true,
                });
            }
            lines.push(Line {
                name,
                colour,
                points: mean_where_all_logged(&curves),
                faint: false,
            });
        }
        lines
    };
    let w = EPISODE_WINDOW;
    let panel =
        |title: String, y: &str, metric: &dyn Fn(&RunMetrics) -> Vec<(f64, f64)>| LinePanel {
            title,
            y_label: y.to_string(),
            lines: lines(metric),
            y_range: None,
            legend: None,
        };
    let mut panels = vec![
        LinePanel {
            legend: Some(SeriesLabelPosition::LowerRight),
            ..panel(
                format!("Episodic return ({w}-episode mean)"),
                "return",
                &|m| episode_line(m, |e| e.1),
            )
        },
        LinePanel {
            y_range: Some((0.0, 1.0)),
            legend: Some(SeriesLabelPosition::LowerRight),
            ..panel(
                format!("Success rate ({w}-episode mean)"),
                "success",
                &|m| episode_line(m, |e| f64::from(u8::from(e.2))),
            )
        },
        panel("Critic loss (mean of Q1, Q2)".into(), "MSE", &|m| {
            update_line(m, |u| u.1)
        }),
        panel("Actor loss".into(), "loss", &|m| update_line(m, |u| u.2)),
        panel("Entropy coefficient α".into(), "α", &|m| {
            update_line(m, |u| u.3)
        }),
        panel(
            format!("Triggered joints per episode ({w}-episode mean)"),
            "joints",
            &|m| episode_line(m, |e| e.3),
        ),
    ];
    if runs.iter().any(|r| !r.metrics.aux.is_empty()) {
        let aux_panel = |whose: &str, value: fn(&(u64, f64, f64)) -> f64| {
            let mut panel = panel(
                format!("Auxiliary dynamics loss, {whose} encoder"),
                "MSE of the normalised Δobs",
                &|m| m.aux.iter().map(|u| (u.0 as f64, value(u))).collect(),
            );
            panel.lines.retain(|l| !l.points.is_empty());
            // A legend here: these two panels show a subset of the models.
            panel.legend = Some(SeriesLabelPosition::UpperRight);
            panel
        };
        panels.push(aux_panel("the actor's", |u| u.1));
        panels.push(aux_panel("the critic's", |u| u.2));
    }
    panels
}

/// The mean over runs of each run's latest value at or before x, on [`MEAN_POINTS`] evenly
/// spaced steps from where the last run starts to where the first run ends; NaN (a break) where
/// any run is inside one of its gaps or has no finite value.
fn mean_where_all_logged(curves: &[Curve]) -> Vec<(f64, f64)> {
    let (Some(lo), Some(hi)) = (
        curves
            .iter()
            .map(|c| c.points.first().map(|p| p.0))
            .collect::<Option<Vec<_>>>(),
        curves
            .iter()
            .map(|c| c.points.last().map(|p| p.0))
            .collect::<Option<Vec<_>>>(),
    ) else {
        return Vec::new(); // a run with no points: no mean
    };
    let lo = lo.into_iter().fold(f64::NEG_INFINITY, f64::max);
    let hi = hi.into_iter().fold(f64::INFINITY, f64::min);
    if lo > hi {
        return Vec::new();
    }
    let n = MEAN_POINTS;
    (0..n)
        .map(|i| {
            let x = lo + (hi - lo) * i as f64 / (n - 1) as f64;
            let mut sum = 0.0;
            for Curve { points, gaps } in curves {
                let in_gap = gaps.iter().any(|&(a, b)| (a as f64) < x && x < b as f64);
                let held = points.partition_point(|p| p.0 <= x);
                sum += if in_gap || held == 0 {
                    f64::NAN
                } else {
                    points[held - 1].1
                };
            }
            (x, sum / curves.len() as f64)
        })
        .collect()
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
    fn lost_lines_show_as_a_gap_that_breaks_the_lines() {
        let updates = |steps: &[u64]| steps.iter().map(|&s| (s, 0.0, 0.0, 0.0)).collect();
        let mut m = RunMetrics {
            updates: updates(&[1000, 2000, 3000, 9000, 10000, 13000, 14000]),
            ..RunMetrics::default()
        };
        // Spacing 1000; 3000 → 9000 and 10000 → 13000 are more than twice that.
        assert_eq!(m.gaps(), vec![(3000, 9000), (10000, 13000)]);
        assert_eq!(m.label("run"), "run (no log 3k–9k, 10k–13k)");
        let line = vec![(2500.0, 1.0), (3000.0, 2.0), (9500.0, 3.0), (14000.0, 4.0)];
        let broken = broken_at(line, &m.gaps());
        let shown: Vec<String> = broken.iter().map(|p| format!("{}:{}", p.0, p.1)).collect();
        assert_eq!(
            shown,
            [
                "2500:1",
                "3000:2",
                "6000:NaN",
                "9500:3",
                "11500:NaN",
                "14000:4"
            ]
        );
        // A checkpoint well past the last line: the tail was lost too. Just past it (lines
        // since the last update, or a checkpoint behind the log): no gap.
        m.steps_done = Some(20000);
        assert_eq!(m.gaps(), vec![(3000, 9000), (10000, 13000), (14000, 20000)]);
        for done in [15000, 14500, 12000] {
            m.steps_done = Some(done);
            assert_eq!(m.gaps().len(), 2, "{done}");
        }
        // Evenly logged, resumed or not: no gaps, the label is the name.
        let even = RunMetrics {
            updates: updates(&[1000, 2000, 3000, 4000]),
            steps_done: Some(4000),
            ..RunMetrics::default()
        };
        assert!(even.gaps().is_empty());
        assert_eq!(even.label("run"), "run");
        assert!(RunMetrics::default().gaps().is_empty());
    }

    #[test]
    fn seeds_of_a_model_share_a_colour_under_their_mean() {
        // α logged every 1000 steps: seed 0 is 1, 2, 3, 4, 5, 6; seed 1 is 3 throughout but
        // lost its lines between 2000 and 5000.
        let run = |group: &str, label: &str, alpha: &[(u64, f64)]| CurveRun {
            group: group.into(),
            label: label.into(),
            metrics: RunMetrics {
                episodes: vec![(1000, 1.0, true, 8.0)],
                updates: alpha.iter().map(|&(s, a)| (s, 0.0, 0.0, a)).collect(),
                ..RunMetrics::default()
            },
        };
        let seed0: Vec<(u64, f64)> = (1..=6).map(|k| (1000 * k, k as f64)).collect();
        let runs = [
            run("lstm", "lstm-s0", &seed0),
            run(
                "lstm",
                "lstm-s1",
                &[(1000, 3.0), (2000, 3.0), (5000, 3.0), (6000, 3.0)],
            ),
            run("baseline", "baseline", &[(1000, 9.0), (2000, 9.0)]),
        ];
        let panels = panels(&runs);
        let alpha = &panels[4];
        assert_eq!(alpha.title, "Entropy coefficient α");
        let names: Vec<(&str, bool)> = alpha
            .lines
            .iter()
            .map(|l| (l.name.as_str(), l.faint))
            .collect();
        assert_eq!(
            names,
            [
                ("lstm (mean of 2 seeds; s1 no log 2k–5k)", true),
                ("lstm (mean of 2 seeds; s1 no log 2k–5k)", true),
                ("lstm (mean of 2 seeds; s1 no log 2k–5k)", false),
                ("baseline", false),
            ]
        );
        // The baseline keeps its colour of every figure (slot 0); lstm takes the next free one.
        let colours: Vec<usize> = alpha.lines.iter().map(|l| l.colour).collect();
        assert_eq!(colours, [1, 1, 1, 0]);
        // The mean on 250 points over 1000…6000 (every 5000/249 steps): the latest value of
        // each seed at or before x, averaged; a break while seed 1 has no log.
        let mean = &alpha.lines[2].points;
        assert_eq!(mean.len(), MEAN_POINTS);
        let at = |x: f64| {
            let i = ((x - 1000.0) / 5000.0 * 249.0).round() as usize;
            assert!(
                (mean[i].0 - x).abs() < 20.1,
                "grid point {} for {x}",
                mean[i].0
            );
            mean[i].1
        };
        assert_eq!(at(1000.0), 2.0); // (1 + 3) / 2
        assert_eq!(at(1500.0), 2.0);
        assert_eq!(at(1900.0), 2.0);
        for x in [2100.0, 3000.0, 4900.0] {
            assert!(
                at(x).is_nan(),
                "{x}: seed 1 logged nothing from 2000 to 5000"
            );
        }
        assert_eq!(at(5200.0), 4.0); // (5 + 3) / 2
        assert_eq!(at(6000.0), 4.5);
        // The seed with the gap is broken there, the other is whole.
        assert!(alpha.lines[1].points.iter().any(|p| p.1.is_nan()));
        assert!(alpha.lines[0].points.iter().all(|p| p.1.is_finite()));
        // Only the first row has legends; no run trained with --aux, so no aux panels.
        let legends: Vec<bool> = panels.iter().map(|p| p.legend.is_some()).collect();
        assert_eq!(legends, [true, true, false, false, false, false]);
    }

    #[test]
    fn aux_losses_get_two_panels_of_the_runs_that_have_them() {
        let dir = tempfile::tempdir().unwrap();
        let write = |group: &str, name: &str, lines: &[&str]| {
            let run = dir.path().join(name);
            std::fs::create_dir_all(&run).unwrap();
            std::fs::write(run.join("metrics.jsonl"), lines.join("\n") + "\n").unwrap();
            CurveRun {
                group: group.into(),
                label: name.into(),
                metrics: RunMetrics::read(&run).unwrap(),
            }
        };
        let episode = r#"{"global_step":500,"charts/episodic_return":1.0,"charts/success":false}"#;
        let update = |step: u64, aux: &str| {
            format!(
                r#"{{"global_step":{step},"losses/qf1":1,"losses/qf2":1,"losses/actor_loss":0,"losses/alpha":0.2{aux}}}"#
            )
        };
        let aux_run = |name: &str, a: [f64; 2], c: [f64; 2]| {
            let u0 = update(
                1000,
                &format!(r#","losses/aux":{},"losses/aux_critic":{}"#, a[0], c[0]),
            );
            let u1 = update(
                2000,
                &format!(r#","losses/aux":{},"losses/aux_critic":{}"#, a[1], c[1]),
            );
            write("encoder-lstm-aux", name, &[episode, &u0, &u1])
        };
        let runs = [
            write(
                "baseline",
                "baseline",
                &[episode, &update(1000, ""), &update(2000, "")],
            ),
            aux_run("encoder-lstm-aux-s0", [1.0, 0.5], [2.0, 1.0]),
            aux_run("encoder-lstm-aux-s1", [3.0, 0.7], [4.0, 2.0]),
        ];
        assert!(runs[0].metrics.aux.is_empty());
        assert_eq!(
            runs[1].metrics.aux,
            vec![(1000, 1.0, 2.0), (2000, 0.5, 1.0)]
        );
        let panels = panels(&runs);
        assert_eq!(panels.len(), 8);
        let actor = &panels[6];
        let critic = &panels[7];
        assert_eq!(actor.title, "Auxiliary dynamics loss, the actor's encoder");
        assert_eq!(
            critic.title,
            "Auxiliary dynamics loss, the critic's encoder"
        );
        // Only the aux model: two faint seeds and their bold mean, in the aux colour (slot 3),
        // with a legend (a subset of the figure's models).
        for (panel, first, last) in [(actor, 2.0, 0.6), (critic, 3.0, 1.5)] {
            let names: Vec<(&str, bool, usize)> = panel
                .lines
                .iter()
                .map(|l| (l.name.as_str(), l.faint, l.colour))
                .collect();
            let name = "encoder-lstm-aux (mean of 2 seeds)";
            assert_eq!(names, [(name, true, 3), (name, true, 3), (name, false, 3)]);
            let mean = &panel.lines[2].points;
            assert_eq!(mean.first().unwrap().1, first);
            assert!((mean.last().unwrap().1 - last).abs() < 1e-12);
            assert!(panel.legend.is_some());
        }
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
