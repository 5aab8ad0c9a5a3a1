//! A push: an external force on one body of the Ant for a few env steps (MuJoCo's
//! `xfrc_applied`, at the body's centre of mass, world frame), the debugger's counterpart of
//! MuJoCo `simulate`'s ctrl-drag. Written `push:BODY=FX,FY,FZ[@N]` wherever damage edits are
//! (`--fork`, the panel, the web page) and `{"push": {...}}` in scenario files.

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// The largest force a push may have, in newtons: about 100 times the Ant's weight (0.9 kg).
/// More is not a push but a launch; the integrator diverges.
pub const MAX_PUSH_NEWTONS: f64 = 1000.0;
/// The longest a push may act, in env steps (an episode's default length).
pub const MAX_PUSH_STEPS: usize = 1000;
/// Pushes acting at once, at most: each is a line in every step's record and stream.
pub const MAX_ACTIVE_PUSHES: usize = 64;

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PushError {
    #[error(
        "bad push '{0}': expected push:BODY=FX,FY,FZ or push:BODY=FX,FY,FZ@N (newtons, world frame; N env steps, default 1), e.g. push:torso=0,40,0@5"
    )]
    Syntax(String),
    #[error("push force {0:?} must be three finite numbers (newtons)")]
    NotFinite([f64; 3]),
    #[error("push force of {0:.0} N is more than the {MAX_PUSH_NEWTONS} N a push may have")]
    TooStrong(f64),
    #[error("a push acts for 1 to {MAX_PUSH_STEPS} env steps, not {0}")]
    BadSteps(usize),
}

/// A force on a body's centre of mass for `steps` env steps, from the step it is applied
/// before. Every `Push` is checked ([`Push::new`]), read from a file too.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "PushFields")]
pub struct Push {
    /// A body of the model, by name (`torso`, `front_left_leg`, `aux_1`, …).
    pub body: String,
    /// Newtons, world frame.
    pub force: [f64; 3],
    pub steps: usize,
}

/// A push as written, before [`Push::new`] checks it.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PushFields {
    body: String,
    force: [f64; 3],
    steps: usize,
}

impl TryFrom<PushFields> for Push {
    type Error = PushError;
    fn try_from(p: PushFields) -> Result<Self, PushError> {
        Push::new(&p.body, p.force, p.steps)
    }
}

impl Push {
    /// A checked push: finite force within [`MAX_PUSH_NEWTONS`], 1..=[`MAX_PUSH_STEPS`] steps.
    /// The body is checked against a model when the push is applied.
    pub fn new(body: &str, force: [f64; 3], steps: usize) -> Result<Self, PushError> {
        if !force.iter().all(|f| f.is_finite()) {
            return Err(PushError::NotFinite(force));
        }
        let norm = force.iter().map(|f| f * f).sum::<f64>().sqrt();
        if norm > MAX_PUSH_NEWTONS {
            return Err(PushError::TooStrong(norm));
        }
        if !(1..=MAX_PUSH_STEPS).contains(&steps) {
            return Err(PushError::BadSteps(steps));
        }
        Ok(Self {
            body: body.to_string(),
            force,
            steps,
        })
    }

    /// The force's magnitude in newtons.
    pub fn magnitude(&self) -> f64 {
        self.force.iter().map(|f| f * f).sum::<f64>().sqrt()
    }

    /// The push in words, the same everywhere it is shown.
    pub fn describe(&self) -> String {
        let [x, y, z] = self.force;
        let steps = if self.steps == 1 { "step" } else { "steps" };
        format!(
            "push {} by ({x}, {y}, {z}) N for {} {steps}",
            self.body, self.steps
        )
    }
}

impl FromStr for Push {
    type Err = PushError;

