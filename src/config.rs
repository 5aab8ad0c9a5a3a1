//! One serde config for the task, the damage model and the context window.
//!
//! Every default is the value the env issue (and the paper) specifies, so `GaitConfig::default()`
//! *is* the experiment; a JSON file only needs the fields it changes.

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub use crate::damage::{ConditionScales, DamageConfig};

/// Physics steps per env step, at most (Ant-v4: 5).
pub const MAX_FRAME_SKIP: usize = 1_000;
/// Steps an episode may last, at most.
pub const MAX_EPISODE_STEPS: usize = 1_000_000;
/// Context window length, at most (the paper's: 16).
pub const MAX_CONTEXT_LEN: usize = 1_024;
/// Goal coordinates, at most this far from the origin on each axis (m).
pub const MAX_GOAL_M: f64 = 1_000.0;
/// Reset noise, at most (Ant-v4: 0.1): a uniform draw over ±1e308 has no width a float can hold.
pub const MAX_RESET_NOISE: f64 = 1.0;
/// Reward weights and bonuses, at most this large: rewards stay far inside what the replay
/// buffer's f32 holds.
pub const MAX_REWARD_TERM: f64 = 1e6;

/// The paper's world: Ant-v4, a goal 7.1 m away, fatigue under three conditions.
pub const PAPER_WORLD: &str = "paper";
/// The paper's evaluation limit: its world trains to 1,000 steps and judges at 500.
pub const PAPER_EVAL_STEPS: usize = 500;

/// The shipped worlds (`--world NAME`; `worlds/NAME.json`, docs/world.md): a world is a named
/// config — env settings and a damage distribution — recorded in every checkpoint trained in it.
pub const WORLDS: [(&str, &str); 4] = [
    (PAPER_WORLD, include_str!("../worlds/paper.json")),
    ("dead-joints", include_str!("../worlds/dead-joints.json")),
    ("dead-legs", include_str!("../worlds/dead-legs.json")),
    (
        "dead-legs-short",
        include_str!("../worlds/dead-legs-short.json"),
    ),
];

/// Everything that defines the damaged-Ant task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct GaitConfig {
    /// The world's name (`paper` unless a world file names another); checkpoints record it.
    #[serde(skip_serializing_if = "is_paper")]
    pub world: WorldName,
    pub env: EnvConfig,
    pub damage: DamageConfig,
    pub context: ContextConfig,
}

/// A world's name: `paper` by default.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct WorldName(pub String);

impl Default for WorldName {
    fn default() -> Self {
        Self(PAPER_WORLD.to_string())
    }
}

impl std::fmt::Display for WorldName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

fn is_paper(name: &WorldName) -> bool {
    name.0 == PAPER_WORLD
}

/// Gymnasium Ant-v4 plus the goal task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EnvConfig {
    /// MJCF file to load; `None` uses the bundled `assets/ant.xml` (compiled into the binary).
    pub model_path: Option<PathBuf>,
    /// Physics steps per env step (Ant-v4: 5, so dt = 5 × 0.01 s).
    pub frame_skip: usize,
    /// Half-width of the uniform qpos noise and std of the qvel noise at reset.
    pub reset_noise_scale: f64,
    pub ctrl_cost_weight: f64,
    pub healthy_reward: f64,
    /// Torso height range (m) in which the Ant counts as healthy.
    pub healthy_z_range: [f64; 2],
    pub goal: [f64; 2],
    /// Episode succeeds (and terminates) once the torso is closer than this to the goal.
    pub success_radius: f64,
    /// Weight of the native Ant reward in the task reward.
    pub native_reward_weight: f64,
    /// Weight of the per-step decrease in goal distance.
    pub progress_weight: f64,
    /// Paid on the step the torso enters the success radius.
    pub success_bonus: f64,
    /// Truncation limit (the paper's world: 1000 for training, 500 for evaluation;
    /// [`GaitConfig::run_step_limit`]).
    pub max_episode_steps: usize,
    /// Also end the episode (unhealthy) once the torso turns upside down. Off in Ant-v4, where a
    /// flipped Ant stays inside the height band and flails until the step limit.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub terminate_upside_down: bool,
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self {
            model_path: None,
            frame_skip: 5,
            reset_noise_scale: 0.1,
            ctrl_cost_weight: 0.5,
            healthy_reward: 1.0,
            healthy_z_range: [0.2, 1.0],
            goal: [5.0, 5.0],
            success_radius: 1.0,
            native_reward_weight: 0.5,
            progress_weight: 50.0,
            success_bonus: 200.0,
            max_episode_steps: 1000,
            terminate_upside_down: false,
        }
    }
}

