//! The `gaitscope` command line: a thin layer over the library.

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use std::io::{BufWriter, Write};
use std::path::PathBuf;

use gaitscope::bench::bench_env;
use gaitscope::policy::EncoderKind;
use gaitscope::policy::sb3::{self, ImportEncoder};
use gaitscope::rollout::{self, BuiltinPolicy};
use gaitscope::train::{self, sac::UpdatePath};
use gaitscope::{AntEnv, Condition, ConditionChoice, GaitConfig};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

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
    /// Run episodes with a built-in policy, or replay an action sequence from a given state.
    Rollout(RolloutArgs),
    /// Train a SAC policy (optionally with a context encoder) on the damaged Ant.
    Train(TrainArgs),
    /// Record episodes headlessly to a .rrd file for the Rerun viewer.
    Record(RecordArgs),
    /// Watch a policy live in the Rerun viewer and damage its joints by hand from a control panel.
    Live(LiveArgs),
    /// Open a recording (.rrd) in the Rerun viewer to scrub it.
    View(ViewArgs),
    /// Evaluate checkpoints under each damage condition (paired seeds, Wilson intervals, McNemar).
    Eval(EvalArgs),
    /// Linear probes and PCA on an encoder's z; saves probe.json next to the checkpoint.
    Probe(ProbeArgs),
    /// Training curves (return, success, losses, α, triggers) from runs' metrics.jsonl, as a PNG.
    Curves(CurvesArgs),
    /// Render an episode to MP4 with MuJoCo's renderer (cargo feature `video`; needs ffmpeg).
    Video(VideoArgs),
    /// Convert a Stable-Baselines3 SAC archive (model.zip) into a gaitscope checkpoint.
    ImportSb3(ImportSb3Args),
    /// Measure performance.
    #[command(subcommand)]
    Bench(BenchCommand),
}

/// Options shared by every command that builds an env.
#[derive(Args)]
struct EnvArgs {
    /// JSON config (any subset of the fields; the rest keep their defaults).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// MJCF model to load instead of the bundled assets/ant.xml.
    #[arg(long, value_name = "FILE")]
    model: Option<PathBuf>,
    /// Scripted damage: a scenario file, or a built-in one (ood-ankle, ood-leg, ood-diagonal,
    /// ood-decay, ood-intermittent, ood-sides, ood-late-fault; docs/scenarios.md).
    #[arg(long, value_name = "NAME|FILE")]
    scenario: Option<String>,
}

impl EnvArgs {
    /// A `--config`/`--model` on a checkpoint command: the checkpoint runs in the task it was
    /// trained in (lane::Actor::world), so say which of the file's sections go unused.
    fn note_unused(&self, actor: &gaitscope::lane::Actor, requested: &GaitConfig) {
        if self.config.is_none() && self.model.is_none() {
            return;
        }
        let unused = actor.unused_settings(requested);
        if !unused.is_empty() {
            eprintln!(
                "note: {} runs in the task it was trained in: the {} settings of --config/--model \
                 are not used (only the condition, scenario and step limit apply)",
                actor.label(),
                unused.join(", ")
            );
        }
    }

