//! `live`'s wiring, from a checked [`LiveSetup`] to a finished session: the models' views, the
//! stream (to a Rerun viewer reached or spawned, or served to the web viewer), the sim thread,
//! and the front end that drives it (the native panel, or the page) until it is done. What it
//! notices on the way is handed to the caller as [`LaunchNote`]s, for the command line to
//! print; it prints nothing itself.

use std::path::{Path, PathBuf};
use std::time::Duration;

use super::viewer::{self, ViewerError};
use super::{LIVE_ROOTS, LiveError, LiveSetup, PanelStats, SimHandle, SimReport};
use crate::telemetry::{self, Sink, TelemetryError};

/// One live session to run.
pub struct LiveLaunch {
    pub setup: LiveSetup,
    /// Where the session's stream is also written as it goes (`--save`'s `.partial` file).
    pub save: Option<PathBuf>,
    /// End the session after this long (scripted runs and tests).
    pub exit_after: Option<Duration>,
    /// The checkpoints the panel or page offers, beside the session's own (which are added).
    pub offered: Vec<PathBuf>,
    /// A search folder's findings the page steps through ("next failure").
    pub findings: Vec<crate::search::Finding>,
}

/// Who drives the session.
pub enum FrontEnd<'a> {
    /// The native control panel beside a Rerun viewer: the one at `connect`, or one spawned
    /// from `viewer` (or found; [`viewer::find_viewer`]).
    Panel {
        connect: Option<String>,
        viewer: Option<PathBuf>,
    },
    /// The page and Rerun's web viewer, served until the page's Quit, the deadline, or `stop`
    /// (the caller's SIGINT/SIGTERM flag).
    #[cfg(feature = "web")]
    Web {
        options: super::web::WebOptions,
        stop: &'a std::sync::atomic::AtomicBool,
    },
    #[doc(hidden)]
    #[cfg(not(feature = "web"))]
    _Unused(std::marker::PhantomData<&'a ()>),
}

/// What a launch reports on its way, in order.
#[derive(Debug, Clone)]
pub enum LaunchNote {
    /// A viewer was spawned and the stream goes to it.
    Streaming { viewer: PathBuf, url: String },
    /// The panel closed; its frame statistics.
    Panel(PanelStats),
    /// `--exit-after` closed the viewer the session spawned.
    ViewerClosed,
    /// A person closed the panel: the spawned viewer stays to scrub the session.
    ViewerKept,
    /// The web ports listen on a non-loopback address: anyone who reaches them drives the sim.
    #[cfg(feature = "web")]
    Exposed { bind: std::net::IpAddr },
    /// The web session is up at these addresses.
    #[cfg(feature = "web")]
    Serving {
        control: String,
        viewer: String,
        tunnel: String,
    },
    /// The web session is over; its request counts.
    #[cfg(feature = "web")]
    Served(super::web::WebStats),
}