    /// `push:BODY=FX,FY,FZ[@N]`.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || PushError::Syntax(text.to_string());
        let rest = text.trim().strip_prefix("push:").ok_or_else(bad)?;
        let (body, value) = rest.split_once('=').ok_or_else(bad)?;
        let body = body.trim();
        if body.is_empty() {
            return Err(bad());
        }
        let (force, steps) = match value.split_once('@') {
            Some((f, n)) => (f, n.trim().parse::<usize>().map_err(|_| bad())?),
            None => (value, 1),
        };
        let parts: Vec<f64> = force
            .split(',')
            .map(|p| p.trim().parse::<f64>().map_err(|_| bad()))
            .collect::<Result<_, _>>()?;
        let force: [f64; 3] = parts.try_into().map_err(|_| bad())?;
        Push::new(body, force, steps)
    }
}

impl fmt::Display for Push {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [x, y, z] = self.force;
        write!(f, "push:{}={x},{y},{z}", self.body)?;
        if self.steps != 1 {
            write!(f, "@{}", self.steps)?;
        }
        Ok(())
    }
}

/// A push acting during one env step, as the step's record carries it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PushRecord {
    pub push: Push,
    /// The env step it was applied before (its first step).
    pub start: usize,
    /// Where the force acted after this step: the body's centre of mass (world frame).
    pub point: [f64; 3],
    /// The scenario that pushed (none for a push by hand or by a fork).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
}

impl PushRecord {
    /// Whether this is the push's first step (an event in the stream).
    pub fn starts_at(&self, step: usize) -> bool {
        self.start == step
    }

    pub fn describe(&self) -> String {
        match &self.source {
            Some(scenario) => format!("scenario {scenario}: {}", self.push.describe()),
            None => self.push.describe(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pushes_parse_and_print_back() {
        let p: Push = "push:torso=0,40,-2.5@5".parse().unwrap();
        assert_eq!(p.body, "torso");
        assert_eq!(p.force, [0.0, 40.0, -2.5]);
        assert_eq!(p.steps, 5);
        assert_eq!(p.to_string(), "push:torso=0,40,-2.5@5");
        let one: Push = "push:aux_1=1,2,3".parse().unwrap();
        assert_eq!(one.steps, 1);
        assert_eq!(one.to_string().parse::<Push>().unwrap(), one);
        assert_eq!(p.describe(), "push torso by (0, 40, -2.5) N for 5 steps");
    }

    #[test]
    fn bad_pushes_are_refused_with_the_reason() {
        for text in [
            "push:torso=1,2",
            "push:torso=1,2,3,4",
            "push:=1,2,3",
            "push:torso",
            "push:torso=a,b,c",
            "push:torso=1,2,3@x",
            "shove:torso=1,2,3",
        ] {
            assert!(
                matches!(text.parse::<Push>(), Err(PushError::Syntax(_))),
                "{text}"
            );
        }
        assert!(matches!(
            "push:torso=NaN,0,0".parse::<Push>(),
            Err(PushError::NotFinite(_))
        ));
        assert!(matches!(
            "push:torso=inf,0,0".parse::<Push>(),
            Err(PushError::NotFinite(_))
        ));
        assert_eq!(
            "push:torso=800,800,0".parse::<Push>(),
            Err(PushError::TooStrong(800.0 * 2f64.sqrt()))
        );
        assert_eq!(
            "push:torso=1,0,0@0".parse::<Push>(),
            Err(PushError::BadSteps(0))
        );
        assert_eq!(
            "push:torso=1,0,0@1001".parse::<Push>(),
            Err(PushError::BadSteps(1001))
        );
        // The limit itself is allowed.
        assert!("push:torso=1000,0,0@1000".parse::<Push>().is_ok());
        // Read from a file (a saved state), a push is checked the same way.
        let read = |json: &str| serde_json::from_str::<Push>(json).map_err(|e| e.to_string());
        let ok = read(r#"{"body": "torso", "force": [0, 40, 0], "steps": 5}"#).unwrap();
        assert_eq!(ok, "push:torso=0,40,0@5".parse().unwrap());
        let err = read(r#"{"body": "torso", "force": [5000, 0, 0], "steps": 1}"#).unwrap_err();
        assert!(err.contains("5000 N"), "{err}");
    }
}