    fn load(&self) -> Result<GaitConfig> {
        let mut config = match &self.config {
            Some(path) => GaitConfig::from_json_file(path)?,
            None => GaitConfig::default(),
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

#[derive(Args)]
struct RolloutArgs {
    #[command(flatten)]
    env: EnvArgs,
    /// Damage condition; without it each episode draws one at random.
    #[arg(long, value_name = "healthy|mild|severe")]
    condition: Option<Condition>,
    #[arg(long, value_enum, default_value_t = BuiltinPolicy::Random, conflicts_with = "init_state")]
    policy: BuiltinPolicy,
    #[arg(long, default_value_t = 5, conflicts_with = "init_state")]
    episodes: usize,
    /// Episode k is reset with seed S + k.
    #[arg(long, default_value_t = 0, conflicts_with = "init_state")]
    seed: u64,
    /// Truncate episodes after this many steps (500, the evaluation's limit, as everywhere a
    /// policy runs; training alone uses the config's 1000).
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
    /// One JSON object per episode instead of a text line.
    #[arg(long, conflicts_with = "init_state")]
    json: bool,
    /// Replay (with --actions) or a --checkpoint's episode: the starting state,
    /// {"qpos": [15], "qvel": [14]}.
    #[arg(long, value_name = "FILE")]
    init_state: Option<PathBuf>,
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

#[derive(Args)]
struct TrainArgs {
    /// Check the options and config (the env is built once), print the resolved config as
    /// JSON and exit: nothing is trained or written (sweep launchers vet specs with it).
    #[arg(long)]
    check: bool,
    /// Feature extractor: none (baseline), lstm (the paper's, default), mlp-window (ablation).
    /// With --resume it must match the run's, and may be left out.
    #[arg(long, value_enum)]
    encoder: Option<EncoderKind>,
    /// Total env steps (a resumed run stops at the same total).
    #[arg(long, default_value_t = 500_000)]
    steps: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Run folder: checkpoint, optimiser state, replay buffer, metrics.jsonl.
    #[arg(
        long,
        value_name = "DIR",
        required_unless_present = "resume",
        conflicts_with = "resume"
    )]
    out: Option<PathBuf>,
    /// Continue the run in DIR (weights, optimiser, RNGs, step counter, replay buffer).
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    #[arg(long, default_value_t = 10_000)]
    checkpoint_every: u64,
    /// Skip saving the replay buffer (~80 MB) with checkpoints; a resume then refills it.
    #[arg(long)]
    no_save_replay: bool,
    /// Keep replay.bin in DIR instead of the run folder (e.g. under ~/.cache/gaitscope/, outside
    /// a git work tree); the run records it, so a later --resume finds it there.
    #[arg(long, value_name = "DIR")]
    replay_dir: Option<PathBuf>,
    /// A resume without its replay buffer first collects min(buffer size, steps done, N)
    /// transitions with the current policy, without updates (at least 10000).
    #[arg(long, value_name = "N", default_value_t = train::DEFAULT_REFILL)]
    refill: usize,
    /// One encoder for actor and critic (SB3's share_features_extractor).
    #[arg(long)]
    share_encoder: bool,
    /// Size of the encoder's latent z (default 32, the paper's); the window length is the
    /// config's `context.len`.
    #[arg(long)]
    z_dim: Option<usize>,
    #[arg(long)]
    batch_size: Option<usize>,
    #[arg(long)]
    buffer_size: Option<usize>,
    #[arg(long)]
    learning_starts: Option<usize>,
    /// No progress bar (logs still go to metrics.jsonl).
    #[arg(long)]
    quiet: bool,
    /// Threads per gradient update (default: every core this process may run on, so a run
    /// pinned with `taskset -c N` uses one). The trained weights do not depend on it.
    #[arg(long)]
    threads: Option<usize>,
    /// The update: fused (fast, the default) or reference (candle's autograd, for comparison).
    #[arg(long, value_enum, default_value_t = UpdatePath::Fused)]
    update: UpdatePath,
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
struct RecordArgs {
    /// Checkpoint to record; without one, a built-in policy acts (see --policy).
    #[arg(long, value_name = "DIR")]
    checkpoint: Option<PathBuf>,
    /// A second checkpoint, side by side under identical damage and seeds.
    #[arg(long, value_name = "DIR", requires = "checkpoint")]
    compare: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t = BuiltinPolicy::Random)]
    policy: BuiltinPolicy,
    /// Damage condition (default: random per episode).
    #[arg(long, value_name = "healthy|mild|severe")]
    condition: Option<Condition>,
    #[arg(long, default_value_t = 1)]
    episodes: usize,
    /// Episode k uses seed S + k (for every model).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
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
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
struct LiveArgs {
    /// Checkpoint to watch (any folder `gaitscope train` wrote).
    #[arg(long, value_name = "DIR", default_value = "checkpoints/encoder-lstm")]
    checkpoint: PathBuf,
    /// A second checkpoint, side by side under the same damage (e.g. checkpoints/baseline).
    #[arg(long, value_name = "DIR")]
    compare: Option<PathBuf>,
    #[arg(
        long,
        value_name = "healthy|mild|severe|manual",
        default_value = "severe"
    )]
    condition: gaitscope::app::LiveCondition,
    /// Seed of the first episode (each next episode uses the next seed).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Playback speed, a multiple of real time (20 env steps/s): 0.25 to 8.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
    /// Sample actions from the policy instead of taking its mean.
    #[arg(long)]
    sampled: bool,
    /// Start paused (step with the panel's Step button).
    #[arg(long)]
    paused: bool,
    /// Pause after any step where one of these holds, comma-separated: trigger, trigger:JOINT,
    /// override, termination, success, probe-flip (needs probe.json), step:N.
    #[arg(long, value_name = "LIST")]
    break_on: Option<String>,
    /// Fork the main model before step K of every episode (a `fork` lane beside it), with
    /// --fork's edits, as the panel's "Fork here" does.
    #[arg(long, value_name = "K", requires = "fork")]
    fork_at: Option<usize>,
    /// The fork's damage edits, as for `rollout --fork`.
    #[arg(long, value_name = "EDIT[,EDIT...]", requires = "fork_at")]
    fork: Option<String>,
    /// Stream to a viewer that is already running, e.g. rerun+http://HOST:9876/proxy.
    #[arg(long, value_name = "URL")]
    connect: Option<String>,
    /// Also save the session to this .rrd file.
    #[arg(long, value_name = "FILE")]
    save: Option<PathBuf>,
    /// The Rerun viewer binary (default: $GAITSCOPE_RERUN, .deps/rerun/rerun, then PATH).
    #[arg(long, value_name = "PATH")]
    viewer: Option<PathBuf>,
    /// Close after this many seconds and print the frame-rate / real-time report (scripts).
    #[arg(long, value_name = "SECONDS")]
    exit_after: Option<f64>,
    /// Serve the session to a browser instead of opening windows: Rerun's web viewer and a
    /// control page (no display needed; prints the URLs and an `ssh -L` line).
    #[arg(long, conflicts_with_all = ["connect", "viewer"])]
    web: bool,
    /// Address the web servers listen on. Anything but loopback lets whoever reaches the
    /// port drive the sim and watch the stream.
    #[arg(
        long,
        value_name = "ADDR",
        default_value = "127.0.0.1",
        requires = "web"
    )]
    bind: std::net::IpAddr,
    /// Port of the control page (the web viewer and its gRPC stream use the next two flags).
    #[arg(long, value_name = "P", default_value_t = 9080, requires = "web")]
    port: u16,
    #[arg(long, value_name = "P", default_value_t = 9090, requires = "web")]
    viewer_port: u16,
    #[arg(long, value_name = "P", default_value_t = 9876, requires = "web")]
    grpc_port: u16,
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
struct CurvesArgs {
    /// Run folders (or metrics.jsonl files); each becomes a line named after its folder.
    #[arg(long = "run", value_name = "DIR", required = true, num_args = 1..)]
    runs: Vec<PathBuf>,
    /// The PNG to write.
    #[arg(long, value_name = "FILE", default_value = "training_curves.png")]
    out: PathBuf,
}

