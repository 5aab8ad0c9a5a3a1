//! gaitscope: watch, train and debug legged-robot policies that adapt to joint damage.
//!
//! Data flows one way: physics ([`env`](mod@env)) → damage ([`damage`]) → policy ([`policy`]) →
//! the stepping core ([`lane`]) → sinks ([`rollout`], [`eval`], [`probe`], [`telemetry`],
//! [`video`]) → front-ends ([`app`], the live viewer; the CLI). The context window ([`window`])
//! is what a context-encoder policy reads; [`train`] learns the policies.

pub mod app;
pub mod bench;
pub mod config;
pub mod damage;
pub mod env;
pub mod eval;
pub mod explain;
pub mod files;
pub mod lane;
pub mod palette;
pub mod plots;
pub mod policy;
pub mod probe;
pub mod progress;
pub mod rollout;
pub mod search;
pub mod telemetry;
pub mod train;
#[cfg(feature = "video")]
pub mod video;
pub mod window;

/// The cause an error keeps: the underlying error itself (I/O, JSON, safetensors, MuJoCo,
/// plotters), or a sentence where there is none, so that `Error::source` walks to it rather
/// than the cause living on only as text (issue 50).
pub type Cause = Box<dyn std::error::Error + Send + Sync + 'static>;

pub use config::GaitConfig;
pub use damage::{Condition, ConditionChoice, DamageEvent, DamageState, JointOverride};
pub use env::{AntEnv, EnvError, Observation, StepOutcome};
pub use window::ContextWindow;
