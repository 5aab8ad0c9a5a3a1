//! Contact-force fatigue (the paper's "DamageWrapper").
//!
//! Each actuator accumulates fatigue `f_i += α·|a_i| + β·‖cfrc_ext[body_i]‖₂` after every env step.
//! The first time `f_i ≥ τ` the actuator triggers, and from the next step on, for the rest of the
//! episode, its applied command is `s·a_i` where `s` is the episode's condition scale. A person
//! (the live viewer) may also override any joint at any step; overrides are events too.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

mod dead;
mod push;
pub mod scenario;
mod settings;

pub use dead::{DeadActuators, DeadCounts, DeadOnset, DeadUnit, MAX_DEAD_UNITS};
pub use push::{MAX_ACTIVE_PUSHES, MAX_PUSH_NEWTONS, MAX_PUSH_STEPS, Push, PushError, PushRecord};
pub use settings::{ConditionScales, DamageConfig};

/// Number of actuators in the Ant.
pub const N_ACTUATORS: usize = 8;

/// An episode's damage condition: the torque scale a triggered actuator is left with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Condition {
    Healthy,
    Mild,
    Severe,
}

impl Condition {
    pub const ALL: [Condition; 3] = [Condition::Healthy, Condition::Mild, Condition::Severe];

    pub fn scale(self, scales: &ConditionScales) -> f64 {
        match self {
            Condition::Healthy => scales.healthy,
            Condition::Mild => scales.mild,
            Condition::Severe => scales.severe,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Condition::Healthy => "healthy",
            Condition::Mild => "mild",
            Condition::Severe => "severe",
        }
    }

    /// Index in [`Condition::ALL`], used as a class label by the probes.
    pub fn index(self) -> usize {
        self as usize
    }
}

impl fmt::Display for Condition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Condition {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().as_str() {
            "healthy" => Ok(Condition::Healthy),
            "mild" => Ok(Condition::Mild),
            "severe" => Ok(Condition::Severe),
            other => Err(format!(
                "unknown condition '{other}' (expected healthy, mild or severe)"
            )),
        }
    }
}

/// How an episode's condition is chosen at reset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ConditionChoice {
    /// Uniform over healthy / mild / severe from the env's seeded RNG (domain randomisation).
    Random,
    Fixed(Condition),
}

/// A hand-made change to one joint, e.g. from the live viewer's panel.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", content = "value", rename_all = "snake_case")]
pub enum JointOverride {
    /// Pin the torque scale to this value (in [0, 1]) until healed.
    SetScale(f64),
    /// Trigger now, as if fatigue had reached the threshold.
    FailNow,
    /// Trigger now, left at this scale (in [0, 1]) instead of the condition's.
    FailTo(f64),
    /// Restore the joint: scale 1, not triggered, fatigue 0.
    Heal,
    /// Zero the fatigue accumulator; the triggered state is kept.
    ResetFatigue,
}

/// What happened to a joint.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum DamageEventKind {
    /// Fatigue reached the threshold.
    Trigger,
    /// A person changed the joint.
    Override { change: JointOverride },
    /// The world's dead-actuator draw killed the joint ([`DeadActuators`]): from this step on
    /// it keeps `scale` of its torque.
    Dead,
}

impl DamageEventKind {
    /// Whether the event is a joint's damage onset as the probes count it: a fatigue trigger or
    /// the world's killing it (a person's changes are not the world's damage).
    pub fn is_onset(&self) -> bool {
        matches!(self, DamageEventKind::Trigger | DamageEventKind::Dead)
    }
}

/// One entry of the damage log.
///
/// `step` is the env step the event belongs to: a trigger during step `t` has `step = t` (it
/// scales step `t + 1` onwards); an override issued before step `t` runs has `step = t` (it
/// scales step `t` onwards).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DamageEvent {
    pub step: usize,
    pub actuator: usize,
    pub joint: String,
    /// Fatigue of the actuator when the event happened.
    pub fatigue: f64,
    /// Torque scale in force from the next applied step.
    pub scale: f64,
    #[serde(flatten)]
    pub kind: DamageEventKind,
    /// The scenario that made the change (none for fatigue and hand-made changes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
}

