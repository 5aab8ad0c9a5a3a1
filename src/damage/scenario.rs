//! Damage scenarios: a written-down schedule of damage for an episode — timed edits, ramps,
//! intermittent faults, seeded random choices of which joint or leg — and whether the fatigue
//! rule stays on. One file format (JSON, docs/scenarios.md) for eval, record, rollout and live;
//! the env applies a scenario's edits before the steps they shape, each one a damage event
//! labelled with the scenario's name.
//!
//! ```json
//! {"name": "locked-ankle", "fatigue": false,
//!  "edits": [{"step": 0, "joint": "ankle_3", "scale": 0.1}]}
//! ```

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;

use super::{Condition, DamageEvent, DamageEventKind, JointOverride, Push};

/// The built-in out-of-distribution suite (`--suite ood`): damage the training distribution
/// (fatigue, all joints at one scale) never shows.
pub const OOD_SUITE: [(&str, &str); 7] = [
    ("ood-ankle", include_str!("../../scenarios/ood-ankle.json")),
    ("ood-leg", include_str!("../../scenarios/ood-leg.json")),
    (
        "ood-diagonal",
        include_str!("../../scenarios/ood-diagonal.json"),
    ),
    ("ood-decay", include_str!("../../scenarios/ood-decay.json")),
    (
        "ood-intermittent",
        include_str!("../../scenarios/ood-intermittent.json"),
    ),
    ("ood-sides", include_str!("../../scenarios/ood-sides.json")),
    (
        "ood-late-fault",
        include_str!("../../scenarios/ood-late-fault.json"),
    ),
];

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScenarioError {
    #[error("cannot read scenario file {path}: {reason}")]
    Read { path: String, reason: String },
    #[error("scenario {origin}: {reason}")]
    Invalid { origin: String, reason: String },
    #[error("unknown suite '{0}' (the built-in suite is ood)")]
    UnknownSuite(String),
}

/// A scenario file's size, at most (the built-in ones are under 1 KB; `/dev/zero` is refused).
pub const MAX_SCENARIO_BYTES: usize = 1 << 20;
/// Edits in one scenario, at most.
pub const MAX_SCENARIO_EDITS: usize = 10_000;

/// Parses JSON, refusing an object key given twice at any depth (serde_json keeps the last one
/// silently): scenarios and saved states both read through it.
pub fn strict_json(text: &str) -> Result<Value, serde_json::Error> {
    serde_json::from_str::<StrictValue>(text).map(|v| v.0)
}

/// A JSON value that refuses duplicate object keys.
struct StrictValue(Value);

impl<'de> serde::Deserialize<'de> for StrictValue {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = StrictValue;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("JSON")
            }
            fn visit_bool<E>(self, v: bool) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::Bool(v)))
            }
            fn visit_i64<E>(self, v: i64) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::from(v)))
            }
            fn visit_u64<E>(self, v: u64) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::from(v)))
            }
            fn visit_f64<E>(self, v: f64) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::from(v)))
            }
            fn visit_str<E>(self, v: &str) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::String(v.to_string())))
            }
            fn visit_string<E>(self, v: String) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::String(v)))
            }
            fn visit_unit<E>(self) -> Result<StrictValue, E> {
                Ok(StrictValue(Value::Null))
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<StrictValue, A::Error> {
                let mut items = Vec::new();
                while let Some(StrictValue(v)) = seq.next_element()? {
                    items.push(v);
                }
                Ok(StrictValue(Value::Array(items)))
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut map: A,
            ) -> Result<StrictValue, A::Error> {
                let mut object = serde_json::Map::new();
                while let Some(key) = map.next_key::<String>()? {
                    if object.contains_key(&key) {
                        return Err(serde::de::Error::custom(format!("duplicate key \"{key}\"")));
                    }
                    let StrictValue(v) = map.next_value()?;
                    object.insert(key, v);
                }
                Ok(StrictValue(Value::Object(object)))
            }
        }
        d.deserialize_any(Visitor)
    }
}

/// Whether the world's own damage — the fatigue rule, and a dead world's drawn deaths — runs
/// during a scenario (the file's `fatigue` field).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FatigueRule {
    /// No fatigue triggers and no drawn deaths: only the scenario damages joints.
    Off,
    /// The world's damage as in training, under the episode's condition.
    On,
    /// The world's damage, under this condition whatever the episode's.
    OnWith(Condition),
}

/// When an edit first applies: a step, or a step drawn per episode from [a, b].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(untagged)]
pub enum StepSpec {
    At(usize),
    Between(usize, usize),
}

/// Which joints an edit hits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Target {
    /// A joint (`ankle_3`), a leg (`back_leg`: its two joints) or `all`.
    Named(String),
    /// One member of a set, drawn per episode (the same draw for every edit naming the set).
    Pick(String),
}

