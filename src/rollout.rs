//! Rollouts with built-in policies, and deterministic replay of an action sequence.
//!
//! Replay is how anyone checks our physics against another implementation (e.g. Gymnasium's
//! Ant-v4), so its file formats are fixed:
//! - init state: `{"qpos": [15 numbers], "qvel": [14 numbers]}` (or a saved state,
//!   [`crate::lane::SavedState`]: the actions then start at its step)
//! - actions: `[[8 numbers], ...]`
//! - output: one [`StepLine`] JSON object per line, the state after step `t`.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use crate::damage::{Condition, N_ACTUATORS};
use crate::env::{ACT_DIM, Action, AntEnv, EnvError, StepOutcome};
use crate::lane::StartState;

pub use crate::lane::{BuiltinPolicy, policy_rng};

/// One episode in a line (or one JSON object).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeSummary {
    pub episode: usize,
    pub seed: u64,
    pub condition: Condition,
    pub steps: usize,
    pub success: bool,
    pub terminated: bool,
    pub truncated: bool,
    /// How it ended: success, leapt, collapsed, timeout, … ([`crate::env::Ending`]).
    pub ending: Option<crate::env::Ending>,
    pub final_distance: f64,
    #[serde(rename = "return")]
    pub episode_return: f64,
    /// First fatigue trigger step per joint, `None` if the joint never triggered.
    pub trigger_steps: BTreeMap<String, Option<usize>>,
    /// `fork` for the counterfactual lane of `--fork-at` (absent for the main lane).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lane: Option<String>,
}

/// Runs one episode of a built-in policy. The env is reset with `seed` and the policy's RNG is
/// seeded from it too, so an episode is reproducible on its own.
pub fn run_builtin_episode(
    env: &mut AntEnv,
    policy: BuiltinPolicy,
    episode: usize,
    seed: u64,
) -> Result<EpisodeSummary, EnvError> {
    run_builtin_episode_with(env, policy, episode, seed, |_| Ok(())).map_err(|e| match e {
        ReplayError::Env(e) => e,
        other => EnvError::BadState(other.to_string()),
    })
}

/// [`run_builtin_episode`], each step's line (lane `main`, with the commanded action) to `sink`.
pub fn run_builtin_episode_with(
    env: &mut AntEnv,
    policy: BuiltinPolicy,
    episode: usize,
    seed: u64,
    mut sink: impl FnMut(&LaneRecord) -> std::io::Result<()>,
) -> Result<EpisodeSummary, ReplayError> {
    let actor = crate::lane::Actor::Builtin(policy);
    let mut lane = crate::lane::Lane::new(&actor, env.config(), seed)?;
    let mut episode_return = 0.0;
    lane.run_to_end(&actor, crate::policy::ActionMode::Deterministic, |record| {
        episode_return += record.outcome.reward.total;
        sink(&LaneRecord::new(episode, seed, "main", record)).map_err(ReplayError::Write)
    })?;
    let last = lane
        .outcome()
        .cloned()
        .ok_or_else(|| ReplayError::Env(EnvError::BadState("the episode took no step".into())))?;
    let summary = summarize(lane.env(), episode, seed, &last, episode_return);
    // The caller's env ends where the episode did (callers read its damage and state).
    env.restore(&lane.env().snapshot())?;
    Ok(summary)
}

/// The summary of an episode that has just ended with `last`.
pub fn summarize(
    env: &AntEnv,
    episode: usize,
    seed: u64,
    last: &StepOutcome,
    episode_return: f64,
) -> EpisodeSummary {
    let damage = env.damage();
    let trigger_steps = damage
        .joint_names()
        .iter()
        .cloned()
        .zip(damage.first_trigger_steps())
        .collect();
    EpisodeSummary {
        episode,
        seed,
        condition: damage.condition(),
        steps: last.step + 1,
        success: last.success,
        terminated: last.terminated,
        truncated: last.truncated,
        ending: last.ending,
        final_distance: last.distance,
        episode_return,
        trigger_steps,
        lane: None,
    }
}

