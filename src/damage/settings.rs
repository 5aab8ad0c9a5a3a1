//! The damage model's own settings: how fatigue accumulates, where a joint triggers, what a
//! triggered joint keeps per condition, how a condition is chosen, and an optional scenario.
//! (A run's `GaitConfig`, config.rs, only composes them: damage depends on nothing above it.)

use serde::{Deserialize, Serialize};

use super::{ConditionChoice, DeadActuators};

/// The fatigue model (the paper's "DamageWrapper").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DamageConfig {
    /// Fatigue per unit of |commanded action| per step.
    pub alpha: f64,
    /// Fatigue per unit of ‖cfrc_ext‖₂ on the actuated body per step.
    pub beta: f64,
    /// Fatigue at which an actuator triggers (permanently, for the episode).
    pub threshold: f64,
    pub scales: ConditionScales,
    /// How each episode's condition is chosen.
    pub condition: ConditionChoice,
    /// Scripted damage on top (or instead) of fatigue ([`super::scenario`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scenario: Option<super::scenario::Scenario>,
    /// Whether fatigue reaching the threshold triggers a joint (fatigue accumulates either
    /// way). A world whose damage is dead actuators alone turns it off; a scenario's own rule
    /// wins over it.
    #[serde(skip_serializing_if = "is_true")]
    pub fatigue: bool,
    /// Actuators that die per episode ([`DeadActuators`]); absent in the paper's world.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dead: Option<DeadActuators>,
}

impl DamageConfig {
    /// What `condition` does in this world, in words for the panel and the page (the paper's
    /// mild: "a joint whose fatigue reaches 30 keeps 0.5× its torque").
    pub fn condition_meaning(&self, condition: super::Condition) -> String {
        let mut parts = Vec::new();
        if self.fatigue {
            let scale = condition.scale(&self.scales);
            parts.push(if scale >= 1.0 {
                "fatigue weakens no joint".to_string()
            } else {
                format!(
                    "a joint whose fatigue reaches {} keeps {scale}× its torque",
                    self.threshold
                )
            });
        }
        if let Some(dead) = &self.dead {
            parts.push(dead.describe(condition));
        }
        if parts.is_empty() {
            "no damage".into()
        } else {
            parts.join("; ")
        }
    }
}

fn is_true(b: &bool) -> bool {
    *b
}

impl Default for DamageConfig {
    fn default() -> Self {
        Self {
            alpha: 1.0,
            beta: 0.1,
            threshold: 30.0,
            scales: ConditionScales::default(),
            condition: ConditionChoice::Random,
            scenario: None,
            fatigue: true,
            dead: None,
        }
    }
}

/// Torque scale applied to a triggered actuator, per condition.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConditionScales {
    pub healthy: f64,
    pub mild: f64,
    pub severe: f64,
}

impl Default for ConditionScales {
    fn default() -> Self {
        Self {
            healthy: 1.0,
            mild: 0.5,
            severe: 0.1,
        }
    }
}
