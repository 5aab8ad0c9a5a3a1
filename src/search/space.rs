//! The damage schedules `gaitscope search` looks through: per joint (or per leg) a torque scale
//! in [0, 1] from an onset step on, under a severity budget Σ(1 − scale) ≤ K over the joints,
//! and optionally one push (a body, a horizontal force, how long, when) under an impulse
//! budget; written as scenario files (docs/scenarios.md) so every command replays them
//! unchanged.

use serde::{Deserialize, Serialize};

use crate::damage::MAX_PUSH_NEWTONS;
use crate::damage::N_ACTUATORS;
use crate::env::N_LEGS;

/// Genes per schedule of joints without a push: a damage and an onset per joint.
pub const GENES: usize = 2 * N_ACTUATORS;
/// Genes of the searched push, after the joints': body, heading, impulse, length, onset.
pub const PUSH_GENES: usize = 5;
/// Scales are searched in steps of this (so a written scenario is exactly what ran).
pub const SCALE_STEP: f64 = 1e-3;
/// Severity budget, at most: every joint dead.
pub const MAX_SEVERITY: f64 = N_ACTUATORS as f64;
/// The bodies a searched push acts on: the torso and each leg's upper part (the bodies a
/// person drags in the panel).
pub const PUSH_BODIES: [&str; 5] = [
    "torso",
    "front_left_leg",
    "front_right_leg",
    "back_leg",
    "right_back_leg",
];
/// The longest searched push, in env steps (half a second in Ant-v4): a shove, not a wind.
pub const MAX_SEARCH_PUSH_STEPS: usize = 10;

/// What one damage gene acts on (`search --unit`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Unit {
    /// Each joint its own scale and onset.
    #[default]
    Joint,
    /// Each leg one scale and one onset for both its joints, as legs die in the dead-legs
    /// world: a dead leg costs 2 of the budget.
    Leg,
}

impl Unit {
    pub fn is_joint(&self) -> bool {
        *self == Unit::Joint
    }
}

/// The Ant's names: its joints in actuator order, and each leg with the actuators of its hip and
/// ankle (what a schedule is described in, and what a leg unit damages).
#[derive(Debug, Clone, PartialEq)]
pub struct Anatomy {
    pub joints: [String; N_ACTUATORS],
    pub legs: [(String, [usize; 2]); N_LEGS],
}

impl Anatomy {
    /// Ant-v4's, as its model declares them: actuators hip_4, ankle_4, hip_1, ankle_1, hip_2,
    /// ankle_2, hip_3, ankle_3; legs front_left (hip_1, ankle_1), front_right (2), back (3),
    /// right_back (4). A policy's evaluator reads its env's (the same, tested); synthetic ones
    /// take this.
    pub fn ant() -> Self {
        let joints = [
            "hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3",
        ];
        let legs = [
            ("front_left_leg", [2, 3]),
            ("front_right_leg", [4, 5]),
            ("back_leg", [6, 7]),
            ("right_back_leg", [0, 1]),
        ];
        Anatomy {
            joints: joints.map(String::from),
            legs: legs.map(|(name, a)| (name.to_string(), a)),
        }
    }
}

/// One push of a schedule: a horizontal force on a body, from `onset` for `steps` env steps.
/// Whole newtons and whole degrees, so a written scenario is exactly what ran.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SearchPush {
    /// One of [`PUSH_BODIES`].
    pub body: String,
    /// Direction in the floor's plane, degrees from +x towards +y, in [0, 360).
    pub heading_deg: u32,
    /// The force's size, 1 to [`MAX_PUSH_NEWTONS`].
    pub newtons: u32,
    pub steps: usize,
    pub onset: usize,
}

impl SearchPush {
    /// The force in newtons, world frame; each component rounded toward zero to 1 mN, so its
    /// size never exceeds `newtons` (nor the push cap).
    pub fn force(&self) -> [f64; 3] {
        let r = f64::from(self.heading_deg).to_radians();
        let f = f64::from(self.newtons);
        let mn = |x: f64| (x * 1e3).trunc() / 1e3;
        [mn(f * r.cos()), mn(f * r.sin()), 0.0]
    }

    /// Newton-seconds: force × duration.
    pub fn impulse(&self, step_seconds: f64) -> f64 {
        f64::from(self.newtons) * self.steps as f64 * step_seconds
    }
}