#[derive(Args)]
struct VideoArgs {
    /// Checkpoint whose deterministic policy acts (default: the random built-in policy).
    #[arg(long, value_name = "DIR")]
    checkpoint: Option<PathBuf>,
    /// A second checkpoint beside the first, same seed and damage, each half the frame.
    #[arg(long, value_name = "DIR", conflicts_with = "fork_at")]
    compare: Option<PathBuf>,
    /// Fork the episode before step K: a second lane from the identical state with --fork's
    /// edits, beside the first.
    #[arg(long, value_name = "K", requires = "fork")]
    fork_at: Option<usize>,
    /// The fork's damage edits, as for `rollout --fork`.
    #[arg(long, value_name = "EDIT[,EDIT...]", requires = "fork_at")]
    fork: Option<String>,
    #[arg(long, value_enum, default_value_t = BuiltinPolicy::Random)]
    policy: BuiltinPolicy,
    #[arg(long, value_name = "healthy|mild|severe", default_value = "severe")]
    condition: Condition,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
    /// The MP4 to write (written to FILE.mp4.partial, renamed when complete).
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    #[arg(long, default_value_t = 1280)]
    width: usize,
    #[arg(long, default_value_t = 720)]
    height: usize,
    /// Frames per second; 20 is real time (one frame per env step).
    #[arg(long, default_value_t = 20)]
    fps: u32,
    /// track: follow the torso; fixed: a still view of start and goal.
    #[arg(long, value_enum, default_value_t = gaitscope::video::CameraMode::Track)]
    camera: gaitscope::video::CameraMode,
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
struct ImportSb3Args {
    /// The SB3 archive, as `model.save()` wrote it.
    model: PathBuf,
    /// The checkpoint folder to create (must not exist).
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// The encoder: auto picks none for a 29-d observation, lstm for the 621-d folded window.
    #[arg(long, value_enum, default_value_t = ImportEncoder::Auto)]
    encoder: ImportEncoder,
}

#[derive(Args)]
struct ViewArgs {
    /// The recording to open.
    file: PathBuf,
    /// The Rerun viewer binary (default: $GAITSCOPE_RERUN, .deps/rerun/rerun, then PATH).
    #[arg(long, value_name = "PATH")]
    viewer: Option<PathBuf>,
}

#[derive(Args)]
struct EvalArgs {
    /// Checkpoint folders (give a baseline and encoders to get paired tests and the recovery fraction).
    #[arg(long = "checkpoint", value_name = "DIR", required = true, num_args = 1..)]
    checkpoints: Vec<PathBuf>,
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
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
    /// First evaluation seed; episode i uses seed + i for every model.
    #[arg(long, default_value_t = gaitscope::eval::EVAL_SEED_BASE)]
    seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Folder for eval.json and the figures.
    #[arg(long, value_name = "DIR", default_value = "eval")]
    out: PathBuf,
}

#[derive(Args)]
struct ProbeArgs {
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
    #[arg(long, default_value_t = 500)]
    max_steps: usize,
    #[arg(long, default_value_t = 2_000_000_000)]
    seed: u64,
    /// Folder for the figures.
    #[arg(long, value_name = "DIR", default_value = "probe")]
    out: PathBuf,
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Env steps/s with random actions against bare MuJoCo on the same model.
    Env {
        #[arg(long, default_value_t = 20_000)]
        steps: usize,
        #[arg(long, default_value_t = 5)]
        runs: usize,
        #[command(flatten)]
        env: EnvArgs,
    },
    /// Telemetry cost: steps/s recorded to .rrd vs the same rollout without, bytes per step, memory.
    Record {
        /// Full-length (500-step) episodes to run each way.
        #[arg(long, default_value_t = 20)]
        episodes: usize,
    },
    /// Live loop: how far the simulation keeps up with real time at 1× and 8× (headless, with
    /// telemetry to a file), for a checkpoint alone and side by side with a second one.
    Live {
        #[arg(long, value_name = "DIR", default_value = "checkpoints/encoder-lstm")]
        checkpoint: PathBuf,
        #[arg(long, value_name = "DIR", default_value = "checkpoints/baseline")]
        compare: PathBuf,
        /// Seconds per measurement.
        #[arg(long, default_value_t = 10.0)]
        seconds: f64,
    },
    /// Evaluation throughput: 100 episodes per condition (300 in all) of one checkpoint.
    Eval {
        #[arg(long, value_name = "DIR")]
        checkpoint: PathBuf,
        #[arg(long, default_value_t = 100)]
        episodes: usize,
    },
    /// Training env steps/s per encoder (one update per step) against the updates alone.
    Train {
        /// Learning steps to time per encoder (after a 1,000-step random warm-up).
        #[arg(long, default_value_t = 1_000)]
        steps: u64,
        #[arg(long, value_enum, num_args = 1.., default_values_t = [EncoderKind::None, EncoderKind::Lstm, EncoderKind::MlpWindow])]
        encoders: Vec<EncoderKind>,
        /// The update to time: fused (what `train` runs) or reference (candle's autograd).
        #[arg(long, value_enum, default_value_t = UpdatePath::Fused)]
        update: UpdatePath,
        /// Threads per fused update (1: per-core figures, comparable with the peers).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// One JSON object per encoder instead of the table.
        #[arg(long)]
        json: bool,
    },
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
        Command::Rollout(args) => rollout_command(args),
        Command::Train(args) => train_command(args),
        Command::Eval(args) => eval_command(args),
        Command::ImportSb3(args) => import_sb3_command(args),
        Command::Video(args) => video_command(args),
        Command::Record(args) => record_command(args),
        Command::Live(args) => live_command(args),
        Command::Curves(args) => {
            use gaitscope::train::curves::{RunMetrics, figure};
            let mut runs = Vec::new();
            for run in &args.runs {
                let dir = if run.is_dir() {
                    run.as_path()
                } else {
                    run.parent().unwrap_or(run)
                };
                runs.push((gaitscope::eval::model_label(dir), RunMetrics::read(run)?));
            }
            figure(&runs, &args.out)?;
            eprintln!("wrote {}", args.out.display());
            Ok(())
        }
        Command::View(args) => view_command(args),
        Command::Bench(BenchCommand::Live {
            checkpoint,
            compare,
            seconds,
        }) => {
            if !(seconds.is_finite() && seconds > 0.0) {
                bail!("--seconds must be a positive number");
            }
            for row in gaitscope::bench::bench_live(&checkpoint, &compare, seconds)? {
                println!("{row}");
            }
            Ok(())
        }
        Command::Probe(args) => probe_command(args),
        Command::Bench(BenchCommand::Env { steps, runs, env }) => {
            if steps == 0 {
                bail!("--steps must be at least 1");
            }
            let report = bench_env(&env.load()?, steps, runs)?;
            println!("{report}");
            Ok(())
        }
        Command::Bench(BenchCommand::Record { episodes }) => {
            if episodes == 0 {
                bail!("--episodes must be at least 1");
            }
            let scratch =
                std::env::temp_dir().join(format!("gaitscope-bench-{}", std::process::id()));
            std::fs::create_dir_all(&scratch)?;
            let r = gaitscope::bench::bench_record(episodes, &scratch)?;
            let _ = std::fs::remove_dir_all(&scratch);
            println!(
                "{} steps: plain {:.0} steps/s, recorded {:.0} steps/s (telemetry {:.0} % of a recorded step), {:.0} bytes/step, RSS {:.0} → {:.0} MB",
                r.steps,
                r.plain_steps_per_s,
                r.recorded_steps_per_s,
                100.0 * r.telemetry_share(),
                r.bytes_per_step,
                r.rss_before_mb,
                r.rss_after_mb
            );
            Ok(())
        }
        Command::Bench(BenchCommand::Eval {
            checkpoint,
            episodes,
        }) => {
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            let opts = gaitscope::eval::EvalOptions {
                checkpoints: vec![checkpoint],
                episodes,
                seed_base: gaitscope::eval::EVAL_SEED_BASE,
                conditions: Condition::ALL.map(Into::into).to_vec(),
                scenarios: Vec::new(),
                max_steps: 500,
                threads,
            };
            let started = std::time::Instant::now();
            let report = gaitscope::eval::evaluate(&opts)?;
            let secs = started.elapsed().as_secs_f64();
            let steps: usize = report.episodes.iter().map(|e| e.steps).sum();
            println!(
                "{} episodes ({steps} env steps) in {secs:.1} s on {threads} threads: {:.1} episodes/s, {:.0} env steps/s",
                report.episodes.len(),
                report.episodes.len() as f64 / secs,
                steps as f64 / secs
            );
            Ok(())
        }
        Command::Bench(BenchCommand::Train {
            steps,
            encoders,
            update,
            threads,
            json,
        }) => {
            if steps == 0 || threads == 0 {
                bail!("--steps and --threads must be at least 1");
            }
            let scratch =
                std::env::temp_dir().join(format!("gaitscope-bench-{}", std::process::id()));
            let rows = gaitscope::bench::bench_train(&encoders, steps, update, threads, &scratch)?;
            let _ = std::fs::remove_dir_all(&scratch);
            if json {
                for r in &rows {
                    println!("{}", serde_json::to_string(r)?);
                }
                return Ok(());
            }
            println!("encoder     train steps/s  updates/s (no env)  act/s (batch 1)");
            for r in rows {
                println!(
                    "{:<11} {:>13.1}  {:>18.1}  {:>15.0}",
                    r.encoder.name(),
                    r.train_steps_per_s,
                    r.updates_per_s,
                    r.act_per_s
                );
            }
            Ok(())
        }
    }
}

