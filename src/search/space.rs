//! The damage schedules `gaitscope search` looks through: per joint a torque scale in [0, 1]
//! from an onset step on, under a severity budget Σ(1 − scale) ≤ K, written as scenario files
//! (docs/scenarios.md) so every command replays them unchanged.

use serde::{Deserialize, Serialize};

use crate::damage::N_ACTUATORS;

/// Genes per schedule: a damage and an onset per joint.
pub const GENES: usize = 2 * N_ACTUATORS;
/// Scales are searched in steps of this (so a written scenario is exactly what ran).
pub const SCALE_STEP: f64 = 1e-3;
/// Severity budget, at most: every joint dead.
pub const MAX_SEVERITY: f64 = N_ACTUATORS as f64;

/// One damage schedule: joint i runs at `scales[i]` from step `onsets[i]` on (scale 1: untouched).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    pub scales: [f64; N_ACTUATORS],
    pub onsets: [usize; N_ACTUATORS],
}

impl Schedule {
    pub fn healthy() -> Self {
        Schedule {
            scales: [1.0; N_ACTUATORS],
            onsets: [0; N_ACTUATORS],
        }
    }

    /// Σ(1 − scale): 0 healthy, 1 one joint dead (or two at 0.5), 8 everything dead.
    pub fn severity(&self) -> f64 {
        self.scales.iter().map(|s| 1.0 - s).sum()
    }

    /// The joints it damages.
    pub fn damaged(&self) -> impl Iterator<Item = usize> + '_ {
        (0..N_ACTUATORS).filter(|&i| self.scales[i] < 1.0)
    }

    /// `hip_2 0.12 @ 31, ankle_4 0.5 @ 0`, or `healthy`.
    pub fn describe(&self, joints: &[String; N_ACTUATORS]) -> String {
        let parts: Vec<String> = self
            .damaged()
            .map(|i| format!("{} {} @ {}", joints[i], self.scales[i], self.onsets[i]))
            .collect();
        if parts.is_empty() {
            "healthy".into()
        } else {
            parts.join(", ")
        }
    }

    /// The schedule as a scenario file: fatigue off (only the schedule damages joints), one
    /// `scale` edit per damaged joint at its onset.
    pub fn scenario_json(
        &self,
        name: &str,
        description: &str,
        joints: &[String; N_ACTUATORS],
    ) -> serde_json::Value {
        let edits: Vec<serde_json::Value> = self
            .damaged()
            .map(|i| {
                serde_json::json!({"step": self.onsets[i], "joint": joints[i], "scale": self.scales[i]})
            })
            .collect();
        serde_json::json!({
            "name": name,
            "description": description,
            "fatigue": false,
            "edits": edits,
        })
    }
}

/// Where schedules live: the budget K and the latest onset step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Space {
    pub severity_budget: f64,
    pub latest_onset: usize,
}

/// `x` folded into [0, 1] by reflection at 0 and 1 (a box constraint CMA-ES can move across
/// without piling up on the edge).
fn reflect(x: f64) -> f64 {
    if !x.is_finite() {
        return 0.0;
    }
    let y = x.rem_euclid(2.0);
    if y > 1.0 { 2.0 - y } else { y }
}

impl Space {
    /// A genome (any reals; [`GENES`] of them: damages, then onsets) as a schedule within the
    /// budget: each gene folded into [0, 1]; damages scaled down together when their sum
    /// exceeds K, then floored to [`SCALE_STEP`] (so the budget holds after rounding).
    pub fn decode(&self, genome: &[f64]) -> Schedule {
        let mut damage = [0.0; N_ACTUATORS];
        for (d, &g) in damage.iter_mut().zip(genome) {
            *d = reflect(g);
        }
        let total: f64 = damage.iter().sum();
        if total > self.severity_budget {
            let shrink = self.severity_budget / total;
            for d in &mut damage {
                *d *= shrink;
            }
        }
        let mut schedule = Schedule::healthy();
        for (i, d) in damage.iter().enumerate() {
            let steps = (d / SCALE_STEP + 1e-9).floor();
            schedule.scales[i] = round_scale(1.0 - steps * SCALE_STEP);
            let onset = genome.get(N_ACTUATORS + i).copied().map_or(0.0, reflect);
            schedule.onsets[i] =
                ((onset * (self.latest_onset + 1) as f64).floor() as usize).min(self.latest_onset);
        }
        schedule
    }

