//! The live viewer: a simulation thread driven by commands, a snapshot the control panel reads,
//! and a Rerun stream that carries every step to the stock Rerun viewer.
//!
//! ```text
//!  panel (egui, main thread) ──Command──▶ sim thread (Session: env → damage → policy → Rerun)
//!        ▲                                     │
//!        └──────── Snapshot (Arc<Mutex>) ◀─────┘
//! ```
//! The panel never blocks on physics: it sends commands over a channel and reads the latest
//! snapshot. The sim thread runs the same [`Session`](crate::telemetry::Session) loop as
//! `gaitscope record`.

pub mod breakpoint;
pub mod launch;
mod sim;
pub mod viewer;

#[cfg(feature = "live")]
pub mod panel;

#[cfg(feature = "web")]
pub mod guard;
#[cfg(feature = "web")]
mod viewer_assets;
#[cfg(feature = "web")]
pub mod web;

pub use breakpoint::{BreakHit, Breakpoint, BreakpointError};
pub use sim::{LaneView, LiveSetup, SimHandle, SimReport, Snapshot, SpeedReport, episode_config};

use std::fmt;
use std::path::PathBuf;
use std::str::FromStr;

use crate::damage::{Condition, JointOverride};
use crate::policy::ActionMode;

/// Slowest and fastest playback, as multiples of real time.
pub const MIN_SPEED: f64 = 0.25;
pub const MAX_SPEED: f64 = 8.0;

/// The panel's damage condition: the three env conditions, or `manual` where fatigue never
/// triggers a joint and only a person damages them ("fail now" then uses the severe scale).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LiveCondition {
    Healthy,
    Mild,
    Severe,
    Manual,
}

impl LiveCondition {
    pub const ALL: [LiveCondition; 4] = [
        LiveCondition::Healthy,
        LiveCondition::Mild,
        LiveCondition::Severe,
        LiveCondition::Manual,
    ];

    /// The env condition an episode runs under.
    pub fn env_condition(self) -> Condition {
        match self {
            LiveCondition::Healthy => Condition::Healthy,
            LiveCondition::Mild => Condition::Mild,
            LiveCondition::Severe | LiveCondition::Manual => Condition::Severe,
        }
    }

    /// Whether the world damages joints by itself (fatigue triggers, a world's deaths): all
    /// but manual, where only a hand does.
    pub fn world_damage(self) -> bool {
        self != LiveCondition::Manual
    }

    /// What it does in a world with `damage` (the panel's and page's hint).
    pub fn meaning(self, damage: &crate::damage::DamageConfig) -> String {
        match self {
            LiveCondition::Manual => format!(
                "only what a hand does (fail now: {}× torque)",
                self.env_condition().scale(&damage.scales)
            ),
            c => damage.condition_meaning(c.env_condition()),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            LiveCondition::Manual => "manual",
            c => c.env_condition().name(),
        }
    }
}

impl fmt::Display for LiveCondition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for LiveCondition {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s.eq_ignore_ascii_case("manual") {
            return Ok(LiveCondition::Manual);
        }
        match s.parse::<Condition>() {
            Ok(Condition::Healthy) => Ok(LiveCondition::Healthy),
            Ok(Condition::Mild) => Ok(LiveCondition::Mild),
            Ok(Condition::Severe) => Ok(LiveCondition::Severe),
            Err(_) => Err(format!(
                "unknown condition '{s}' (expected healthy, mild, severe or manual)"
            )),
        }
    }
}

/// Which model a checkpoint command is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// The model the panel drives (entity root `ant`).
    Main,
    /// The optional second model, side by side under the same damage (entity root `compare`).
    Compare,
}

