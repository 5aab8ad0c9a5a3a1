//! The episode a demo shows: not seed 0 by habit, but the candidate seed on which every model
//! does what it typically does. Over a handful of paired seeds each model has a typical outcome
//! (reaching the goal if it does so on at least half of them) and a median; the chosen seed is
//! the one where each model's outcome is its typical one and its steps to the goal (or its
//! final distance, for a model that typically fails) lie closest to its median. The caption
//! says so, with the counts, so a picture never suggests a difference the episodes do not show.

use std::ops::Range;

use super::{Case, EpisodeRecord, EvalError, run_lockstep};
use crate::config::GaitConfig;
use crate::damage::{Condition, ConditionChoice};
use crate::lane::Actor;

/// Seeds a demo chooses from by default (paired: every model runs each one).
pub const DEFAULT_CANDIDATES: Range<u64> = 0..8;

/// One model's outcomes over the candidates, and its episode on the chosen seed.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelOutcomes {
    pub label: String,
    pub successes: usize,
    pub episodes: usize,
    /// Median steps to the goal over the episodes that reached it.
    pub median_steps: Option<f64>,
    /// Median final distance over all episodes (m).
    pub median_distance: f64,
    /// On the chosen seed.
    pub shown: EpisodeRecord,
}

impl ModelOutcomes {
    /// Whether the model typically reaches the goal: on at least half of the seeds.
    pub fn typically_succeeds(&self) -> bool {
        typically_succeeds(self.successes, self.episodes)
    }
}

/// A model typically reaches the goal when it does so on at least half of the seeds.
fn typically_succeeds(successes: usize, episodes: usize) -> bool {
    2 * successes >= episodes
}

/// The chosen seed and why.
#[derive(Debug, Clone, PartialEq)]
pub struct TypicalPick {
    pub seed: u64,
    pub candidates: Range<u64>,
    pub condition: Option<Condition>,
    /// The scenario the episodes ran under, if one was set.
    pub scenario: Option<String>,
    pub models: Vec<ModelOutcomes>,
}

impl TypicalPick {
    /// One paragraph: how the episode was chosen, each model's record over the candidates and
    /// here, and where the real statistics are.
    pub fn caption(&self) -> String {
        let condition = match (&self.scenario, self.condition) {
            (Some(name), _) => format!("scenario {name}"),
            (None, Some(c)) => format!("{c} damage"),
            (None, None) => "random damage".to_string(),
        };
        let mut text = format!(
            "Seed {} is the most typical of seeds {}–{} under {condition}: every model does what it \
             usually does there, as close to its median as any seed.",
            self.seed,
            self.candidates.start,
            self.candidates.end - 1
        );
        for m in &self.models {
            let here = match m.shown.ending {
                Some(crate::env::Ending::Success) => {
                    format!("here the goal in {} steps", m.shown.steps)
                }
                other => format!(
                    "here {} after {} steps, {:.1} m short",
                    other.map_or("no ending", crate::env::Ending::name),
                    m.shown.steps,
                    m.shown.final_distance
                ),
            };
            // The median the pick used: steps for a model that usually arrives, else distance.
            let median = match (m.typically_succeeds(), m.median_steps) {
                (true, Some(s)) => format!("median {s:.0} steps to the goal"),
                _ => format!("median final distance {:.1} m", m.median_distance),
            };
            text += &format!(
                " {}: {}/{} reached the goal ({median}); {here}.",
                m.label, m.successes, m.episodes
            );
        }
        text + &format!(
            " {} episodes are an illustration, not a result: success rates over hundreds of \
             paired episodes and several training seeds are in docs/results.md.",
            self.candidates.end - self.candidates.start
        )
    }
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    })
}

/// Runs every checkpoint actor on every candidate seed (under `config`'s condition, each in its
/// own world) and picks the most typical seed. Builtin policies have nothing to pick for.
pub fn typical_episode(
    actors: &[Actor],
    config: &GaitConfig,
    candidates: Range<u64>,
) -> Result<TypicalPick, EvalError> {
    if candidates.is_empty() || actors.is_empty() {
        return Err(EvalError::Options(
            "a typical episode needs at least one model and one candidate seed".into(),
        ));
    }
    let condition = match config.damage.condition {
        ConditionChoice::Fixed(c) => Some(c),
        ConditionChoice::Random => None,
    };
    let seeds: Vec<u64> = candidates.clone().collect();
    let mut runs = Vec::new();
    for actor in actors {
        let label = actor.label();
        // The case only labels the records; each lane draws its condition from the config.
        let case = Case::Condition(condition.unwrap_or(Condition::Healthy));
        // In lockstep: a row decides the same bits in any batch as alone
        // (tests/batch_invariance.rs), so these are the episodes `record` and `live` show.
        let mut records = run_lockstep(actor, &label, config, case, &seeds, 0)?;
        records.sort_by_key(|r| r.seed);
        runs.push((label, records));
    }
    let outcomes: Vec<ModelRuns> = runs
        .into_iter()
        .map(|(label, records)| {
            let successes = records.iter().filter(|r| r.success).count();
            let median_steps = median(
                records
                    .iter()
                    .filter(|r| r.success)
                    .map(|r| r.steps as f64)
                    .collect(),
            );
            let median_distance =
                median(records.iter().map(|r| r.final_distance).collect()).unwrap_or(0.0);
            ModelRuns {
                label,
                records,
                successes,
                median_steps,
                median_distance,
            }
        })
        .collect();
    // A seed's distance from typical: a model off its typical outcome costs a whole unit, then
    // the relative distance from its median (steps for a model that usually succeeds, final
    // distance for one that usually fails). The lowest total wins; ties go to the lower seed.
    let cost = |i: usize| -> f64 {
        outcomes
            .iter()
            .map(|m| {
                let r = &m.records[i];
                let typical_success = typically_succeeds(m.successes, m.records.len());
                if r.success != typical_success {
                    return 10.0;
                }
                match (r.success, m.median_steps) {
                    (true, Some(steps)) => (r.steps as f64 - steps).abs() / steps.max(1.0),
                    _ => (r.final_distance - m.median_distance).abs() / m.median_distance.max(0.1),
                }
            })
            .sum()
    };
    let best = (0..seeds.len())
        .min_by(|&a, &b| cost(a).total_cmp(&cost(b)).then(a.cmp(&b)))
        .unwrap_or(0);
    Ok(TypicalPick {
        seed: seeds[best],
        candidates,
        condition,
        scenario: config.damage.scenario.as_ref().map(|s| s.name.clone()),
        models: outcomes
            .into_iter()
            .map(|m| ModelOutcomes {
                label: m.label,
                episodes: m.records.len(),
                successes: m.successes,
                median_steps: m.median_steps,
                median_distance: m.median_distance,
                shown: m.records[best].clone(),
            })
            .collect(),
    })
}

/// One model's episodes on the candidate seeds (in seed order) and their summary.
struct ModelRuns {
    label: String,
    records: Vec<EpisodeRecord>,
    successes: usize,
    median_steps: Option<f64>,
    median_distance: f64,
}

#[cfg(test)]
mod tests {
    use super::median;

    #[test]
    fn medians_by_hand() {
        assert_eq!(median(vec![]), None);
        assert_eq!(median(vec![3.0]), Some(3.0));
        assert_eq!(median(vec![5.0, 1.0, 3.0]), Some(3.0));
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), Some(2.5));
    }
}