impl DamageEvent {
    /// The event in words, the same everywhere it is shown (stream, page, panel):
    /// "ankle_3 triggered at fatigue 31.2; scale → 0.1", "hip_1 scale → 0.4 (manual)".
    pub fn describe(&self) -> String {
        let joint = &self.joint;
        let what = match &self.kind {
            DamageEventKind::Trigger => format!(
                "{joint} triggered at fatigue {:.1}; scale → {}",
                self.fatigue, self.scale
            ),
            DamageEventKind::Dead => format!("{joint} died; scale → {}", self.scale),
            DamageEventKind::Override { change } => match change {
                JointOverride::SetScale(s) => format!("{joint} scale → {s} (manual)"),
                JointOverride::FailNow | JointOverride::FailTo(_) => {
                    format!("{joint} failed by hand; scale → {}", self.scale)
                }
                JointOverride::Heal => format!("{joint} healed; scale → 1"),
                JointOverride::ResetFatigue => format!("{joint} fatigue reset to 0"),
            },
        };
        match &self.source {
            Some(scenario) => format!("scenario {scenario}: {what}"),
            None => what,
        }
    }
}

impl DamageEvent {
    /// Who made the change, in the views' words: fatigue, the world (a dead actuator), a
    /// scenario, or a hand (panel, page, API, fork).
    pub fn cause(&self) -> String {
        match (&self.source, &self.kind) {
            (Some(scenario), _) => format!("scenario {scenario}"),
            (None, DamageEventKind::Trigger) => "fatigue".into(),
            (None, DamageEventKind::Dead) => "the world".into(),
            (None, DamageEventKind::Override { .. }) => "manual".into(),
        }
    }
}

/// Per-joint state as the viewer shows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JointState {
    Healthy,
    Triggered,
    /// Scale pinned by hand.
    Manual,
    /// Killed by the world's dead-actuator draw.
    Dead,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DamageError {
    #[error(
        "actuator index {0} out of range (the Ant has {N_ACTUATORS} actuators, 0..{N_ACTUATORS})"
    )]
    NoSuchActuator(usize),
    #[error("torque scale {0} must be a finite number in [0, 1]")]
    BadScale(f64),
    #[error("fatigue {0} must be a finite number ≥ 0")]
    BadFatigue(f64),
    #[error("unknown joint '{name}' (the Ant's joints: {known}; or `all` for every joint)")]
    NoSuchJoint { name: String, known: String },
    #[error(
        "bad damage edit '{0}': expected none, heal:JOINT, fail:JOINT, fail:JOINT=S, scale:JOINT=S, \
         reset-fatigue:JOINT (JOINT a joint name, e.g. ankle_3, or all) or push:BODY=FX,FY,FZ[@N]"
    )]
    BadEdit(String),
}

/// The joints a [`DamageEdit`] changes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EditTarget {
    /// One joint, by name (`ankle_3`).
    Joint(String),
    All,
}

/// One change to the damage, wherever it comes from: the CLI (`fail:ankle_3`, `heal:all`,
/// `scale:ankle_3=0.1`, `reset-fatigue:hip_1`), a fork, the live panel.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DamageEdit {
    pub target: EditTarget,
    pub change: JointOverride,
}

impl EditTarget {
    /// The actuators this target names among `joint_names` (actuator order).
    pub fn resolve(&self, joint_names: &[String; N_ACTUATORS]) -> Result<Vec<usize>, DamageError> {
        match self {
            EditTarget::All => Ok((0..N_ACTUATORS).collect()),
            EditTarget::Joint(name) => match joint_names.iter().position(|j| j == name) {
                Some(i) => Ok(vec![i]),
                None => Err(DamageError::NoSuchJoint {
                    name: name.clone(),
                    known: joint_names.join(", "),
                }),
            },
        }
    }
}

impl DamageEdit {
    /// A comma-separated list of edits; `none` is the empty list.
    pub fn parse_list(text: &str) -> Result<Vec<DamageEdit>, DamageError> {
        if text.trim() == "none" {
            return Ok(Vec::new());
        }
        text.split(',').map(|e| e.trim().parse()).collect()
    }
}