impl std::fmt::Display for EpisodeSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let outcome = self.ending.map_or("running", crate::env::Ending::name);
        write!(
            f,
            "episode {:>3}  seed {:<6} {:<7}  {:>4} steps  {:<9}  final distance {:6.2} m  return {:9.1}  fatigue triggers:",
            self.episode,
            self.seed,
            self.condition.name(),
            self.steps,
            outcome,
            self.final_distance,
            self.episode_return
        )?;
        // Only the joints that triggered, in step order ("--json" has every joint).
        let mut triggered: Vec<(usize, &str)> = self
            .trigger_steps
            .iter()
            .filter_map(|(joint, step)| step.map(|s| (s, joint.as_str())))
            .collect();
        triggered.sort();
        if triggered.is_empty() {
            return write!(f, " none");
        }
        for (k, (step, joint)) in triggered.iter().enumerate() {
            let sep = if k == 0 { " " } else { ", " };
            write!(f, "{sep}{joint} at step {step}")?;
        }
        Ok(())
    }
}

/// The state after one step; the JSONL line format of `rollout --jsonl` and of a replay.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepLine {
    pub step: usize,
    pub obs: Vec<f64>,
    pub reward: f64,
    pub terminated: bool,
    pub truncated: bool,
    pub fatigue: [f64; N_ACTUATORS],
    pub triggered: [bool; N_ACTUATORS],
    pub applied_action: [f64; N_ACTUATORS],
    pub torso_xy: [f64; 2],
    pub qpos: Vec<f64>,
    pub qvel: Vec<f64>,
    /// Per leg (front_left, front_right, back, right_back: the model's body order), whether its
    /// foot touches the floor.
    pub contacts: [bool; crate::env::N_LEGS],
    /// The pushes that acted during this step (left out when none did).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub pushes: Vec<crate::damage::PushRecord>,
}

