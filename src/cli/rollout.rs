//! `gaitscope rollout`: built-in policies, checkpoints, replays, forks.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::io::{BufWriter, Write};
use std::path::PathBuf;

use gaitscope::rollout;

use super::values::BuiltinArg;
use gaitscope::{AntEnv, Condition, ConditionChoice};

use super::{EnvArgs, fork_option};

#[derive(Args)]
pub(crate) struct RolloutArgs {
    #[command(flatten)]
    env: EnvArgs,
    /// Damage condition (default severe, as in `record`, `live` and `video`; with --init-state,
    /// a saved state's own).
    #[arg(long, value_name = "healthy|mild|severe")]
    condition: Option<Condition>,
    #[arg(long, value_enum, default_value_t = BuiltinArg::Random, conflicts_with = "init_state")]
    policy: BuiltinArg,
    /// Episodes to run (default 5; with --init-state there is one, from that state).
    #[arg(long, value_name = "N")]
    episodes: Option<usize>,
    /// Episode k is reset with seed S + k (default 0; not with --init-state, whose state is
    /// the start).
    #[arg(long, value_name = "S")]
    seed: Option<u64>,
    /// Truncate episodes after this many steps (default: the world's limit for a trained
    /// policy — 500, the evaluation's, in the paper's world, which trains to 1000; dead-legs
    /// 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
    /// One JSON object per episode instead of a text line.
    #[arg(long, conflicts_with = "init_state")]
    json: bool,
    /// Replay (with --actions) or a --checkpoint's episode: the starting state, a saved state
    /// (--save-state-at: physics, damage, window) or a bare {"qpos": [15], "qvel": [14]}.
    #[arg(long, value_name = "FILE")]
    init_state: Option<PathBuf>,
    /// Write the first episode's state before step K to FILE (for --init-state, and an MJCF
    /// <key> for MuJoCo).
    #[arg(long, num_args = 2, value_names = ["K", "FILE"], requires = "checkpoint")]
    save_state_at: Option<Vec<String>>,
    /// Replay: the actions, [[8 numbers], ...].
    #[arg(long, value_name = "FILE", requires = "init_state")]
    actions: Option<PathBuf>,
    /// One JSON line per step, the state after that step (replay; or the episodes of a
    /// --checkpoint or built-in policy, with "lane" and the commanded "action").
    #[arg(long)]
    jsonl: bool,
    /// Run this checkpoint's deterministic policy instead of a built-in one.
    #[arg(long, value_name = "DIR", conflicts_with = "actions")]
    checkpoint: Option<PathBuf>,
    /// Fork each episode before step K: a second lane from the identical state, with --fork's
    /// edits applied, runs to its own end.
    #[arg(long, value_name = "K", requires_all = ["checkpoint", "fork"])]
    fork_at: Option<usize>,
    /// The fork's damage edits: none, heal:all, heal:JOINT, fail:JOINT, scale:JOINT=S,
    /// reset-fatigue:JOINT, comma-separated (JOINT by name, e.g. ankle_3).
    #[arg(long, value_name = "EDIT[,EDIT...]", requires = "fork_at")]
    fork: Option<String>,
}

