//! Where does z look when damage begins? The attribution of ‖z − z(0)‖ (the live view's
//! integrated gradients, [`crate::explain::z_shift_attribution`]) from 10 steps before the first
//! fatigue trigger to 50 after, per feature group — the joint that triggered, the other joints,
//! the torso, the goal vector — averaged over mild and severe episodes, then across seeds.

use serde::Serialize;
use std::ops::RangeInclusive;
use std::path::Path;

use super::ProbeError;
use crate::damage::{Condition, N_ACTUATORS};
use crate::lane::{Actor, Lane};
use crate::policy::ActionMode;

/// Steps relative to the first trigger (0: the step it triggered on).
pub const ONSET_RANGE: RangeInclusive<i64> = -10..=50;
/// The series, in the figure's order.
pub const ONSET_GROUPS: [&str; 4] = [
    "the joint that triggered first",
    "each other joint (mean of 7)",
    "torso",
    "goal vector",
];
/// Interpolation points per step, as the live view uses.
const POINTS: usize = crate::explain::SHIFT_POINTS;

/// One checkpoint's onset attribution.
#[derive(Debug, Clone, Serialize)]
pub struct OnsetAttribution {
    pub label: String,
    /// Episodes with a first trigger early enough to see 10 steps before it.
    pub episodes: usize,
    pub offsets: Vec<i64>,
    /// [`ONSET_GROUPS`] × offsets: the mean attribution to ‖z − z(0)‖ (episodes that reach the
    /// offset).
    pub mean: Vec<Vec<f64>>,
    /// The triggered joint's share split into its position, velocity and action features, over
    /// offsets 0…50 (mean per step).
    pub triggered_joint_features: [f64; 3],
    /// ‖z − z(0)‖ itself, per offset.
    pub shift: Vec<f64>,
}

/// Runs `episodes_per_condition` mild and severe episodes of `actor` (seeds as `collect` draws
/// them) and explains z around each one's first trigger.
pub fn onset_attribution(
    actor: &Actor,
    label: &str,
    episodes_per_condition: usize,
    max_steps: usize,
    seed: u64,
) -> Result<OnsetAttribution, ProbeError> {
    let policy = actor
        .policy()
        .ok_or_else(|| ProbeError::Options(format!("{label}: no policy to explain")))?;
    let offsets: Vec<i64> = ONSET_RANGE.collect();
    let (mut sums, mut counts) = (
        vec![vec![0.0; offsets.len()]; 4],
        vec![0usize; offsets.len()],
    );
    let mut shift = vec![0.0; offsets.len()];
    let (mut features, mut feature_steps) = ([0.0; 3], 0usize);
    let mut episodes = 0;
    for k in 0..episodes_per_condition {
        for condition in [Condition::Mild, Condition::Severe] {
            let (requested, episode_seed) =
                super::collect::probe_episode(seed, k, condition, max_steps);
            let mut lane = Lane::new(actor, &requested, episode_seed)?;
            // The window each step's decision read; explained once the trigger is known.
            let mut windows = Vec::new();
            lane.run_while(
                actor,
                ActionMode::Deterministic,
                |lane| {
                    windows.push(lane.window().as_slice().to_vec());
                    true
                },
                |_| Ok::<(), ProbeError>(()),
            )?;
            let firsts = lane.env().damage().first_onset_steps();
            let Some((joint, first)) = firsts
                .iter()
                .enumerate()
                .filter_map(|(j, t)| t.map(|t| (j, t)))
                .min_by_key(|&(_, t)| t)
            else {
                continue;
            };
            if (first as i64) < -ONSET_RANGE.start() {
                continue;
            }
            episodes += 1;
            let groups = crate::explain::feature_groups(lane.env().actuators());
            for (i, &offset) in offsets.iter().enumerate() {
                let Some(window) = usize::try_from(first as i64 + offset)
                    .ok()
                    .and_then(|t| windows.get(t))
                else {
                    continue;
                };
                let a = crate::explain::z_shift_attribution(policy, window, POINTS)?;
                // Per feature, summed over the window's slots.
                let per_feature: Vec<f64> = (0..a.attribution[0].len())
                    .map(|f| a.attribution.iter().map(|slot| slot[f]).sum())
                    .collect();
                let group = |g: &crate::explain::FeatureGroup| -> f64 {
                    g.features.iter().map(|&f| per_feature[f]).sum()
                };
                let joints: Vec<f64> = groups[..N_ACTUATORS].iter().map(group).collect();
                let others = (joints.iter().sum::<f64>() - joints[joint]) / 7.0;
                for (g, v) in [
                    joints[joint],
                    others,
                    group(&groups[N_ACTUATORS]),
                    group(&groups[N_ACTUATORS + 1]),
                ]
                .into_iter()
                .enumerate()
                {
                    sums[g][i] += v;
                }
                shift[i] += a.shift;
                counts[i] += 1;
                if offset >= 0 {
                    for (s, &f) in features.iter_mut().zip(&groups[joint].features) {
                        *s += per_feature[f];
                    }
                    feature_steps += 1;
                }
            }
        }
    }
    let mean_of = |v: f64, n: usize| if n == 0 { f64::NAN } else { v / n as f64 };
    Ok(OnsetAttribution {
        label: label.to_string(),
        episodes,
        mean: sums
            .iter()
            .map(|row| {
                row.iter()
                    .zip(&counts)
                    .map(|(&s, &n)| mean_of(s, n))
                    .collect()
            })
            .collect(),
        shift: shift
            .iter()
            .zip(&counts)
            .map(|(&s, &n)| mean_of(s, n))
            .collect(),
        triggered_joint_features: features.map(|s| mean_of(s, feature_steps)),
        offsets,
    })
}