/// One damage schedule: joint i runs at `scales[i]` from step `onsets[i]` on (scale 1: untouched),
/// and at most one push.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    pub scales: [f64; N_ACTUATORS],
    pub onsets: [usize; N_ACTUATORS],
    /// Absent from a search without pushes (its lines read as before pushes were searched).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub push: Option<SearchPush>,
}

impl Schedule {
    pub fn healthy() -> Self {
        Schedule {
            scales: [1.0; N_ACTUATORS],
            onsets: [0; N_ACTUATORS],
            push: None,
        }
    }

    /// Σ(1 − scale): 0 healthy, 1 one joint dead (or two at 0.5), 8 everything dead. A push
    /// has its own budget (its impulse), so it does not count here.
    pub fn severity(&self) -> f64 {
        self.scales.iter().map(|s| 1.0 - s).sum()
    }

    /// The joints it damages.
    pub fn damaged(&self) -> impl Iterator<Item = usize> + '_ {
        (0..N_ACTUATORS).filter(|&i| self.scales[i] < 1.0)
    }

    /// `hip_2 0.12 @ 31, back_leg 0 @ 40, push torso 420 N toward 135° for 3 steps @ 60`, or
    /// `healthy`: a leg whose joints share one scale and onset is named as the leg.
    pub fn describe(&self, anatomy: &Anatomy) -> String {
        let mut named = [false; N_ACTUATORS];
        let mut parts = Vec::new();
        for i in self.damaged() {
            if named[i] {
                continue;
            }
            let leg = anatomy.legs.iter().find(|(_, a)| {
                a.contains(&i)
                    && a.iter().all(|&j| {
                        (self.scales[j], self.onsets[j]) == (self.scales[i], self.onsets[i])
                    })
            });
            let name = match leg {
                Some((leg, actuators)) => {
                    actuators.iter().for_each(|&j| named[j] = true);
                    leg
                }
                None => &anatomy.joints[i],
            };
            parts.push(format!("{name} {} @ {}", self.scales[i], self.onsets[i]));
        }
        if let Some(p) = &self.push {
            parts.push(format!(
                "push {} {} N toward {}° for {} step{} @ {}",
                p.body,
                p.newtons,
                p.heading_deg,
                p.steps,
                if p.steps == 1 { "" } else { "s" },
                p.onset
            ));
        }
        if parts.is_empty() {
            "healthy".into()
        } else {
            parts.join(", ")
        }
    }

    /// The schedule as a scenario file: fatigue off (only the schedule damages joints), one
    /// `scale` edit per damaged joint at its onset, then the push.
    pub fn scenario_json(
        &self,
        name: &str,
        description: &str,
        joints: &[String; N_ACTUATORS],
    ) -> serde_json::Value {
        let mut edits: Vec<serde_json::Value> = self
            .damaged()
            .map(|i| {
                serde_json::json!({"step": self.onsets[i], "joint": joints[i], "scale": self.scales[i]})
            })
            .collect();
        if let Some(p) = &self.push {
            edits.push(serde_json::json!({
                "step": p.onset,
                "push": {"body": p.body, "force": p.force(), "steps": p.steps},
            }));
        }
        serde_json::json!({
            "name": name,
            "description": description,
            "fatigue": false,
            "edits": edits,
        })
    }
}

/// Pushes in the search: the impulse one push may have, and the seconds one env step lasts
/// (the world's, so the impulse means newton-seconds).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PushSpace {
    pub impulse: f64,
    pub step_seconds: f64,
}

impl PushSpace {
    /// The largest impulse budget worth asking for: the strongest push for the longest time.
    pub fn max_impulse(step_seconds: f64) -> f64 {
        MAX_PUSH_NEWTONS * MAX_SEARCH_PUSH_STEPS as f64 * step_seconds
    }
}

