//! `gaitscope video`.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

use gaitscope::Condition;
use gaitscope::rollout::BuiltinPolicy;

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
    #[cfg(feature = "video")]
    #[arg(long, value_enum, default_value_t = gaitscope::video::CameraMode::Track)]
    camera: gaitscope::video::CameraMode,
    /// (This build has no renderer: `video` says so whatever the camera.)
    #[cfg(not(feature = "video"))]
    #[arg(long, value_name = "track|fixed")]
    camera: Option<String>,
    #[command(flatten)]
    env: EnvArgs,
}

#[cfg(not(feature = "video"))]
pub(crate) fn video_command(_: VideoArgs) -> Result<()> {
    bail!(
        "this gaitscope was built without the `video` feature (MuJoCo's offscreen renderer): \
         build with the default features (needs libegl1, libgl1-mesa-dri and ffmpeg)"
    )
}

#[cfg(feature = "video")]
pub(crate) fn video_command(args: VideoArgs) -> Result<()> {
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
    config.damage.condition = gaitscope::ConditionChoice::Fixed(args.condition);
    let compare = args
        .compare
        .as_deref()
        .map(gaitscope::lane::Actor::load)
        .transpose()?;
    let fork = super::fork_option(args.fork_at, args.fork.as_deref())?;
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
