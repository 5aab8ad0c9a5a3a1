//! Dead actuators: a world's second damage kind beside fatigue. Per episode a number of units
//! (single joints or whole legs, drawn from the episode's RNG) die at onsets drawn over the
//! journey: from its onset step a dead actuator keeps a residual scale in [0, max_scale] of its
//! torque (0: none) for the rest of the episode. The count depends on the episode's condition,
//! so in a world with dead actuators "healthy / mild / severe" read "0 / 1 / 2 units dead"
//! (the defaults) and every table, probe and breakpoint keyed by condition works unchanged.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use super::{Condition, N_ACTUATORS};

/// Units that die in one episode, at most (a bound for configs; the Ant has 4 legs, 8 joints).
pub const MAX_DEAD_UNITS: usize = N_ACTUATORS;

/// What one dying unit is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DeadUnit {
    /// One actuator.
    Joint,
    /// A leg's two actuators (hip and ankle), dying together.
    Leg,
    /// A joint or a leg, each with probability ½.
    JointOrLeg,
}

/// Units that die per condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DeadCounts {
    pub healthy: usize,
    pub mild: usize,
    pub severe: usize,
}

impl Default for DeadCounts {
    fn default() -> Self {
        Self {
            healthy: 0,
            mild: 1,
            severe: 2,
        }
    }
}

impl DeadCounts {
    pub fn of(&self, condition: Condition) -> usize {
        match condition {
            Condition::Healthy => self.healthy,
            Condition::Mild => self.mild,
            Condition::Severe => self.severe,
        }
    }
}

/// The dead-actuator distribution of a world (`damage.dead` in a config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DeadActuators {
    pub count: DeadCounts,
    pub unit: DeadUnit,
    /// A dead actuator keeps a scale drawn from U[0, max_scale] (0: exactly none).
    pub max_scale: f64,
    /// Each unit's onset step, drawn from [first, last] (inclusive).
    pub onset: [usize; 2],
}

impl Default for DeadActuators {
    fn default() -> Self {
        Self {
            count: DeadCounts::default(),
            unit: DeadUnit::JointOrLeg,
            max_scale: 0.0,
            onset: [0, 0],
        }
    }
}

/// One actuator's death in an episode's plan.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeadOnset {
    /// The first step the actuator runs dead.
    pub step: usize,
    pub actuator: usize,
    /// The torque scale it keeps.
    pub scale: f64,
}

impl DeadActuators {
    /// What happens under `condition`, in words for the panel and the page: "2 legs die, each
    /// from a step in 10–60".
    pub fn describe(&self, condition: Condition) -> String {
        let n = self.count.of(condition);
        if n == 0 {
            return "nothing dies".into();
        }
        let (one, many) = match self.unit {
            DeadUnit::Joint => ("joint", "joints"),
            DeadUnit::Leg => ("leg", "legs"),
            DeadUnit::JointOrLeg => ("joint or leg", "joints or legs"),
        };
        let (what, verb, each) = if n == 1 {
            (one, "dies", "")
        } else {
            (many, "die", "each ")
        };
        let fate = if self.max_scale > 0.0 {
            format!(" (keeping U[0, {}] of its torque)", self.max_scale)
        } else {
            String::new()
        };
        let [first, last] = self.onset;
        let when = if first == last {
            format!("at step {first}")
        } else {
            format!("from a step in {first}–{last}")
        };
        format!("{n} {what} {verb}{fate}, {each}{when}")
    }

    /// Why this distribution cannot be drawn from, if it cannot.
    pub fn check(&self) -> Result<(), String> {
        if !(self.max_scale.is_finite() && (0.0..=1.0).contains(&self.max_scale)) {
            return Err(format!(
                "damage.dead.max_scale must lie in [0, 1], got {}",
                self.max_scale
            ));
        }
        if self.onset[0] > self.onset[1] {
            return Err(format!(
                "damage.dead.onset {:?} is empty (first > last)",
                self.onset
            ));
        }
        let most = match self.unit {
            DeadUnit::Joint | DeadUnit::JointOrLeg => N_ACTUATORS,
            DeadUnit::Leg => N_ACTUATORS / 2,
        };
        let c = self.count;
        for (name, n) in [
            ("healthy", c.healthy),
            ("mild", c.mild),
            ("severe", c.severe),
        ] {
            if n > most.min(MAX_DEAD_UNITS) {
                return Err(format!(
                    "damage.dead.count.{name} is {n}; at most {most} units of this kind can die"
                ));
            }
        }
        Ok(())
    }