pub(crate) fn rollout_command(args: RolloutArgs) -> Result<()> {
    let mut config = args.env.load()?;
    if let Some(condition) = args.condition {
        config.damage.condition = ConditionChoice::Fixed(condition);
    } else if args.init_state.is_none() {
        config.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    }
    let mut out = BufWriter::new(std::io::stdout().lock());

    if args.init_state.is_some() && args.actions.is_none() && args.checkpoint.is_none() {
        bail!("--init-state needs --actions (a replay) or --checkpoint (a policy from that state)");
    }
    if let (Some(init_path), Some(actions_path)) = (&args.init_state, &args.actions) {
        let init = rollout::read_init_state(init_path)?;
        let actions = rollout::read_actions(actions_path)?;
        config.env.max_episode_steps = super::step_limit(args.max_steps, &[], &config)?;
        rollout::replay(&config, &init, args.condition, &actions, |record| {
            serde_json::to_writer(&mut out, record)?;
            writeln!(out)
        })?;
        out.flush()?;
        return Ok(());
    }

    if args.init_state.is_some() {
        // Said with the reason, where clap's conflict would only name the flags.
        for (flag, given) in [
            ("--episodes", args.episodes.is_some()),
            ("--seed", args.seed.is_some()),
        ] {
            if given {
                bail!(
                    "{flag} does not apply with --init-state: an episode from a given state is \
                     one episode, and its state (not a seed) is where it starts"
                );
            }
        }
    }
    let episodes = args.episodes.unwrap_or(5);
    let seed = args.seed.unwrap_or(0);
    if episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    if let Some(dir) = &args.checkpoint {
        // The checkpoint runs in its own world (lane::Actor::world), with this condition and limit.
        let actor = gaitscope::lane::Actor::load(dir)?;
        config.env.max_episode_steps =
            super::step_limit(args.max_steps, std::slice::from_ref(&actor), &config)?;
        args.env.note_unused(&actor, &config);
        let fork = fork_option(args.fork_at, args.fork.as_deref())?;
        let save_at = save_state_option(args.save_state_at.as_deref())?;
        let init = super::start_state(args.init_state.as_deref(), std::slice::from_ref(&actor))?;
        // From a given state there is one episode to run (--episodes conflicts with it).
        let episodes = if init.is_some() { 1 } else { episodes };
        for episode in 0..episodes {
            // A saved state's episode keeps its seed.
            let seed = match &init {
                Some(gaitscope::lane::StartState::Saved(s)) => s.seed,
                _ => seed.wrapping_add(episode as u64),
            };
            let start = match &init {
                Some(state) => rollout::Start::State(state, args.condition),
                None => rollout::Start::Reset,
            };
            let save = save_at.as_ref().filter(|_| episode == 0).map(|(k, _)| *k);
            let run = rollout::run_policy_episode(
                &actor,
                &config,
                episode,
                seed,
                start,
                fork.as_ref(),
                save,
                |r| step_line(&mut out, args.jsonl, r),
            )
            .with_context(|| format!("episode {episode} (seed {seed})"))?;
            if let (Some(state), Some((k, path))) = (&run.saved, &save_at) {
                gaitscope::policy::checkpoint::write_atomic(path, state.to_json().as_bytes())
                    .with_context(|| format!("writing the state before step {k}"))?;
                eprintln!("saved the state before step {k} to {}", path.display());
            }
            summary_line(&mut out, &args, &run.summary)?;
            if let Some(fork) = &run.fork {
                if !args.json && !args.jsonl {
                    write!(out, "  fork ")?;
                }
                summary_line(&mut out, &args, fork)?;
            }
        }
        return Ok(());
    }
    config.env.max_episode_steps = super::step_limit(args.max_steps, &[], &config)?;
    let mut env = AntEnv::new(config, seed)?;
    for episode in 0..episodes {
        let seed = seed.wrapping_add(episode as u64);
        let summary =
            rollout::run_builtin_episode_with(&mut env, args.policy.into(), episode, seed, |r| {
                step_line(&mut out, args.jsonl, r)
            })
            .with_context(|| format!("episode {episode} (seed {seed})"))?;
        summary_line(&mut out, &args, &summary)?;
    }
    Ok(())
}

/// `--save-state-at K FILE`, parsed.
fn save_state_option(values: Option<&[String]>) -> Result<Option<(usize, PathBuf)>> {
    let Some(values) = values else {
        return Ok(None);
    };
    let [k, file] = values else {
        bail!("--save-state-at takes two values: K FILE");
    };
    let k: usize = k
        .parse()
        .with_context(|| format!("--save-state-at K: '{k}' is not a step number"))?;
    Ok(Some((k, PathBuf::from(file))))
}

/// One step's JSON line (with --jsonl).
pub(crate) fn step_line(
    out: &mut impl Write,
    jsonl: bool,
    r: &rollout::LaneRecord,
) -> std::io::Result<()> {
    if jsonl {
        serde_json::to_writer(&mut *out, r)?;
        writeln!(out)?;
    }
    Ok(())
}

/// An episode's summary: a JSON object (--json), a text line, or nothing (--jsonl).
pub(crate) fn summary_line(
    out: &mut impl Write,
    args: &RolloutArgs,
    summary: &rollout::EpisodeSummary,
) -> Result<()> {
    if args.json {
        serde_json::to_writer(&mut *out, summary)?;
        writeln!(out)?;
    } else if !args.jsonl {
        writeln!(out, "{summary}")?;
    }
    out.flush()?;
    Ok(())
}