fn rollout_command(args: RolloutArgs) -> Result<()> {
    let mut config = args.env.load()?;
    if args.max_steps == 0 {
        bail!("--max-steps must be at least 1");
    }
    config.env.max_episode_steps = args.max_steps;
    if let Some(condition) = args.condition {
        config.damage.condition = ConditionChoice::Fixed(condition);
    }
    let mut out = BufWriter::new(std::io::stdout().lock());

    if args.init_state.is_some() && args.actions.is_none() && args.checkpoint.is_none() {
        bail!("--init-state needs --actions (a replay) or --checkpoint (a policy from that state)");
    }
    if let (Some(init_path), Some(actions_path)) = (&args.init_state, &args.actions) {
        let Some(condition) = args.condition else {
            bail!(
                "replay needs --condition healthy|mild|severe (the damage scale must be explicit)"
            );
        };
        let init = rollout::read_init_state(init_path)?;
        let actions = rollout::read_actions(actions_path)?;
        rollout::replay(&config, &init, condition, &actions, |record| {
            serde_json::to_writer(&mut out, record)?;
            writeln!(out)
        })?;
        out.flush()?;
        return Ok(());
    }

    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    if let Some(dir) = &args.checkpoint {
        // The checkpoint runs in its own world (lane::Actor::world), with this condition and limit.
        let actor = gaitscope::lane::Actor::load(dir)?;
        args.env.note_unused(&actor, &config);
        let fork = fork_option(args.fork_at, args.fork.as_deref())?;
        let init = match &args.init_state {
            Some(path) => {
                let Some(condition) = args.condition else {
                    bail!(
                        "--init-state needs --condition healthy|mild|severe (the damage scale must be explicit)"
                    );
                };
                Some((rollout::read_init_state(path)?, condition))
            }
            None => None,
        };
        // From a given state there is one episode to run (--episodes conflicts with it).
        let episodes = if init.is_some() { 1 } else { args.episodes };
        for episode in 0..episodes {
            let seed = args.seed.wrapping_add(episode as u64);
            let start = match &init {
                Some((state, condition)) => rollout::Start::State(state, *condition),
                None => rollout::Start::Reset,
            };
            let (summary, fork_summary) = rollout::run_policy_episode(
                &actor,
                &config,
                episode,
                seed,
                start,
                fork.as_ref(),
                |r| step_line(&mut out, args.jsonl, r),
            )
            .with_context(|| format!("episode {episode} (seed {seed})"))?;
            summary_line(&mut out, &args, &summary)?;
            if let Some(fork) = &fork_summary {
                if !args.json && !args.jsonl {
                    write!(out, "  fork ")?;
                }
                summary_line(&mut out, &args, fork)?;
            }
        }
        return Ok(());
    }
    let mut env = AntEnv::new(config, args.seed)?;
    for episode in 0..args.episodes {
        let seed = args.seed.wrapping_add(episode as u64);
        let summary =
            rollout::run_builtin_episode_with(&mut env, args.policy, episode, seed, |r| {
                step_line(&mut out, args.jsonl, r)
            })
            .with_context(|| format!("episode {episode} (seed {seed})"))?;
        summary_line(&mut out, &args, &summary)?;
    }
    Ok(())
}