    /// This episode's deaths under `condition`, drawn from `seed`: distinct actuators, sorted
    /// by onset (then actuator). `legs[l]` are leg `l`'s actuators. A leg cannot be drawn once
    /// one of its joints is dead, so `JointOrLeg` falls back to a joint when no leg is whole.
    pub fn plan(&self, condition: Condition, seed: u64, legs: &[[usize; 2]]) -> Vec<DeadOnset> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut dead = [false; N_ACTUATORS];
        let mut out = Vec::new();
        for _ in 0..self.count.of(condition) {
            let whole_legs: Vec<&[usize; 2]> = legs
                .iter()
                .filter(|l| l.iter().all(|&a| !dead[a]))
                .collect();
            let as_leg = match self.unit {
                DeadUnit::Joint => false,
                DeadUnit::Leg => true,
                DeadUnit::JointOrLeg => rng.random_bool(0.5),
            } && !whole_legs.is_empty();
            let actuators: Vec<usize> = if as_leg {
                whole_legs[rng.random_range(0..whole_legs.len())].to_vec()
            } else {
                let alive: Vec<usize> = (0..N_ACTUATORS).filter(|&a| !dead[a]).collect();
                if alive.is_empty() {
                    break;
                }
                vec![alive[rng.random_range(0..alive.len())]]
            };
            let step = rng.random_range(self.onset[0]..=self.onset[1]);
            let scale = if self.max_scale > 0.0 {
                rng.random_range(0.0..=self.max_scale)
            } else {
                0.0
            };
            for a in actuators {
                dead[a] = true;
                out.push(DeadOnset {
                    step,
                    actuator: a,
                    scale,
                });
            }
        }
        out.sort_by_key(|d| (d.step, d.actuator));
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LEGS: [[usize; 2]; 4] = [[0, 1], [2, 3], [4, 5], [6, 7]];

    #[test]
    fn counts_follow_the_condition_and_actuators_are_distinct() {
        let d = DeadActuators {
            onset: [10, 120],
            ..DeadActuators::default()
        };
        d.check().unwrap();
        for seed in 0..200 {
            assert!(d.plan(Condition::Healthy, seed, &LEGS).is_empty());
            for (condition, units) in [(Condition::Mild, 1), (Condition::Severe, 2)] {
                let plan = d.plan(condition, seed, &LEGS);
                // A unit is one joint or both of a leg's joints: units ≤ deaths ≤ 2·units.
                assert!((units..=2 * units).contains(&plan.len()), "{plan:?}");
                let mut seen = [false; N_ACTUATORS];
                for o in &plan {
                    assert!(!seen[o.actuator], "{plan:?}");
                    seen[o.actuator] = true;
                    assert!((10..=120).contains(&o.step));
                    assert_eq!(o.scale, 0.0);
                }
                assert!(plan.windows(2).all(|w| w[0].step <= w[1].step));
            }
        }
        // Both kinds of unit occur, and the draw is the seed's alone.
        let sizes: Vec<usize> = (0..50)
            .map(|s| d.plan(Condition::Mild, s, &LEGS).len())
            .collect();
        assert!(sizes.contains(&1) && sizes.contains(&2));
        assert_eq!(
            d.plan(Condition::Severe, 7, &LEGS),
            d.plan(Condition::Severe, 7, &LEGS)
        );
    }

    #[test]
    fn the_description_says_what_dies_and_when() {
        let mut d = DeadActuators {
            unit: DeadUnit::Leg,
            onset: [10, 60],
            ..DeadActuators::default()
        };
        assert_eq!(d.describe(Condition::Healthy), "nothing dies");
        assert_eq!(
            d.describe(Condition::Mild),
            "1 leg dies, from a step in 10–60"
        );
        assert_eq!(
            d.describe(Condition::Severe),
            "2 legs die, each from a step in 10–60"
        );
        d.unit = DeadUnit::JointOrLeg;
        d.max_scale = 0.2;
        d.onset = [5, 5];
        assert_eq!(
            d.describe(Condition::Mild),
            "1 joint or leg dies (keeping U[0, 0.2] of its torque), at step 5"
        );
    }

    #[test]
    fn legs_die_whole_and_a_residual_scale_stays_in_range() {
        let d = DeadActuators {
            unit: DeadUnit::Leg,
            max_scale: 0.2,
            count: DeadCounts {
                healthy: 4,
                mild: 4,
                severe: 4,
            },
            onset: [5, 5],
        };
        d.check().unwrap();
        let plan = d.plan(Condition::Severe, 3, &LEGS);
        assert_eq!(plan.len(), N_ACTUATORS, "four legs: every actuator");
        for leg in LEGS {
            let s: Vec<f64> = plan
                .iter()
                .filter(|o| leg.contains(&o.actuator))
                .map(|o| o.scale)
                .collect();
            assert_eq!(s.len(), 2);
            assert_eq!(s[0], s[1], "a leg's joints die together, to one scale");
            assert!((0.0..=0.2).contains(&s[0]));
        }
    }

    #[test]
    fn impossible_distributions_are_refused_with_the_field() {
        let bad = [
            (
                DeadActuators {
                    max_scale: 1.5,
                    ..DeadActuators::default()
                },
                "max_scale",
            ),
            (
                DeadActuators {
                    onset: [9, 3],
                    ..DeadActuators::default()
                },
                "onset",
            ),
            (
                DeadActuators {
                    unit: DeadUnit::Leg,
                    count: DeadCounts {
                        healthy: 0,
                        mild: 1,
                        severe: 5,
                    },
                    ..DeadActuators::default()
                },
                "count.severe",
            ),
        ];
        for (d, field) in bad {
            let err = d.check().unwrap_err();
            assert!(err.contains(field), "{err}");
        }
    }
}
