//! `gaitscope record` and `gaitscope view`.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use super::values::BuiltinArg;
use gaitscope::{Condition, ConditionChoice};

use super::{EnvArgs, fork_option};

#[derive(Args)]
pub(crate) struct RecordArgs {
    /// Checkpoint to record; without one, a built-in policy acts (see --policy).
    #[arg(long, value_name = "DIR")]
    checkpoint: Option<PathBuf>,
    /// A second checkpoint, side by side under identical damage and seeds.
    #[arg(long, value_name = "DIR", requires = "checkpoint")]
    compare: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = BuiltinArg::Random)]
    policy: BuiltinArg,
    /// Damage condition (default severe, as in `live` and `video`).
    #[arg(long, value_name = "healthy|mild|severe")]
    condition: Option<Condition>,
    #[arg(long, default_value_t = 1)]
    episodes: usize,
    /// Episode k uses seed S + k (for every model). Default for checkpoints: the most typical
    /// of seeds 0–7 (each model's usual outcome, nearest its median; the recording's key and
    /// the terminal say how it was chosen); for a built-in policy, 0.
    #[arg(long)]
    seed: Option<u64>,
    /// Truncate episodes after this many steps (default: the models' world's limit — 500 in the
    /// paper's world, dead-legs 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
    /// The .rrd file to write.
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Fork the (first) checkpoint's episode before step K: a second lane (`fork`, drawn beside
    /// it) from the identical state with --fork's edits.
    #[arg(long, value_name = "K", requires_all = ["checkpoint", "fork"])]
    fork_at: Option<usize>,
    /// The fork's damage edits, as for `rollout --fork`.
    #[arg(long, value_name = "EDIT[,EDIT...]", requires = "fork_at")]
    fork: Option<String>,
    /// Start every episode from this state (a saved state, `rollout --save-state-at`, with its
    /// damage; or a bare {"qpos", "qvel"} under the episode's condition).
    #[arg(long, value_name = "FILE")]
    init_state: Option<PathBuf>,
    /// Also record why z moved at every step (integrated gradients of ‖z − z(0)‖ over the
    /// window: a slot × joint heatmap; encoder models).
    #[arg(long)]
    attribution: bool,
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
pub(crate) struct ViewArgs {
    /// The recording to open.
    file: PathBuf,
    /// The Rerun viewer binary (default: $GAITSCOPE_RERUN, .deps/rerun/rerun, then PATH).
    #[arg(long, value_name = "PATH")]
    viewer: Option<PathBuf>,
}

pub(crate) fn record_command(args: RecordArgs) -> Result<()> {
    use gaitscope::telemetry::{self, Actor, RecordOptions, Sink};
    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    if args.out.extension().and_then(|e| e.to_str()) != Some("rrd") {
        bail!(
            "--out {} should end in .rrd (the file the Rerun viewer opens)",
            args.out.display()
        );
    }
    let mut config = args.env.load()?;
    config.damage.condition = ConditionChoice::Fixed(args.condition.unwrap_or(Condition::Severe));
    let mut actors = Vec::new();
    for dir in args.checkpoint.iter().chain(&args.compare) {
        actors.push(Actor::load(dir)?);
    }
    if actors.is_empty() {
        actors.push(Actor::Builtin(args.policy.into()));
    }
    config.env.max_episode_steps = super::step_limit(args.max_steps, &actors, &config)?;
    for actor in &actors {
        args.env.note_unused(actor, &config);
    }
    let (seed, caption) = super::demo_seed(args.seed, &actors, &config)?;
    let start = super::start_state(args.init_state.as_deref(), &actors)?;
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
        .context("installing the Ctrl-C handler")?;
    let opts = RecordOptions {
        actors,
        config,
        episodes: args.episodes,
        seed,
        sink: Sink::File(args.out.clone()),
        fork: fork_option(args.fork_at, args.fork.as_deref())?,
        start,
        attribution: args.attribution,
        caption,
    };
    let summary = telemetry::record(opts, &stop)?;
    for ending in &summary.endings {
        eprintln!("{ending}");
    }
    let size = std::fs::metadata(&args.out).map(|m| m.len()).unwrap_or(0);
    eprintln!(
        "{}: {} episodes, {} steps, {:.1} MB → {} (open with `gaitscope view {}`)",
        if summary.interrupted {
            "interrupted, recording flushed"
        } else {
            "done"
        },
        summary.episodes,
        summary.steps,
        size as f64 / 1e6,
        args.out.display(),
        args.out.display()
    );
    Ok(())
}

pub(crate) fn view_command(args: ViewArgs) -> Result<()> {
    use gaitscope::app::viewer;
    // The file first: a wrong path is the likelier mistake, and needs no display to report.
    viewer::check_recording(&args.file)?;
    // Read through once: a file cut short (a killed writer, a full disk) or damaged still opens,
    // but the viewer would show the part before without a word.
    if let Err(reason) = gaitscope::telemetry::read_back(&args.file) {
        eprintln!(
            "warning: {} is not whole: {reason}; the viewer shows what comes before",
            args.file.display()
        );
    }
    viewer::require_display("gaitscope view")?;
    let path = viewer::find_viewer(args.viewer.as_deref())?;
    viewer::view_recording(&path, &args.file)?;
    Ok(())
}
