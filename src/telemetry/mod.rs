//! Rerun telemetry: every env step of a damaged Ant, drawn from MuJoCo's own state.
//!
//! Timelines: `step` (env steps since the recording started), `sim_time` (seconds) and
//! `episode`. No wall-clock timeline, so a recording is a pure function of its inputs.
//!
//! Entity layout, under a root per model (`ant` alone, or one root per model with `--compare`):
//!
//! | path | archetype | when |
//! |---|---|---|
//! | `{root}/world/legs` | Capsules3D, one instance per leg capsule (labels = geom names) | shapes static; poses and damage colours per step |
//! | `{root}/world/torso` | Ellipsoids3D | radius static; pose per step |
//! | `{root}/world/floor`, `{root}/world/goal`, `{root}/world/goal/radius` | Boxes3D, Ellipsoids3D, LineStrips3D | static |
//! | `{root}/world/trail` | LineStrips3D (torso path, every 5th step) | every 5 steps |
//! | `{root}/world/ending` | Points3D labelled with how the lane's episode ended, above the Ant | at the end; cleared at the next episode |
//! | `{root}/world/focus` | LineStrips3D, a faint 2.5 m ring on the floor under the torso: what the 3-D view's camera tracks (from a starting eye 5 m behind and above) | per step |
//! | `{root}/joints/fatigue`, `{root}/joints/scale` | Scalars × 8 (series named by joint, actuator order) | per step |
//! | `{root}/joints/threshold` | Scalars | episode start and end |
//! | `{root}/events` | TextLog (triggers WARN, overrides INFO, breakpoint hits BREAK, rewinds and forks BRANCH, pushes PUSH) | on events |
//! | `{root}/world/push` | Arrows3D, one per acting push, pointing at the pushed body's centre of mass (head 0.3 m short of it; 1 m per 50 N), labelled "40 N on torso" | while a push acts; cleared after |
//! | `{root}/actions/commanded`, `{root}/actions/applied` | Scalars × 8 | per step |
//! | `{root}/reward` | Scalars × 4: native, progress, success, total | per step |
//! | `{root}/goal/distance`, `{root}/goal/progress_rate` | Scalars | per step |
//! | `{root}/gait/{leg}` | StateChange: a stance state named by the leg's damage while its foot touches the floor, an empty state (a gap) in swing; StateConfiguration (colours) static | on changes |
//! | `{root}/latent/z` | Scalars × 32 | per step (encoder policies) |
//! | `{root}/latent/attribution`, `{root}/latent/attribution_groups` | Tensor 16 × 10 (window slot × feature group: why ‖z − z(0)‖ is what it is, integrated gradients) and its group totals as Scalars × 10 | per step, with the attribution view on |
//! | `{root}/latent/attribution_map`, `…/labels` | the same grid as an RGB Image (one pixel a cell, white 0, red raised ‖z − z(0)‖, blue lowered it) and its row names as labelled Points2D | per step / static |
//! | `{root}/latent/pca`, `{root}/latent/pca_trail` | Points2D (current point, large; episode every 5th step), coloured by triggered joints | with `probe.json` |
//! | `{root}/latent/pca3`, `{root}/latent/pca3_trail` | Points3D, the same in the first three PCA axes | with `probe.json` |
//! | `{root}/probe/predicted`, `{root}/probe/truth` | Scalars × 8: P(joint damaged) from z, and the truth | with `probe.json` |
//! | `{root}/episode` | TextDocument (checkpoint, encoder, condition, seed, outcome) | episode start and end |

use rerun::blueprint::{
    Blueprint, Horizontal, Spatial2DView, Spatial3DView, TextLogView, TimeSeriesView, Vertical,
};
use rerun::{RecordingStream, RecordingStreamBuilder};
use std::path::PathBuf;

use crate::damage::{DamageEventKind, N_ACTUATORS};
use crate::env::{AntEnv, StepOutcome};
use crate::palette::{self, LegTorque, Torque};
use crate::probe::ProbeFile;

mod blueprint;
mod logger;
#[cfg(feature = "web")]
pub mod proxy;
mod record;
mod session;
pub use blueprint::*;
pub use logger::*;
pub use record::{PartialFile, RecordOptions, RecordSummary, model_roots, read_back, record};
pub use session::{
    Actor, FORK_ROOT, HISTORY_CAP, LOG_CAP, Lane, LaneEnding, LaneSnapshot, LaneSpec, LogEntry,
    RecordError, RewindError, Session, side_by_side_offset,
};