#[derive(Debug, thiserror::Error)]
pub enum LaunchError {
    #[error(transparent)]
    Viewer(#[from] ViewerError),
    // Boxed: a stream's and a session's errors are large, the others small.
    #[error(transparent)]
    Telemetry(Box<TelemetryError>),
    #[error(transparent)]
    Live(Box<LiveError>),
    #[cfg(feature = "live")]
    #[error(transparent)]
    Panel(#[from] super::panel::PanelError),
    #[cfg(feature = "web")]
    #[error(transparent)]
    Web(#[from] super::web::WebError),
    #[error("this gaitscope was built without the `live` feature (the control panel)")]
    NoPanel,
}

impl From<TelemetryError> for LaunchError {
    fn from(e: TelemetryError) -> Self {
        LaunchError::Telemetry(Box::new(e))
    }
}

impl From<LiveError> for LaunchError {
    fn from(e: LiveError) -> Self {
        LaunchError::Live(Box::new(e))
    }
}

/// The session's lanes' entity roots and the titles of their 3-D views (by checkpoint: the
/// roots are fixed names), one per model shown from the start; a model added later from the
/// panel streams too, and the viewer's "+" adds a view for it.
pub fn views(checkpoint: &Path, compare: Option<&Path>) -> (Vec<String>, Vec<String>) {
    let dirs: Vec<&Path> = std::iter::once(checkpoint).chain(compare).collect();
    let roots: Vec<String> = LIVE_ROOTS[..dirs.len()]
        .iter()
        .map(|r| r.to_string())
        .collect();
    let labels: Vec<String> = dirs
        .iter()
        .map(|dir| crate::policy::checkpoint::model_label(dir))
        .collect();
    let titles = telemetry::view_titles(&labels, &roots);
    (roots, titles)
}

/// Runs the session to its end. The outer error is a session that could not start or whose
/// front end failed; the inner result is the sim's own ending (its report, or what stopped it),
/// which the caller needs either way to finish `--save`.
pub fn run_live(
    launch: LiveLaunch,
    front: FrontEnd<'_>,
    note: &mut dyn FnMut(LaunchNote),
) -> Result<Result<SimReport, LiveError>, LaunchError> {
    let (roots, titles) = views(&launch.setup.checkpoint, launch.setup.compare.as_deref());
    // The views for the checkpoints' own worlds and encoders (a checkpoint that cannot be read
    // fails in the sim, which says why; the default views meanwhile).
    let metas: Result<Vec<crate::policy::checkpoint::CheckpointMeta>, _> =
        std::iter::once(&launch.setup.checkpoint)
            .chain(&launch.setup.compare)
            .map(|dir| crate::policy::checkpoint::read_meta(dir))
            .collect();
    let shown = metas.map_or_else(
        |_| telemetry::ViewOptions::default(),
        |metas| {
            telemetry::ViewOptions::for_worlds(metas.iter().map(|m| &m.env))
                .with_latent(metas.iter().map(|m| m.net.encoder.uses_window()))
        },
    );
    let mut offered = launch.offered;
    for dir in std::iter::once(&launch.setup.checkpoint).chain(&launch.setup.compare) {
        if !offered.contains(dir) {
            offered.push(dir.clone());
        }
    }
    let recording_id = format!("gaitscope-live-{}", std::process::id());
    match front {
        FrontEnd::Panel { connect, viewer } => {
            viewer::require_display("gaitscope live")?;
            let (url, spawned) = match connect {
                Some(url) => {
                    viewer::check_reachable(&url)?;
                    (url, None)
                }
                None => {
                    let path = viewer::find_viewer(viewer.as_deref())?;
                    let spawned = viewer::spawn_viewer(&path)?;
                    note(LaunchNote::Streaming {
                        viewer: path,
                        url: spawned.url.clone(),
                    });
                    (spawned.url.clone(), Some(spawned))
                }
            };
            let sink = Sink::Viewer {
                url,
                save: launch.save,
            };
            let (rec, _) = telemetry::open_titled(&sink, &recording_id, &roots, &titles, shown)?;
            let sim = SimHandle::spawn(rec, launch.setup)?;
            let panel = run_panel(&sim, offered, launch.findings, launch.exit_after);
            let finished = sim.shutdown();
            note(LaunchNote::Panel(panel?));
            // A person closing the panel keeps the viewer to scrub the session; a scripted
            // --exit-after run leaves nothing running.
            if let Some(viewer) = &spawned {
                if launch.exit_after.is_some() {
                    if viewer.stop(Duration::from_secs(5)) {
                        note(LaunchNote::ViewerClosed);
                    }
                } else {
                    note(LaunchNote::ViewerKept);
                }
            }
            Ok(finished)
        }
        #[cfg(feature = "web")]
        FrontEnd::Web { options, stop } => {
            use super::web;
            options.check_ports()?;
            if !options.is_loopback() {
                note(LaunchNote::Exposed { bind: options.bind });
            }
            // The public ports behind guards (connection cap, header timeout, Host check); the
            // servers themselves on Unix sockets in a private folder behind them.
            let front = web::Front::bind(&options)?;
            let sink = Sink::Serve {
                socket: front.grpc_backend.clone(),
                save: launch.save,
                admit_host: if options.is_loopback() {
                    super::guard::is_loopback_host
                } else {
                    |_| true
                },
            };
            let (rec, _) = telemetry::open_titled(&sink, &recording_id, &roots, &titles, shown)?;
            let sim = SimHandle::spawn(rec, launch.setup)?;
            let server = web::WebServer::start(options.clone(), front, offered, launch.findings)?;
            note(LaunchNote::Serving {
                control: options.control_url(),
                viewer: options.viewer_url(),
                tunnel: options.ssh_tunnel(),
            });
            let deadline = launch.exit_after.map(|d| std::time::Instant::now() + d);
            let stats = server.serve(&sim, deadline, stop);
            let finished = sim.shutdown();
            note(LaunchNote::Served(stats));
            Ok(finished)
        }
        #[cfg(not(feature = "web"))]
        FrontEnd::_Unused(_) => Err(LaunchError::NoPanel),
    }
}

#[cfg(feature = "live")]
fn run_panel(
    sim: &SimHandle,
    checkpoints: Vec<PathBuf>,
    findings: Vec<crate::search::Finding>,
    exit_after: Option<Duration>,
) -> Result<PanelStats, LaunchError> {
    let options = super::panel::PanelOptions {
        checkpoints,
        findings,
        exit_after,
    };
    Ok(super::panel::run_panel(sim.link(), options)?)
}

#[cfg(not(feature = "live"))]
fn run_panel(
    _sim: &SimHandle,
    _checkpoints: Vec<PathBuf>,
    _findings: Vec<crate::search::Finding>,
    _exit_after: Option<Duration>,
) -> Result<PanelStats, LaunchError> {
    Err(LaunchError::NoPanel)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup(compare: Option<&str>) -> (Vec<String>, Vec<String>) {
        views(
            Path::new("checkpoints/encoder-lstm"),
            compare.map(Path::new),
        )
    }

    /// One view per model shown from the start, titled by its checkpoint; the same checkpoint
    /// twice is told apart by its root.
    #[test]
    fn views_are_one_per_model_titled_by_checkpoint() {
        let (roots, titles) = setup(None);
        assert_eq!(roots, ["ant"]);
        assert_eq!(titles, ["Ant: encoder-lstm"]);
        let (roots, titles) = setup(Some("checkpoints/baseline"));
        assert_eq!(roots, ["ant", "compare"]);
        assert_eq!(titles, ["Ant: encoder-lstm", "Ant: baseline"]);
        let (_, titles) = setup(Some("checkpoints/encoder-lstm"));
        assert_eq!(
            titles,
            ["Ant: encoder-lstm (ant)", "Ant: encoder-lstm (compare)"]
        );
    }
}
