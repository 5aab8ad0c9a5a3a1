//! `gaitscope live`: the native panel or the web page beside the Rerun viewer.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use gaitscope::{app, telemetry};

use super::{EnvArgs, fork_option};

#[derive(Args)]
pub(crate) struct LiveArgs {
    /// Checkpoint to watch (any folder `gaitscope train` wrote). Default: the bundled
    /// checkpoints/encoder-lstm, found from the working directory or else in the clone this
    /// binary was built from.
    #[arg(long, value_name = "DIR")]
    checkpoint: Option<PathBuf>,
    /// A second checkpoint, side by side under the same damage (e.g. checkpoints/baseline).
    #[arg(long, value_name = "DIR")]
    compare: Option<PathBuf>,
    #[arg(
        long,
        value_name = "healthy|mild|severe|manual",
        default_value = "severe"
    )]
    condition: gaitscope::app::LiveCondition,
    /// Seed of the first episode (each next episode uses the next seed). Default: the most
    /// typical of seeds 0–7 for the checkpoints under the condition (printed; 0 for `manual`).
    #[arg(long)]
    seed: Option<u64>,
    /// Playback speed, a multiple of real time (20 env steps/s): 0.25 to 8.
    #[arg(long, default_value_t = 1.0)]
    speed: f64,
    /// Truncate episodes after this many steps (default: the checkpoints' world's limit — 500
    /// in the paper's world, dead-legs 1000, dead-legs-short 400; a model loaded later from
    /// another world brings its own, unless the limit was changed from the old model's).
    #[arg(long, value_name = "N")]
    max_steps: Option<usize>,
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
    /// Start every episode (each reset) from this state: a saved state (`rollout
    /// --save-state-at`, the panel's "Save state") with its damage, or a bare {"qpos", "qvel"}.
    #[arg(long, value_name = "FILE")]
    init_state: Option<PathBuf>,
    /// A `gaitscope search` folder: the panel or the page lists its findings and steps through
    /// the held-out episodes they broke ("Next failure"; the panel can also load one itself).
    #[arg(long, value_name = "DIR")]
    search: Option<PathBuf>,
    /// Start with the attribution view on: why z moved, per step (the panel and page toggle it).
    #[arg(long)]
    attribution: bool,
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

/// The bundled checkpoint a bare `live` watches: relative to the working directory where it
/// exists there (a clone's root), else in the clone the binary was built from.
fn bundled_checkpoint() -> Result<PathBuf> {
    const BUNDLED: &str = "checkpoints/encoder-lstm";
    let here = PathBuf::from(BUNDLED);
    if here.join("checkpoint.json").is_file() {
        return Ok(here);
    }
    let built = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(BUNDLED);
    if built.join("checkpoint.json").is_file() {
        return Ok(built);
    }
    bail!(
        "no --checkpoint given, and the bundled {BUNDLED} is neither under the working directory \
         nor at {}: pass --checkpoint DIR (any folder `gaitscope train` wrote)",
        built.display()
    )
}