/// One step's JSON line (with --jsonl).
fn step_line(out: &mut impl Write, jsonl: bool, r: &rollout::LaneRecord) -> std::io::Result<()> {
    if jsonl {
        serde_json::to_writer(&mut *out, r)?;
        writeln!(out)?;
    }
    Ok(())
}

/// An episode's summary: a JSON object (--json), a text line, or nothing (--jsonl).
fn summary_line(
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

fn train_command(args: TrainArgs) -> Result<()> {
    let resume = args.resume.is_some();
    let Some(out) = args.resume.clone().or(args.out.clone()) else {
        bail!("train needs --out DIR (or --resume DIR)");
    };
    let encoder = match (&args.resume, args.encoder) {
        (Some(dir), expected) => {
            let found = gaitscope::policy::checkpoint::read_meta(dir)?.net.encoder;
            if let Some(expected) = expected
                && expected != found
            {
                bail!(
                    "{} is a '{found}' run; --encoder {expected} does not match",
                    dir.display()
                );
            }
            found
        }
        (None, encoder) => encoder.unwrap_or(EncoderKind::Lstm),
    };
    let mut opts = train::ant_options(encoder, args.steps, args.seed, out.clone());
    opts.env = args.env.load()?;
    // The config's window length is the one the encoder reads and the replay buffer stores.
    opts.net.context_len = opts.env.context.len;
    if let Some(z) = args.z_dim {
        opts.net.z_dim = z;
    }
    opts.net.share_encoder = args.share_encoder;
    opts.checkpoint_every = args.checkpoint_every;
    opts.save_replay = !args.no_save_replay;
    opts.replay_dir = args.replay_dir.clone();
    opts.refill = args.refill;
    opts.progress_bar = !args.quiet;
    if let Some(b) = args.batch_size {
        opts.sac.batch_size = b;
    }
    if let Some(b) = args.buffer_size {
        opts.sac.buffer_size = b;
    }
    if let Some(l) = args.learning_starts {
        opts.sac.learning_starts = l;
    }
    opts.update = args.update;
    opts.threads = match args.threads {
        Some(0) => bail!("--threads must be at least 1"),
        Some(n) => n,
        None => std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    if args.check {
        if resume {
            bail!("--check is for a fresh run (a resumed run keeps its own options)");
        }
        train::check_ant(&opts)?;
        eprintln!(
            "note: training episodes end after {} steps (the config's env.max_episode_steps); \
             eval, record, live, video and rollout run policies for 500 unless told otherwise",
            opts.env.env.max_episode_steps
        );
        // The task config at the top level, and the network and SAC settings the run would use.
        let mut resolved = serde_json::to_value(&opts.env)?;
        resolved["net"] = serde_json::to_value(&opts.net)?;
        resolved["sac"] = serde_json::to_value(&opts.sac)?;
        println!("{resolved}");
        return Ok(());
    }
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
        .context("installing the Ctrl-C handler")?;
    let summary = train::train_ant(opts, resume, stop)?;
    let how = match (summary.interrupted, summary.saved) {
        (false, _) => "done",
        (true, true) => "interrupted; checkpoint saved",
        (true, false) => "interrupted before a new checkpoint; the last one stands",
    };
    eprintln!(
        "{how}: {} steps, {} episodes, {:.0} s, {:.1} steps/s → {}",
        summary.steps_done,
        summary.episodes_done,
        summary.wall_time_s,
        summary.steps_per_s,
        out.display()
    );
    Ok(())
}

fn record_command(args: RecordArgs) -> Result<()> {
    use gaitscope::telemetry::{self, Actor, RecordOptions, Sink};
    if args.episodes == 0 || args.max_steps == 0 {
        bail!("--episodes and --max-steps must be at least 1");
    }
    if args.out.extension().and_then(|e| e.to_str()) != Some("rrd") {
        bail!(
            "--out {} should end in .rrd (the file the Rerun viewer opens)",
            args.out.display()
        );
    }
    let mut config = args.env.load()?;
    config.env.max_episode_steps = args.max_steps;
    if let Some(c) = args.condition {
        config.damage.condition = ConditionChoice::Fixed(c);
    }
    let mut actors = Vec::new();
    for dir in args.checkpoint.iter().chain(&args.compare) {
        actors.push(Actor::load(dir)?);
    }
    if actors.is_empty() {
        actors.push(Actor::Builtin(args.policy));
    }
    for actor in &actors {
        args.env.note_unused(actor, &config);
    }
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
        .context("installing the Ctrl-C handler")?;
    let opts = RecordOptions {
        actors,
        config,
        episodes: args.episodes,
        seed: args.seed,
        sink: Sink::File(args.out.clone()),
        fork: fork_option(args.fork_at, args.fork.as_deref())?,
    };
    let summary = telemetry::record(opts, &stop)?;
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

fn live_command(args: LiveArgs) -> Result<()> {
    use gaitscope::app::{self, viewer};
    use gaitscope::telemetry::{self, Sink};
    if !args.web && !cfg!(feature = "live") {
        bail!(
            "this gaitscope was built without the `live` feature (the control panel); rebuild \
             with default features, use `live --web`, or `gaitscope record` to write a .rrd"
        );
    }
    if let Some(secs) = args.exit_after
        && !(secs.is_finite() && secs > 0.0)
    {
        bail!("--exit-after must be a positive number of seconds");
    }
    if let Some(path) = &args.save
        && path.extension().and_then(|e| e.to_str()) != Some("rrd")
    {
        bail!("--save {} should end in .rrd", path.display());
    }
    let config = args.env.load()?;
    let setup = app::LiveSetup {
        checkpoint: args.checkpoint.clone(),
        compare: args.compare.clone(),
        condition: args.condition,
        seed: args.seed,
        speed: args.speed,
        step_limit: args.max_steps,
        mode: if args.sampled {
            gaitscope::policy::ActionMode::Sampled
        } else {
            gaitscope::policy::ActionMode::Deterministic
        },
        paused: args.paused,
        breakpoints: gaitscope::app::Breakpoint::parse_list(
            args.break_on.as_deref().unwrap_or_default(),
        )?,
        fork: fork_option(args.fork_at, args.fork.as_deref())?,
        config,
    };
    // Check what can be checked before any window opens: the input first, then the display.
    setup.validate()?;
    for dir in std::iter::once(&args.checkpoint).chain(&args.compare) {
        let requested = app::episode_config(&setup.config, setup.condition, setup.step_limit);
        args.env
            .note_unused(&gaitscope::lane::Actor::load(dir)?, &requested);
    }
    let mut checkpoints = app::discover_checkpoints(std::path::Path::new("checkpoints"));
    for dir in std::iter::once(&args.checkpoint).chain(&args.compare) {
        if !checkpoints.contains(dir) {
            checkpoints.push(dir.clone());
        }
    }
    let recording_id = format!("gaitscope-live-{}", std::process::id());
    // The blueprint gets a 3-D view per model shown from the start (a model added later from
    // the panel streams too; the viewer's "+" adds a view for it).
    let models = 1 + usize::from(args.compare.is_some());
    let roots: Vec<String> = app::LIVE_ROOTS[..models]
        .iter()
        .map(|r| r.to_string())
        .collect();
    // The 3-D views titled by checkpoint (the lanes' roots are fixed names).
    let labels: Vec<String> = std::iter::once(&args.checkpoint)
        .chain(&args.compare)
        .map(|dir| gaitscope::eval::model_label(dir))
        .collect();
    let titles = telemetry::view_titles(&labels, &roots);
    let finished = if args.web {
        live_web(&args, setup, checkpoints, &recording_id, &roots, &titles)?
    } else {
        viewer::require_display("gaitscope live")?;
        let url = match &args.connect {
            Some(url) => {
                viewer::check_reachable(url)?;
                url.clone()
            }
            None => {
                let path = viewer::find_viewer(args.viewer.as_deref())?;
                let url = viewer::spawn_viewer(&path)?;
                eprintln!(
                    "streaming to the Rerun viewer ({}) at {url}",
                    path.display()
                );
                url
            }
        };
        let sink = Sink::Viewer {
            url,
            save: args.save.clone(),
        };
        let (rec, _) = telemetry::open_titled(&sink, &recording_id, &roots, &titles)?;
        let sim = app::SimHandle::spawn(rec, setup)?;
        let panel = run_panel(&sim, checkpoints, args.exit_after);
        let finished = sim.shutdown();
        let stats = panel?;
        eprintln!(
            "panel: {} frames in {:.1} s ({:.1} fps, {:.2} ms CPU per frame)",
            stats.frames,
            stats.seconds,
            stats.fps(),
            stats.mean_frame_cpu_ms
        );
        finished
    };
    // A viewer closed before the end leaves data unsent; the session's report still prints.
    let (report, unflushed) = match finished {
        Ok(report) => (report, None),
        Err(app::LiveError::Unflushed { report, source }) => (*report, Some(source)),
        Err(e) => return Err(e.into()),
    };
    for s in &report.speeds {
        eprintln!(
            "sim at {}×: {:.1} of {:.0} env steps/s ({:.0} % of real time asked for) over {:.1} s",
            s.speed,
            s.steps_per_s(),
            s.target_steps_per_s,
            100.0 * s.keeps_up(),
            s.seconds
        );
    }
    if let Some(path) = &args.save {
        eprintln!("session saved to {}", path.display());
    }
    match unflushed {
        Some(e) => Err(e.into()),
        None => Ok(()),
    }
}

/// `live --web`: the same session, its stream served to Rerun's web viewer and its controls
/// to a page, until the page quits it or --exit-after passes.
#[cfg(feature = "web")]
fn live_web(
    args: &LiveArgs,
    setup: gaitscope::app::LiveSetup,
    checkpoints: Vec<PathBuf>,
    recording_id: &str,
    roots: &[String],
    titles: &[String],
) -> Result<Result<gaitscope::app::SimReport, gaitscope::app::LiveError>> {
    use gaitscope::app::{self, web};
    use gaitscope::telemetry::{self, Sink};
    let options = web::WebOptions {
        bind: args.bind,
        port: args.port,
        viewer_port: args.viewer_port,
        grpc_port: args.grpc_port,
    };
    options.check_ports()?;
    if !options.is_loopback() {
        eprintln!(
            "warning: listening on {}: anyone who can reach these ports can drive the sim and \
             watch the stream (the default, 127.0.0.1, keeps them on this machine)",
            options.bind
        );
    }
    let sink = Sink::Serve {
        bind: options.bind,
        port: options.grpc_port,
        save: args.save.clone(),
    };
    let (rec, _) = telemetry::open_titled(&sink, recording_id, roots, titles)?;
    let sim = app::SimHandle::spawn(rec, setup)?;
    let server = web::WebServer::start(options.clone(), checkpoints)?;
    eprintln!("control page:     {}", options.control_url());
    eprintln!("Rerun web viewer: {}", options.viewer_url());
    eprintln!("from another machine: {}", options.ssh_tunnel());
    eprintln!("(Quit on the page, or Ctrl-C, ends the session)");
    let deadline = args
        .exit_after
        .map(|s| std::time::Instant::now() + std::time::Duration::from_secs_f64(s));
    // Ctrl-C / SIGTERM end the session like Quit: the report and the --save file come out.
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
        .context("installing the Ctrl-C handler")?;
    let stats = server.serve(&sim, deadline, &stop);
    let finished = sim.shutdown();
    eprintln!(
        "web: {} requests in {:.1} s ({} commands, {} refused)",
        stats.requests, stats.seconds, stats.commands, stats.refused
    );
    Ok(finished)
}

#[cfg(not(feature = "web"))]
fn live_web(
    _: &LiveArgs,
    _: gaitscope::app::LiveSetup,
    _: Vec<PathBuf>,
    _: &str,
    _: &[String],
    _: &[String],
) -> Result<Result<gaitscope::app::SimReport, gaitscope::app::LiveError>> {
    bail!(
        "this gaitscope was built without the `web` feature (Rerun's web viewer and the control page); build with the default features"
    )
}

#[cfg(feature = "live")]
fn run_panel(
    sim: &gaitscope::app::SimHandle,
    checkpoints: Vec<PathBuf>,
    exit_after: Option<f64>,
) -> Result<gaitscope::app::PanelStats> {
    let options = gaitscope::app::panel::PanelOptions {
        checkpoints,
        exit_after: exit_after.map(std::time::Duration::from_secs_f64),
    };
    Ok(gaitscope::app::panel::run_panel(sim.link(), options)?)
}

#[cfg(not(feature = "live"))]
fn run_panel(
    _sim: &gaitscope::app::SimHandle,
    _checkpoints: Vec<PathBuf>,
    _exit_after: Option<f64>,
) -> Result<gaitscope::app::PanelStats> {
    bail!("this gaitscope was built without the `live` feature (the control panel)")
}

fn view_command(args: ViewArgs) -> Result<()> {
    use gaitscope::app::viewer;
    // The file first: a wrong path is the likelier mistake, and needs no display to report.
    viewer::check_recording(&args.file)?;
    viewer::require_display("gaitscope view")?;
    let path = viewer::find_viewer(args.viewer.as_deref())?;
    viewer::view_recording(&path, &args.file)?;
    Ok(())
}

#[cfg(not(feature = "video"))]
fn video_command(_: VideoArgs) -> Result<()> {
    bail!(
        "this gaitscope was built without the `video` feature (MuJoCo's offscreen renderer): \
         build with the default features (needs libegl1, libgl1-mesa-dri and ffmpeg)"
    )
}

#[cfg(feature = "video")]
fn video_command(args: VideoArgs) -> Result<()> {
    use gaitscope::video::{Encoder, FrameSpec, VideoLane, render_episode};
    let spec = FrameSpec {
        width: args.width,
        height: args.height,
        fps: args.fps,
        camera: args.camera,
    };
    spec.check()?;
    if args.out.extension().and_then(|e| e.to_str()) != Some("mp4") {
        bail!("--out {} should end in .mp4", args.out.display());
    }
    if args.max_steps == 0 {
        bail!("--max-steps must be at least 1");
    }
    // Each model runs in its own world (lane::Actor::world) under this condition and limit.
    let actor = match &args.checkpoint {
        Some(dir) => gaitscope::lane::Actor::load(dir)?,
        None => gaitscope::lane::Actor::Builtin(args.policy),
    };
    let mut config = args.env.load()?;
    config.env.max_episode_steps = args.max_steps;
    config.damage.condition = ConditionChoice::Fixed(args.condition);
    let compare = args
        .compare
        .as_deref()
        .map(gaitscope::lane::Actor::load)
        .transpose()?;
    let fork = fork_option(args.fork_at, args.fork.as_deref())?;
    if let Some(f) = &fork {
        f.validate(&actor.world(&config))?;
    }
    for a in std::iter::once(&actor).chain(&compare) {
        args.env.note_unused(a, &config);
    }
    // Side by side: two lanes, each half the width (kept even for the encoder).
    let two = compare.is_some() || fork.is_some();
    let lane_spec = if two {
        if !args.width.is_multiple_of(4) {
            bail!(
                "--width {} must be a multiple of 4 for two lanes side by side",
                args.width
            );
        }
        FrameSpec {
            width: args.width / 2,
            ..spec
        }
    } else {
        spec
    };
    let label_of = |dir: &Option<PathBuf>| match dir {
        Some(dir) => gaitscope::eval::model_label(dir),
        None => format!("{:?} policy", args.policy).to_lowercase(),
    };
    let first_label = if two {
        label_of(&args.checkpoint)
    } else {
        String::new()
    };
    let mut lanes = vec![VideoLane::new(
        first_label,
        actor,
        &config,
        args.seed,
        lane_spec,
    )?];
    if let Some(other) = compare {
        lanes.push(VideoLane::new(
            label_of(&args.compare),
            other,
            &config,
            args.seed,
            lane_spec,
        )?);
    }
    let mut encoder = Encoder::start(&args.out, spec)?;
    let started = std::time::Instant::now();
    let frames = render_episode(lanes, fork.as_ref(), spec, lane_spec, &mut encoder)?;
    encoder.finish()?;
    let secs = started.elapsed().as_secs_f64();
    eprintln!(
        "{frames} frames {}×{} in {secs:.1} s ({:.1} frames/s) → {}",
        spec.width,
        spec.height,
        frames as f64 / secs,
        args.out.display()
    );
    Ok(())
}

/// `--fork-at K --fork EDITS` (clap makes each require the other), parsed.
fn fork_option(at: Option<usize>, edits: Option<&str>) -> Result<Option<rollout::Fork>> {
    Ok(match (at, edits) {
        (Some(at), Some(edits)) => Some(rollout::Fork {
            at,
            edits: gaitscope::damage::DamageEdit::parse_list(edits)?,
        }),
        _ => None,
    })
}

/// `--suite`'s long help: each built-in scenario with its one-line description.
fn suite_help() -> String {
    let mut help = String::from(
        "A built-in suite of scenarios, each its own column (fatigue off in all):\n\nood:",
    );
    for s in gaitscope::damage::scenario::Scenario::suite("ood").unwrap_or_default() {
        help += &format!("\n  {:<18} {}", s.name, s.description);
    }
    help
}

fn import_sb3_command(args: ImportSb3Args) -> Result<()> {
    let summary = sb3::import_sb3(&args.model, &args.out, args.encoder)?;
    let net = &summary.net;
    println!(
        "imported {} (Stable-Baselines3 {}, {} steps) → {}",
        summary.provenance.file,
        summary.provenance.version,
        summary.num_timesteps,
        args.out.display()
    );
    println!(
        "  encoder {}{}, hidden {:?}, z {}, α {:.4}, {} tensors, sha256 {}",
        net.encoder,
        if net.share_encoder { " (shared)" } else { "" },
        net.hidden,
        net.z_dim,
        summary.alpha,
        summary.tensors,
        &summary.provenance.sha256[..12]
    );
    Ok(())
}

fn eval_command(args: EvalArgs) -> Result<()> {
    let threads = args
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    use gaitscope::eval::Case;
    let scenarios = gaitscope::damage::scenario::collect(&args.scenario, &args.suite)?;
    for (i, s) in scenarios.iter().enumerate() {
        if scenarios[..i].iter().any(|t| t.name == s.name) {
            bail!(
                "two scenarios are named '{}': each needs its own name",
                s.name
            );
        }
        // Every joint and set name fits the Ant, before minutes of evaluation.
        let mut config = GaitConfig::default();
        config.damage.scenario = Some(s.clone());
        AntEnv::new(config, 0)?;
    }
    let conditions: Vec<Condition> = match (args.conditions.is_empty(), scenarios.is_empty()) {
        (false, _) => args.conditions,
        (true, true) => Condition::ALL.to_vec(),
        (true, false) => vec![Condition::Healthy],
    };
    let cases: Vec<Case> = conditions
        .into_iter()
        .map(Case::from)
        .chain(scenarios.iter().map(|s| Case::scenario(&s.name)))
        .collect();
    let opts = gaitscope::eval::EvalOptions {
        checkpoints: args.checkpoints,
        episodes: args.episodes,
        seed_base: args.seed,
        conditions: cases,
        scenarios,
        max_steps: args.max_steps,
        threads,
    };
    let report = gaitscope::eval::evaluate(&opts)?;
    println!("{}", report.markdown());
    for (model, secs) in &report.wall_time_s {
        let n = opts.episodes * opts.conditions.len();
        eprintln!(
            "{model}: {n} episodes in {secs:.1} s ({:.1} episodes/s, {threads} threads)",
            n as f64 / secs
        );
    }
    for path in gaitscope::eval::write_outputs(&report, &args.out)? {
        eprintln!("wrote {}", path.display());
    }
    Ok(())
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

fn probe_command(args: ProbeArgs) -> Result<()> {
    use gaitscope::probe;
    if args.episodes == 0 || args.max_steps == 0 || args.window_every == 0 {
        bail!("--episodes, --max-steps and --window-every must be at least 1");
    }
    if args.folds < 2 || args.folds > args.episodes * Condition::ALL.len() {
        bail!(
            "--folds must be between 2 and the number of episodes ({})",
            args.episodes * Condition::ALL.len()
        );
    }
    // Load everything first: a bad checkpoint fails before minutes of rollouts.
    let mut policies = Vec::new();
    for dir in &args.checkpoints {
        let policy = gaitscope::policy::Policy::load(dir, None)?;
        if !policy.net().encoder.uses_window() {
            return Err(probe::ProbeError::NoLatent(dir.clone()).into());
        }
        let actor = gaitscope::lane::Actor::from_policy(dir, policy.clone());
        policies.push((actor, policy));
    }
    let baseline = match &args.baseline {
        Some(dir) => {
            let base = gaitscope::lane::Actor::from_policy(
                dir,
                gaitscope::policy::Policy::load(dir, Some(EncoderKind::None))?,
            );
            Some(probe::collect(
                &base,
                args.episodes,
                args.max_steps,
                args.seed,
                0,
            )?)
        }
        None => None,
    };
    let mut report = probe::ProbeReport { runs: Vec::new() };
    for (dir, (actor, policy)) in args.checkpoints.iter().zip(&policies) {
        let label = gaitscope::eval::model_label(dir);
        let steps = probe::collect(
            actor,
            args.episodes,
            args.max_steps,
            args.seed,
            args.window_every,
        )?;
        let joint_names: Vec<String> = AntEnv::new(policy.meta.env.clone(), 0)?
            .actuators()
            .iter()
            .map(|a| a.joint.clone())
            .collect();
        let file = probe::fit_probes(&steps, &joint_names, policy.meta.steps_done, args.seed)?;
        println!(
            "{label}: the probes live telemetry reads\n\n{}",
            file.markdown()
        );
        if !args.no_save {
            eprintln!("wrote {}", probe::save(&file, dir)?.display());
        }
        let figures_dir = if args.checkpoints.len() > 1 {
            args.out.join(&label)
        } else {
            args.out.clone()
        };
        for path in probe::figures(&file, &steps, baseline.as_deref(), &figures_dir)? {
            eprintln!("wrote {}", path.display());
        }
        let cv = probe::probe_cv(
            &label,
            &steps,
            &joint_names,
            args.window_every,
            args.folds,
            args.seed,
        )?;
        eprintln!(
            "{label}: {} episodes, {} steps cross-validated",
            cv.episodes, cv.steps
        );
        report.runs.push(cv);
    }
    let markdown = report.markdown();
    println!("{markdown}");
    let json = serde_json::to_vec_pretty(&report)?;
    let json_path = args.out.join("probe-cv.json");
    gaitscope::policy::checkpoint::write_atomic(&json_path, &json)?;
    let md_path = args.out.join("probe-cv.md");
    gaitscope::policy::checkpoint::write_atomic(&md_path, markdown.as_bytes())?;
    let latency_path = args.out.join("probe_latency.png");
    report.latency_figure(&latency_path)?;
    for path in [json_path, md_path, latency_path] {
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}

fn is_broken_pipe(err: &anyhow::Error) -> bool {
    err.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
    })
}
