//! Saved states (`rollout --save-state-at K FILE`, the panel's and page's "Save state"): a
//! lane paused before step K, written as JSON that `--init-state` starts from — physics (with
//! the solver's warm start), damage, pushes still acting, the policy's context window — plus an
//! MJCF `<key>` line to paste into the model for MuJoCo itself.
//!
//! `--init-state` also takes the bare `{"qpos": [15], "qvel": [14]}` of a replay; that starts
//! with fresh damage under the caller's condition and an empty window.

use serde::{Deserialize, Serialize};
use std::path::Path;

use super::{Lane, LaneError, policy_rng};
use crate::env::{EnvSave, NQ, NV};

/// The `format` a saved state file declares.
pub const STATE_FORMAT: &str = "gaitscope-state/1";
/// A state file's size, at most (a saved state is about 20 KB).
pub const MAX_STATE_BYTES: u64 = 4 << 20;

#[derive(Debug, thiserror::Error)]
pub enum StateFileError {
    #[error("cannot read state file {path}: {source}")]
    Read {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
    #[error("state file {path} is malformed: {reason}")]
    Malformed {
        path: std::path::PathBuf,
        #[source]
        reason: crate::Cause,
    },
}

/// A saved episode's clock, at most (the longest episode is far shorter).
const MAX_STATE_TIME_S: f64 = 1e6;
/// The farthest a saved torso or goal may be, in metres.
const MAX_STATE_DISTANCE_M: f64 = 1e4;
/// Positions, velocities and the solver's warm start, in absolute value at most.
const MAX_STATE_MAGNITUDE: f64 = 1e6;

/// The policy's context window at the saved step: its filled entries, oldest first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SavedWindow {
    /// Entries the window holds (the model's context length).
    pub len: usize,
    /// Up to `len` entries of observation (29) then commanded action (8).
    pub entries: Vec<Vec<f32>>,
}

/// A lane paused between two steps (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SavedState {
    pub format: String,
    /// The model whose episode this was (its folder name), when a checkpoint acted.
    #[serde(default)]
    pub checkpoint: Option<String>,
    /// The episode's seed.
    pub seed: u64,
    /// The condition as a person would name it: `manual` where only hands and scenarios damage
    /// joints (fatigue triggers off; `damage.condition` then gives the thresholds and a "fail"'s
    /// scale, severe's in the live viewer), else `damage.condition`'s name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub condition: Option<String>,
    #[serde(flatten)]
    pub env: EnvSave,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<SavedWindow>,
    /// `<key .../>` for the model's `<keyframe>`: MuJoCo's own way to start from this pose.
    pub mjcf_key: String,
}

/// What `--init-state` starts from.
#[derive(Debug, Clone, PartialEq)]
pub enum StartState {
    /// A replay's start: qpos and qvel alone, fresh damage.
    Bare {
        qpos: Vec<f64>,
        qvel: Vec<f64>,
    },
    Saved(Box<SavedState>),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BareState {
    qpos: Vec<f64>,
    qvel: Vec<f64>,
}

impl SavedState {
    /// The MJCF `<key>` line for a state (MuJoCo reads doubles printed shortest-round-trip
    /// exactly).
    pub fn mjcf_key(name: &str, time: f64, qpos: &[f64], qvel: &[f64]) -> String {
        let join = |v: &[f64]| {
            v.iter()
                .map(|x| x.to_string())
                .collect::<Vec<_>>()
                .join(" ")
        };
        format!(
            r#"<key name="{name}" time="{time}" qpos="{}" qvel="{}"/>"#,
            join(qpos),
            join(qvel)
        )
    }

    /// The file's text (pretty JSON, one trailing newline).
    pub fn to_json(&self) -> String {
        // Plain data of numbers and strings: serialising cannot fail.
        format!(
            "{}\n",
            serde_json::to_string_pretty(self).unwrap_or_default()
        )
    }
}

impl StartState {
    /// What a person should know before `actor` starts from this state: another model saved it,
    /// or its window is of another length (the model then starts with an empty window).
    pub fn notes_for(&self, actor: &super::Actor) -> Vec<String> {
        let StartState::Saved(saved) = self else {
            return Vec::new();
        };
        let mut notes = Vec::new();
        let acting = actor.label();
        if let Some(saver) = &saved.checkpoint
            && *saver != acting
        {
            notes.push(format!(
                "the state was saved with {saver} acting; {acting} acts from it now"
            ));
        }
        if let Some(w) = &saved.window
            && w.len != actor.context_len()
        {
            notes.push(format!(
                "the state's window holds {} steps' context, {acting} reads {}: it starts with an \
                 empty window",
                w.len,
                actor.context_len()
            ));
        }
        notes
    }