impl FromStr for DamageEdit {
    type Err = DamageError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || DamageError::BadEdit(text.to_string());
        let (verb, rest) = text.split_once(':').ok_or_else(bad)?;
        let target = |name: &str| match name {
            "" => Err(bad()),
            // A list's pieces are split at commas before this: one left over is a stray value.
            name if name.contains(',') => Err(bad()),
            "all" => Ok(EditTarget::All),
            joint => Ok(EditTarget::Joint(joint.to_string())),
        };
        let (target, change) = match verb {
            "heal" => (target(rest)?, JointOverride::Heal),
            "fail" => match rest.split_once('=') {
                Some((joint, value)) => {
                    let s: f64 = value.trim().parse().map_err(|_| bad())?;
                    if !(s.is_finite() && (0.0..=1.0).contains(&s)) {
                        return Err(DamageError::BadScale(s));
                    }
                    (target(joint)?, JointOverride::FailTo(s))
                }
                None => (target(rest)?, JointOverride::FailNow),
            },
            "reset-fatigue" => (target(rest)?, JointOverride::ResetFatigue),
            "scale" => {
                let (joint, value) = rest.split_once('=').ok_or_else(bad)?;
                let s: f64 = value.trim().parse().map_err(|_| bad())?;
                if !(s.is_finite() && (0.0..=1.0).contains(&s)) {
                    return Err(DamageError::BadScale(s));
                }
                (target(joint)?, JointOverride::SetScale(s))
            }
            _ => return Err(bad()),
        };
        Ok(DamageEdit { target, change })
    }
}

impl fmt::Display for DamageEdit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let target = match &self.target {
            EditTarget::All => "all",
            EditTarget::Joint(j) => j.as_str(),
        };
        match self.change {
            JointOverride::Heal => write!(f, "heal:{target}"),
            JointOverride::FailNow => write!(f, "fail:{target}"),
            JointOverride::FailTo(s) => write!(f, "fail:{target}={s}"),
            JointOverride::ResetFatigue => write!(f, "reset-fatigue:{target}"),
            JointOverride::SetScale(s) => write!(f, "scale:{target}={s}"),
        }
    }
}

/// Anything a person, a fork or a scenario does to a running Ant before a step: a change to
/// joints' damage, or a push. Written as a comma-separated list on the command line
/// (`fail:ankle_3,push:torso=0,40,0@5`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Edit {
    Joint(DamageEdit),
    Push(Push),
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum EditError {
    #[error(transparent)]
    Joint(#[from] DamageError),
    #[error(transparent)]
    Push(#[from] PushError),
}

impl Edit {
    /// A comma-separated list of edits; `none` is the empty list. A push's force has commas of
    /// its own: a piece without a `verb:` continues the edit before it.
    pub fn parse_list(text: &str) -> Result<Vec<Edit>, EditError> {
        if text.trim() == "none" {
            return Ok(Vec::new());
        }
        let mut items: Vec<String> = Vec::new();
        for piece in text.split(',') {
            match items.last_mut() {
                Some(last) if !piece.contains(':') => {
                    last.push(',');
                    last.push_str(piece);
                }
                _ => items.push(piece.to_string()),
            }
        }
        items.iter().map(|e| e.parse()).collect()
    }
}

impl FromStr for Edit {
    type Err = EditError;
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let text = text.trim();
        if text.starts_with("push:") {
            Ok(Edit::Push(text.parse()?))
        } else {
            Ok(Edit::Joint(text.parse()?))
        }
    }
}

impl fmt::Display for Edit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Edit::Joint(e) => e.fmt(f),
            Edit::Push(p) => p.fmt(f),
        }
    }
}

impl From<DamageEdit> for Edit {
    fn from(e: DamageEdit) -> Self {
        Edit::Joint(e)
    }
}

/// The damage state between two steps, as a saved state file holds it (`--save-state-at`).
/// Events are history, not state: they are left out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DamageSave {
    pub condition: Condition,
    pub fatigue: [f64; N_ACTUATORS],
    pub triggered: [bool; N_ACTUATORS],
    /// Joints whose scale a person pinned (an override), kept when fatigue triggers them.
    pub manual: [bool; N_ACTUATORS],
    pub scale: [f64; N_ACTUATORS],
    pub fatigue_triggers: bool,
    /// Joints the world's dead-actuator draw killed (absent in states saved before that kind).
    #[serde(default, skip_serializing_if = "none_set")]
    pub dead: [bool; N_ACTUATORS],
}

fn none_set(flags: &[bool; N_ACTUATORS]) -> bool {
    flags.iter().all(|&f| !f)
}

/// Fatigue, triggers and torque scales of one episode.
#[derive(Debug, Clone)]
pub struct DamageState {
    config: DamageConfig,
    joint_names: [String; N_ACTUATORS],
    condition: Condition,
    fatigue: [f64; N_ACTUATORS],
    triggered: [bool; N_ACTUATORS],
    manual: [bool; N_ACTUATORS],
    /// Killed by the world's dead-actuator draw: fatigue triggers leave their scale alone.
    dead: [bool; N_ACTUATORS],
    scale: [f64; N_ACTUATORS],
    events: Vec<DamageEvent>,
    /// Whether fatigue reaching τ triggers a joint (off in the live viewer's manual condition,
    /// where only a person damages joints). Kept across resets.
    fatigue_triggers: bool,
}