/// Where schedules live: the budget K, the latest onset step, pushes if searched, and the legs
/// (their actuators) when a gene damages a whole leg.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Space {
    pub severity_budget: f64,
    pub latest_onset: usize,
    pub pushes: Option<PushSpace>,
    pub legs: Option<[[usize; 2]; N_LEGS]>,
    /// Over the budget, keep the largest damages whole and cut the rest (concentrated damage:
    /// dead joints and legs are reachable), instead of scaling every damage down together.
    pub concentrate: bool,
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
    /// The actuators each damage gene acts on, in gene order: one joint each, or one leg each.
    pub fn units(&self) -> Vec<Vec<usize>> {
        match &self.legs {
            Some(legs) => legs.iter().map(|l| l.to_vec()).collect(),
            None => (0..N_ACTUATORS).map(|i| vec![i]).collect(),
        }
    }

    /// Genes per genome: a damage per unit, an onset per unit, then the push's where pushes are
    /// searched.
    pub fn genes(&self) -> usize {
        self.push_gene() + if self.pushes.is_some() { PUSH_GENES } else { 0 }
    }

    /// Where the push's genes start.
    fn push_gene(&self) -> usize {
        2 * self.units().len()
    }

    /// An onset gene (folded into [0, 1]) as a step in [0, latest onset].
    fn onset(&self, gene: f64) -> usize {
        ((reflect(gene) * (self.latest_onset + 1) as f64).floor() as usize).min(self.latest_onset)
    }

    /// A genome (any reals; [`Space::genes`] of them: damages, onsets, then the push's) as a
    /// schedule within the budgets: each gene folded into [0, 1]; when the damages' sum over the
    /// joints (a leg's counts twice) exceeds K, scaled down together — or, concentrated, the
    /// largest kept whole, the next cut to what is left, the rest dropped — then floored to
    /// [`SCALE_STEP`] (so the budget holds after rounding); the push's impulse a fraction of its
    /// budget, floored to whole newtons.
    pub fn decode(&self, genome: &[f64]) -> Schedule {
        let units = self.units();
        let mut damage: Vec<f64> = (0..units.len())
            .map(|k| reflect(genome.get(k).copied().unwrap_or(0.0)))
            .collect();
        let total: f64 = units
            .iter()
            .zip(&damage)
            .map(|(u, d)| u.len() as f64 * d)
            .sum();
        if total > self.severity_budget && self.concentrate {
            // Largest first (ties in gene order); each costs its width.
            let mut order: Vec<usize> = (0..units.len()).collect();
            order.sort_by(|&a, &b| damage[b].total_cmp(&damage[a]).then(a.cmp(&b)));
            let mut left = self.severity_budget;
            for k in order {
                let width = units[k].len() as f64;
                if width * damage[k] <= left {
                    left -= width * damage[k];
                } else {
                    damage[k] = left / width;
                    left = 0.0;
                }
            }
        } else if total > self.severity_budget {
            let shrink = self.severity_budget / total;
            for d in &mut damage {
                *d *= shrink;
            }
        }
        let mut schedule = Schedule::healthy();
        for (k, (unit, d)) in units.iter().zip(&damage).enumerate() {
            let steps = (d / SCALE_STEP + 1e-9).floor();
            let scale = round_scale(1.0 - steps * SCALE_STEP);
            let onset = self.onset(genome.get(units.len() + k).copied().unwrap_or(0.0));
            for &i in unit {
                schedule.scales[i] = scale;
                schedule.onsets[i] = onset;
            }
        }
        if let Some(space) = self.pushes {
            let first = self.push_gene();
            let gene = |k: usize| reflect(genome.get(first + k).copied().unwrap_or(0.0));
            let body = ((gene(0) * PUSH_BODIES.len() as f64) as usize).min(PUSH_BODIES.len() - 1);
            let heading_deg = ((gene(1) * 360.0) as u32).min(359);
            let steps = 1
                + ((gene(3) * MAX_SEARCH_PUSH_STEPS as f64) as usize)
                    .min(MAX_SEARCH_PUSH_STEPS - 1);
            let impulse = gene(2) * space.impulse;
            let newtons =
                (impulse / (steps as f64 * space.step_seconds) + 1e-9).min(MAX_PUSH_NEWTONS);
            // Below one newton there is no push to speak of.
            if newtons >= 1.0 {
                schedule.push = Some(SearchPush {
                    body: PUSH_BODIES[body].to_string(),
                    heading_deg,
                    newtons: newtons.floor() as u32,
                    steps,
                    onset: self.onset(genome.get(first + 4).copied().unwrap_or(0.0)),
                });
            }
        }
        schedule
    }

    /// The single reductions of a schedule a shrinker tries, least damage first: drop a unit
    /// (a joint, or a leg: scale → 1) or the push, raise a unit's scale by 0.1 or halve the
    /// push's force, start a unit or the push 10 % of the latest onset later.
    pub fn reductions(&self, s: &Schedule) -> Vec<Schedule> {
        let mut out = Vec::new();
        let later = (self.latest_onset / 10).max(1);
        let damaged: Vec<Vec<usize>> = self
            .units()
            .into_iter()
            .filter(|u| u.iter().any(|&i| s.scales[i] < 1.0))
            .collect();
        for unit in &damaged {
            let mut dropped = s.clone();
            for &i in unit {
                dropped.scales[i] = 1.0;
                dropped.onsets[i] = 0;
            }
            out.push(dropped);
        }
        if s.push.is_some() {
            out.push(Schedule {
                push: None,
                ..s.clone()
            });
        }
        for unit in &damaged {
            if unit.iter().all(|&i| s.scales[i] < 0.9) {
                let mut raised = s.clone();
                for &i in unit {
                    raised.scales[i] = round_scale(s.scales[i] + 0.1);
                }
                out.push(raised);
            }
        }
        if let Some(p) = s.push.as_ref().filter(|p| p.newtons >= 2) {
            let mut halved = s.clone();
            halved.push = Some(SearchPush {
                newtons: p.newtons / 2,
                ..p.clone()
            });
            out.push(halved);
        }
        for unit in &damaged {
            if unit
                .iter()
                .all(|&i| s.onsets[i] + later <= self.latest_onset)
            {
                let mut delayed = s.clone();
                for &i in unit {
                    delayed.onsets[i] += later;
                }
                out.push(delayed);
            }
        }
        if let Some(p) = s
            .push
            .as_ref()
            .filter(|p| p.onset + later <= self.latest_onset)
        {
            let mut delayed = s.clone();
            delayed.push = Some(SearchPush {
                onset: p.onset + later,
                ..p.clone()
            });
            out.push(delayed);
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

    /// `n` genes uniform in [−spread, spread] from a 64-bit LCG (genes outside [0, 1] test the
    /// reflection).
    fn genome(rng: &mut u64, n: usize, spread: f64) -> Vec<f64> {
        (0..n)
            .map(|_| {
                *rng = rng
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((*rng >> 11) as f64 / (1u64 << 53) as f64) * 2.0 * spread - spread
            })
            .collect()
    }

    #[test]
    fn decoded_schedules_keep_the_budget_and_the_box() {
        let space = Space {
            severity_budget: 1.5,
            latest_onset: 100,
            pushes: None,
            legs: None,
            concentrate: false,
        };
        let mut rng = 12345u64;
        for _ in 0..2000 {
            let s = space.decode(&genome(&mut rng, GENES, 4.0));
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
            pushes: None,
            legs: None,
            concentrate: false,
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
        s.scales[4] = 0.2;
        s.onsets[4] = 30;
        let v = s.scenario_json("x", "y", &Anatomy::ant().joints);
        assert_eq!(v["fatigue"], false);
        assert_eq!(
            v["edits"],
            serde_json::json!([{"step": 30, "joint": "hip_2", "scale": 0.2}])
        );
        assert_eq!(s.describe(&Anatomy::ant()), "hip_2 0.2 @ 30");
    }

    #[test]
    fn every_reduction_reduces() {
        let space = Space {
            severity_budget: 2.0,
            latest_onset: 100,
            pushes: None,
            legs: None,
            concentrate: false,
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

    fn push_space(impulse: f64) -> Space {
        Space {
            severity_budget: 1.0,
            latest_onset: 99,
            pushes: Some(PushSpace {
                impulse,
                step_seconds: 0.05,
            }),
            legs: None,
            concentrate: false,
        }
    }

    #[test]
    fn a_push_decodes_by_hand_and_replays_as_the_same_scenario_push() {
        let space = push_space(60.0);
        let mut genome = vec![0.0; space.genes()];
        // Body 0.3 · 5 → 1 (front_left_leg); heading 0.25 → 90°; impulse 0.5 · 60 = 30 N·s;
        // length 1 + ⌊0.25 · 10⌋ = 3 steps, so 30 / (3 · 0.05) = 200 N; onset 0.5 · 100 → 50.
        genome[GENES..].copy_from_slice(&[0.3, 0.25, 0.5, 0.25, 0.5]);
        let s = space.decode(&genome);
        let p = s.push.clone().expect("a push");
        assert_eq!(
            p,
            SearchPush {
                body: "front_left_leg".into(),
                heading_deg: 90,
                newtons: 200,
                steps: 3,
                onset: 50,
            }
        );
        assert_eq!(p.force(), [0.0, 200.0, 0.0]);
        assert!((p.impulse(0.05) - 30.0).abs() < 1e-9);
        assert_eq!(s.severity(), 0.0); // a push spends its own budget, not the joints'
        assert_eq!(
            s.describe(&Anatomy::ant()),
            "push front_left_leg 200 N toward 90° for 3 steps @ 50"
        );
        // The scenario file carries the same push, and the scenario reader accepts it.
        let v = s.scenario_json("x", "y", &Anatomy::ant().joints);
        assert_eq!(
            v["edits"],
            serde_json::json!([{"step": 50, "push": {"body": "front_left_leg", "force": [0.0, 200.0, 0.0], "steps": 3}}])
        );
        let read = crate::damage::scenario::Scenario::from_json(&v.to_string(), "x").unwrap();
        assert_eq!(read.pushes.len(), 1);
        assert_eq!(
            read.pushes[0].step,
            crate::damage::scenario::StepSpec::At(50)
        );
        assert_eq!(read.pushes[0].push.force, [0.0, 200.0, 0.0]);
        assert_eq!(read.pushes[0].push.steps, 3);
        // One step at the whole budget would be 1,200 N: held to the push cap, 1,000 N.
        genome[GENES + 2] = 1.0;
        genome[GENES + 3] = 0.0;
        let p = space.decode(&genome).push.unwrap();
        assert_eq!((p.newtons, p.steps), (1000, 1));
        // No impulse, no push; a search without pushes reads no push genes.
        genome[GENES + 2] = 0.0;
        assert_eq!(space.decode(&genome).push, None);
        let plain = Space {
            pushes: None,
            ..space
        };
        assert_eq!(plain.genes(), GENES);
        assert_eq!(plain.decode(&[0.5; GENES + PUSH_GENES]).push, None);
    }

    #[test]
    fn decoded_pushes_keep_their_budget_and_the_cap() {
        for impulse in [0.5, 7.0, 60.0, PushSpace::max_impulse(0.05)] {
            let space = push_space(impulse);
            let mut rng = 99u64;
            let mut pushes = 0;
            for _ in 0..2000 {
                let Some(p) = space.decode(&genome(&mut rng, space.genes(), 3.0)).push else {
                    continue;
                };
                pushes += 1;
                assert!(p.impulse(0.05) <= impulse + 1e-9, "{p:?} over {impulse}");
                assert!((1..=1000).contains(&p.newtons), "{p:?}");
                let f = p.force();
                assert!(f[0].hypot(f[1]) <= f64::from(p.newtons), "{p:?}");
                assert!((1..=MAX_SEARCH_PUSH_STEPS).contains(&p.steps));
                assert!(p.heading_deg < 360 && p.onset <= 99);
                assert!(PUSH_BODIES.contains(&p.body.as_str()));
                crate::damage::Push::new(&p.body, f, p.steps).unwrap();
            }
            assert!(pushes > 100, "{impulse}: only {pushes} pushes of 2000");
        }
    }

    #[test]
    fn a_push_is_dropped_halved_and_delayed_by_the_shrinker() {
        let space = push_space(60.0);
        let mut s = Schedule::healthy();
        s.scales[1] = 0.5;
        s.push = Some(SearchPush {
            body: "torso".into(),
            heading_deg: 10,
            newtons: 301,
            steps: 2,
            onset: 20,
        });
        let r = space.reductions(&s);
        // Drop joint 1, drop the push, raise joint 1, halve the push, delay joint 1, delay it.
        assert_eq!(r.len(), 6);
        assert_eq!(r[1].push, None);
        assert_eq!(r[1].scales[1], 0.5);
        assert_eq!(r[3].push.as_ref().unwrap().newtons, 150);
        assert_eq!(r[5].push.as_ref().unwrap().onset, 29);
        assert_eq!(r[5].scales, s.scales);
    }

    fn leg_space(budget: f64) -> Space {
        Space {
            severity_budget: budget,
            latest_onset: 100,
            pushes: None,
            legs: Some(Anatomy::ant().legs.map(|(_, a)| a)),
            concentrate: false,
        }
    }

    #[test]
    fn a_leg_gene_damages_both_joints_and_costs_both() {
        let space = leg_space(2.0);
        assert_eq!(space.genes(), 8);
        // Leg 2 (back_leg: hip_3, ankle_3 = actuators 6, 7) at damage 1: 2 of the budget of 2.
        let mut genes = vec![0.0; 8];
        genes[2] = 1.0;
        genes[4 + 2] = 0.4; // onset 0.4 · 101 → 40
        let s = space.decode(&genes);
        assert_eq!(s.scales, [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0]);
        assert_eq!(s.onsets, [0, 0, 0, 0, 0, 0, 40, 40]);
        assert_eq!(s.severity(), 2.0);
        assert_eq!(s.describe(&Anatomy::ant()), "back_leg 0 @ 40");
        // Two legs at 0.8 cost 3.2 > 2: both scaled by 2 / 3.2 to damage 0.5.
        genes[2] = 0.8;
        genes[0] = 0.8;
        let s = space.decode(&genes);
        assert_eq!(s.scales[2..4], [0.5, 0.5]); // front_left_leg: hip_1, ankle_1
        assert_eq!(s.scales[6..8], [0.5, 0.5]);
        assert_eq!(s.severity(), 2.0);
        // Random genomes: the budget holds and a leg's joints never part.
        let mut rng = 777u64;
        for _ in 0..2000 {
            let s = space.decode(&genome(&mut rng, 8, 4.0));
            assert!(s.severity() <= 2.0 + 1e-9, "{s:?}");
            for (_, [a, b]) in Anatomy::ant().legs {
                assert_eq!((s.scales[a], s.onsets[a]), (s.scales[b], s.onsets[b]));
            }
        }
    }

    #[test]
    fn a_leg_is_dropped_raised_and_delayed_whole() {
        let space = leg_space(4.0);
        let mut s = Schedule::healthy();
        for i in [0, 1] {
            s.scales[i] = 0.2; // right_back_leg
            s.onsets[i] = 30;
        }
        let r = space.reductions(&s);
        // Drop it, raise it, delay it: each to both joints.
        assert_eq!(r.len(), 3);
        assert_eq!(r[0], Schedule::healthy());
        assert_eq!(r[1].scales[..2], [0.3, 0.3]);
        assert_eq!(r[2].onsets[..2], [40, 40]);
        assert_eq!(s.describe(&Anatomy::ant()), "right_back_leg 0.2 @ 30");
        // A joint search still names a leg whose joints happen to agree, and joints otherwise.
        s.scales[1] = 0.5;
        assert_eq!(
            s.describe(&Anatomy::ant()),
            "hip_4 0.2 @ 30, ankle_4 0.5 @ 30"
        );
    }

    /// The names a synthetic evaluator takes are the Ant's own, from its model.
    #[test]
    fn the_ants_anatomy_is_its_models() {
        let env = crate::env::AntEnv::new(crate::config::GaitConfig::default(), 0).unwrap();
        let ant = Anatomy::ant();
        assert_eq!(&ant.joints, env.damage().joint_names());
        assert_eq!(
            ant.legs.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(),
            env.leg_names()
        );
        assert_eq!(
            ant.legs.iter().map(|(_, a)| *a).collect::<Vec<_>>(),
            env.leg_actuators()
        );
    }

    #[test]
    fn concentrated_damage_keeps_the_largest_whole() {
        let space = Space {
            concentrate: true,
            ..leg_space(2.0)
        };
        // Legs' damages 0.9, 0.8, 0.5, 0 cost 1.8, 1.6, 1.0 (4.4 > 2): the first kept whole,
        // the second cut to the 0.2 left (damage 0.1), the third dropped.
        let genes = [0.9, 0.8, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0];
        let s = space.decode(&genes);
        assert_eq!(s.scales, [1.0, 1.0, 0.1, 0.1, 0.9, 0.9, 1.0, 1.0]);
        assert!(s.severity() <= 2.0);
        // Within the budget nothing changes: the same as scaling.
        let within = [0.5, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(space.decode(&within), leg_space(2.0).decode(&within));
        // Over random genomes: the budget holds, and a leg near death (scale ≤ 0.1) is common
        // where scaling everything down together almost never gives one.
        let near_dead = |space: &Space| {
            let mut rng = 4242u64;
            (0..2000)
                .filter(|_| {
                    let s = space.decode(&genome(&mut rng, 8, 1.0));
                    assert!(s.severity() <= 2.0 + 1e-9, "{s:?}");
                    s.scales.iter().any(|&x| x <= 0.1)
                })
                .count()
        };
        let (concentrated, scaled) = (near_dead(&space), near_dead(&leg_space(2.0)));
        eprintln!(
            "a leg at scale ≤ 0.1 in 2,000 genomes: concentrated {concentrated}, scaled {scaled}"
        );
        assert!(
            concentrated > 300 && scaled < 20,
            "{concentrated} vs {scaled}"
        );
    }
}