    /// Reads a state file: a saved state (it declares `"format"`) or a bare one.
    pub fn read(path: &Path) -> Result<Self, StateFileError> {
        let text = crate::files::read_text_capped(path, MAX_STATE_BYTES).map_err(|source| {
            StateFileError::Read {
                path: path.to_owned(),
                source,
            }
        })?;
        Self::parse(&text).map_err(|reason| StateFileError::Malformed {
            path: path.to_owned(),
            reason: reason.into(),
        })
    }

    /// Parses and checks a state file's text.
    pub fn parse(text: &str) -> Result<Self, String> {
        if text.len() as u64 > MAX_STATE_BYTES {
            return Err(format!("more than {MAX_STATE_BYTES} bytes"));
        }
        let value = crate::damage::scenario::strict_json(text).map_err(|e| e.to_string())?;
        let state = if value.get("format").is_some() {
            // serde's messages through `flatten` name no field: the lists and the damage
            // object are checked by name first.
            for k in ["qpos", "qvel", "qacc_warmstart", "torso_xy"] {
                let list = value[k].as_array();
                if !list.is_some_and(|l| l.iter().all(serde_json::Value::is_number)) {
                    return Err(format!("{k}: missing, or not a list of numbers"));
                }
            }
            if !value["damage"].is_object() {
                return Err("damage: missing, or not an object".into());
            }
            let saved: SavedState =
                serde_json::from_value(value.clone()).map_err(|e| e.to_string())?;
            // `flatten` lets unknown keys through: a typo must not be dropped silently.
            let known = serde_json::to_value(&saved).map_err(|e| e.to_string())?;
            let omitted = ["checkpoint", "window", "pushes"];
            if let (Some(given), Some(known)) = (value.as_object(), known.as_object())
                && let Some(k) = given
                    .keys()
                    .find(|k| !known.contains_key(*k) && !omitted.contains(&k.as_str()))
            {
                return Err(format!("unknown field `{k}`"));
            }
            // Every number the env takes as it is, bounded: a goal 1e308 m away made the reward
            // infinite (issue 49).
            let env = &saved.env;
            let bounded = [
                ("time", env.time, 0.0, MAX_STATE_TIME_S),
                (
                    "goal_distance",
                    env.goal_distance,
                    0.0,
                    MAX_STATE_DISTANCE_M,
                ),
                (
                    "torso_xy[0]",
                    env.torso_xy[0],
                    -MAX_STATE_DISTANCE_M,
                    MAX_STATE_DISTANCE_M,
                ),
                (
                    "torso_xy[1]",
                    env.torso_xy[1],
                    -MAX_STATE_DISTANCE_M,
                    MAX_STATE_DISTANCE_M,
                ),
            ];
            for (name, x, lo, hi) in bounded {
                if !(x.is_finite() && (lo..=hi).contains(&x)) {
                    return Err(format!("{name} is {x}, expected a number in [{lo}, {hi}]"));
                }
            }
            for (name, list) in [
                ("qpos", &env.qpos),
                ("qvel", &env.qvel),
                ("qacc_warmstart", &env.qacc_warmstart),
            ] {
                if let Some((i, x)) = list
                    .iter()
                    .enumerate()
                    .find(|(_, x)| !(x.is_finite() && x.abs() <= MAX_STATE_MAGNITUDE))
                {
                    return Err(format!(
                        "{name}[{i}] is {x}, expected a finite number within ±{MAX_STATE_MAGNITUDE}"
                    ));
                }
            }
            // The label a person reads must say what the state holds (the saver writes it from
            // the damage below): a label edited to "x" or "healthy" over a severe state is refused.
            let d = &saved.env.damage;
            let label = condition_label(d);
            if let Some(given) = &saved.condition
                && given != label
            {
                return Err(format!(
                    "condition: '{given}', but the state's damage says '{label}' (damage.condition \
                     {}, fatigue triggers {})",
                    d.condition.name(),
                    if d.fatigue_triggers { "on" } else { "off" }
                ));
            }
            if saved.format != STATE_FORMAT {
                return Err(format!(
                    "format '{}' (this gaitscope reads {STATE_FORMAT})",
                    saved.format
                ));
            }
            if let Some(w) = &saved.window {
                let entry = crate::window::ENTRY_DIM;
                if w.entries.len() > w.len {
                    return Err(format!(
                        "the window holds {} entries, more than its length {}",
                        w.entries.len(),
                        w.len
                    ));
                }
                if let Some(e) = w.entries.iter().find(|e| e.len() != entry) {
                    return Err(format!(
                        "a window entry has {} numbers, expected {entry}",
                        e.len()
                    ));
                }
                if w.entries.iter().flatten().any(|v| !v.is_finite()) {
                    return Err("the window holds a number that is not finite".into());
                }
            }
            StartState::Saved(Box::new(saved))
        } else {
            let bare: BareState = serde_json::from_value(value).map_err(|e| {
                format!(
                    "{e} (expected {{\"qpos\": [{NQ} numbers], \"qvel\": [{NV} numbers]}} or a saved state with \"format\": \"{STATE_FORMAT}\")"
                )
            })?;
            StartState::Bare {
                qpos: bare.qpos,
                qvel: bare.qvel,
            }
        };
        // Lengths and finiteness, as the env checks them, so a bad file fails before any step.
        let (qpos, qvel) = state.pose();
        for (name, v, n) in [("qpos", qpos, NQ), ("qvel", qvel, NV)] {
            if v.len() != n {
                return Err(format!("{name} has {} numbers, expected {n}", v.len()));
            }
            if let Some((i, x)) = v.iter().enumerate().find(|(_, x)| !x.is_finite()) {
                return Err(format!("{name}[{i}] is {x}, expected a finite number"));
            }
        }
        Ok(state)
    }

