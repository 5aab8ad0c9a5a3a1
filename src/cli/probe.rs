//! `gaitscope probe`.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

#[derive(Args)]
pub(crate) struct ProbeArgs {
    /// Encoder checkpoints whose z is probed (probe.json is written into each); seeds of one
    /// model (`encoder-lstm`, `encoder-lstm-s1`, …) are also summarised together.
    #[arg(long = "checkpoint", value_name = "DIR", required = true, num_args = 1..)]
    checkpoints: Vec<PathBuf>,
    /// Baseline checkpoint, for the progress-at-onset comparison.
    #[arg(long, value_name = "DIR")]
    baseline: Option<PathBuf>,
    /// Episodes per condition.
    #[arg(long, default_value_t = 50)]
    episodes: usize,
    /// Cross-validation folds (grouped by episode).
    #[arg(long, default_value_t = 5)]
    folds: usize,
    /// Keep the raw window for the window probe on every this-many-th step.
    #[arg(long, default_value_t = 4)]
    window_every: usize,
    /// Leave each checkpoint's probe.json (the live readout's probes) as it is.
    #[arg(long)]
    no_save: bool,
    /// Episodes end after this many steps (default: the models' world's limit — 500 in the
    /// paper's world, dead-legs 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
    #[arg(long, default_value_t = 2_000_000_000)]
    seed: u64,
    /// Folder for the figures.
    #[arg(long, value_name = "DIR", default_value = "probe")]
    out: PathBuf,
}

pub(crate) fn probe_command(args: ProbeArgs) -> Result<()> {
    let max_steps = super::step_limit_of_dirs(
        args.max_steps,
        args.checkpoints.iter().chain(&args.baseline),
    )?;
    let run = gaitscope::probe::pipeline::run(&gaitscope::probe::pipeline::ProbeOptions {
        checkpoints: args.checkpoints,
        baseline: args.baseline,
        episodes: args.episodes,
        max_steps,
        seed: args.seed,
        window_every: args.window_every,
        folds: args.folds,
        save: !args.no_save,
        out: args.out,
    })?;
    for (label, probes) in &run.probes {
        println!("{label}: the probes live telemetry reads\n\n{probes}");
    }
    for cv in &run.report.runs {
        eprintln!(
            "{}: {} episodes, {} steps cross-validated",
            cv.model, cv.episodes, cv.steps
        );
    }
    println!("{}", run.report.markdown());
    for path in &run.written {
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}