/// What an edit does to its joints.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Change {
    /// Pin the scale from the step on.
    Scale(f64),
    /// Trigger the joints now, left at this scale.
    Fail(f64),
    Heal,
    ResetFatigue,
    /// The scale moves linearly from `from` (at the edit's step) to `to` (at `until`), then stays.
    Ramp {
        from: f64,
        to: f64,
        until: usize,
    },
    /// The scale alternates between `scales[0]` and `scales[1]`, `period` steps each, from the
    /// edit's step (until `until`, if given).
    Intermittent {
        scales: [f64; 2],
        period: usize,
        until: Option<usize>,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub struct ScheduledEdit {
    pub step: StepSpec,
    pub target: Target,
    pub change: Change,
}

/// A push at a step (`{"step": s, "push": {"body": "torso", "force": [fx, fy, fz], "steps": n}}`).
#[derive(Debug, Clone, PartialEq)]
pub struct ScheduledPush {
    pub step: StepSpec,
    pub push: Push,
}

/// A damage scenario (parsed and checked; see the module docs for the format).
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub name: String,
    pub description: String,
    pub fatigue: FatigueRule,
    /// Named sets for `pick`, beyond the built-in ones: each member a joint, a leg or a
    /// `+`-joined group (`front_left_leg+back_leg`).
    pub sets: BTreeMap<String, Vec<String>>,
    pub edits: Vec<ScheduledEdit>,
    pub pushes: Vec<ScheduledPush>,
    /// The JSON it was read from (what a checkpoint or report records).
    pub source: Value,
}

impl Serialize for Scenario {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        self.source.serialize(serializer)
    }
}