    pub fn pose(&self) -> (&[f64], &[f64]) {
        match self {
            StartState::Bare { qpos, qvel } => (qpos, qvel),
            StartState::Saved(s) => (&s.env.qpos, &s.env.qvel),
        }
    }

    /// The condition the state fixes (a saved state's), if any.
    pub fn condition(&self) -> Option<crate::damage::Condition> {
        match self {
            StartState::Bare { .. } => None,
            StartState::Saved(s) => Some(s.env.damage.condition),
        }
    }
}

/// The condition a state is labelled with, from its damage alone: the condition its fatigue
/// rule runs under, or "manual" where fatigue triggers nothing. The saver writes it; the reader
/// refuses a label that says otherwise.
fn condition_label(damage: &crate::damage::DamageSave) -> &'static str {
    if damage.fatigue_triggers {
        damage.condition.name()
    } else {
        "manual"
    }
}

impl Lane {
    /// This lane's state before its next step, as a file holds it: `actor` is who acts in it
    /// (a checkpoint is named in the file), `seed` the episode's.
    pub fn save_state(&self, actor: &super::Actor, seed: u64) -> SavedState {
        let checkpoint = actor.checkpoint_dir().map(|_| actor.label());
        let env = self.env.save();
        let window = &self.run.window;
        let entry = window.entry_dim();
        let all = window.as_slice();
        let first = window.len() - window.filled();
        let entries = all[first * entry..]
            .chunks(entry)
            .map(<[f32]>::to_vec)
            .collect();
        let key_name = format!("gaitscope-step-{}", env.step);
        let condition = condition_label(&env.damage).to_string();
        SavedState {
            format: STATE_FORMAT.to_string(),
            checkpoint,
            seed,
            condition: Some(condition),
            mjcf_key: SavedState::mjcf_key(&key_name, env.time, &env.qpos, &env.qvel),
            env,
            window: Some(SavedWindow {
                len: window.len(),
                entries,
            }),
        }
    }

    /// Starts this lane's episode from `start` (after a [`Self::reset`], whose condition a bare
    /// state keeps). A saved window is restored when this model reads one of the same length;
    /// returns whether it was (a built-in policy or another model starts with an empty one).
    pub fn start_from(&mut self, start: &StartState) -> Result<bool, LaneError> {
        match start {
            StartState::Bare { qpos, qvel } => {
                let condition = self.env.damage().condition();
                self.reset_to_state(qpos, qvel, condition)?;
                Ok(false)
            }
            StartState::Saved(saved) => {
                self.run.obs = self.env.start_from_save(&saved.env)?;
                self.run.window.clear();
                self.run.rng = policy_rng(saved.seed);
                self.run.last = None;
                self.run.done = false;
                self.run.first_step = saved.env.step;
                let restored = match &saved.window {
                    Some(w) if w.len == self.run.window.len() => {
                        let obs_dim = crate::env::OBS_DIM;
                        for e in &w.entries {
                            let wide: Vec<f64> = e.iter().map(|&v| f64::from(v)).collect();
                            self.run.window.push(&wide[..obs_dim], &wide[obs_dim..]);
                        }
                        true
                    }
                    _ => false,
                };
                Ok(restored)
            }
        }
    }
}