pub const APP_ID: &str = "gaitscope";
/// Where each 3-D view's eye starts, behind and above the Ant's start, looking at it (m):
/// Rerun 0.41 frames the whole scene by default (the Ant a few pixels tall); tracking the
/// focus ring keeps this offset as the Ant walks.
const EYE_START: [f32; 3] = [-2.5, -4.0, 3.0];
const EYE_TARGET: [f32; 3] = [0.0, 0.0, 0.4];
/// The ring the 3-D camera tracks: its radius (m) and segments.
const FOCUS_RADIUS: f32 = 2.5;
const FOCUS_SEGMENTS: usize = 32;
/// Log the trail (torso path, PCA path) every this many steps: bounded bytes per step.
pub const TRAIL_EVERY: usize = 5;
/// A foot's stance states in the gait diagram, by the torque its leg's worst joint has left
/// (the same colours as the legs): what a person reads as "this leg is damaged".
pub const GAIT_STATES: [&str; 4] = [
    LegTorque::Full.stance_name(),
    LegTorque::Reduced.stance_name(),
    LegTorque::Dead.stance_name(),
    LegTorque::Pinned.stance_name(),
];
/// Swing: an empty state, which the state view draws as a gap. Not a null: the state column is
/// non-nullable, and nulls made every recording fail `rerun rrd verify`.
pub const GAIT_SWING: &str = "";

/// Where the recording's key lives (a static markdown document, [`key_markdown`]).
pub const KEY_ENTITY: &str = "key";

/// The PCA points' colour, in words (the key's line).
pub const PCA_KEY: &str = "points coloured by the number of joints that have lost torque: 0 dark purple → 8 yellow (viridis)";

/// The key to every colour in the views, for lanes given as (model label, hue index): which
/// line and trail is which model, what a leg's colour means, the gait, probe and PCA views,
/// and the endings' words.
pub fn key_markdown(lanes: &[(String, usize)], probe: bool) -> String {
    let mut md = String::from("**Models** — trail, goal-distance line; with several models, ");
    md += "each one's plot lines are shades of its colour, its joints dark → light (hip_1 … ankle_4)  \n";
    for (label, hue) in lanes {
        md += &format!("- **{}**: {label}\n", palette::model_hue_name(*hue));
    }
    md += "\n**Legs and gait bars** — the torque a joint has left (never fatigue alone)  \n";
    md += "- **green**: full torque (a fatigue trigger that takes nothing, as under `healthy`, stays green)\n";
    md += "- **amber → red**: torque lost, scale just under 1 → near 0\n";
    md += "- **slate**: dead (scale 0)\n";
    md += "- **violet**: pinned by hand (panel, page, fork)\n";
    md += "\n**Gait**: a bar while the foot is on the floor, a gap while it swings, tinted by the leg's worst joint.  \n";
    if probe {
        md += "**Probe**: lines are P(damaged) read from z, crosses the truth (1 = the joint has lost torque), one colour per joint.  \n";
        md += &format!("**PCA of z**: {PCA_KEY}.  \n");
    }
    md += "**Endings**: ";
    md += &crate::env::Ending::ALL
        .iter()
        .map(|e| format!("{} = {}", e.name().to_uppercase(), e.meaning()))
        .collect::<Vec<_>>()
        .join("; ");
    md += ".\n";
    md
}

/// Logs the key ([`key_markdown`]) as static data: it describes the whole recording.
pub fn log_key(
    rec: &RecordingStream,
    lanes: &[(String, usize)],
    probe: bool,
    caption: Option<&str>,
) -> Result<(), TelemetryError> {
    let mut md = String::new();
    if let Some(caption) = caption {
        md += &format!("**This episode**: {caption}\n\n");
    }
    md += &key_markdown(lanes, probe);
    rec.log_static(KEY_ENTITY, &rerun::TextDocument::from_markdown(md))?;
    Ok(())
}

/// The time-series entities under a lane's root (what [`AntLogger::log_series_gap`] breaks).
pub const SERIES_ENTITIES: [&str; 11] = [
    "joints/fatigue",
    "joints/scale",
    "joints/threshold",
    "actions/commanded",
    "actions/applied",
    "reward",
    "goal/distance",
    "goal/progress_rate",
    "latent/z",
    "probe/predicted",
    "probe/truth",
];