impl DamageState {
    /// `joint_names[i]` names the joint actuator `i` drives (used in events).
    pub fn new(config: DamageConfig, joint_names: [String; N_ACTUATORS]) -> Self {
        Self {
            config,
            joint_names,
            condition: Condition::Healthy,
            fatigue: [0.0; N_ACTUATORS],
            triggered: [false; N_ACTUATORS],
            manual: [false; N_ACTUATORS],
            dead: [false; N_ACTUATORS],
            scale: [1.0; N_ACTUATORS],
            events: Vec::new(),
            fatigue_triggers: true,
        }
    }

    /// Turns fatigue triggers on or off; fatigue still accumulates either way.
    pub fn set_fatigue_triggers(&mut self, on: bool) {
        self.fatigue_triggers = on;
    }

    pub fn fatigue_triggers(&self) -> bool {
        self.fatigue_triggers
    }

    /// Starts a new episode under `condition`: no fatigue, no triggers, full torque.
    pub fn reset(&mut self, condition: Condition) {
        self.condition = condition;
        self.fatigue = [0.0; N_ACTUATORS];
        self.triggered = [false; N_ACTUATORS];
        self.manual = [false; N_ACTUATORS];
        self.dead = [false; N_ACTUATORS];
        self.scale = [1.0; N_ACTUATORS];
        self.events.clear();
    }

    /// The state to save (see [`DamageSave`]).
    pub fn save(&self) -> DamageSave {
        DamageSave {
            condition: self.condition,
            fatigue: self.fatigue,
            triggered: self.triggered,
            manual: self.manual,
            scale: self.scale,
            fatigue_triggers: self.fatigue_triggers,
            dead: self.dead,
        }
    }

    /// Starts from a saved state (no events yet); scales and fatigue are checked.
    pub fn restore_save(&mut self, saved: &DamageSave) -> Result<(), DamageError> {
        if let Some(&s) = saved
            .scale
            .iter()
            .find(|s| !(s.is_finite() && (0.0..=1.0).contains(*s)))
        {
            return Err(DamageError::BadScale(s));
        }
        if let Some(&f) = saved
            .fatigue
            .iter()
            .find(|f| !(f.is_finite() && **f >= 0.0))
        {
            return Err(DamageError::BadFatigue(f));
        }
        self.reset(saved.condition);
        self.fatigue = saved.fatigue;
        self.triggered = saved.triggered;
        self.manual = saved.manual;
        self.scale = saved.scale;
        self.fatigue_triggers = saved.fatigue_triggers;
        self.dead = saved.dead;
        Ok(())
    }

    /// The command each actuator actually receives for a commanded action.
    pub fn applied_action(&self, commanded: &[f64; N_ACTUATORS]) -> [f64; N_ACTUATORS] {
        std::array::from_fn(|i| self.scale[i] * commanded[i])
    }

    /// Adds one env step's fatigue and triggers the actuators that reach the threshold.
    /// `contact_norms[i]` is ‖cfrc_ext‖₂ of the body actuator `i` drives. Returns how many
    /// actuators triggered on this step (their events are the last ones in [`Self::events`]).
    pub fn accumulate(
        &mut self,
        step: usize,
        commanded: &[f64; N_ACTUATORS],
        contact_norms: &[f64; N_ACTUATORS],
    ) -> usize {
        let (alpha, beta, threshold) = (self.config.alpha, self.config.beta, self.config.threshold);
        let mut new_triggers = 0;
        for i in 0..N_ACTUATORS {
            self.fatigue[i] += alpha * commanded[i].abs() + beta * contact_norms[i];
            if self.fatigue_triggers && !self.triggered[i] && self.fatigue[i] >= threshold {
                self.triggered[i] = true;
                if !self.manual[i] && !self.dead[i] {
                    self.scale[i] = self.condition.scale(&self.config.scales);
                }
                self.push_event(step, i, DamageEventKind::Trigger);
                new_triggers += 1;
            }
        }
        new_triggers
    }

    /// Applies a hand-made change before env step `step` runs; it scales that step onwards.
    pub fn apply_override(
        &mut self,
        step: usize,
        actuator: usize,
        change: JointOverride,
    ) -> Result<(), DamageError> {
        self.apply_change(step, actuator, change, None)
    }

