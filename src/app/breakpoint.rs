//! Breakpoints: predicates over what one lane's step did, checked by the sim thread after every
//! step; the first that holds pauses the sim after that step.
//!
//! Syntax (the `--break-on` flag and the panel's field), comma-separated: `trigger` (any joint)
//! or `trigger:JOINT`, `override`, `termination` (the step that ends an episode unhealthy),
//! `success`, `probe-flip` (the live probe's P(damaged) crosses 0.5 for a joint), `step:N`
//! (after the episode's N-th step).

use std::fmt;

use crate::damage::{DamageEvent, DamageEventKind, N_ACTUATORS};
use crate::env::StepOutcome;

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Breakpoint {
    /// A joint's fatigue crossed τ (any joint, or the one named).
    Trigger(Option<String>),
    /// A hand-made change took effect (panel or fork edit).
    Override,
    /// The episode ended unhealthy (the torso left the healthy height range).
    Termination,
    /// The Ant reached the goal.
    Success,
    /// The probe's P(damaged) crossed 0.5 for some joint (needs the checkpoint's probe.json).
    ProbeFlip,
    /// After the episode's N-th step.
    Step(usize),
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum BreakpointError {
    #[error(
        "unknown breakpoint '{0}' (expected trigger, trigger:JOINT, override, termination, success, probe-flip or step:N)"
    )]
    Unknown(String),
    #[error("breakpoint '{0}': N must be a whole number of steps ≥ 1")]
    BadStep(String),
    #[error("breakpoint trigger:{joint}: no joint '{joint}' (joints: {known})")]
    UnknownJoint { joint: String, known: String },
    #[error(
        "breakpoint probe-flip needs a probe.json beside the checkpoint (make one with `gaitscope probe`)"
    )]
    NoProbe,
}

impl Breakpoint {
    pub fn parse(text: &str) -> Result<Self, BreakpointError> {
        let text = text.trim();
        let (kind, arg) = match text.split_once(':') {
            Some((k, a)) => (k.trim(), Some(a.trim())),
            None => (text, None),
        };
        match (kind.to_ascii_lowercase().as_str(), arg) {
            ("trigger", None) => Ok(Self::Trigger(None)),
            ("trigger", Some(joint)) if !joint.is_empty() => {
                Ok(Self::Trigger(Some(joint.to_string())))
            }
            ("override", None) => Ok(Self::Override),
            ("termination", None) => Ok(Self::Termination),
            ("success", None) => Ok(Self::Success),
            ("probe-flip", None) => Ok(Self::ProbeFlip),
            ("step", Some(n)) => match n.parse::<usize>() {
                Ok(n) if n >= 1 => Ok(Self::Step(n)),
                _ => Err(BreakpointError::BadStep(text.to_string())),
            },
            _ => Err(BreakpointError::Unknown(text.to_string())),
        }
    }

    /// A comma-separated list; empty text is no breakpoints.
    pub fn parse_list(text: &str) -> Result<Vec<Self>, BreakpointError> {
        text.split(',')
            .filter(|t| !t.trim().is_empty())
            .map(Self::parse)
            .collect()
    }

    /// Checks a breakpoint against the model it will watch.
    pub fn validate(
        &self,
        joint_names: &[String; N_ACTUATORS],
        has_probe: bool,
    ) -> Result<(), BreakpointError> {
        match self {
            Self::Trigger(Some(joint)) if !joint_names.contains(joint) => {
                Err(BreakpointError::UnknownJoint {
                    joint: joint.clone(),
                    known: joint_names.join(", "),
                })
            }
            Self::ProbeFlip if !has_probe => Err(BreakpointError::NoProbe),
            _ => Ok(()),
        }
    }