#[derive(Debug, thiserror::Error)]
pub enum TelemetryError {
    #[error("rerun: {0}")]
    Rerun(#[from] rerun::RecordingStreamError),
    #[error("cannot write recording {path}: {reason}")]
    File {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("flushing the recording")]
    Flush(#[source] rerun::sink::SinkFlushError),
    #[error("the blueprint has no activation command")]
    NoBlueprintActivation,
    #[error("the viewer did not take the last data within {0:?} (was it closed?)")]
    FlushTimeout(std::time::Duration),
    #[error(
        "'{url}' is not a Rerun viewer address (expected rerun+http://HOST:PORT/proxy): {reason}"
    )]
    Url {
        url: String,
        #[source]
        reason: crate::Cause,
    },
    #[cfg(feature = "web")]
    #[error("starting the gRPC stream")]
    Proxy(#[source] proxy::ProxyError),
}

/// Where a recording goes.
#[derive(Debug, Clone)]
pub enum Sink {
    File(PathBuf),
    Memory,
    /// A running Rerun viewer (`rerun+http://HOST:PORT/proxy`), and optionally a file as well.
    Viewer {
        url: String,
        save: Option<PathBuf>,
    },
    /// Rerun's message proxy served by us on a Unix socket (behind `live --web`'s guarded gRPC
    /// port, for Rerun's web viewer or any viewer given that port; [`proxy`]), and optionally a
    /// file as well.
    #[cfg(feature = "web")]
    Serve {
        socket: PathBuf,
        save: Option<PathBuf>,
        /// Which request hosts the proxy answers (the guard's rule: loopback names only on a
        /// loopback bind).
        admit_host: fn(&str) -> bool,
    },
}

/// What the gRPC server keeps for viewers that connect late (oldest data dropped beyond it).
#[cfg(feature = "web")]
pub const SERVE_MEMORY_LIMIT_BYTES: u64 = 2 << 30;

/// How often the web stream sends what was logged since, as one batch of chunks. Rerun's
/// default for live streams (8 ms) makes a chunk per entity per step; a browser painting WebGL
/// on the CPU (SwiftShader, 2 cores) ingests about 10 steps/s of that and falls behind a 1×
/// two-model session (20 steps/s) without bound: 710 steps after 90 s. In 0.5 s batches it
/// keeps up (docs/web.md, "Measured"); a browser with a GPU only sees the Ant move in
/// half-second strides. `RERUN_FLUSH_TICK_SECS` overrides it, as for any Rerun stream.
#[cfg(feature = "web")]
pub const WEB_STREAM_BATCH: std::time::Duration = std::time::Duration::from_millis(500);

/// The web stream's batch period: [`WEB_STREAM_BATCH`], or `RERUN_FLUSH_TICK_SECS` where set
/// (an explicit batcher config would otherwise skip Rerun's environment overrides).
#[cfg(feature = "web")]
pub fn web_stream_batch() -> std::time::Duration {
    let ours = rerun::log::ChunkBatcherConfig {
        flush_tick: WEB_STREAM_BATCH,
        ..rerun::log::ChunkBatcherConfig::LOW_LATENCY
    };
    match ours.apply_env() {
        Ok(config) => config.flush_tick,
        Err(e) => {
            log::warn!("{e}; the web stream keeps its {WEB_STREAM_BATCH:?} batches");
            WEB_STREAM_BATCH
        }
    }
}

fn file_sink_error(path: &std::path::Path, e: impl Into<crate::Cause>) -> TelemetryError {
    TelemetryError::File {
        path: path.to_path_buf(),
        reason: e.into(),
    }
}

fn create_parent_dir(path: &std::path::Path) -> Result<(), TelemetryError> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => std::fs::create_dir_all(dir).map_err(|e| file_sink_error(path, e)),
        None => Ok(()),
    }
}

/// Opens a recording with our blueprint (made active: its views depend on the models, so a
/// layout the viewer kept from another recording must not win) and no wall-clock timeline.
/// `recording_id` makes the recording reproducible (same id for the same inputs).
pub fn open(
    sink: &Sink,
    recording_id: &str,
    roots: &[String],
) -> Result<(RecordingStream, Option<rerun::sink::MemorySinkStorage>), TelemetryError> {
    open_titled(
        sink,
        recording_id,
        roots,
        &default_titles(roots),
        ViewOptions::default(),
    )
}

