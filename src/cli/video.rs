//! `gaitscope video`.

use anyhow::Result;
use clap::Args;
use std::path::PathBuf;

use super::values::BuiltinArg;
#[cfg(feature = "video")]
use super::values::CameraArg;
use gaitscope::Condition;

use super::EnvArgs;

#[derive(Args)]
pub(crate) struct VideoArgs {
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
    /// Start from this state (a saved state with its damage, or a bare {"qpos", "qvel"}).
    #[arg(long, value_name = "FILE")]
    init_state: Option<std::path::PathBuf>,
    #[arg(long, value_enum, default_value_t = BuiltinArg::Random)]
    policy: BuiltinArg,
    #[arg(long, value_name = "healthy|mild|severe", default_value = "severe")]
    condition: Condition,
    /// The episode's seed. Default: the most typical of seeds 0–7 for the checkpoints (printed);
    /// 0 for a built-in policy.
    #[arg(long)]
    seed: Option<u64>,
    /// Truncate the episode after this many steps (default: the models' world's limit — 500 in
    /// the paper's world, dead-legs 1000, dead-legs-short 400).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
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
    #[cfg(feature = "video")]
    #[arg(long, value_enum, default_value_t = CameraArg::Track)]
    camera: CameraArg,
    /// (This build has no renderer: `video` says so whatever the camera.)
    #[cfg(not(feature = "video"))]
    #[arg(long, value_name = "track|fixed")]
    camera: Option<String>,
    #[command(flatten)]
    env: EnvArgs,
}

#[cfg(not(feature = "video"))]
pub(crate) fn video_command(_: VideoArgs) -> Result<()> {
    anyhow::bail!(
        "this gaitscope was built without the `video` feature (MuJoCo's offscreen renderer): \
         build with the default features (needs libegl1, libgl1-mesa-dri and ffmpeg)"
    )
}

#[cfg(feature = "video")]
pub(crate) fn video_command(args: VideoArgs) -> Result<()> {
    use gaitscope::video::{FrameSpec, VideoOptions, render};
    // Each model runs in its own world (lane::Actor::world) under this condition and limit.
    let actor = match &args.checkpoint {
        Some(dir) => gaitscope::lane::Actor::load(dir)?,
        None => gaitscope::lane::Actor::Builtin(args.policy.into()),
    };
    let mut config = args.env.load()?;
    config.damage.condition = gaitscope::ConditionChoice::Fixed(args.condition);
    let compare = args
        .compare
        .as_deref()
        .map(gaitscope::lane::Actor::load)
        .transpose()?;
    let actors: Vec<gaitscope::lane::Actor> =
        std::iter::once(&actor).chain(&compare).cloned().collect();
    config.env.max_episode_steps = super::step_limit(args.max_steps, &actors, &config)?;
    for a in &actors {
        args.env.note_unused(a, &config);
    }
    let (seed, _) = super::demo_seed(args.seed, &actors, &config)?;
    let spec = FrameSpec {
        width: args.width,
        height: args.height,
        fps: args.fps,
        camera: args.camera.into(),
    };
    let started = std::time::Instant::now();
    let summary = render(VideoOptions {
        out: args.out.clone(),
        spec,
        actor,
        compare,
        config,
        seed,
        fork: super::fork_option(args.fork_at, args.fork.as_deref())?,
        start: super::start_state(args.init_state.as_deref(), &actors)?,
    })?;
    let secs = started.elapsed().as_secs_f64();
    for ending in &summary.endings {
        eprintln!("{ending}");
    }
    let frames = summary.frames;
    eprintln!(
        "{frames} frames {}×{} in {secs:.1} s ({:.1} frames/s) → {}",
        spec.width,
        spec.height,
        frames as f64 / secs,
        args.out.display()
    );
    Ok(())
}