/// The context window (the paper's "ContextHistoryWrapper").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ContextConfig {
    /// Number of past (observation, action) pairs the encoder sees.
    pub len: usize,
}

impl Default for ContextConfig {
    fn default() -> Self {
        Self { len: 16 }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("config file {path} is not a valid gaitscope config: {source}")]
    Parse {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("invalid config: {0}")]
    Invalid(String),
    #[error("unknown world '{name}' (the shipped worlds: {known}; or a world file, FILE.json)")]
    UnknownWorld { name: String, known: String },
}

/// A config file's size, at most (the shipped ones are under 2 KB; `/dev/zero` is refused).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

impl GaitConfig {
    /// Reads a JSON config; missing fields take their defaults, unknown fields are an error.
    /// Only a regular file is read, and at most [`MAX_CONFIG_BYTES`] of it.
    pub fn from_json_file(path: &Path) -> Result<Self, ConfigError> {
        let text = crate::files::read_text_capped(path, MAX_CONFIG_BYTES).map_err(|source| {
            if source.kind() == std::io::ErrorKind::FileTooLarge {
                ConfigError::Invalid(format!(
                    "{} is larger than the {MAX_CONFIG_BYTES} bytes a config may have",
                    path.display()
                ))
            } else {
                ConfigError::Read {
                    path: path.to_owned(),
                    source,
                }
            }
        })?;
        let config: Self = serde_json::from_str(&text).map_err(|source| ConfigError::Parse {
            path: path.to_owned(),
            source,
        })?;
        config.validate()?;
        Ok(config)
    }

    /// The step limit a trained policy runs to when a command is not told one: the paper's
    /// evaluation limit in the paper's world (which trains to 1,000 and judges at 500), the
    /// world's own limit in any other (dead-legs: 1,000; dead-legs-short: 400), so a policy is
    /// never run past the episode its world defines.
    pub fn run_step_limit(&self) -> usize {
        if is_paper(&self.world) {
            self.env.max_episode_steps.min(PAPER_EVAL_STEPS)
        } else {
            self.env.max_episode_steps
        }
    }

    /// A shipped world by name ([`WORLDS`]), or a world file (a path ending in `.json`).
    pub fn world(name_or_path: &str) -> Result<Self, ConfigError> {
        if let Some((_, text)) = WORLDS.iter().find(|(n, _)| *n == name_or_path) {
            let config: Self = serde_json::from_str(text).map_err(|source| ConfigError::Parse {
                path: PathBuf::from(format!("worlds/{name_or_path}.json")),
                source,
            })?;
            config.validate()?;
            return Ok(config);
        }
        if name_or_path.ends_with(".json") {
            return Self::from_json_file(Path::new(name_or_path));
        }
        Err(ConfigError::UnknownWorld {
            name: name_or_path.to_string(),
            known: WORLDS.map(|(n, _)| n).join(", "),
        })
    }