    /// Applies a change before env step `step` runs, from `source` (a scenario's name) or by
    /// hand (`None`).
    pub fn apply_change(
        &mut self,
        step: usize,
        actuator: usize,
        change: JointOverride,
        source: Option<&str>,
    ) -> Result<(), DamageError> {
        if actuator >= N_ACTUATORS {
            return Err(DamageError::NoSuchActuator(actuator));
        }
        match change {
            JointOverride::SetScale(s) => {
                if !(s.is_finite() && (0.0..=1.0).contains(&s)) {
                    return Err(DamageError::BadScale(s));
                }
                self.manual[actuator] = true;
                self.dead[actuator] = false;
                self.scale[actuator] = s;
            }
            JointOverride::FailNow => {
                self.triggered[actuator] = true;
                if !self.manual[actuator] && !self.dead[actuator] {
                    self.scale[actuator] = self.condition.scale(&self.config.scales);
                }
            }
            JointOverride::FailTo(s) => {
                if !(s.is_finite() && (0.0..=1.0).contains(&s)) {
                    return Err(DamageError::BadScale(s));
                }
                self.triggered[actuator] = true;
                self.manual[actuator] = false;
                self.dead[actuator] = false;
                self.scale[actuator] = s;
            }
            JointOverride::Heal => {
                self.triggered[actuator] = false;
                self.manual[actuator] = false;
                self.dead[actuator] = false;
                self.scale[actuator] = 1.0;
                self.fatigue[actuator] = 0.0;
            }
            JointOverride::ResetFatigue => self.fatigue[actuator] = 0.0,
        }
        self.push_event(step, actuator, DamageEventKind::Override { change });
        if let Some(e) = self.events.last_mut() {
            e.source = source.map(str::to_string);
        }
        Ok(())
    }

    /// Kills an actuator before env step `step` runs (the world's dead-actuator draw): it keeps
    /// `scale` of its torque from that step on, whatever fatigue does; only a person's edit
    /// (heal, a new scale) revives it.
    pub fn kill(&mut self, step: usize, actuator: usize, scale: f64) -> Result<(), DamageError> {
        if actuator >= N_ACTUATORS {
            return Err(DamageError::NoSuchActuator(actuator));
        }
        if !(scale.is_finite() && (0.0..=1.0).contains(&scale)) {
            return Err(DamageError::BadScale(scale));
        }
        // Triggered too: whatever reads "this joint lost torque" (probe labels, the record's
        // damaged joints) reads a death as it reads a fatigue trigger.
        self.dead[actuator] = true;
        self.triggered[actuator] = true;
        self.manual[actuator] = false;
        self.scale[actuator] = scale;
        self.push_event(step, actuator, DamageEventKind::Dead);
        Ok(())
    }

    /// The actuators an edit's target names.
    pub fn resolve(&self, target: &EditTarget) -> Result<Vec<usize>, DamageError> {
        target.resolve(&self.joint_names)
    }

    /// Applies an edit before env step `step` runs (each joint it changes is one event).
    pub fn apply_edit(&mut self, step: usize, edit: &DamageEdit) -> Result<(), DamageError> {
        for actuator in self.resolve(&edit.target)? {
            self.apply_override(step, actuator, edit.change)?;
        }
        Ok(())
    }

    fn push_event(&mut self, step: usize, actuator: usize, kind: DamageEventKind) {
        self.events.push(DamageEvent {
            step,
            actuator,
            joint: self.joint_names[actuator].clone(),
            fatigue: self.fatigue[actuator],
            scale: self.scale[actuator],
            kind,
            source: None,
        });
    }

    pub fn condition(&self) -> Condition {
        self.condition
    }
    pub fn config(&self) -> &DamageConfig {
        &self.config
    }
    pub fn joint_names(&self) -> &[String; N_ACTUATORS] {
        &self.joint_names
    }
    pub fn fatigue(&self) -> &[f64; N_ACTUATORS] {
        &self.fatigue
    }
    pub fn triggered(&self) -> &[bool; N_ACTUATORS] {
        &self.triggered
    }
    /// Torque scale each actuator will apply on the next step.
    pub fn scale(&self) -> &[f64; N_ACTUATORS] {
        &self.scale
    }
    pub fn events(&self) -> &[DamageEvent] {
        &self.events
    }
    pub fn n_triggered(&self) -> usize {
        self.triggered.iter().filter(|&&t| t).count()
    }
    /// Who last changed each joint's torque ([`DamageEvent::cause`]), none if nothing did.
    pub fn causes(&self) -> [Option<String>; N_ACTUATORS] {
        std::array::from_fn(|i| {
            self.events
                .iter()
                .rev()
                .find(|e| e.actuator == i)
                .map(DamageEvent::cause)
        })
    }