impl From<&crate::lane::StepRecord> for StepLine {
    fn from(r: &crate::lane::StepRecord) -> Self {
        let out = &r.outcome;
        Self {
            step: out.step,
            obs: out.obs.to_vec(),
            reward: out.reward.total,
            terminated: out.terminated,
            truncated: out.truncated,
            fatigue: r.fatigue,
            triggered: r.triggered,
            applied_action: out.applied_action,
            torso_xy: r.torso_xy,
            contacts: r.contacts,
            qpos: r.qpos.clone(),
            qvel: r.qvel.clone(),
            pushes: r.pushes.clone(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error("cannot read {what} file {path}: {source}")]
    Read {
        what: &'static str,
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{what} file {path} is malformed: {reason}")]
    Malformed {
        what: &'static str,
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error(transparent)]
    Env(#[from] EnvError),
    #[error("writing replay output: {0}")]
    Write(#[source] std::io::Error),
    #[error("policy inference failed: {0}")]
    Policy(#[from] candle_core::Error),
    #[error(transparent)]
    ForkBeyondEpisode(#[from] crate::lane::ForkBeyondEpisode),
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error(
        "a bare initial state (qpos, qvel) needs --condition healthy|mild|severe (the damage scale must be explicit)"
    )]
    NeedsCondition,
    #[error(
        "the saved state's condition is {saved}, not {asked}: its damage state belongs to it (leave --condition out)"
    )]
    ConditionConflict { saved: Condition, asked: Condition },
    #[error("the episode ended after {steps} steps, before step {at}: no state to save")]
    SaveBeyondEpisode { at: usize, steps: usize },
}

/// The most a replay's action list or bare state file may hold (1,000 steps of 8 actions as
/// JSON are under 200 KB).
pub const MAX_REPLAY_FILE_BYTES: u64 = 16 << 20;

fn read_json<T: serde::de::DeserializeOwned>(
    what: &'static str,
    path: &Path,
    expected: &str,
) -> Result<T, ReplayError> {
    let text = crate::files::read_text_capped(path, MAX_REPLAY_FILE_BYTES).map_err(|source| {
        ReplayError::Read {
            what,
            path: path.to_owned(),
            source,
        }
    })?;
    serde_json::from_str(&text).map_err(|e| ReplayError::Malformed {
        what,
        path: path.to_owned(),
        reason: format!("{e} (expected {expected})").into(),
    })
}

/// Reads an initial state: a saved state (`--save-state-at`), or a replay's bare
/// `{"qpos": [15], "qvel": [14]}`; lengths and finiteness checked.
pub fn read_init_state(path: &Path) -> Result<StartState, ReplayError> {
    StartState::read(path).map_err(|e| match e {
        crate::lane::StateFileError::Read { path, source } => ReplayError::Read {
            what: "init-state",
            path,
            source,
        },
        crate::lane::StateFileError::Malformed { path, reason } => ReplayError::Malformed {
            what: "init-state",
            path,
            reason,
        },
    })
}

/// Starts `lane` from `init`: a saved state under its own condition (a different `condition`
/// is refused), a bare one under `condition`, which it then needs.
fn start_lane_from(
    lane: &mut crate::lane::Lane,
    init: &StartState,
    condition: Option<Condition>,
) -> Result<(), ReplayError> {
    match (init, init.condition(), condition) {
        (StartState::Bare { qpos, qvel }, _, Some(c)) => lane.reset_to_state(qpos, qvel, c)?,
        (StartState::Bare { .. }, _, None) => return Err(ReplayError::NeedsCondition),
        (_, Some(saved), Some(asked)) if saved != asked => {
            return Err(ReplayError::ConditionConflict { saved, asked });
        }
        (StartState::Saved(_), _, _) => {
            lane.start_from(init)?;
        }
    }
    Ok(())
}

/// Reads `[[8 numbers], ...]` and checks every row.
pub fn read_actions(path: &Path) -> Result<Vec<Action>, ReplayError> {
    const WHAT: &str = "actions";
    let rows: Vec<Vec<f64>> = read_json(WHAT, path, "[[8 numbers], ...]")?;
    let malformed = |reason: String| ReplayError::Malformed {
        what: WHAT,
        path: path.to_owned(),
        reason: reason.into(),
    };
    if rows.is_empty() {
        return Err(malformed("no actions (an empty list)".into()));
    }
    rows.iter()
        .enumerate()
        .map(|(t, row)| {
            let action: Action = row.as_slice().try_into().map_err(|_| {
                malformed(format!(
                    "actions[{t}] has {} numbers, expected {ACT_DIM}",
                    row.len()
                ))
            })?;
            if let Some((i, v)) = action.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(malformed(format!(
                    "actions[{t}][{i}] is {v}, expected a finite number"
                )));
            }
            Ok(action)
        })
        .collect()
}

/// Replays `actions` from `init` under `condition` in the world `config` (a lane with a
/// scripted actor), handing each step's line to `sink`. Stops at the end of the actions or when
/// the episode ends; returns the steps replayed.
pub fn replay(
    config: &crate::config::GaitConfig,
    init: &StartState,
    condition: Option<Condition>,
    actions: &[Action],
    mut sink: impl FnMut(&StepLine) -> std::io::Result<()>,
) -> Result<usize, ReplayError> {
    let actor = crate::lane::Actor::Scripted(actions.into());
    let mut lane = crate::lane::Lane::unstarted(&actor, config, 0)?;
    start_lane_from(&mut lane, init, condition)?;
    // A saved state starts at its step; the actions are those from there on.
    let first = lane.steps();
    let actor = crate::lane::Actor::Scripted(
        (0..first)
            .map(|_| [0.0; ACT_DIM])
            .chain(actions.iter().copied())
            .collect(),
    );
    let end = first + actions.len();
    lane.run_while(
        &actor,
        crate::policy::ActionMode::Deterministic,
        |lane| lane.steps() < end,
        |record| sink(&StepLine::from(record)).map_err(ReplayError::Write),
    )?;
    Ok(lane.steps() - first)
}

/// One line of a policy rollout: the replay record, the lane it belongs to (`main`, or `fork`
/// for the counterfactual) and the commanded action.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LaneRecord {
    /// The episode (0, 1, …) and its reset seed, so several episodes' lines tell apart.
    pub episode: usize,
    pub seed: u64,
    pub lane: &'static str,
    #[serde(flatten)]
    pub record: StepLine,
    pub action: Action,
}

impl LaneRecord {
    fn new(episode: usize, seed: u64, lane: &'static str, r: &crate::lane::StepRecord) -> Self {
        Self {
            episode,
            seed,
            lane,
            record: StepLine::from(r),
            action: r.outcome.commanded_action,
        }
    }
}

/// A counterfactual lane (`--fork-at K --fork EDITS`); see [`crate::lane::Fork`].
pub use crate::lane::Fork;

/// Where a policy episode starts: the reset with the episode's seed, or a given state.
#[derive(Debug, Clone, Copy)]
pub enum Start<'a> {
    Reset,
    /// From a state file (see [`read_init_state`]); a bare state under `condition`.
    State(&'a StartState, Option<Condition>),
}

/// A policy episode's outcome: the main lane's summary, the fork's, and the state saved
/// before step `save_at` (when asked).
#[derive(Debug, Clone)]
pub struct PolicyEpisode {
    pub summary: EpisodeSummary,
    pub fork: Option<EpisodeSummary>,
    pub saved: Option<crate::lane::SavedState>,
}

/// A deterministic episode of `actor` in its world (see [`crate::lane::Actor::world`]) from
/// `start` (the env seeded with `seed`), each step's line to `sink` (lane `main`), then the
/// fork's steps from `fork.at` on (lane `fork`) if asked. Returns the main episode's summary,
/// and the fork lane's (its return counts the main lane's steps before the fork: both are whole
/// episodes from the same reset).
#[allow(clippy::too_many_arguments)]
pub fn run_policy_episode(
    actor: &crate::lane::Actor,
    requested: &crate::config::GaitConfig,
    episode: usize,
    seed: u64,
    start: Start,
    fork: Option<&Fork>,
    save_at: Option<usize>,
    mut sink: impl FnMut(&LaneRecord) -> std::io::Result<()>,
) -> Result<PolicyEpisode, ReplayError> {
    use crate::lane::Lane;
    let mode = crate::policy::ActionMode::Deterministic;
    if let Some(fork) = fork {
        // Every edit names a joint of this world's model, before minutes of stepping.
        fork.validate(&actor.world(requested))?;
    }
    let mut lane = Lane::new(actor, requested, seed)?;
    if let Start::State(init, condition) = start {
        start_lane_from(&mut lane, init, condition)?;
    }
    let mut saved = None;
    // Steps the lane to its episode's end, each step's line to `sink`; the return.
    let mut run = |lane: &mut Lane,
                   name: &'static str,
                   stop_at: Option<usize>,
                   saved: &mut Option<crate::lane::SavedState>|
     -> Result<f64, ReplayError> {
        let mut episode_return = 0.0;
        lane.run_while(
            actor,
            mode,
            |lane| {
                let go_on = stop_at.is_none_or(|k| lane.steps() < k);
                if go_on && save_at == Some(lane.steps()) && name == "main" {
                    *saved = Some(lane.save_state(actor, seed));
                }
                go_on
            },
            |record| {
                episode_return += record.outcome.reward.total;
                sink(&LaneRecord::new(episode, seed, name, record)).map_err(ReplayError::Write)
            },
        )?;
        Ok(episode_return)
    };
    let before = run(&mut lane, "main", fork.map(|f| f.at), &mut saved)?;
    let branch = fork
        .filter(|f| f.due(&lane))
        .map(|f| lane.fork(&f.edits))
        .transpose()?;
    let after = run(&mut lane, "main", None, &mut saved)?;
    let last = lane
        .outcome()
        .cloned()
        .ok_or_else(|| ReplayError::Env(EnvError::BadState("the episode took no step".into())))?;
    let summary = summarize(lane.env(), episode, seed, &last, before + after);
    if let Some(at) = save_at
        && saved.is_none()
    {
        return Err(ReplayError::SaveBeyondEpisode {
            at,
            steps: summary.steps,
        });
    }
    let Some(f) = fork else {
        return Ok(PolicyEpisode {
            summary,
            fork: None,
            saved,
        });
    };
    let Some(mut fork_lane) = branch else {
        return Err(f.beyond(&lane).into());
    };
    let fork_return = run(&mut fork_lane, "fork", None, &mut None)?;
    let fork_last = fork_lane
        .outcome()
        .cloned()
        .ok_or_else(|| ReplayError::Env(EnvError::BadState("the fork took no step".into())))?;
    let mut fork_summary = summarize(
        fork_lane.env(),
        episode,
        seed,
        &fork_last,
        before + fork_return,
    );
    fork_summary.lane = Some("fork".into());
    Ok(PolicyEpisode {
        summary,
        fork: Some(fork_summary),
        saved,
    })
}
