//! `gaitscope train` and `gaitscope curves`.

use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use gaitscope::policy::{EncoderKind, Privileged};
use gaitscope::train;

use super::EnvArgs;
use super::values::{AuxArg, EncoderArg, PrivilegedArg, UpdateArg};

#[derive(Args)]
pub(crate) struct TrainArgs {
    /// Check the options and config (the env is built once), print the resolved config as
    /// JSON and exit: nothing is trained or written (sweep launchers vet specs with it).
    #[arg(long)]
    check: bool,
    /// Feature extractor: none (baseline), lstm (the paper's, default), mlp-window (ablation).
    /// With --resume it must match the run's, and may be left out.
    #[arg(long, value_enum)]
    encoder: Option<EncoderArg>,
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
    /// A fresh run that starts from a trained memoryless model's weights (a baseline, in the
    /// same world): as it is, as an oracle (--privileged) whose damage inputs start at zero
    /// weight, or as an encoder model (--encoder lstm|mlp-window) whose z starts at zero weight
    /// and whose encoders start fresh, so each begins by acting exactly as that model. Its own
    /// step count, optimiser and replay buffer; the --learning-starts steps before the first
    /// update act with the model's policy, not at random. --encoder defaults to none here.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    init_from: Option<PathBuf>,
    #[arg(long, default_value_t = 10_000)]
    checkpoint_every: u64,
    /// Skip saving the replay buffer (~80 MB) with checkpoints; a resume then refills it.
    #[arg(long)]
    no_save_replay: bool,
    /// Keep replay.bin in DIR instead of the run folder (e.g. under ~/.cache/gaitscope/, outside
    /// a git work tree). The run records it; a --resume names it again (a run folder does not
    /// choose where the trainer writes).
    #[arg(long, value_name = "DIR")]
    replay_dir: Option<PathBuf>,
    /// A resume without its replay buffer first collects min(buffer size, steps done, N)
    /// transitions with the current policy, without updates (at least 10000).
    #[arg(long, value_name = "N", default_value_t = train::DEFAULT_REFILL)]
    refill: usize,
    /// One encoder for actor and critic (SB3's share_features_extractor).
    #[arg(long)]
    share_encoder: bool,
    /// Privileged inputs for an oracle: the memoryless model gets the true per-joint damage
    /// beside the observation (a measured ceiling, never a deployable policy), as torque
    /// scales (damage) or as the torque lost, 1 − scale (torque-lost: 0 while whole);
    /// implies --encoder none. With --resume it must match the run's, and may be left out.
    #[arg(long, value_enum, value_name = "KIND")]
    privileged: Option<PrivilegedArg>,
    /// Size of the encoder's latent z (default 32, the paper's); the window length is the
    /// config's `context.len`.
    #[arg(long)]
    z_dim: Option<usize>,
    /// Transitions per gradient update (default 256, SB3's).
    #[arg(long, value_name = "N")]
    batch_size: Option<usize>,
    /// Replay buffer capacity in transitions (default 1,000,000, SB3's).
    #[arg(long, value_name = "N")]
    buffer_size: Option<usize>,
    /// Env steps of uniformly random actions, and no updates, before learning (default 100).
    #[arg(long, value_name = "N")]
    learning_starts: Option<usize>,
    /// No progress bar (logs still go to metrics.jsonl).
    #[arg(long)]
    quiet: bool,
    /// Threads per gradient update (default: every core this process may run on, so a run
    /// pinned with `taskset -c N` uses one). The trained weights do not depend on it.
    #[arg(long)]
    threads: Option<usize>,
    /// The update: fused (fast, the default) or reference (candle's autograd, for comparison).
    #[arg(long, value_enum, default_value_t = UpdateArg::Fused)]
    update: UpdateArg,
    /// A self-supervised auxiliary loss for the encoders: dynamics (a head predicts the
    /// normalised change of the observation from [z, o_t, a_t]); none is plain SAC. No damage
    /// label enters it. With --resume it must match the run's, and may be left out.
    #[arg(long, value_enum)]
    aux: Option<AuxArg>,
    /// Weight of the auxiliary loss in each network's loss (default 1).
    #[arg(long, value_name = "W")]
    aux_weight: Option<f64>,
    #[command(flatten)]
    env: EnvArgs,
}