pub(crate) fn live_command(mut args: LiveArgs) -> Result<()> {
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
    let checkpoint = match args.checkpoint.take() {
        Some(dir) => dir,
        None => bundled_checkpoint()?,
    };
    let config = args.env.load()?;
    let mut actors = Vec::new();
    for dir in std::iter::once(&checkpoint).chain(&args.compare) {
        actors.push(gaitscope::lane::Actor::load(dir)?);
    }
    let step_limit = super::step_limit(args.max_steps, &actors, &config)?;
    let seed = match (args.seed, args.condition) {
        (Some(seed), _) => seed,
        // By hand, nothing is typical: a person breaks what they like.
        (None, app::LiveCondition::Manual) => 0,
        (None, condition) => {
            let mut typical = config.clone();
            typical.env.max_episode_steps = step_limit;
            typical.damage.condition = gaitscope::ConditionChoice::Fixed(condition.env_condition());
            super::demo_seed(None, &actors, &typical)?.0
        }
    };
    let setup = app::LiveSetup {
        checkpoint: checkpoint.clone(),
        compare: args.compare.clone(),
        condition: args.condition,
        seed,
        speed: args.speed,
        step_limit,
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
        start: super::start_state(args.init_state.as_deref(), &actors)?,
        attribution: args.attribution,
    };
    // Check what can be checked before any window opens: the input first, then the display.
    setup.validate()?;
    for dir in std::iter::once(&checkpoint).chain(&args.compare) {
        let requested = app::episode_config(&setup.config, setup.condition, setup.step_limit);
        args.env
            .note_unused(&gaitscope::lane::Actor::load(dir)?, &requested);
    }
    // --save writes NAME.partial and renames it once the session's data is flushed.
    let save_file = args.save.as_deref().map(telemetry::PartialFile::new);
    let launch = app::launch::LiveLaunch {
        setup,
        save: save_file.as_ref().map(|f| f.partial().to_path_buf()),
        exit_after: args.exit_after.map(std::time::Duration::from_secs_f64),
        offered: app::discover_checkpoints(std::path::Path::new("checkpoints")),
        findings: match &args.search {
            Some(dir) => gaitscope::search::findings(dir)?,
            None => Vec::new(),
        },
    };
    // Ctrl-C / SIGTERM end a web session like the page's Quit: the report and the --save file
    // come out (the native panel handles its own window's close).
    let stop = Arc::new(AtomicBool::new(false));
    let front = if args.web {
        web_front(&args, &stop)?
    } else {
        app::launch::FrontEnd::Panel {
            connect: args.connect.clone(),
            viewer: args.viewer.clone(),
        }
    };
    let finished = app::launch::run_live(launch, front, &mut print_note)?;
    // A viewer closed before the end leaves data unsent; the session's report still prints.
    // The file is flushed before the viewer (a multi-sink flushes in order), so it is whole
    // then too; on any other error it stays under its .partial name.
    let (report, unflushed) = match finished {
        Ok(report) => (report, None),
        Err(app::LiveError::Unflushed { report, source }) => (*report, Some(source)),
        Err(e) => {
            if let Some(f) = &save_file {
                eprintln!(
                    "the session's file stays at {} (it may be incomplete)",
                    f.partial().display()
                );
            }
            return Err(e.into());
        }
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
    if let Some(f) = &save_file {
        // A sink that did not flush may be the file (a full disk), not the viewer: only a file
        // that reads back whole takes the name asked for.
        if unflushed.is_some()
            && let Err(e) = f.check_whole()
        {
            return Err(e.into());
        }
        f.rename_into_place()?;
    }
    if let Some(path) = &args.save {
        eprintln!("session saved to {}", path.display());
    }
    match unflushed {
        Some(e) => Err(e.into()),
        None => Ok(()),
    }
}

/// What the launch noticed, said as `live` always said it.
fn print_note(note: app::launch::LaunchNote) {
    use app::launch::LaunchNote;
    match note {
        LaunchNote::Streaming { viewer, url } => {
            eprintln!(
                "streaming to the Rerun viewer ({}) at {url}",
                viewer.display()
            );
        }
        LaunchNote::Panel(stats) => eprintln!(
            "panel: {} frames in {:.1} s ({:.1} fps, {:.2} ms CPU per frame)",
            stats.frames,
            stats.seconds,
            stats.fps(),
            stats.mean_frame_cpu_ms
        ),
        LaunchNote::ViewerClosed => eprintln!("closed the Rerun viewer it started (--exit-after)"),
        LaunchNote::ViewerKept => {
            eprintln!("the Rerun viewer stays open to scrub the session; close it when done");
        }
        #[cfg(feature = "web")]
        LaunchNote::Exposed { bind } => eprintln!(
            "warning: listening on {bind}: anyone who can reach these ports can drive the sim and \
             watch the stream (the default, 127.0.0.1, keeps them on this machine)"
        ),
        #[cfg(feature = "web")]
        LaunchNote::Serving {
            control,
            viewer,
            tunnel,
        } => {
            eprintln!("control page:     {control}");
            eprintln!("Rerun web viewer: {viewer}");
            eprintln!("from another machine: {tunnel}");
            eprintln!("(Quit on the page, or Ctrl-C, ends the session)");
        }
        #[cfg(feature = "web")]
        LaunchNote::Served(stats) => eprintln!(
            "web: {} requests in {:.1} s ({} commands, {} refused)",
            stats.requests, stats.seconds, stats.commands, stats.refused
        ),
    }
}

/// `live --web`: the page and Rerun's web viewer, ended by Quit, --exit-after or the signal
/// flag `stop` (installed here, at the edge).
#[cfg(feature = "web")]
fn web_front<'a>(args: &LiveArgs, stop: &'a Arc<AtomicBool>) -> Result<app::launch::FrontEnd<'a>> {
    use anyhow::Context;
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::Relaxed))
        .context("installing the Ctrl-C handler")?;
    Ok(app::launch::FrontEnd::Web {
        options: app::web::WebOptions {
            bind: args.bind,
            port: args.port,
            viewer_port: args.viewer_port,
            grpc_port: args.grpc_port,
        },
        stop,
    })
}

#[cfg(not(feature = "web"))]
fn web_front<'a>(_: &LiveArgs, _: &'a Arc<AtomicBool>) -> Result<app::launch::FrontEnd<'a>> {
    bail!(
        "this gaitscope was built without the `web` feature (Rerun's web viewer and the control page); build with the default features"
    )
}