impl<'de> Deserialize<'de> for Scenario {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let value = Value::deserialize(deserializer)?;
        Scenario::from_json(&value.to_string(), "in the config").map_err(serde::de::Error::custom)
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawScenario {
    name: String,
    #[serde(default)]
    description: String,
    #[serde(default = "fatigue_on")]
    fatigue: Value,
    #[serde(default)]
    sets: BTreeMap<String, Vec<String>>,
    #[serde(default)]
    edits: Vec<RawEdit>,
}

fn fatigue_on() -> Value {
    Value::Bool(true)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEdit {
    step: Value,
    joint: Option<String>,
    pick: Option<String>,
    scale: Option<f64>,
    fail: Option<f64>,
    heal: Option<bool>,
    reset_fatigue: Option<bool>,
    /// [from, to], with `until`.
    ramp: Option<[f64; 2]>,
    intermittent: Option<RawIntermittent>,
    until: Option<i64>,
    push: Option<RawPush>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPush {
    body: String,
    force: [f64; 3],
    #[serde(default = "one_step")]
    steps: i64,
}

fn one_step() -> i64 {
    1
}

/// One entry of a scenario's `edits`: a change to joints, or a push.
enum Scheduled {
    Edit(ScheduledEdit),
    Push(ScheduledPush),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawIntermittent {
    scales: [f64; 2],
    period: i64,
}

fn check_scale(field: &str, s: f64) -> Result<f64, String> {
    if s.is_finite() && (0.0..=1.0).contains(&s) {
        Ok(s)
    } else {
        Err(format!("{field}: {s} is outside [0, 1]"))
    }
}

fn check_step(field: &str, v: i64) -> Result<usize, String> {
    usize::try_from(v).map_err(|_| format!("{field}: {v} is negative (steps count from 0)"))
}

fn parse_step(field: &str, v: &Value) -> Result<StepSpec, String> {
    let int = |v: &Value| -> Result<usize, String> {
        match v.as_i64() {
            Some(n) => check_step(field, n),
            None => Err(format!(
                "{field}: {v} is not a whole number of steps (or a [first, last] range)"
            )),
        }
    };
    match v {
        Value::Array(range) if range.len() == 2 => {
            let (a, b) = (int(&range[0])?, int(&range[1])?);
            if a > b {
                return Err(format!("{field}: the range [{a}, {b}] is empty"));
            }
            Ok(StepSpec::Between(a, b))
        }
        v => Ok(StepSpec::At(int(v)?)),
    }
}

impl RawEdit {
    fn parse(self, i: usize) -> Result<Scheduled, String> {
        let at = |f: &str| format!("edits[{i}].{f}");
        let step = parse_step(&at("step"), &self.step)?;
        if let Some(raw) = self.push {
            let others = self.joint.is_some()
                || self.pick.is_some()
                || self.scale.is_some()
                || self.fail.is_some()
                || self.heal.is_some()
                || self.reset_fatigue.is_some()
                || self.ramp.is_some()
                || self.intermittent.is_some()
                || self.until.is_some();
            if others {
                return Err(format!(
                    "edits[{i}]: a push stands alone (no joint, pick or damage change beside it)"
                ));
            }
            let steps = usize::try_from(raw.steps).unwrap_or(0);
            let push = Push::new(&raw.body, raw.force, steps)
                .map_err(|e| format!("{}: {e}", at("push")))?;
            return Ok(Scheduled::Push(ScheduledPush { step, push }));
        }
        let target = match (self.joint, self.pick) {
            (Some(j), None) => Target::Named(j),
            (None, Some(p)) => Target::Pick(p),
            (Some(_), Some(_)) => {
                return Err(format!("edits[{i}]: give `joint` or `pick`, not both"));
            }
            (None, None) => {
                return Err(format!(
                    "edits[{i}]: no target (`joint`: a joint, a leg or all; or `pick`: a set)"
                ));
            }
        };
        let until = self
            .until
            .map(|u| check_step(&at("until"), u))
            .transpose()?;
        let mut changes = Vec::new();
        if let Some(s) = self.scale {
            changes.push(Change::Scale(check_scale(&at("scale"), s)?));
        }
        if let Some(s) = self.fail {
            changes.push(Change::Fail(check_scale(&at("fail"), s)?));
        }
        if self.heal == Some(true) {
            changes.push(Change::Heal);
        }
        if self.reset_fatigue == Some(true) {
            changes.push(Change::ResetFatigue);
        }
        if let Some([from, to]) = self.ramp {
            let from = check_scale(&at("ramp[0]"), from)?;
            let to = check_scale(&at("ramp[1]"), to)?;
            let Some(until) = until else {
                return Err(format!(
                    "{}: a ramp needs `until` (its last step)",
                    at("ramp")
                ));
            };
            let StepSpec::At(start) = step else {
                return Err(format!("{}: a ramp starts at a fixed step", at("step")));
            };
            if until <= start {
                return Err(format!(
                    "{}: {until} must come after the ramp's first step {start}",
                    at("until")
                ));
            }
            changes.push(Change::Ramp { from, to, until });
        }
        if let Some(raw) = self.intermittent {
            let a = check_scale(&at("intermittent.scales[0]"), raw.scales[0])?;
            let b = check_scale(&at("intermittent.scales[1]"), raw.scales[1])?;
            let period = match usize::try_from(raw.period) {
                Ok(p) if p >= 1 => p,
                _ => {
                    return Err(format!(
                        "{}: {} must be at least 1 step",
                        at("intermittent.period"),
                        raw.period
                    ));
                }
            };
            changes.push(Change::Intermittent {
                scales: [a, b],
                period,
                until,
            });
        }
        match changes.as_slice() {
            [change] => {
                if until.is_some()
                    && !matches!(change, Change::Ramp { .. } | Change::Intermittent { .. })
                {
                    return Err(format!(
                        "{}: only ramps and intermittent faults end",
                        at("until")
                    ));
                }
                Ok(Scheduled::Edit(ScheduledEdit {
                    step,
                    target,
                    change: *change,
                }))
            }
            [] => Err(format!(
                "edits[{i}]: no change (one of scale, fail, heal, reset_fatigue, ramp, intermittent, push)"
            )),
            _ => Err(format!("edits[{i}]: one change per edit")),
        }
    }
}

impl Scenario {
    /// Parses scenario JSON; `origin` names it in errors (a path or a built-in name).
    pub fn from_json(text: &str, origin: &str) -> Result<Self, ScenarioError> {
        let invalid = |reason: String| ScenarioError::Invalid {
            origin: origin.to_string(),
            reason,
        };
        if text.len() > MAX_SCENARIO_BYTES {
            return Err(invalid(format!(
                "{} bytes, more than the {MAX_SCENARIO_BYTES} a scenario may have",
                text.len()
            )));
        }
        // Duplicate keys are refused (serde_json would keep the last one silently).
        let source = strict_json(text).map_err(|e| invalid(e.to_string()))?;
        let edit_count = source["edits"].as_array().map_or(0, Vec::len);
        if edit_count > MAX_SCENARIO_EDITS {
            return Err(invalid(format!(
                "{edit_count} edits, more than the {MAX_SCENARIO_EDITS} a scenario may have"
            )));
        }
        let raw: RawScenario =
            serde_json::from_value(source.clone()).map_err(|e| invalid(e.to_string()))?;
        if raw.name.trim().is_empty() {
            return Err(invalid("name: must not be empty".into()));
        }
        let fatigue = match &raw.fatigue {
            Value::Bool(false) => FatigueRule::Off,
            Value::Bool(true) => FatigueRule::On,
            Value::String(c) => FatigueRule::OnWith(
                c.parse()
                    .map_err(|e: String| invalid(format!("fatigue: {e}")))?,
            ),
            other => {
                return Err(invalid(format!(
                    "fatigue: {other} (expected true, false, or a condition: healthy, mild, severe)"
                )));
            }
        };
        let (mut edits, mut pushes) = (Vec::new(), Vec::new());
        for (i, e) in raw.edits.into_iter().enumerate() {
            match e.parse(i).map_err(invalid)? {
                Scheduled::Edit(e) => edits.push(e),
                Scheduled::Push(p) => pushes.push(p),
            }
        }
        Ok(Self {
            name: raw.name,
            description: raw.description,
            fatigue,
            sets: raw.sets,
            edits,
            pushes,
            source,
        })
    }

    /// A built-in scenario by name, or a file.
    pub fn load(name_or_path: &str) -> Result<Self, ScenarioError> {
        if let Some((name, text)) = OOD_SUITE.iter().find(|(n, _)| *n == name_or_path) {
            return Self::from_json(text, name);
        }
        let path = Path::new(name_or_path);
        // A regular file only (a FIFO would block), read no further than the bound.
        let text =
            crate::files::read_text_capped(path, MAX_SCENARIO_BYTES as u64).map_err(|e| {
                ScenarioError::Read {
                    path: name_or_path.to_string(),
                    reason: if path.extension().is_none() && !path.exists() {
                        format!(
                            "{e} (not a file, nor a built-in scenario: {})",
                            OOD_SUITE.map(|(n, _)| n).join(", ")
                        )
                    } else {
                        e.to_string()
                    },
                }
            })?;
        Self::from_json(&text, name_or_path)
    }

    /// The scenarios of a built-in suite.
    pub fn suite(name: &str) -> Result<Vec<Self>, ScenarioError> {
        match name {
            "ood" => OOD_SUITE
                .iter()
                .map(|(n, text)| Self::from_json(text, n))
                .collect(),
            other => Err(ScenarioError::UnknownSuite(other.to_string())),
        }
    }

    /// The scenario as JSON (what it was read from).
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(&self.source).unwrap_or_default()
    }

    /// Checks every joint, leg and set name against a model, so a typo fails before stepping.
    pub fn check(&self, joints: &JointMap) -> Result<(), ScenarioError> {
        for (i, edit) in self.edits.iter().enumerate() {
            let checked = match &edit.target {
                Target::Named(n) => joints.group(n).map(|_| ()),
                Target::Pick(set) => self.members(set, joints).map(|_| ()),
            };
            checked.map_err(|reason| ScenarioError::Invalid {
                origin: self.name.clone(),
                reason: format!("edits[{i}]: {reason}"),
            })?;
        }
        for p in &self.pushes {
            if !joints.bodies.contains(&p.push.body) {
                return Err(ScenarioError::Invalid {
                    origin: self.name.clone(),
                    reason: format!(
                        "push: unknown body '{}' (the model's bodies: {})",
                        p.push.body,
                        joints.bodies.join(", ")
                    ),
                });
            }
        }
        Ok(())
    }

    /// The alternatives a set offers, each a group of actuators.
    fn members(&self, set: &str, joints: &JointMap) -> Result<Vec<Vec<usize>>, String> {
        let custom = self.sets.get(set);
        let names: Vec<String> = match (custom, set) {
            (Some(members), _) => members.clone(),
            (None, "any_joint") => joints.joints.clone(),
            (None, "any_hip") => joints.joints_named("hip"),
            (None, "any_ankle") => joints.joints_named("ankle"),
            (None, "any_leg") => joints.legs.clone(),
            (None, "diagonal_legs") => joints.diagonals(),
            (None, other) => {
                return Err(format!(
                    "pick: unknown set '{other}' (built-in: any_joint, any_hip, any_ankle, any_leg, diagonal_legs; or define it under \"sets\")"
                ));
            }
        };
        if names.is_empty() {
            return Err(format!("pick: set '{set}' is empty"));
        }
        names.iter().map(|n| joints.group(n)).collect()
    }

    /// The concrete schedule of one episode: random steps and picks drawn from `seed`.
    pub fn plan(&self, seed: u64, joints: &JointMap) -> Result<ScenarioPlan, ScenarioError> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut picks: BTreeMap<String, Vec<usize>> = BTreeMap::new();
        let mut items = Vec::new();
        for (i, edit) in self.edits.iter().enumerate() {
            let actuators = match &edit.target {
                Target::Named(n) => joints.group(n),
                Target::Pick(set) => match picks.get(set) {
                    Some(group) => Ok(group.clone()),
                    None => self.members(set, joints).map(|members| {
                        let group = members[rng.random_range(0..members.len())].clone();
                        picks.insert(set.clone(), group.clone());
                        group
                    }),
                },
            }
            .map_err(|reason| ScenarioError::Invalid {
                origin: self.name.clone(),
                reason: format!("edits[{i}]: {reason}"),
            })?;
            let start = match edit.step {
                StepSpec::At(t) => t,
                StepSpec::Between(a, b) => rng.random_range(a..=b),
            };
            items.push(PlanItem {
                start,
                actuators,
                change: edit.change,
            });
        }
        // Pushes draw after every damage edit, so a push added to a file leaves its damage
        // schedule as it was.
        let pushes = self
            .pushes
            .iter()
            .map(|p| {
                let start = match p.step {
                    StepSpec::At(t) => t,
                    StepSpec::Between(a, b) => rng.random_range(a..=b),
                };
                (start, p.push.clone())
            })
            .collect();
        Ok(ScenarioPlan {
            name: self.name.clone(),
            items,
            pushes,
        })
    }
}

/// Names a model's joints and legs, for resolving scenario targets.
#[derive(Debug, Clone)]
pub struct JointMap {
    pub joints: Vec<String>,
    pub legs: Vec<String>,
    /// The leg of each actuator.
    pub leg_of: Vec<usize>,
    /// The model's named bodies (what a push may name).
    pub bodies: Vec<String>,
}

impl JointMap {
    fn joints_named(&self, prefix: &str) -> Vec<String> {
        self.joints
            .iter()
            .filter(|j| j.starts_with(prefix))
            .cloned()
            .collect()
    }

    /// Opposite legs: for the Ant's four legs in body order (front_left, front_right, back,
    /// right_back), legs 0 and 2, and legs 1 and 3.
    fn diagonals(&self) -> Vec<String> {
        if self.legs.len() != 4 {
            return Vec::new();
        }
        vec![
            format!("{}+{}", self.legs[0], self.legs[2]),
            format!("{}+{}", self.legs[1], self.legs[3]),
        ]
    }

    /// The actuators a name means: a joint, a leg, `all`, or a `+`-joined group of them.
    pub fn group(&self, name: &str) -> Result<Vec<usize>, String> {
        let mut out = Vec::new();
        for part in name.split('+').map(str::trim) {
            if part == "all" {
                out.extend(0..self.joints.len());
            } else if let Some(i) = self.joints.iter().position(|j| j == part) {
                out.push(i);
            } else if let Some(leg) = self.legs.iter().position(|l| l == part) {
                out.extend((0..self.leg_of.len()).filter(|&i| self.leg_of[i] == leg));
            } else {
                return Err(format!(
                    "unknown joint or leg '{part}' (joints: {}; legs: {}; or all)",
                    self.joints.join(", "),
                    self.legs.join(", ")
                ));
            }
        }
        out.sort_unstable();
        out.dedup();
        Ok(out)
    }
}

#[derive(Debug, Clone, PartialEq)]
struct PlanItem {
    start: usize,
    actuators: Vec<usize>,
    change: Change,
}

/// One episode's concrete schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct ScenarioPlan {
    pub name: String,
    items: Vec<PlanItem>,
    /// (first step, push).
    pushes: Vec<(usize, Push)>,
}

impl ScenarioPlan {
    /// The changes to apply before env step `step` runs, in the file's order.
    pub fn changes_before(&self, step: usize) -> Vec<(usize, JointOverride)> {
        let mut out = Vec::new();
        for item in &self.items {
            let change = match item.change {
                _ if step < item.start => None,
                Change::Scale(s) => (step == item.start).then_some(JointOverride::SetScale(s)),
                Change::Fail(s) => (step == item.start).then_some(JointOverride::FailTo(s)),
                Change::Heal => (step == item.start).then_some(JointOverride::Heal),
                Change::ResetFatigue => (step == item.start).then_some(JointOverride::ResetFatigue),
                Change::Ramp { from, to, until } => (step <= until).then(|| {
                    let f = (step - item.start) as f64 / (until - item.start) as f64;
                    JointOverride::SetScale(from + (to - from) * f)
                }),
                Change::Intermittent {
                    scales,
                    period,
                    until,
                } => {
                    let k = step - item.start;
                    (k.is_multiple_of(period) && until.is_none_or(|u| step <= u))
                        .then(|| JointOverride::SetScale(scales[(k / period) % 2]))
                }
            };
            if let Some(change) = change {
                out.extend(item.actuators.iter().map(|&a| (a, change)));
            }
        }
        out
    }

