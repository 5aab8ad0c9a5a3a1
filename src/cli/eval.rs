//! `gaitscope eval`.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

use gaitscope::Condition;

use super::suite_help;

#[derive(Args)]
pub(crate) struct EvalArgs {
    /// Checkpoint folders (give a baseline and encoders to get paired tests and the recovery fraction).
    #[arg(
        long = "checkpoint",
        value_name = "DIR",
        required_unless_present = "rescore",
        num_args = 1..
    )]
    checkpoints: Vec<PathBuf>,
    /// Summarise a saved evaluation again instead (its eval.json): this version's tables and
    /// figures from its episodes, no model run (options that choose episodes are refused).
    #[arg(long, value_name = "FILE", conflicts_with_all = [
        "checkpoints", "conditions", "scenario", "suite", "told_healthy", "episodes",
        "max_steps", "seed", "threads",
    ])]
    rescore: Option<PathBuf>,
    #[arg(long, default_value_t = 100)]
    episodes: usize,
    /// Conditions to evaluate (default: all three; with --scenario or --suite: healthy, the
    /// reference the scenarios are measured against).
    #[arg(long, num_args = 1.., value_name = "healthy|mild|severe")]
    conditions: Vec<Condition>,
    /// Scenarios to evaluate as well, each its own column: a file or a built-in name (repeat
    /// the flag for several).
    #[arg(long, value_name = "NAME|FILE")]
    scenario: Vec<String>,
    /// A built-in suite of scenarios: ood (one ankle, one leg, diagonal legs, decay,
    /// intermittent fault, sides mild/severe, a late fault; docs/scenarios.md).
    #[arg(long, value_name = "ood", long_help = suite_help())]
    suite: Vec<String>,
    /// Episodes end after this many steps; success is counted within it and within the paper's
    /// tighter budgets below it (default: the models' world's limit — 500 in the paper's world,
    /// dead-legs 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
    /// First evaluation seed; episode i uses seed + i for every model.
    #[arg(long, default_value_t = gaitscope::eval::EVAL_SEED_BASE)]
    seed: u64,
    /// An oracle checkpoint to evaluate again told every joint is healthy, whatever the damage:
    /// what knowing the damage is worth to that network (labelled MODEL-told-healthy-sN; give
    /// it with --checkpoint too to pair the two).
    #[arg(long, value_name = "DIR")]
    told_healthy: Vec<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Folder for eval.json and the figures.
    #[arg(long, value_name = "DIR", default_value = "eval")]
    out: PathBuf,
}

pub(crate) fn eval_command(args: EvalArgs) -> Result<()> {
    if let Some(saved) = &args.rescore {
        let report = gaitscope::eval::rescore(saved)?;
        println!("{}", report.markdown());
        for path in gaitscope::eval::write_outputs(&report, &args.out)? {
            eprintln!("wrote {}", path.display());
        }
        return Ok(());
    }
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let scenarios = gaitscope::damage::scenario::collect(&args.scenario, &args.suite)?;
    let cases = gaitscope::eval::cases(&args.conditions, &scenarios);
    let max_steps = super::step_limit_of_dirs(
        args.max_steps,
        args.checkpoints.iter().chain(&args.told_healthy),
    )?;
    let opts = gaitscope::eval::EvalOptions {
        checkpoints: args.checkpoints,
        told_healthy: args.told_healthy,
        episodes: args.episodes,
        seed_base: args.seed,
        conditions: cases,
        scenarios,
        max_steps,
        threads,
    };
    let report = gaitscope::eval::evaluate(&opts)?;
    println!("{}", report.markdown());
    for (model, secs) in &report.wall_time_s {
        let n = opts.episodes * opts.conditions.len();
        eprintln!(
            "{model}: {n} episodes in {secs:.1} s ({:.1} episodes/s, {threads} thread{})",
            n as f64 / secs,
            if threads == 1 { "" } else { "s" }
        );
    }
    for path in gaitscope::eval::write_outputs(&report, &args.out)? {
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}