/// What the panel asks of the simulation. Each applies before the next env step.
#[derive(Debug, Clone, PartialEq)]
pub enum Command {
    /// A hand-made change to one joint, applied to every model; logged as an event.
    Override {
        actuator: usize,
        change: JointOverride,
    },
    /// Push every model's body (an external force for a few steps); logged as an event.
    Push(crate::damage::Push),
    /// Log why z moved (the attribution view) with every step, or stop.
    SetAttribution(bool),
    /// Condition of the next episode.
    SetCondition(LiveCondition),
    /// Seed of the next episode.
    SetSeed(u64),
    /// Step limit of the next episode.
    SetStepLimit(usize),
    /// Start a new episode now, with the current seed, condition and step limit.
    Reset,
    Pause,
    Resume,
    /// One env step (while paused).
    StepOnce,
    /// Playback speed, a multiple of real time (clamped to [`MIN_SPEED`], [`MAX_SPEED`]).
    SetSpeed(f64),
    SetActionMode(ActionMode),
    /// Open another checkpoint folder in a slot; a new episode starts.
    Load {
        slot: Slot,
        dir: PathBuf,
    },
    /// Run the second model side by side (needs one loaded), or stop doing so.
    SetCompare(bool),
    /// Pause after any step where one of these holds (replaces the list; empty: none).
    SetBreakpoints(Vec<Breakpoint>),
    /// Go back to the state after this many steps of the current episode (a new branch).
    Rewind(usize),
    /// Start a counterfactual lane of the main model from the current state with these edits.
    Fork(Vec<crate::damage::Edit>),
    /// Stop the fork lane.
    EndFork,
    /// Run this scenario from the next episode on (`None`: back to the condition alone).
    SetScenario(Option<crate::damage::scenario::Scenario>),
    /// Write this episode's hand-made overrides (main model) as a scenario file.
    SaveScenario(PathBuf),
    /// Write the main model's state before its next step (`--init-state` starts from it).
    SaveState(PathBuf),
    /// Stop the simulation thread.
    Quit,
}

/// A checkpoint folder the panel offers: `checkpoints/*` with a `checkpoint.json`, sorted.
pub fn discover_checkpoints(root: &std::path::Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(root) else {
        return Vec::new();
    };
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join(crate::policy::checkpoint::META_FILE).is_file())
        .collect();
    dirs.sort();
    dirs
}

/// Entity roots in a live stream: the main model and the side-by-side one.
pub const LIVE_ROOTS: [&str; 2] = ["ant", "compare"];

#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(transparent)]
    Record(#[from] crate::telemetry::RecordError),
    #[error(transparent)]
    Telemetry(#[from] crate::telemetry::TelemetryError),
    #[error(transparent)]
    Checkpoint(#[from] crate::policy::CheckpointError),
    #[error("speed {0} must be between {MIN_SPEED}× and {MAX_SPEED}× real time")]
    BadSpeed(f64),
    #[error("the step limit must be at least 1")]
    BadStepLimit,
    #[error(transparent)]
    Breakpoint(#[from] BreakpointError),
    #[error(transparent)]
    Rewind(#[from] crate::telemetry::RewindError),
    #[error("the episode is over: rewind or reset before forking")]
    ForkAfterEnd,
    #[error("cannot write scenario {path}: {reason}")]
    SaveScenario {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("cannot write the saved state {path}: {reason}")]
    SaveState {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("the simulation thread stopped unexpectedly")]
    SimThreadPanicked,
    #[error("starting the simulation thread: {0}")]
    ThreadStart(std::io::Error),
    /// The session ran, but its last data did not reach every sink (a closed viewer).
    #[error("the live session's last data did not reach every sink")]
    Unflushed {
        report: Box<SimReport>,
        source: crate::telemetry::TelemetryError,
    },
}

/// Frame statistics of the panel window, for the frame-rate report.
#[derive(Debug, Clone, Default)]
pub struct PanelStats {
    pub frames: u64,
    pub seconds: f64,
    /// Mean CPU time egui spent per frame (ms), as eframe reports it.
    pub mean_frame_cpu_ms: f64,
}

impl PanelStats {
    pub fn fps(&self) -> f64 {
        self.frames as f64 / self.seconds.max(1e-9)
    }
}

/// The models a live session runs, as lanes (main first).
fn live_specs(
    main: crate::telemetry::Actor,
    compare: Option<crate::telemetry::Actor>,
) -> Vec<crate::telemetry::LaneSpec> {
    std::iter::once(main)
        .chain(compare)
        .zip(LIVE_ROOTS)
        .enumerate()
        .map(|(k, (actor, root))| crate::telemetry::LaneSpec {
            actor,
            root: root.to_string(),
            world_offset: crate::telemetry::side_by_side_offset(k),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn live_conditions_parse_and_map_to_env_conditions() {
        assert_eq!("Manual".parse::<LiveCondition>(), Ok(LiveCondition::Manual));
        assert_eq!("mild".parse::<LiveCondition>(), Ok(LiveCondition::Mild));
        assert!(
            "broken"
                .parse::<LiveCondition>()
                .unwrap_err()
                .contains("manual")
        );
        assert_eq!(LiveCondition::Manual.env_condition(), Condition::Severe);
        assert!(!LiveCondition::Manual.world_damage());
        assert!(LiveCondition::Healthy.world_damage());
        assert_eq!(LiveCondition::Severe.to_string(), "severe");
    }
}