    /// Joints the world's dead-actuator draw killed (and no person revived).
    pub fn dead(&self) -> &[bool; N_ACTUATORS] {
        &self.dead
    }
    pub fn joint_state(&self, actuator: usize) -> JointState {
        if self.dead[actuator] {
            JointState::Dead
        } else if self.manual[actuator] && !self.pinned_by_scenario(actuator) {
            JointState::Manual
        } else if self.triggered[actuator] || self.manual[actuator] {
            JointState::Triggered
        } else {
            JointState::Healthy
        }
    }
    /// Whether the joint's pin came from a scenario (scripted damage, shown by its torque like
    /// a trigger) rather than a hand: its latest change says so.
    fn pinned_by_scenario(&self, actuator: usize) -> bool {
        self.events
            .iter()
            .rev()
            .find(|e| e.actuator == actuator && matches!(e.kind, DamageEventKind::Override { .. }))
            .is_some_and(|e| e.source.is_some())
    }

    /// The first step run under damage, if any: the step after the first fatigue trigger (a
    /// trigger during step `t` scales `t + 1` on, under every condition, healthy's 1.0
    /// included), or the step from which a scenario or a person first failed or weakened a
    /// joint. Scenario damage never triggers (`ood` turns fatigue off), so this, not
    /// [`Self::first_trigger_steps`], says when an `ood` episode began under damage.
    pub fn damage_onset(&self) -> Option<usize> {
        self.events
            .iter()
            .filter_map(|e| match e.kind {
                DamageEventKind::Trigger => Some(e.step + 1),
                DamageEventKind::Dead => Some(e.step),
                DamageEventKind::Override {
                    change: JointOverride::FailNow | JointOverride::FailTo(_),
                } => Some(e.step),
                DamageEventKind::Override { .. } => (e.scale < 1.0).then_some(e.step),
            })
            .min()
    }

    /// Step from which each actuator ran dead (the world's dead-actuator draw), if it died.
    pub fn dead_steps(&self) -> [Option<usize>; N_ACTUATORS] {
        let mut steps = [None; N_ACTUATORS];
        for e in &self.events {
            if e.kind == DamageEventKind::Dead && steps[e.actuator].is_none() {
                steps[e.actuator] = Some(e.step);
            }
        }
        steps
    }

    /// Step at which each actuator first triggered by fatigue, if it did.
    pub fn first_trigger_steps(&self) -> [Option<usize>; N_ACTUATORS] {
        self.first_steps(|kind| *kind == DamageEventKind::Trigger)
    }

    /// Each joint's damage onset: its first fatigue trigger or the world's killing it,
    /// whichever came first — where the probes time detection from in every world (a world
    /// of dead actuators has no fatigue triggers).
    pub fn first_onset_steps(&self) -> [Option<usize>; N_ACTUATORS] {
        self.first_steps(DamageEventKind::is_onset)
    }