    /// Whether this breakpoint holds for `step`; the reason, in words, if so.
    pub fn hit(&self, step: &LaneStep) -> Option<String> {
        let events = || step.events.iter();
        match self {
            Self::Trigger(joint) => events()
                .find(|e| {
                    e.kind == DamageEventKind::Trigger
                        && joint.as_ref().is_none_or(|j| *j == e.joint)
                })
                .map(|e| format!("{} triggered at fatigue {:.1}", e.joint, e.fatigue)),
            Self::Override => events()
                .find(|e| matches!(e.kind, DamageEventKind::Override { .. }))
                .map(|e| format!("override on {} (scale → {})", e.joint, e.scale)),
            Self::Termination => (step.outcome.terminated && !step.outcome.healthy).then(|| {
                if step.outcome.unstable {
                    "the episode ended: the simulation diverged".to_string()
                } else {
                    "the episode ended unhealthy (torso height out of range)".to_string()
                }
            }),
            Self::Success => step
                .outcome
                .success
                .then(|| format!("reached the goal ({:.2} m)", step.outcome.distance)),
            Self::ProbeFlip => {
                let (Some(before), Some(after)) = (step.probe_before, step.probe_after) else {
                    return None;
                };
                (0..N_ACTUATORS)
                    .find(|&i| (before[i] >= 0.5) != (after[i] >= 0.5))
                    .map(|i| {
                        format!(
                            "probe P(damaged) for {} crossed 0.5 ({:.2} → {:.2})",
                            step.joint_names[i], before[i], after[i]
                        )
                    })
            }
            Self::Step(n) => (step.outcome.step + 1 == *n).then(|| format!("step {n}")),
        }
    }
}

impl fmt::Display for Breakpoint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Trigger(None) => f.write_str("trigger"),
            Self::Trigger(Some(j)) => write!(f, "trigger:{j}"),
            Self::Override => f.write_str("override"),
            Self::Termination => f.write_str("termination"),
            Self::Success => f.write_str("success"),
            Self::ProbeFlip => f.write_str("probe-flip"),
            Self::Step(n) => write!(f, "step:{n}"),
        }
    }
}

/// Writes a list back in the syntax it parses from.
pub fn format_list(breakpoints: &[Breakpoint]) -> String {
    breakpoints
        .iter()
        .map(Breakpoint::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// What one lane's step did, as the breakpoints read it.
pub struct LaneStep<'a> {
    pub outcome: &'a StepOutcome,
    /// The damage events of this step (triggers, and edits applied since the last step).
    pub events: &'a [DamageEvent],
    /// The probe's P(damaged) per joint before and after the step (with a probe.json).
    pub probe_before: Option<&'a [f64; N_ACTUATORS]>,
    pub probe_after: Option<&'a [f64; N_ACTUATORS]>,
    pub joint_names: &'a [String; N_ACTUATORS],
}

/// A breakpoint that fired.
#[derive(Debug, Clone, PartialEq)]
pub struct BreakHit {
    pub breakpoint: Breakpoint,
    /// The lane's entity root.
    pub lane: String,
    /// Env steps of the episode when it fired (the sim paused after this many).
    pub step: usize,
    pub reason: String,
}

impl fmt::Display for BreakHit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "break on {} after step {} ({}): {}",
            self.breakpoint, self.step, self.lane, self.reason
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_parse_and_print_back() {
        let list = Breakpoint::parse_list(
            "trigger, trigger:ankle_3,override,termination,success,probe-flip,step:120",
        )
        .unwrap();
        assert_eq!(
            list,
            [
                Breakpoint::Trigger(None),
                Breakpoint::Trigger(Some("ankle_3".into())),
                Breakpoint::Override,
                Breakpoint::Termination,
                Breakpoint::Success,
                Breakpoint::ProbeFlip,
                Breakpoint::Step(120),
            ]
        );
        assert_eq!(
            format_list(&list),
            "trigger,trigger:ankle_3,override,termination,success,probe-flip,step:120"
        );
        assert_eq!(Breakpoint::parse_list(" ").unwrap(), []);
    }

    #[test]
    fn bad_breakpoints_say_what_is_wrong() {
        assert!(matches!(
            Breakpoint::parse("trig"),
            Err(BreakpointError::Unknown(_))
        ));
        assert!(matches!(
            Breakpoint::parse("step:0"),
            Err(BreakpointError::BadStep(_))
        ));
        assert!(matches!(
            Breakpoint::parse("step:x"),
            Err(BreakpointError::BadStep(_))
        ));
        let names: [String; N_ACTUATORS] = std::array::from_fn(|i| format!("j{i}"));
        let err = Breakpoint::parse("trigger:knee")
            .unwrap()
            .validate(&names, true)
            .unwrap_err();
        assert!(err.to_string().contains("j0, j1"), "{err}");
        assert_eq!(
            Breakpoint::ProbeFlip.validate(&names, false),
            Err(BreakpointError::NoProbe)
        );
    }
}
