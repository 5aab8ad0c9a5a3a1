//! The `gaitscope` command line: a thin layer over the library.

use anyhow::Result;
use clap::{Parser, Subcommand};

mod cli;
use cli::bench::BenchCommand;
use cli::eval::EvalArgs;
use cli::explain::ExplainArgs;
use cli::import::ImportSb3Args;
use cli::live::LiveArgs;
use cli::probe::ProbeArgs;
use cli::record::{RecordArgs, ViewArgs};
use cli::rollout::RolloutArgs;
use cli::search::SearchArgs;
use cli::train::{CurvesArgs, TrainArgs};
use cli::video::VideoArgs;

#[derive(Parser)]
#[command(
    name = "gaitscope",
    version,
    about = "Watch, train and debug legged-robot policies that adapt to joint damage"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run episodes of a checkpoint or a built-in policy as JSON lines, or replay an action sequence.
    Rollout(RolloutArgs),
    /// Train a SAC policy (optionally with a context encoder) on the damaged Ant.
    Train(TrainArgs),
    /// Record episodes headlessly to a .rrd file for the Rerun viewer.
    Record(RecordArgs),
    /// Watch a policy live in the Rerun viewer and damage its joints by hand from a control panel.
    Live(LiveArgs),
    /// Open a recording (.rrd) in the Rerun viewer to scrub it.
    View(ViewArgs),
    /// Evaluate checkpoints under each damage condition or scenario: paired episodes, tests across training seeds.
    Eval(EvalArgs),
    /// Linear probes and PCA on an encoder's z; saves probe.json next to the checkpoint.
    Probe(ProbeArgs),
    /// Which past steps drive z (or the action) at one step: integrated gradients over the window.
    Explain(ExplainArgs),
    /// Training curves (return, success, losses, α, triggers, aux losses) from metrics.jsonl, as a PNG.
    Curves(CurvesArgs),
    /// Render an episode to MP4 with MuJoCo's renderer (cargo feature `video`; needs ffmpeg).
    Video(VideoArgs),
    /// Convert a Stable-Baselines3 SAC archive (model.zip) into a gaitscope checkpoint.
    ImportSb3(ImportSb3Args),
    /// Find the damage that breaks a policy (or separates two): CMA-ES over damage schedules under a severity budget.
    Search(SearchArgs),
    /// Measure performance.
    #[command(subcommand)]
    Bench(BenchCommand),
}

fn main() {
    // candle asks for the thread count on every matmul; unset, that re-parses /proc/cpuinfo each
    // time, and on this 2-core machine its 2-thread GEMM is slower than 1 thread at our sizes
    // (measured: 30 vs 53 training steps/s). Set before any thread exists.
    if std::env::var_os("RAYON_NUM_THREADS").is_none() {
        // SAFETY: single-threaded here; nothing reads the environment concurrently.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    }
    let cli = Cli::parse();
    cli::notes::install();
    // SAFETY: no other thread exists yet.
    unsafe { gaitscope::env::keep_mujoco_logs_on_console() };
    if let Err(err) = run(cli) {
        if is_broken_pipe(&err) {
            return; // e.g. `gaitscope rollout --jsonl ... | head`
        }
        eprintln!("error: {}", error_chain(&err));
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Rollout(args) => cli::rollout::rollout_command(args),
        Command::Train(args) => cli::train::train_command(args),
        Command::Eval(args) => cli::eval::eval_command(args),
        Command::ImportSb3(args) => cli::import::import_sb3_command(args),
        Command::Video(args) => cli::video::video_command(args),
        Command::Record(args) => cli::record::record_command(args),
        Command::Live(args) => cli::live::live_command(args),
        Command::Curves(args) => cli::train::curves_command(args),
        Command::View(args) => cli::record::view_command(args),
        Command::Probe(args) => cli::probe::probe_command(args),
        Command::Explain(args) => cli::explain::explain_command(args),
        Command::Search(args) => cli::search::search_command(args),
        Command::Bench(command) => cli::bench::bench_command(command),
    }
}

/// The error and its causes, skipping a cause whose text its parent's message already contains
/// (our library errors name their cause inline).
fn error_chain(err: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in err.chain() {
        let part = cause.to_string();
        if !text.contains(&part) {
            if !text.is_empty() {
                text.push_str(": ");
            }
            text.push_str(&part);
        }
    }
    text
}

fn is_broken_pipe(err: &anyhow::Error) -> bool {
    err.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
    })
}