    fn first_steps(
        &self,
        counts: impl Fn(&DamageEventKind) -> bool,
    ) -> [Option<usize>; N_ACTUATORS] {
        let mut steps = [None; N_ACTUATORS];
        for e in &self.events {
            if counts(&e.kind) && steps[e.actuator].is_none() {
                steps[e.actuator] = Some(e.step);
            }
        }
        steps
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edit_lists_mix_joint_edits_and_pushes() {
        let edits = Edit::parse_list("fail:ankle_3, push:torso=0,40,0@5,heal:all,push:aux_1=1,2,3")
            .unwrap();
        let text: Vec<String> = edits.iter().map(Edit::to_string).collect();
        assert_eq!(
            text,
            [
                "fail:ankle_3",
                "push:torso=0,40,0@5",
                "heal:all",
                "push:aux_1=1,2,3"
            ]
        );
        assert_eq!(Edit::parse_list(" none ").unwrap(), []);
        assert!(matches!(
            Edit::parse_list("push:torso=0,40"),
            Err(EditError::Push(PushError::Syntax(_)))
        ));
        assert!(matches!(
            Edit::parse_list("fail:ankle_3,1,2"),
            Err(EditError::Joint(DamageError::BadEdit(_)))
        ));
        assert!(matches!(
            Edit::parse_list("push:torso=NaN,0,0"),
            Err(EditError::Push(PushError::NotFinite(_)))
        ));
    }

    #[test]
    fn damage_edits_parse_print_and_resolve() {
        let edits = DamageEdit::parse_list("heal:all, fail:ankle_3,scale:hip_1=0.25").unwrap();
        assert_eq!(
            edits,
            [
                DamageEdit {
                    target: EditTarget::All,
                    change: JointOverride::Heal
                },
                DamageEdit {
                    target: EditTarget::Joint("ankle_3".into()),
                    change: JointOverride::FailNow
                },
                DamageEdit {
                    target: EditTarget::Joint("hip_1".into()),
                    change: JointOverride::SetScale(0.25)
                },
            ]
        );
        let printed: Vec<String> = edits.iter().map(ToString::to_string).collect();
        assert_eq!(printed, ["heal:all", "fail:ankle_3", "scale:hip_1=0.25"]);
        assert_eq!(DamageEdit::parse_list("none").unwrap(), []);
        for bad in [
            "",
            "heal",
            "heal:",
            "scale:hip_1",
            "scale:hip_1=x",
            "melt:hip_1",
        ] {
            assert!(
                matches!(bad.parse::<DamageEdit>(), Err(DamageError::BadEdit(_))),
                "{bad}"
            );
        }
        assert_eq!(
            "scale:all=2".parse::<DamageEdit>(),
            Err(DamageError::BadScale(2.0))
        );
        let names = std::array::from_fn(|i| format!("j{i}"));
        let mut d = DamageState::new(DamageConfig::default(), names);
        d.reset(Condition::Severe);
        assert_eq!(d.resolve(&EditTarget::Joint("j3".into())), Ok(vec![3]));
        assert_eq!(d.resolve(&EditTarget::All).unwrap().len(), N_ACTUATORS);
        assert!(matches!(
            d.resolve(&EditTarget::Joint("ankle_9".into())),
            Err(DamageError::NoSuchJoint { .. })
        ));
        // "all" is one edit and eight events, one per joint.
        d.apply_edit(4, &"fail:all".parse().unwrap()).unwrap();
        assert!(d.triggered().iter().all(|&t| t));
        assert_eq!(d.events().len(), N_ACTUATORS);
    }

    fn state(condition: Condition) -> DamageState {
        let names = std::array::from_fn(|i| format!("j{i}"));
        let mut d = DamageState::new(DamageConfig::default(), names);
        d.reset(condition);
        d
    }

    #[test]
    fn fatigue_is_alpha_abs_action_plus_beta_force() {
        let mut d = state(Condition::Mild);
        let a = [0.5, -0.5, 1.0, 0.0, -1.0, 0.25, 0.0, 0.0];
        let f = [10.0, 0.0, 0.0, 20.0, 0.0, 0.0, 0.0, 0.0];
        d.accumulate(0, &a, &f);
        // α = 1, β = 0.1: 0.5 + 1.0, 0.5, 1.0, 2.0, 1.0, 0.25, 0, 0
        assert_eq!(d.fatigue(), &[1.5, 0.5, 1.0, 2.0, 1.0, 0.25, 0.0, 0.0]);
    }

    #[test]
    fn trigger_at_threshold_scales_from_next_step_and_persists() {
        let mut d = state(Condition::Severe);
        let a = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let none = [0.0; N_ACTUATORS];
        // 29 steps of |a| = 1 → fatigue 29 < 30: nothing yet.
        for t in 0..29 {
            assert_eq!(d.accumulate(t, &a, &none), 0);
        }
        assert_eq!(d.applied_action(&a)[0], 1.0);
        // Step 29 reaches exactly 30 = τ: triggers ("reaches" includes equality).
        assert_eq!(d.accumulate(29, &a, &none), 1);
        assert_eq!(d.applied_action(&a)[0], 0.1);
        assert_eq!(d.events()[0].step, 29);
        assert_eq!(d.events()[0].fatigue, 30.0);
        assert_eq!(d.first_trigger_steps()[0], Some(29));
        assert_eq!(d.damage_onset(), Some(30));
        // Persists and does not re-trigger.
        for t in 30..100 {
            assert_eq!(d.accumulate(t, &a, &none), 0);
        }
        assert!(d.triggered()[0]);
        assert_eq!(d.events().len(), 1);
        // A new episode starts clean.
        d.reset(Condition::Healthy);
        assert_eq!(d.n_triggered(), 0);
        assert!(d.events().is_empty());
    }

    #[test]
    fn damage_onset_is_the_first_step_run_under_damage() {
        let mut d = state(Condition::Mild);
        assert_eq!(d.damage_onset(), None);
        // Neither a scale of 1 nor a heal weakens anything.
        d.apply_override(2, 1, JointOverride::SetScale(1.0))
            .unwrap();
        d.apply_override(3, 1, JointOverride::Heal).unwrap();
        assert_eq!(d.damage_onset(), None);
        // A scenario's weak joint counts from the step it was set before (`ood` never triggers).
        d.apply_override(7, 4, JointOverride::SetScale(0.3))
            .unwrap();
        assert_eq!(d.damage_onset(), Some(7));
        // A failure by hand counts even at the healthy condition's scale of 1, as a trigger does.
        let mut h = state(Condition::Healthy);
        h.apply_override(5, 0, JointOverride::FailNow).unwrap();
        assert_eq!(h.damage_onset(), Some(5));
    }

    #[test]
    fn dead_steps_are_the_steps_the_world_killed_each_actuator() {
        let mut d = state(Condition::Severe);
        // A failure by hand is not a death by the world's draw.
        d.apply_override(2, 1, JointOverride::FailNow).unwrap();
        d.kill(10, 4, 0.0).unwrap();
        d.kill(10, 5, 0.0).unwrap();
        d.kill(40, 0, 0.0).unwrap();
        let mut want = [None; N_ACTUATORS];
        want[4] = Some(10);
        want[5] = Some(10);
        want[0] = Some(40);
        assert_eq!(d.dead_steps(), want);
        assert_eq!(d.damage_onset(), Some(2));
    }

    #[test]
    fn overrides_apply_and_are_logged() {
        let mut d = state(Condition::Mild);
        let a = [1.0; N_ACTUATORS];
        d.apply_override(3, 2, JointOverride::FailNow).unwrap();
        assert_eq!(d.applied_action(&a)[2], 0.5);
        assert_eq!(d.joint_state(2), JointState::Triggered);
        d.apply_override(4, 5, JointOverride::SetScale(0.25))
            .unwrap();
        assert_eq!(d.applied_action(&a)[5], 0.25);
        assert_eq!(d.joint_state(5), JointState::Manual);
        // A manual scale wins over a later fatigue trigger.
        d.accumulate(4, &[0.0; N_ACTUATORS], &[400.0; N_ACTUATORS]);
        assert_eq!(d.applied_action(&a)[5], 0.25);
        assert_eq!(d.applied_action(&a)[0], 0.5);
        d.apply_override(5, 5, JointOverride::Heal).unwrap();
        assert_eq!((d.applied_action(&a)[5], d.fatigue()[5]), (1.0, 0.0));
        assert_eq!(d.joint_state(5), JointState::Healthy);
        d.apply_override(5, 0, JointOverride::ResetFatigue).unwrap();
        assert_eq!(d.fatigue()[0], 0.0);
        assert!(d.triggered()[0], "reset fatigue keeps the trigger");
        let overrides = d
            .events()
            .iter()
            .filter(|e| matches!(e.kind, DamageEventKind::Override { .. }))
            .count();
        assert_eq!(overrides, 4);
        assert_eq!(
            d.apply_override(0, 8, JointOverride::Heal),
            Err(DamageError::NoSuchActuator(8))
        );
        assert_eq!(
            d.apply_override(0, 1, JointOverride::SetScale(f64::NAN))
                .unwrap_err()
                .to_string(),
            "torque scale NaN must be a finite number in [0, 1]"
        );
    }

    #[test]
    fn fatigue_triggers_can_be_switched_off() {
        let mut d = state(Condition::Severe);
        d.set_fatigue_triggers(false);
        let a = [1.0; N_ACTUATORS];
        // 40 steps of |a| = 1: fatigue 40 > τ = 30, but nothing triggers.
        for t in 0..40 {
            assert_eq!(d.accumulate(t, &a, &[0.0; N_ACTUATORS]), 0);
        }
        assert_eq!(d.fatigue()[0], 40.0);
        assert_eq!(d.applied_action(&a), a);
        // A person still can: fail-now uses the condition's scale.
        d.apply_override(40, 3, JointOverride::FailNow).unwrap();
        assert_eq!(d.applied_action(&a)[3], 0.1);
        // The setting survives a reset; the next step past τ does not trigger either.
        d.reset(Condition::Severe);
        assert!(!d.fatigue_triggers());
    }

    #[test]
    fn condition_parses_and_names() {
        assert_eq!("Severe".parse::<Condition>(), Ok(Condition::Severe));
        assert!(
            "broken"
                .parse::<Condition>()
                .unwrap_err()
                .contains("healthy, mild or severe")
        );
        assert_eq!(Condition::Mild.scale(&ConditionScales::default()), 0.5);
    }
}
