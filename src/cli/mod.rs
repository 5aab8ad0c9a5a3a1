//! The command line, one module per command; each parses its flags and calls the library.

pub mod bench;
pub mod eval;
pub mod explain;
pub mod import;
pub mod live;
pub(crate) mod notes;
pub mod probe;
pub mod record;
pub mod rollout;
pub mod search;
pub mod train;
mod values;
pub mod video;

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

use gaitscope::GaitConfig;

/// Options shared by every command that builds an env.
#[derive(Args)]
pub(crate) struct EnvArgs {
    /// A shipped world (paper, the default; dead-joints: actuators die over a longer walk;
    /// dead-legs: whole legs die early in it; dead-legs-short: the same in 400 steps, where only
    /// a fall — a flip, not a leap — ends an episode early; docs/world.md) or a world file. A checkpoint runs in its own world
    /// whatever this says.
    #[arg(long, value_name = "NAME|FILE", conflicts_with = "config")]
    pub(crate) world: Option<String>,
    /// JSON config (any subset of the fields; the rest keep their defaults).
    #[arg(long, value_name = "FILE")]
    pub(crate) config: Option<PathBuf>,
    /// MJCF model to load instead of the bundled assets/ant.xml.
    #[arg(long, value_name = "FILE")]
    pub(crate) model: Option<PathBuf>,
    /// Scripted damage: a scenario file, or a built-in one (ood-ankle, ood-leg, ood-diagonal,
    /// ood-decay, ood-intermittent, ood-sides, ood-late-fault; docs/scenarios.md).
    #[arg(long, value_name = "NAME|FILE")]
    pub(crate) scenario: Option<String>,
}

impl EnvArgs {
    /// A `--config`/`--model` on a checkpoint command: the checkpoint runs in the task it was
    /// trained in (lane::Actor::world), so say which of the file's sections go unused.
    pub(crate) fn note_unused(&self, actor: &gaitscope::lane::Actor, requested: &GaitConfig) {
        if self.config.is_none() && self.model.is_none() && self.world.is_none() {
            return;
        }
        let unused = actor.unused_settings(requested);
        if !unused.is_empty() {
            eprintln!(
                "note: {} runs in the task it was trained in: the {} settings of --world/--config/--model \
                 are not used (only the condition, scenario and step limit apply)",
                actor.label(),
                unused.join(", ")
            );
        }
    }

    pub(crate) fn load(&self) -> Result<GaitConfig> {
        let mut config = match (&self.world, &self.config) {
            (Some(world), _) => GaitConfig::world(world)?,
            (None, Some(path)) => GaitConfig::from_json_file(path)?,
            (None, None) => GaitConfig::default(),
        };
        if let Some(model) = &self.model {
            config.env.model_path = Some(model.clone());
        }
        if let Some(scenario) = &self.scenario {
            config.damage.scenario = Some(gaitscope::damage::scenario::Scenario::load(scenario)?);
        }
        Ok(config)
    }
}

/// `--fork-at K --fork EDITS` (clap makes each require the other), parsed.
pub(crate) fn fork_option(
    at: Option<usize>,
    edits: Option<&str>,
) -> Result<Option<gaitscope::lane::Fork>> {
    Ok(match (at, edits) {
        (Some(at), Some(edits)) => Some(gaitscope::lane::Fork {
            at,
            edits: gaitscope::damage::Edit::parse_list(edits)?,
        }),
        _ => None,
    })
}

/// `--init-state`'s file, read and checked, with a warning for each model it does not fit
/// as saved (another model saved it, a window of another length).
pub(crate) fn start_state(
    path: Option<&std::path::Path>,
    actors: &[gaitscope::lane::Actor],
) -> Result<Option<gaitscope::lane::StartState>> {
    let Some(p) = path else {
        return Ok(None);
    };
    let state = gaitscope::rollout::read_init_state(p)?;
    for actor in actors {
        for note in state.notes_for(actor) {
            log::warn!("{}: {note}", p.display());
        }
    }
    Ok(Some(state))
}