    /// Rejects values that would make the env meaningless or numerically broken.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |msg: String| Err(ConfigError::Invalid(msg));
        let e = &self.env;
        let d = &self.damage;
        let finite = [
            ("env.reset_noise_scale", e.reset_noise_scale),
            ("env.ctrl_cost_weight", e.ctrl_cost_weight),
            ("env.healthy_reward", e.healthy_reward),
            ("env.healthy_z_range[0]", e.healthy_z_range[0]),
            ("env.healthy_z_range[1]", e.healthy_z_range[1]),
            ("env.goal[0]", e.goal[0]),
            ("env.goal[1]", e.goal[1]),
            ("env.success_radius", e.success_radius),
            ("env.native_reward_weight", e.native_reward_weight),
            ("env.progress_weight", e.progress_weight),
            ("env.success_bonus", e.success_bonus),
            ("damage.alpha", d.alpha),
            ("damage.beta", d.beta),
            ("damage.threshold", d.threshold),
            ("damage.scales.healthy", d.scales.healthy),
            ("damage.scales.mild", d.scales.mild),
            ("damage.scales.severe", d.scales.severe),
        ];
        if let Some((name, value)) = finite.iter().find(|(_, v)| !v.is_finite()) {
            return invalid(format!("{name} must be finite, got {value}"));
        }
        // Upper bounds too: a huge frame_skip runs "forever", a huge window allocates
        // gigabytes, a goal at 1e308 turns distances into infinities that poison training.
        if !(1..=MAX_FRAME_SKIP).contains(&e.frame_skip) {
            return invalid(format!(
                "env.frame_skip must lie in 1..={MAX_FRAME_SKIP}, got {}",
                e.frame_skip
            ));
        }
        if !(1..=MAX_EPISODE_STEPS).contains(&e.max_episode_steps) {
            return invalid(format!(
                "env.max_episode_steps must lie in 1..={MAX_EPISODE_STEPS}, got {}",
                e.max_episode_steps
            ));
        }
        if e.goal.iter().any(|g| g.abs() > MAX_GOAL_M) {
            return invalid(format!(
                "env.goal {:?} must lie within ±{MAX_GOAL_M} m (the floor is 80 m wide)",
                e.goal
            ));
        }
        if !(0.0..=MAX_RESET_NOISE).contains(&e.reset_noise_scale) {
            return invalid(format!(
                "env.reset_noise_scale must lie in [0, {MAX_RESET_NOISE}], got {}",
                e.reset_noise_scale
            ));
        }
        for (name, value) in [
            ("env.ctrl_cost_weight", e.ctrl_cost_weight),
            ("env.healthy_reward", e.healthy_reward),
            ("env.native_reward_weight", e.native_reward_weight),
            ("env.progress_weight", e.progress_weight),
            ("env.success_bonus", e.success_bonus),
        ] {
            if value.abs() > MAX_REWARD_TERM {
                return invalid(format!(
                    "{name} must lie within ±{MAX_REWARD_TERM}, got {value}"
                ));
            }
        }
        if e.healthy_z_range.iter().any(|z| z.abs() > MAX_GOAL_M) {
            return invalid(format!(
                "env.healthy_z_range {:?} must lie within ±{MAX_GOAL_M} m",
                e.healthy_z_range
            ));
        }
        if e.healthy_z_range[0] > e.healthy_z_range[1] {
            return invalid(format!(
                "env.healthy_z_range {:?} is empty",
                e.healthy_z_range
            ));
        }
        if !(e.success_radius > 0.0 && e.success_radius <= MAX_GOAL_M) {
            return invalid(format!(
                "env.success_radius must lie in (0, {MAX_GOAL_M}] m, got {}",
                e.success_radius
            ));
        }
        // Fatigue grows by alpha·|a| + beta·‖force‖ a step: past 1e6 it triggers at once anyway.
        if !((0.0..=1e6).contains(&d.alpha)
            && (0.0..=1e6).contains(&d.beta)
            && d.threshold > 0.0
            && d.threshold <= 1e12)
        {
            return invalid(format!(
                "damage.alpha and damage.beta must lie in [0, 1e6] and damage.threshold in (0, 1e12] \
                 (got {}, {}, {})",
                d.alpha, d.beta, d.threshold
            ));
        }
        for (name, s) in [
            ("healthy", d.scales.healthy),
            ("mild", d.scales.mild),
            ("severe", d.scales.severe),
        ] {
            if !(0.0..=1.0).contains(&s) {
                return invalid(format!("damage.scales.{name} must lie in [0, 1], got {s}"));
            }
        }
        if let Some(dead) = &d.dead {
            dead.check().map_err(ConfigError::Invalid)?;
        }
        let name = &self.world.0;
        if name.trim().is_empty() || name.len() > 64 || name.chars().any(char::is_control) {
            return invalid(format!(
                "world: {name:?} must be a name of 1 to 64 printable characters"
            ));
        }
        if !(1..=MAX_CONTEXT_LEN).contains(&self.context.len) {
            return invalid(format!(
                "context.len must lie in 1..={MAX_CONTEXT_LEN}, got {}",
                self.context.len
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn numbers_past_their_ranges_are_refused_with_the_range() {
        type Edit = fn(&mut super::GaitConfig);
        let cases: [(&str, Edit); 10] = [
            ("env.frame_skip must lie in 1..=1000", |c| {
                c.env.frame_skip = 100_000_000
            }),
            // A uniform draw over ±1e308 panicked inside rand (a --config or resumed run).
            ("env.reset_noise_scale must lie in [0, 1]", |c| {
                c.env.reset_noise_scale = 1e308
            }),
            ("env.success_bonus must lie within ±1000000", |c| {
                c.env.success_bonus = 1e308
            }),
            ("env.healthy_reward must lie within", |c| {
                c.env.healthy_reward = -2e6
            }),
            ("env.success_radius must lie in (0, 1000] m", |c| {
                c.env.success_radius = f64::MAX
            }),
            ("damage.alpha and damage.beta must lie in [0, 1e6]", |c| {
                c.damage.beta = 1e308
            }),
            ("env.healthy_z_range", |c| {
                c.env.healthy_z_range = [0.2, 1e300]
            }),
            ("context.len must lie in 1..=1024", |c| {
                c.context.len = 100_000_000
            }),
            ("env.goal", |c| c.env.goal = [1e308, 1e308]),
            ("env.max_episode_steps must lie in", |c| {
                c.env.max_episode_steps = usize::MAX
            }),
        ];
        for (says, edit) in cases {
            let mut c = super::GaitConfig::default();
            edit(&mut c);
            let err = c.validate().unwrap_err().to_string();
            assert!(err.contains(says), "{err}");
        }
        // The bounds themselves are allowed.
        let mut c = super::GaitConfig::default();
        c.env.frame_skip = super::MAX_FRAME_SKIP;
        c.context.len = super::MAX_CONTEXT_LEN;
        c.env.goal = [super::MAX_GOAL_M, -super::MAX_GOAL_M];
        assert!(c.validate().is_ok());
    }

    use super::*;

    #[test]
    fn defaults_are_the_specified_experiment() {
        let c = GaitConfig::default();
        assert_eq!(c.env.frame_skip, 5);
        assert_eq!(c.env.goal, [5.0, 5.0]);
        assert_eq!(
            (c.damage.alpha, c.damage.beta, c.damage.threshold),
            (1.0, 0.1, 30.0)
        );
        assert_eq!(
            c.damage.scales,
            ConditionScales {
                healthy: 1.0,
                mild: 0.5,
                severe: 0.1
            }
        );
        assert_eq!(c.context.len, 16);
        c.validate().expect("defaults are valid");
    }

    #[test]
    fn partial_json_keeps_defaults_and_unknown_fields_fail() {
        let c: GaitConfig = serde_json::from_str(r#"{"damage": {"threshold": 10.0}}"#).unwrap();
        assert_eq!(c.damage.threshold, 10.0);
        assert_eq!(c.damage.alpha, 1.0);
        assert!(serde_json::from_str::<GaitConfig>(r#"{"damage": {"treshold": 10.0}}"#).is_err());
    }

    #[test]
    fn a_policy_runs_to_its_worlds_own_limit() {
        let limit = |name: &str| GaitConfig::world(name).unwrap().run_step_limit();
        // The paper trains to 1,000 and judges at 500; the new worlds judge where they end.
        assert_eq!(GaitConfig::default().env.max_episode_steps, 1000);
        assert_eq!(limit("paper"), 500);
        assert_eq!(limit("dead-joints"), 1000);
        assert_eq!(limit("dead-legs"), 1000);
        assert_eq!(limit("dead-legs-short"), 400);
        // Never past the episode a config defines, in the paper's world either.
        let mut short_paper = GaitConfig::default();
        short_paper.env.max_episode_steps = 300;
        assert_eq!(short_paper.run_step_limit(), 300);
    }

    #[test]
    fn shipped_worlds_parse_and_name_themselves() {
        for (name, _) in WORLDS {
            let c = GaitConfig::world(name).unwrap();
            assert_eq!(c.world.0, name);
        }
        assert_eq!(GaitConfig::world("paper").unwrap(), GaitConfig::default());
        let dead = GaitConfig::world("dead-joints").unwrap();
        assert!(dead.damage.dead.is_some() && !dead.damage.fatigue);
        let err = GaitConfig::world("moon").unwrap_err().to_string();
        assert!(err.contains("paper, dead-joints, dead-legs"), "{err}");
        // dead-legs: whole legs only, 0 / 1 / 2 of them, all dead by step 60.
        let legs = GaitConfig::world("dead-legs").unwrap().damage.dead.unwrap();
        assert_eq!(legs.unit, crate::damage::DeadUnit::Leg);
        assert_eq!(legs.onset, [10, 60]);
        // dead-legs-short: the same deaths, a 400-step budget, and only a fall ends an episode
        // early — a flip or the torso sinking — not a leap (no ceiling worth the name).
        let short = GaitConfig::world("dead-legs-short").unwrap();
        assert_eq!(short.damage.dead, Some(legs));
        assert_eq!(short.env.max_episode_steps, 400);
        assert!(short.env.terminate_upside_down);
        assert_eq!(short.env.healthy_z_range, [0.2, 10.0]);
        assert!(!GaitConfig::default().env.terminate_upside_down);
        // The paper world writes no name (its checkpoints read as before); others do.
        assert!(
            !serde_json::to_string(&GaitConfig::default())
                .unwrap()
                .contains("world")
        );
        let text = serde_json::to_string(&dead).unwrap();
        assert!(text.contains(r#""world":"dead-joints""#), "{text}");
        assert_eq!(serde_json::from_str::<GaitConfig>(&text).unwrap(), dead);
    }

    #[test]
    fn each_world_says_what_its_conditions_mean() {
        use crate::damage::Condition;
        let paper = GaitConfig::default().damage;
        assert_eq!(
            paper.condition_meaning(Condition::Healthy),
            "fatigue weakens no joint"
        );
        assert_eq!(
            paper.condition_meaning(Condition::Mild),
            "a joint whose fatigue reaches 30 keeps 0.5× its torque"
        );
        let legs = GaitConfig::world("dead-legs").unwrap().damage;
        assert_eq!(legs.condition_meaning(Condition::Healthy), "nothing dies");
        assert_eq!(
            legs.condition_meaning(Condition::Severe),
            "2 legs die, each from a step in 10–60"
        );
        let joints = GaitConfig::world("dead-joints").unwrap().damage;
        assert_eq!(
            joints.condition_meaning(Condition::Mild),
            "1 joint or leg dies, from a step in 10–120"
        );
    }

    #[test]
    fn a_world_file_must_be_a_bounded_regular_file() {
        let err = GaitConfig::from_json_file(Path::new("/dev/zero"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("not a regular file"), "{err}");
        let err = GaitConfig::world("/nonexistent/w.json")
            .unwrap_err()
            .to_string();
        assert!(err.contains("/nonexistent/w.json"), "{err}");
    }

    #[test]
    fn invalid_values_are_named() {
        let mut c = GaitConfig::default();
        c.damage.scales.severe = 1.5;
        let err = c.validate().unwrap_err().to_string();
        assert!(err.contains("damage.scales.severe"), "{err}");
        let mut c = GaitConfig::default();
        c.env.goal[1] = f64::NAN;
        assert!(
            c.validate()
                .unwrap_err()
                .to_string()
                .contains("env.goal[1]")
        );
    }
}