#[derive(Args)]
pub(crate) struct CurvesArgs {
    /// Run folders (or metrics.jsonl files), each a line named after its folder; folders named
    /// MODEL-sN are seeds of one model: one colour, a thin line per seed under their mean.
    #[arg(long = "run", value_name = "DIR", required = true, num_args = 1..)]
    runs: Vec<PathBuf>,
    /// The PNG to write.
    #[arg(long, value_name = "FILE", default_value = "training_curves.png")]
    out: PathBuf,
}

pub(crate) fn train_command(args: TrainArgs) -> Result<()> {
    let resume = args.resume.is_some();
    let Some(out) = args.resume.clone().or(args.out.clone()) else {
        bail!("train needs --out DIR (or --resume DIR)");
    };
    let encoder_flag: Option<EncoderKind> = args.encoder.map(Into::into);
    let requested = train::RunIdentity {
        encoder: encoder_flag,
        aux: args.aux.map(Into::into),
        aux_weight: args.aux_weight,
    };
    // A resumed run keeps what it is; the flags may only repeat it.
    let aux = match &args.resume {
        Some(dir) => requested.check_against(dir)?.sac.aux,
        None => requested.fresh_aux()?,
    };
    let privileged = match &args.resume {
        Some(dir) => {
            let found = gaitscope::policy::checkpoint::read_meta(dir)?
                .net
                .privileged;
            if let Some(p) = args.privileged
                && Privileged::from(p) != found
            {
                bail!(
                    "{} is a run with privileged inputs '{found}'; --privileged {} does not match",
                    dir.display(),
                    Privileged::from(p)
                );
            }
            found
        }
        None => args.privileged.map_or(Privileged::None, Privileged::from),
    };
    let encoder = match &args.resume {
        Some(dir) => gaitscope::policy::checkpoint::read_meta(dir)?.net.encoder,
        None if privileged != Privileged::None => match encoder_flag {
            None | Some(EncoderKind::None) => EncoderKind::None,
            Some(other) => bail!(
                "--privileged {privileged} makes the memoryless oracle (encoder none); it takes \
                 no --encoder {other} (an oracle that reads the true damage needs no memory)"
            ),
        },
        // A warm start's source is memoryless: the same model unless an encoder is asked for.
        None if args.init_from.is_some() => encoder_flag.unwrap_or(EncoderKind::None),
        None => encoder_flag.unwrap_or(EncoderKind::Lstm),
    };
    let mut opts = train::ant_options(encoder, args.steps, args.seed, out.clone());
    if privileged != Privileged::None {
        opts.net = gaitscope::policy::NetConfig {
            context_len: opts.net.context_len,
            ..gaitscope::policy::NetConfig::ant_oracle(privileged)
        };
    }
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
    opts.init_from = args.init_from.clone();
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
    opts.sac.aux = aux;
    opts.update = args.update.into();
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
             eval, record, live, video and rollout run its policies for {} unless told otherwise",
            opts.env.env.max_episode_steps,
            opts.env.run_step_limit()
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

/// `gaitscope curves`.
pub(crate) fn curves_command(args: CurvesArgs) -> Result<()> {
    use gaitscope::train::curves::{CurveRun, RunMetrics, figure};
    let mut runs = Vec::new();
    for run in &args.runs {
        let dir = if run.is_dir() {
            run.as_path()
        } else {
            run.parent().unwrap_or(run)
        };
        let metrics = RunMetrics::read(run)?;
        for (from, to) in metrics.gaps() {
            eprintln!(
                "note: {}: metrics.jsonl has no lines between steps {from} and {to}; its curves \
                 break there",
                run.display()
            );
        }
        let label = gaitscope::eval::model_label(dir);
        runs.push(CurveRun {
            group: gaitscope::eval::seeds::group_of(&label),
            label,
            metrics,
        });
    }
    figure(&runs, &args.out)?;
    eprintln!("wrote {}", args.out.display());
    Ok(())
}