    /// The pushes that start before env step `step` runs, in the file's order.
    pub fn pushes_before(&self, step: usize) -> Vec<Push> {
        self.pushes
            .iter()
            .filter(|(start, _)| *start == step)
            .map(|(_, p)| p.clone())
            .collect()
    }

    /// Each planned edit's first step and actuators (for reports and tests).
    pub fn starts(&self) -> Vec<(usize, Vec<usize>)> {
        self.items
            .iter()
            .map(|i| (i.start, i.actuators.clone()))
            .collect()
    }
}

/// A session's hand-made overrides written as a scenario: each at the step it applied to
/// ("fail now" with the scale it left), with the session's fatigue rule (`fatigue`: the
/// condition triggers ran under, or none when they were off).
pub fn from_events(name: &str, fatigue: Option<Condition>, events: &[DamageEvent]) -> Value {
    let edits: Vec<Value> = events
        .iter()
        .filter(|e| e.source.is_none())
        .filter_map(|e| {
            let DamageEventKind::Override { change } = e.kind else {
                return None;
            };
            let mut edit = serde_json::json!({"step": e.step, "joint": e.joint});
            match change {
                JointOverride::SetScale(s) => edit["scale"] = s.into(),
                JointOverride::FailTo(_) | JointOverride::FailNow => edit["fail"] = e.scale.into(),
                JointOverride::Heal => edit["heal"] = true.into(),
                JointOverride::ResetFatigue => edit["reset_fatigue"] = true.into(),
            }
            Some(edit)
        })
        .collect();
    let fatigue = match fatigue {
        Some(c) => Value::String(c.name().to_string()),
        None => Value::Bool(false),
    };
    serde_json::json!({
        "name": name,
        "description": "saved from a gaitscope live session: its hand-made overrides",
        "fatigue": fatigue,
        "edits": edits,
    })
}

/// Resolves `--scenario` values and `--suite` names into scenarios, in order.
pub fn collect(names: &[String], suites: &[String]) -> Result<Vec<Scenario>, ScenarioError> {
    let mut out = Vec::new();
    for suite in suites {
        out.extend(Scenario::suite(suite)?);
    }
    for name in names {
        out.push(Scenario::load(name)?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #[test]
    fn oversized_endless_and_duplicate_key_scenarios_are_refused() {
        let edit = r#"{"step": 1, "joint": "hip_1", "fail": true}"#;
        let many = format!(
            r#"{{"name": "many", "fatigue": false, "edits": [{}]}}"#,
            vec![edit; MAX_SCENARIO_EDITS + 1].join(",")
        );
        let err = Scenario::from_json(&many, "many.json")
            .unwrap_err()
            .to_string();
        assert!(err.contains("10001 edits, more than the 10000"), "{err}");
        let big = format!(
            r#"{{"name": "big", "description": "{}"}}"#,
            "x".repeat(MAX_SCENARIO_BYTES)
        );
        let err = Scenario::from_json(&big, "big.json")
            .unwrap_err()
            .to_string();
        assert!(err.contains("more than the 1048576"), "{err}");
        let err = Scenario::load("/dev/zero").unwrap_err().to_string();
        assert!(err.contains("/dev/zero"), "{err}");
        let dup = r#"{"name": "a", "name": "b", "fatigue": false, "edits": []}"#;
        let err = Scenario::from_json(dup, "dup.json")
            .unwrap_err()
            .to_string();
        assert!(err.contains("duplicate key \"name\""), "{err}");
        let nested = r#"{"name": "n", "fatigue": false, "edits": [{"step": 1, "step": 2, "joint": "hip_1", "fail": true}]}"#;
        let err = Scenario::from_json(nested, "n.json")
            .unwrap_err()
            .to_string();
        assert!(err.contains("duplicate key \"step\""), "{err}");
    }

    use super::*;

    fn ant() -> JointMap {
        JointMap {
            joints: [
                "hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3",
            ]
            .map(String::from)
            .to_vec(),
            legs: [
                "front_left_leg",
                "front_right_leg",
                "back_leg",
                "right_back_leg",
            ]
            .map(String::from)
            .to_vec(),
            leg_of: vec![3, 3, 0, 0, 1, 1, 2, 2],
            bodies: ["torso", "front_left_leg", "aux_1"]
                .map(String::from)
                .to_vec(),
        }
    }

    #[test]
    fn pushes_in_a_scenario_parse_check_and_plan() {
        let s = Scenario::from_json(
            r#"{"name": "shove", "edits": [
                {"step": 3, "joint": "ankle_3", "scale": 0.5},
                {"step": 40, "push": {"body": "torso", "force": [0, 50, 0], "steps": 5}},
                {"step": [10, 20], "push": {"body": "aux_1", "force": [1, 0, 0]}}]}"#,
            "test",
        )
        .unwrap();
        assert_eq!(s.edits.len(), 1);
        assert_eq!(s.pushes.len(), 2);
        assert_eq!(s.pushes[0].push.steps, 5);
        assert_eq!(s.pushes[1].push.steps, 1, "one step unless told");
        s.check(&ant()).unwrap();
        let plan = s.plan(7, &ant()).unwrap();
        assert_eq!(plan.pushes_before(40), [s.pushes[0].push.clone()]);
        assert!(plan.pushes_before(41).is_empty());
        let drawn = (10..=20)
            .filter(|&t| !plan.pushes_before(t).is_empty())
            .count();
        assert_eq!(drawn, 1, "a ranged push starts once, inside its range");
        // The damage schedule is the one without the pushes.
        let alone = Scenario::from_json(
            r#"{"name": "shove", "edits": [{"step": 3, "joint": "ankle_3", "scale": 0.5}]}"#,
            "test",
        )
        .unwrap();
        assert_eq!(alone.plan(7, &ant()).unwrap().starts(), plan.starts());
        // Bad pushes are clear errors.
        let err = |json: &str| Scenario::from_json(json, "t").unwrap_err().to_string();
        let unknown = Scenario::from_json(
            r#"{"name": "x", "edits": [{"step": 1, "push": {"body": "tail", "force": [1, 0, 0]}}]}"#,
            "t",
        )
        .unwrap()
        .check(&ant())
        .unwrap_err()
        .to_string();
        assert!(
            unknown.contains("tail") && unknown.contains("torso"),
            "{unknown}"
        );
        let e = err(
            r#"{"name": "x", "edits": [{"step": 1, "push": {"body": "torso", "force": [5000, 0, 0]}}]}"#,
        );
        assert!(e.contains("edits[0].push") && e.contains("5000 N"), "{e}");
        let e = err(
            r#"{"name": "x", "edits": [{"step": 1, "joint": "hip_1", "push": {"body": "torso", "force": [1, 0, 0]}}]}"#,
        );
        assert!(e.contains("stands alone"), "{e}");
        let e = err(
            r#"{"name": "x", "edits": [{"step": 1, "push": {"body": "torso", "force": [1, 0, 0], "steps": -2}}]}"#,
        );
        assert!(e.contains("1 to 1000 env steps"), "{e}");
    }

    fn parse(text: &str) -> Result<Scenario, String> {
        Scenario::from_json(text, "test").map_err(|e| e.to_string())
    }

    #[test]
    fn the_minimal_form_parses() {
        let s = parse(r#"{"name": "x", "fatigue": false, "edits": [{"step": 0, "joint": "ankle_3", "scale": 0.1}]}"#).unwrap();
        assert_eq!(s.fatigue, FatigueRule::Off);
        let plan = s.plan(0, &ant()).unwrap();
        assert_eq!(plan.changes_before(0), [(7, JointOverride::SetScale(0.1))]);
        assert_eq!(plan.changes_before(1), []);
    }

    #[test]
    fn ramps_and_intermittent_faults_follow_their_schedules() {
        let s = parse(r#"{"name": "r", "edits": [
            {"step": 10, "until": 20, "joint": "hip_1", "ramp": [1.0, 0.0]},
            {"step": 5, "until": 14, "joint": "back_leg", "intermittent": {"scales": [0.2, 0.8], "period": 3}}]}"#)
        .unwrap();
        let plan = s.plan(0, &ant()).unwrap();
        let ramp = |t: usize| {
            plan.changes_before(t)
                .into_iter()
                .find(|(a, _)| *a == 2)
                .map(|(_, c)| c)
        };
        assert_eq!(ramp(9), None);
        assert_eq!(ramp(10), Some(JointOverride::SetScale(1.0)));
        assert_eq!(ramp(15), Some(JointOverride::SetScale(0.5)));
        assert_eq!(ramp(20), Some(JointOverride::SetScale(0.0)));
        assert_eq!(ramp(21), None, "it stays where it ended");
        // back_leg = hip_3 and ankle_3 (actuators 6, 7): 0.2 at 5, 0.8 at 8, 0.2 at 11, 0.8 at
        // 14, nothing after `until`.
        let leg = |t: usize| -> Vec<(usize, JointOverride)> {
            plan.changes_before(t)
                .into_iter()
                .filter(|(a, _)| *a >= 6)
                .collect()
        };
        for (t, s) in [(5, 0.2), (8, 0.8), (11, 0.2), (14, 0.8)] {
            assert_eq!(
                leg(t),
                [
                    (6, JointOverride::SetScale(s)),
                    (7, JointOverride::SetScale(s))
                ],
                "step {t}"
            );
        }
        for t in [4, 6, 7, 9, 12, 17] {
            assert_eq!(leg(t), [], "step {t}");
        }
    }

    #[test]
    fn random_choices_repeat_per_seed_and_vary_across_seeds() {
        let s = parse(
            r#"{"name": "p", "edits": [
            {"step": [50, 150], "pick": "any_joint", "fail": 0.1},
            {"step": 200, "pick": "any_joint", "heal": true}]}"#,
        )
        .unwrap();
        let map = ant();
        let plans: Vec<_> = (0..20)
            .map(|seed| s.plan(seed, &map).unwrap().starts())
            .collect();
        assert_eq!(
            s.plan(3, &map).unwrap().starts(),
            plans[3],
            "same seed, same plan"
        );
        for p in &plans {
            assert!((50..=150).contains(&p[0].0));
            assert_eq!(p[0].1.len(), 1);
            assert_eq!(p[0].1, p[1].1, "one draw per set per episode");
        }
        let joints: std::collections::BTreeSet<_> = plans.iter().map(|p| p[0].1[0]).collect();
        let steps: std::collections::BTreeSet<_> = plans.iter().map(|p| p[0].0).collect();
        assert!(
            joints.len() >= 4 && steps.len() >= 10,
            "{joints:?} {steps:?}"
        );
    }

    #[test]
    fn legs_and_diagonals_resolve_to_their_joints() {
        let map = ant();
        assert_eq!(map.group("back_leg").unwrap(), [6, 7]);
        assert_eq!(map.group("front_left_leg+ankle_2").unwrap(), [2, 3, 5]);
        let s = parse(
            r#"{"name": "d", "edits": [{"step": 0, "pick": "diagonal_legs", "scale": 0.1}]}"#,
        )
        .unwrap();
        for seed in 0..10 {
            let group = &s.plan(seed, &map).unwrap().starts()[0].1;
            assert!(
                group == &[2, 3, 6, 7] || group == &[0, 1, 4, 5],
                "{group:?}"
            );
        }
    }

    #[test]
    fn bad_files_name_what_is_wrong() {
        let cases = [
            (
                r#"{"name": "x", "edits": [], "colour": 1}"#,
                "unknown field `colour`",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "joint": "a", "scale": 1.5}]}"#,
                "edits[0].scale: 1.5 is outside [0, 1]",
            ),
            (
                r#"{"name": "x", "edits": [{"step": -3, "joint": "a", "scale": 0.5}]}"#,
                "edits[0].step: -3 is negative",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "joint": "a"}]}"#,
                "edits[0]: no change",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "scale": 0.1}]}"#,
                "edits[0]: no target",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "joint": "a", "ramp": [1, 0]}]}"#,
                "needs `until`",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "joint": "a", "scale": 0.1, "heal": true}]}"#,
                "one change per edit",
            ),
            (
                r#"{"name": "x", "fatigue": "awful"}"#,
                "fatigue: unknown condition 'awful'",
            ),
            (
                r#"{"name": "x", "edits": [{"step": [9, 3], "joint": "a", "heal": true}]}"#,
                "the range [9, 3] is empty",
            ),
            (
                r#"{"name": "x", "edits": [{"step": 0, "joint": "a", "intermittent": {"scales": [1, 0], "period": 0}}]}"#,
                "intermittent.period: 0 must be at least 1",
            ),
            (r#"{"edits": []}"#, "missing field `name`"),
        ];
        for (text, expected) in cases {
            let err = parse(text).unwrap_err();
            assert!(err.contains(expected), "{text}: {err}");
        }
        let s = parse(r#"{"name": "x", "edits": [{"step": 0, "joint": "knee_9", "scale": 0.1}]}"#)
            .unwrap();
        let err = s.check(&ant()).unwrap_err().to_string();
        assert!(
            err.contains("edits[0]: unknown joint or leg 'knee_9'"),
            "{err}"
        );
        let s = parse(r#"{"name": "x", "edits": [{"step": 0, "pick": "any_toe", "scale": 0.1}]}"#)
            .unwrap();
        assert!(
            s.check(&ant())
                .unwrap_err()
                .to_string()
                .contains("unknown set 'any_toe'")
        );
    }

    #[test]
    fn the_ood_suite_parses_and_fits_the_ant() {
        let suite = Scenario::suite("ood").unwrap();
        assert_eq!(suite.len(), 7);
        for s in &suite {
            s.check(&ant()).unwrap();
            assert!(!s.description.is_empty(), "{}", s.name);
            assert_eq!(s.fatigue, FatigueRule::Off, "{}", s.name);
        }
        assert!(Scenario::suite("wild").is_err());
    }
}