    /// The single reductions of a schedule a shrinker tries, least damage first: drop a joint
    /// (scale → 1), raise its scale by 0.1, start it 10 % of the latest onset later.
    pub fn reductions(&self, s: &Schedule) -> Vec<Schedule> {
        let mut out = Vec::new();
        let later = (self.latest_onset / 10).max(1);
        for i in s.damaged() {
            let mut dropped = s.clone();
            dropped.scales[i] = 1.0;
            dropped.onsets[i] = 0;
            out.push(dropped);
        }
        for i in s.damaged() {
            if s.scales[i] < 0.9 {
                let mut raised = s.clone();
                raised.scales[i] = round_scale(s.scales[i] + 0.1);
                out.push(raised);
            }
        }
        for i in s.damaged() {
            if s.onsets[i] + later <= self.latest_onset {
                let mut delayed = s.clone();
                delayed.onsets[i] += later;
                out.push(delayed);
            }
        }
        out
    }
}

/// A scale on the [`SCALE_STEP`] grid, printed without float noise (0.3, not 0.30000000000000004).
fn round_scale(s: f64) -> f64 {
    ((s / SCALE_STEP).round() * SCALE_STEP * 1e6).round() / 1e6
}

#[cfg(test)]
mod tests {
    use super::*;

    fn joints() -> [String; N_ACTUATORS] {
        [
            "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3", "hip_4", "ankle_4",
        ]
        .map(String::from)
    }

    #[test]
    fn decoded_schedules_keep_the_budget_and_the_box() {
        let space = Space {
            severity_budget: 1.5,
            latest_onset: 100,
        };
        let mut rng = 12345u64;
        for _ in 0..2000 {
            let genome: Vec<f64> = (0..GENES)
                .map(|_| {
                    rng = rng
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    ((rng >> 11) as f64 / (1u64 << 53) as f64) * 8.0 - 4.0
                })
                .collect();
            let s = space.decode(&genome);
            assert!(s.severity() <= 1.5 + 1e-9, "{s:?}");
            assert!(s.scales.iter().all(|&x| (0.0..=1.0).contains(&x)));
            assert!(s.onsets.iter().all(|&t| t <= 100));
            for &x in &s.scales {
                assert!(
                    ((x / SCALE_STEP).round() * SCALE_STEP - x).abs() < 1e-9,
                    "{x}"
                );
            }
        }
    }

    #[test]
    fn reflection_and_scaling_by_hand() {
        let space = Space {
            severity_budget: 1.0,
            latest_onset: 99,
        };
        // Damages 0.8 and 0.6 (1.4, reflected from 1.4) sum to 1.4 > 1: scaled by 1/1.4.
        let mut genome = vec![0.0; GENES];
        genome[2] = 0.8;
        genome[3] = 1.4;
        genome[N_ACTUATORS + 2] = 0.5;
        genome[N_ACTUATORS + 3] = -0.25;
        let s = space.decode(&genome);
        assert_eq!(s.scales[2], 0.429); // 1 − floor(0.8/1.4 · 1000)/1000 = 1 − 0.571
        assert_eq!(s.scales[3], 0.572); // 1 − 0.428
        assert_eq!(s.onsets[2], 50); // 0.5 · 100
        assert_eq!(s.onsets[3], 25); // reflect(−0.25) = 0.25
        assert_eq!(s.scales[0], 1.0);
        assert!(s.severity() <= 1.0);
    }

    #[test]
    fn scenario_names_each_damaged_joint_once() {
        let mut s = Schedule::healthy();
        s.scales[2] = 0.2;
        s.onsets[2] = 30;
        let v = s.scenario_json("x", "y", &joints());
        assert_eq!(v["fatigue"], false);
        assert_eq!(
            v["edits"],
            serde_json::json!([{"step": 30, "joint": "hip_2", "scale": 0.2}])
        );
        assert_eq!(s.describe(&joints()), "hip_2 0.2 @ 30");
    }

    #[test]
    fn every_reduction_reduces() {
        let space = Space {
            severity_budget: 2.0,
            latest_onset: 100,
        };
        let mut s = Schedule::healthy();
        s.scales[0] = 0.05;
        s.scales[5] = 0.95;
        s.onsets[5] = 95;
        let r = space.reductions(&s);
        // Drop both, raise joint 0 only (0.95 + 0.1 > 1), delay joint 0 only (95 + 10 > 100).
        assert_eq!(r.len(), 4);
        for t in &r {
            assert!(
                t.severity() < s.severity() - 1e-9
                    || t.onsets.iter().zip(&s.onsets).any(|(a, b)| a > b)
            );
        }
        assert_eq!(r[2].scales[0], 0.15);
    }
}