/// `--max-steps`, or else the step limit the models' world runs a policy to
/// ([`GaitConfig::run_step_limit`]: 500 in the paper's world, the world's own elsewhere) — a
/// checkpoint's own world, the requested one for a built-in policy or a script. Models whose
/// worlds end at different steps need the flag: one limit is chosen for all of them.
pub(crate) fn step_limit(
    given: Option<usize>,
    actors: &[gaitscope::lane::Actor],
    requested: &GaitConfig,
) -> Result<usize> {
    let labels: Vec<String> = actors.iter().map(|a| a.label()).collect();
    let worlds = actors
        .iter()
        .map(|a| a.trained_world().unwrap_or(requested));
    step_limit_of(
        given,
        labels.iter().map(String::as_str).zip(worlds),
        requested,
    )
}

/// [`step_limit`] for checkpoint folders (their checkpoint.json says their world).
pub(crate) fn step_limit_of_dirs<'a>(
    given: Option<usize>,
    dirs: impl IntoIterator<Item = &'a PathBuf>,
) -> Result<usize> {
    let default = GaitConfig::default();
    if given.is_some() {
        return step_limit_of(given, [], &default);
    }
    let mut named = Vec::new();
    for dir in dirs {
        let meta = gaitscope::policy::checkpoint::read_meta(dir)?;
        named.push((gaitscope::eval::model_label(dir), meta.env));
    }
    step_limit_of(None, named.iter().map(|(l, w)| (l.as_str(), w)), &default)
}

/// [`step_limit`] for models named by label and world.
pub(crate) fn step_limit_of<'a>(
    given: Option<usize>,
    worlds: impl IntoIterator<Item = (&'a str, &'a GaitConfig)>,
    requested: &GaitConfig,
) -> Result<usize> {
    if let Some(limit) = given {
        if limit == 0 {
            bail!("--max-steps must be at least 1");
        }
        return Ok(limit);
    }
    let mut worlds = worlds.into_iter();
    let Some((first, first_world)) = worlds.next() else {
        return Ok(requested.run_step_limit());
    };
    let limit = first_world.run_step_limit();
    if let Some((other, other_world)) = worlds.find(|(_, w)| w.run_step_limit() != limit) {
        bail!(
            "{first} runs to {limit} steps in its world ({}) and {other} to {} in its own ({}): \
             give --max-steps to run them to one limit",
            first_world.world,
            other_world.run_step_limit(),
            other_world.world
        );
    }
    Ok(limit)
}

/// `--suite`'s long help: each built-in scenario with its one-line description.
pub(crate) fn suite_help() -> String {
    let mut help = String::from(
        "A built-in suite of scenarios, each its own column (fatigue off in all):\n\nood:",
    );
    for s in gaitscope::damage::scenario::Scenario::suite("ood").unwrap_or_default() {
        help += &format!("\n  {:<18} {}", s.name, s.description);
    }
    help
}

/// The seed a demo starts from: the caller's, or for checkpoints the most typical of
/// [`gaitscope::eval::typical::DEFAULT_CANDIDATES`] (printed, and the caption for the key).
pub(crate) fn demo_seed(
    seed: Option<u64>,
    actors: &[gaitscope::lane::Actor],
    config: &GaitConfig,
) -> Result<(u64, Option<String>)> {
    if let Some(seed) = seed {
        return Ok((seed, None));
    }
    if actors.iter().any(|a| a.policy().is_none()) {
        return Ok((0, None));
    }
    use gaitscope::eval::typical::{DEFAULT_CANDIDATES, typical_episode};
    let pick = typical_episode(actors, config, DEFAULT_CANDIDATES)?;
    let caption = pick.caption();
    eprintln!("{caption}");
    Ok((pick.seed, Some(caption)))
}