/// [`open`] with the 3-D views titled (see [`view_titles`]) and the views `views` asks for.
pub fn open_titled(
    sink: &Sink,
    recording_id: &str,
    roots: &[String],
    titles: &[String],
    views: ViewOptions,
) -> Result<(RecordingStream, Option<rerun::sink::MemorySinkStorage>), TelemetryError> {
    let builder = RecordingStreamBuilder::new(APP_ID).recording_id(recording_id.to_string());
    let (rec, storage) = match sink {
        Sink::File(path) => {
            create_parent_dir(path)?;
            let rec = builder.save(path).map_err(|e| file_sink_error(path, e))?;
            (rec, None)
        }
        Sink::Memory => {
            let (rec, storage) = builder.memory()?;
            (rec, Some(storage))
        }
        Sink::Viewer { url, save } => {
            let uri: rerun::external::re_uri::ProxyUri =
                url.parse().map_err(|e| TelemetryError::Url {
                    url: url.clone(),
                    reason: format!("{e}").into(),
                })?;
            let viewer = rerun::sink::GrpcSink::new(uri);
            let rec = match save {
                Some(path) => {
                    create_parent_dir(path)?;
                    let file =
                        rerun::sink::FileSink::new(path).map_err(|e| file_sink_error(path, e))?;
                    // The file first: a multi-sink flushes in order, and the file must not wait
                    // on a slow or vanished viewer.
                    builder.set_sinks((file, viewer))?
                }
                None => builder.set_sinks((viewer,))?,
            };
            (rec, None)
        }
        #[cfg(feature = "web")]
        Sink::Serve {
            socket,
            save,
            admit_host,
        } => {
            let options = rerun::ServerOptions {
                memory_limit: rerun::MemoryLimit::from_bytes(SERVE_MEMORY_LIMIT_BYTES),
                // A viewer that joins late gets the present first and the history behind it,
                // so its lag does not start at the session's whole length.
                playback_behavior: rerun::PlaybackBehavior::NewestFirst,
                ..Default::default()
            };
            let batching = rerun::log::ChunkBatcherConfig {
                flush_tick: web_stream_batch(),
                ..rerun::log::ChunkBatcherConfig::LOW_LATENCY
            };
            let builder = builder.batcher_config(batching);
            let file = match save {
                Some(path) => {
                    create_parent_dir(path)?;
                    Some(rerun::sink::FileSink::new(path).map_err(|e| file_sink_error(path, e))?)
                }
                None => None,
            };
            let sink = proxy::UnixProxySink::start(socket, options, file, *admit_host)
                .map_err(TelemetryError::Proxy)?;
            // Our sink cannot join Rerun's (sealed) multi-sink: it writes the file itself.
            let rec = builder.buffered()?;
            rec.set_sink(Box::new(sink));
            (rec, None)
        }
    };
    rec.set_log_time_enabled(false);
    rec.set_log_tick_enabled(false);
    send_layout_for(&rec, roots, titles, roots, views)?;
    Ok((rec, storage))
}

#[cfg(test)]
mod tests {
    #[test]
    fn views_are_titled_by_model_and_lane_only_where_models_repeat() {
        let s = |v: &[&str]| v.iter().map(|x| x.to_string()).collect::<Vec<_>>();
        assert_eq!(
            super::view_titles(&s(&["encoder-lstm", "baseline"]), &s(&["ant", "compare"])),
            s(&["Ant: encoder-lstm", "Ant: baseline"])
        );
        assert_eq!(
            super::view_titles(&s(&["run", "run"]), &s(&["ant", "compare"])),
            s(&["Ant: run (ant)", "Ant: run (compare)"])
        );
    }

    #[test]
    fn hsl_primaries_and_family_shades() {
        use crate::palette::hsl_to_rgb;
        assert_eq!(hsl_to_rgb(240.0, 1.0, 0.5), [0, 0, 255]);
        assert_eq!(hsl_to_rgb(60.0, 0.0, 0.5), [128, 128, 128]);
        // Shades of one family run dark to light.
        let shades: Vec<[u8; 4]> = (0..8).map(|i| super::family_color(1, i, 8)).collect();
        let lum = |c: &[u8; 4]| c[0] as u32 + c[1] as u32 + c[2] as u32;
        assert!(
            shades.windows(2).all(|w| lum(&w[0]) < lum(&w[1])),
            "{shades:?}"
        );
    }
}