/// The figure across seeds (mean line, band: the seeds' range) and its numbers in words.
pub fn onset_figure(runs: &[OnsetAttribution], path: &Path) -> Result<String, ProbeError> {
    let mut series = Vec::new();
    for (g, name) in ONSET_GROUPS.iter().enumerate() {
        let (mut x, mut mean, mut low, mut high) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (i, &offset) in ONSET_RANGE.clone().collect::<Vec<_>>().iter().enumerate() {
            let at: Vec<f64> = runs
                .iter()
                .map(|r| r.mean[g][i])
                .filter(|v| v.is_finite())
                .collect();
            if at.len() == runs.len() && !at.is_empty() {
                x.push(offset as f64);
                mean.push(at.iter().sum::<f64>() / at.len() as f64);
                low.push(at.iter().copied().fold(f64::INFINITY, f64::min));
                high.push(at.iter().copied().fold(f64::NEG_INFINITY, f64::max));
            }
        }
        series.push(crate::plots::BandSeries {
            label: (*name).to_string(),
            colour: g,
            dashed: false,
            x,
            mean,
            low,
            high,
        });
    }
    crate::plots::bands(
        path,
        &format!(
            "What moves z around the first trigger: {} ({} seeds; band: their range)",
            runs.first()
                .map_or(String::new(), |r| crate::eval::seeds::group_of(&r.label)),
            runs.len()
        ),
        "steps since the first trigger",
        "attribution to ‖z − z(0)‖",
        &series,
        Some(0.0),
        // z drifts from z(0) as the episode goes on: the early, low part stays clear.
        crate::plots::SeriesLabelPosition::UpperLeft,
    )?;
    // In words: each series' mean before (−10…−1) and after (0…50) the trigger.
    let window_mean = |s: &crate::plots::BandSeries, after: bool| {
        let v: Vec<f64> =
            s.x.iter()
                .zip(&s.mean)
                .filter(|(x, _)| (**x >= 0.0) == after)
                .map(|(_, m)| *m)
                .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    };
    let mut text = format!(
        "| attribution to ‖z − z(0)‖, mean over seeds ({}) | steps −10…−1 | steps 0…50 |\n|---|---:|---:|\n",
        runs.iter()
            .map(|r| format!("{}: {} episodes", r.label, r.episodes))
            .collect::<Vec<_>>()
            .join(", ")
    );
    for s in &series {
        text += &format!(
            "| {} | {:.3} | {:.3} |\n",
            s.label,
            window_mean(s, false),
            window_mean(s, true)
        );
    }
    let n = runs.len().max(1) as f64;
    let split: Vec<f64> = (0..3)
        .map(|k| {
            runs.iter()
                .map(|r| r.triggered_joint_features[k])
                .sum::<f64>()
                / n
        })
        .collect();
    text += &format!(
        "\nThe triggered joint's share after the trigger, by feature: position {:.3}, velocity {:.3}, action {:.3}.\n",
        split[0], split[1], split[2]
    );
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_onset_figure_averages_seeds_and_says_so() {
        let offsets: Vec<i64> = ONSET_RANGE.collect();
        let run = |label: &str, level: f64| OnsetAttribution {
            label: label.into(),
            episodes: 3,
            mean: (0..4)
                .map(|g| {
                    offsets
                        .iter()
                        .map(|&o| level * (g + 1) as f64 * if o >= 0 { 2.0 } else { 1.0 })
                        .collect()
                })
                .collect(),
            triggered_joint_features: [0.1, 0.2, 0.3],
            shift: vec![1.0; offsets.len()],
            offsets: offsets.clone(),
        };
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("onset.png");
        let text = onset_figure(&[run("a", 1.0), run("b", 3.0)], &path).unwrap();
        assert!(path.metadata().unwrap().len() > 1000);
        // Group 1 ("the joint that triggered first"): mean of 1 and 3 = 2 before, 4 after.
        assert!(
            text.contains("| the joint that triggered first | 2.000 | 4.000 |"),
            "{text}"
        );
        assert!(text.contains("| goal vector | 8.000 | 16.000 |"), "{text}");
        assert!(text.contains("position 0.100, velocity 0.200, action 0.300"));
    }
}
