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

mod session;
pub use session::{
    Actor, FORK_ROOT, HISTORY_CAP, LOG_CAP, Lane, LaneEnding, LaneSnapshot, LaneSpec, LogEntry,
    PartialFile, RecordError, RecordOptions, RecordSummary, RewindError, Session, model_roots,
    record, side_by_side_offset,
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
    File { path: PathBuf, reason: String },
    #[error("flushing the recording")]
    Flush(#[source] rerun::sink::SinkFlushError),
    #[error("the blueprint has no activation command")]
    NoBlueprintActivation,
    #[error("the viewer did not take the last data within {0:?} (was it closed?)")]
    FlushTimeout(std::time::Duration),
    #[error(
        "'{url}' is not a Rerun viewer address (expected rerun+http://HOST:PORT/proxy): {reason}"
    )]
    Url { url: String, reason: String },
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
    /// Our own gRPC server on `bind:port` (for Rerun's web viewer, or any viewer that connects
    /// to `rerun+http://bind:port/proxy`), and optionally a file as well.
    #[cfg(feature = "web")]
    Serve {
        bind: std::net::IpAddr,
        port: u16,
        save: Option<PathBuf>,
    },
}

/// What the gRPC server keeps for viewers that connect late (oldest data dropped beyond it).
#[cfg(feature = "web")]
pub const SERVE_MEMORY_LIMIT_BYTES: u64 = 2 << 30;

fn file_sink_error(path: &std::path::Path, e: impl std::fmt::Display) -> TelemetryError {
    TelemetryError::File {
        path: path.to_path_buf(),
        reason: e.to_string(),
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
    open_titled(sink, recording_id, roots, &default_titles(roots))
}

/// [`open`] with the 3-D views titled (see [`view_titles`]).
pub fn open_titled(
    sink: &Sink,
    recording_id: &str,
    roots: &[String],
    titles: &[String],
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
                    reason: format!("{e}"),
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
        Sink::Serve { bind, port, save } => {
            let options = rerun::ServerOptions {
                memory_limit: rerun::MemoryLimit::from_bytes(SERVE_MEMORY_LIMIT_BYTES),
                ..Default::default()
            };
            let server = rerun::grpc_server::GrpcServerSink::new(&bind.to_string(), *port, options)
                .map_err(|e| TelemetryError::Url {
                    url: format!("{bind}:{port}"),
                    reason: e.to_string(),
                })?;
            let rec = match save {
                Some(path) => {
                    create_parent_dir(path)?;
                    let file =
                        rerun::sink::FileSink::new(path).map_err(|e| file_sink_error(path, e))?;
                    builder.set_sinks((file, server))?
                }
                None => builder.set_sinks((server,))?,
            };
            (rec, None)
        }
    };
    rec.set_log_time_enabled(false);
    rec.set_log_tick_enabled(false);
    send_layout_with(&rec, roots, titles, roots)?;
    Ok((rec, storage))
}

/// What someone opening the file sees first: the Ant large, fatigue, z / PCA, progress, events.
pub fn default_blueprint(roots: &[String]) -> Blueprint {
    default_layout(roots).blueprint
}

/// Our blueprint and the view properties the Rust view builders do not expose, by view path.
pub struct Layout {
    pub blueprint: Blueprint,
    /// (blueprint entity path, property archetype) to log on the blueprint stream.
    pub properties: Vec<(String, Box<dyn rerun::AsComponents + Send>)>,
}

/// The view's path in the blueprint store (`view/{id}`), where its properties live.
fn view_path(view: &rerun::blueprint::ContainerLike) -> Option<String> {
    match view {
        rerun::blueprint::ContainerLike::View(v) => Some(v.blueprint_path().to_string()),
        _ => None,
    }
}

/// The layout, with its properties: each 3-D view follows its Ant's torso, and time-series
/// legends are hidden (they covered the lines; hovering a line names it).
pub fn default_layout(roots: &[String]) -> Layout {
    layout_with(roots, &default_titles(roots), roots)
}

/// 3-D view titles by model: "Ant: LABEL", with the lane's root where two lanes share a label
/// (one checkpoint side by side with itself).
pub fn view_titles(labels: &[String], roots: &[String]) -> Vec<String> {
    labels
        .iter()
        .zip(roots)
        .map(|(label, root)| {
            if labels.iter().filter(|l| *l == label).count() > 1 {
                format!("Ant: {label} ({root})")
            } else {
                format!("Ant: {label}")
            }
        })
        .collect()
}

/// "Ant" for one model, "Ant: ROOT" for several (a session titles views by checkpoint instead).
pub fn default_titles(roots: &[String]) -> Vec<String> {
    roots
        .iter()
        .map(|r| {
            if roots.len() == 1 {
                "Ant".to_string()
            } else {
                format!("Ant: {r}")
            }
        })
        .collect()
}

/// The layout with a 3-D view per `world_roots` (titled by `titles`, in the same order) and every
/// root of `plot_roots` overlaid in the plots (a rewind's branches beside the history they left).
pub fn layout_with(world_roots: &[String], titles: &[String], plot_roots: &[String]) -> Layout {
    layout_for(world_roots, titles, plot_roots, false)
}

/// [`layout_with`]; with `attribution`, the tabs holding the attribution views come up on them.
pub fn layout_for(
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
    attribution: bool,
) -> Layout {
    let roots = world_roots;
    let mut properties: Vec<(String, Box<dyn rerun::AsComponents + Send>)> = Vec::new();
    let paths = |leaves: &[&str]| -> Vec<String> {
        plot_roots
            .iter()
            .flat_map(|r| leaves.iter().map(move |l| format!("/{r}/{l}")))
            .collect()
    };
    // One 3-D view per model: side-by-side models each get their own camera.
    let mut worlds: Vec<rerun::blueprint::ContainerLike> = Vec::new();
    for (k, r) in roots.iter().enumerate() {
        let name = titles
            .get(k)
            .cloned()
            .unwrap_or_else(|| format!("Ant: {r}"));
        let view: rerun::blueprint::ContainerLike = Spatial3DView::new(name)
            .with_origin("/")
            .with_contents([format!("/{r}/world/**")])
            .into();
        if let Some(path) = view_path(&view) {
            properties.push((
                format!("{path}/EyeControls3D"),
                Box::new(
                    rerun::external::re_sdk_types::blueprint::archetypes::EyeControls3D::new()
                        .with_tracking_entity(format!("/{r}/world/focus"))
                        .with_position(EYE_START)
                        .with_look_target(EYE_TARGET),
                ),
            ));
        }
        worlds.push(view);
    }
    let world: rerun::blueprint::ContainerLike = if worlds.len() == 1 {
        worlds.remove(0)
    } else {
        Horizontal::new(worlds).into()
    };
    let mut series = |view: TimeSeriesView| -> rerun::blueprint::ContainerLike {
        let view = view.into();
        if let Some(path) = view_path(&view) {
            properties.push((
                format!("{path}/PlotLegend"),
                Box::new(
                    rerun::external::re_sdk_types::blueprint::archetypes::PlotLegend::new()
                        .with_visible(false),
                ),
            ));
        }
        view
    };
    let fatigue = series(
        TimeSeriesView::new("Fatigue per joint (τ = threshold)")
            .with_contents(paths(&["joints/fatigue", "joints/threshold"])),
    );
    let scale = series(TimeSeriesView::new("Torque scale").with_contents(paths(&["joints/scale"])));
    let latent = series(TimeSeriesView::new("z").with_contents(paths(&["latent/z"])));
    // Its legend stays: ten named groups are the point of this plot.
    let why: rerun::blueprint::ContainerLike =
        TimeSeriesView::new("Why z moved: each group's share of ‖z − z(0)‖")
            .with_contents(paths(&["latent/attribution_groups"]))
            .into();
    let why_grid: rerun::blueprint::ContainerLike = rerun::blueprint::Spatial2DView::new(
        "Why z moved: group × window slot (red raised ‖z − z(0)‖, blue lowered it)",
    )
    .with_contents(paths(&["latent/attribution_map/**"]))
    .into();
    let tabs = |views: Vec<rerun::blueprint::ContainerLike>, shown: Option<String>| {
        let tabs = rerun::blueprint::Tabs::new(views);
        match shown {
            Some(path) if attribution => tabs.with_active_tab(path),
            _ => tabs,
        }
    };
    let (why_path, grid_path) = (view_path(&why), view_path(&why_grid));
    let probe = series(
        TimeSeriesView::new("Probe: P(damaged) vs truth").with_contents(paths(&["probe/**"])),
    );
    // Its legend stays, top right: one line per model, named by it — the models' key.
    let progress: rerun::blueprint::ContainerLike = TimeSeriesView::new("Goal distance (m)")
        .with_contents(paths(&["goal/distance"]))
        .into();
    if let Some(path) = view_path(&progress) {
        properties.push((
            format!("{path}/PlotLegend"),
            Box::new(
                rerun::external::re_sdk_types::blueprint::archetypes::PlotLegend::new()
                    .with_visible(true)
                    .with_corner(
                        rerun::external::re_sdk_types::blueprint::components::Corner2D::RightTop,
                    ),
            ),
        ));
    }
    let pca = Spatial2DView::new("z in PCA basis")
        .with_contents(paths(&["latent/pca", "latent/pca_trail"]));
    let pca3 = Spatial3DView::new("z in PCA basis, 3-D")
        .with_contents(paths(&["latent/pca3", "latent/pca3_trail"]));
    let events: rerun::blueprint::ContainerLike = TextLogView::new("Damage events")
        .with_contents(paths(&["events"]))
        .into();
    if let Some(path) = view_path(&events) {
        // The text before the entity path: a narrow view cut the path to "/enc…" and the text
        // with it; each text names its lane's model anyway.
        use rerun::external::re_sdk_types::blueprint::encodings::{
            TextLogColumn, TextLogColumnKind,
        };
        let column = |kind| TextLogColumn {
            kind,
            visible: true.into(),
        };
        properties.push((
            format!("{path}/TextLogColumns"),
            Box::new(
                rerun::external::re_sdk_types::blueprint::archetypes::TextLogColumns::new()
                    .with_text_log_columns([
                        column(TextLogColumnKind::LogLevel),
                        column(TextLogColumnKind::Body),
                        column(TextLogColumnKind::EntityPath),
                    ]),
            ),
        ));
    }
    let key = rerun::blueprint::TextDocumentView::new("Key: what each colour means")
        .with_contents([format!("/{KEY_ENTITY}")]);
    let gait = rerun::blueprint::StateTimelineView::new("Gait: stance per leg")
        .with_contents(paths(&["gait/**"]));
    let blueprint = Blueprint::new(
        Horizontal::new([
            Vertical::new([
                world,
                Horizontal::new([events, key.into()])
                    .with_column_shares([1.4, 1.0])
                    .into(),
            ])
            .with_row_shares([3.0, 1.2])
            .into(),
            Vertical::new([gait.into(), fatigue, scale, progress])
                .with_row_shares([1.5, 1.0, 1.0, 1.0])
                .into(),
            Vertical::new([
                tabs(vec![latent, why], why_path).into(),
                tabs(vec![pca.into(), pca3.into(), why_grid], grid_path).into(),
                probe,
            ])
            .into(),
        ])
        .with_column_shares([2.0, 1.2, 1.2]),
    )
    .with_auto_views(false)
    // The views get the screen: the blueprint tree and the selection start collapsed.
    .with_blueprint_panel(
        rerun::blueprint::BlueprintPanel::new()
            .with_state(rerun::blueprint::components::PanelState::Collapsed),
    )
    .with_selection_panel(
        rerun::blueprint::SelectionPanel::new()
            .with_state(rerun::blueprint::components::PanelState::Collapsed),
    )
    // On the step timeline, following the latest data: live, the views show now; a file
    // opens at its end, where the damage it recorded is in the legs (scrub back from there).
    .with_time_panel(
        rerun::blueprint::TimePanel::new()
            .with_timeline("step")
            .with_play_state(rerun::blueprint::components::PlayState::Following),
    );
    Layout {
        blueprint,
        properties,
    }
}

/// Sends our layout to `rec`, made active and default (its views depend on the models, so a
/// layout the viewer kept from another recording must not win), properties included: the
/// blueprint's messages are built on a memory stream, the properties logged into the same
/// blueprint store, and all of it goes out before the activation command.
pub fn send_layout(rec: &RecordingStream, roots: &[String]) -> Result<(), TelemetryError> {
    send_layout_with(rec, roots, &default_titles(roots), roots)
}

/// [`send_layout`] with [`layout_with`]'s split of 3-D views and plotted roots.
pub fn send_layout_with(
    rec: &RecordingStream,
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
) -> Result<(), TelemetryError> {
    send_layout_for(rec, world_roots, titles, plot_roots, false)
}

/// [`send_layout_with`], the attribution views up front when `attribution` (see
/// [`layout_for`]).
pub fn send_layout_for(
    rec: &RecordingStream,
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
    attribution: bool,
) -> Result<(), TelemetryError> {
    use rerun::log::LogMsg;
    let layout = layout_for(world_roots, titles, plot_roots, attribution);
    let (scratch, storage) = RecordingStreamBuilder::new(APP_ID).memory()?;
    layout.blueprint.send(
        &scratch,
        rerun::blueprint::BlueprintActivation {
            make_active: true,
            make_default: true,
        },
    )?;
    scratch.flush_blocking().map_err(TelemetryError::Flush)?;
    let mut messages = Vec::new();
    let mut activation = None;
    for msg in storage.take() {
        match msg {
            LogMsg::BlueprintActivationCommand(cmd) => activation = Some(cmd),
            msg if msg.store_id().is_blueprint() => messages.push(msg),
            _ => {} // the scratch recording's own store info
        }
    }
    let activation = activation.ok_or(TelemetryError::NoBlueprintActivation)?;
    let (props, props_storage) =
        RecordingStreamBuilder::from_store_id(&activation.blueprint_id).memory()?;
    props.set_time_sequence("blueprint", 0);
    for (path, archetype) in &layout.properties {
        props.log(path.as_str(), archetype.as_ref())?;
    }
    props.flush_blocking().map_err(TelemetryError::Flush)?;
    messages.extend(
        props_storage
            .take()
            .into_iter()
            .filter(|m| matches!(m, LogMsg::ArrowMsg(..))),
    );
    rec.send_blueprint(messages, activation);
    Ok(())
}

/// A capsule of the model: MuJoCo's capsule is centred on its frame, axis along local z.
#[derive(Debug, Clone)]
struct CapsuleGeom {
    id: usize,
    name: String,
    radius: f32,
    half_length: f32,
    /// The actuator whose joint moves this geom's body (leg segments), for damage colours.
    actuator: Option<usize>,
    rgba: [u8; 4],
}

/// Logs one model's rollouts under `root`, a handful of batched calls per step.
pub struct AntLogger {
    rec: RecordingStream,
    root: String,
    capsules: Vec<CapsuleGeom>,
    /// (geom id, radius) of the torso sphere.
    torso: Option<(usize, f32)>,
    floor_half: Option<[f32; 2]>,
    joint_names: Vec<String>,
    probe: Option<std::sync::Arc<ProbeFile>>,
    trail: Vec<[f32; 3]>,
    /// PCA projections of this episode (up to 3 axes) with their colour (triggered joints).
    pca_trail: Vec<([f32; 3], rerun::Color)>,
    static_logged: bool,
    dt: f64,
    threshold: f64,
    /// PCA point colour by the number of joints with torque lost (0..=8; [`PCA_KEY`]).
    pca_palette: Vec<rerun::Color>,
    /// Where this model's world is drawn, so side-by-side Ants do not overlap.
    world_offset: [f32; 3],
    /// Each leg's last logged gait state, so only changes are logged.
    gait_states: [Option<&'static str>; crate::env::N_LEGS],
    /// With several lanes in one recording: this lane's name in every series and its own hue.
    series_style: Option<SeriesStyle>,
    /// The z size whose series names are logged (with a series style), so they go out once.
    z_named: Option<usize>,
    /// The `step` timeline's value now: event texts name it.
    now_step: u64,
    /// Whether a push arrow is on screen (cleared the step after its push ends).
    push_drawn: bool,
    /// Whether the attribution series' names are out (static, once).
    attribution_named: bool,
    /// The window entry's feature groups the attribution view sums over (this model's joints).
    feature_groups: Vec<crate::explain::FeatureGroup>,
}

/// How a lane's plot lines are told apart from another lane's in the same views.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SeriesStyle {
    /// Prefixed to every series name (`"encoder-lstm: hip_1"`).
    pub label: String,
    /// Hue family: 0 orange, 1 blue, 2 green, 3 purple, then around again.
    pub family: usize,
}

/// The `i`-th of `n` shades of lane `family`'s hue ([`palette::model_shade`]), as RGBA.
pub fn family_color(family: usize, i: usize, n: usize) -> [u8; 4] {
    let [r, g, b] = palette::model_shade(family, i, n);
    [r, g, b, 255]
}

/// A leg segment's colour: the torque its joint has left ([`Torque`]), never fatigue or a
/// trigger that took nothing (fatigue has its own plot).
pub fn leg_color(scale: f64, state: crate::damage::JointState) -> [u8; 4] {
    Torque::of(scale, state).rgba()
}

fn color([r, g, b, a]: [u8; 4]) -> rerun::Color {
    rerun::Color::from_unmultiplied_rgba(r, g, b, a)
}

impl AntLogger {
    pub fn new(
        rec: RecordingStream,
        root: &str,
        env: &AntEnv,
        probe: Option<std::sync::Arc<ProbeFile>>,
    ) -> Self {
        let model = env.physics().model();
        let mut capsules = Vec::new();
        let (mut torso, mut floor_half) = (None, None);
        for g in 0..model.ngeom() as usize {
            let name = model
                .id_to_name(mujoco_rs::prelude::MjtObjBase::mjOBJ_GEOM, g)
                .filter(|n| !n.is_empty())
                .map_or_else(|| format!("geom{g}"), str::to_string);
            let size = model.geom_size()[g];
            let body = model.geom_bodyid()[g] as usize;
            match model.geom_type()[g] as i32 {
                0 => floor_half = Some([size[0] as f32, size[1] as f32]),
                2 if body == env.torso_body() => torso = Some((g, size[0] as f32)),
                3 => capsules.push(CapsuleGeom {
                    id: g,
                    name,
                    radius: size[0] as f32,
                    half_length: size[1] as f32,
                    actuator: env.actuators().iter().position(|a| a.body_id == body),
                    rgba: model.geom_rgba()[g].map(|v| (v * 255.0) as u8),
                }),
                _ => {}
            }
        }
        Self {
            rec,
            root: root.to_string(),
            capsules,
            torso,
            floor_half,
            // Series named by joint and the leg it moves (the gait view's lane names).
            joint_names: env
                .actuators()
                .iter()
                .enumerate()
                .map(|(i, a)| {
                    format!(
                        "{} ({})",
                        a.joint,
                        env.leg_names()[env.leg_of_actuator()[i]]
                    )
                })
                .collect(),
            probe,
            trail: Vec::new(),
            pca_trail: Vec::new(),
            static_logged: false,
            dt: env.dt(),
            threshold: env.config().damage.threshold,
            pca_palette: crate::plots::viridis(N_ACTUATORS + 1)
                .into_iter()
                .map(|c| rerun::Color::from_rgb(c.0, c.1, c.2))
                .collect(),
            world_offset: [0.0; 3],
            gait_states: [None; crate::env::N_LEGS],
            series_style: None,
            z_named: None,
            now_step: 0,
            push_drawn: false,
            attribution_named: false,
            feature_groups: crate::explain::feature_groups(env.actuators()),
        }
    }

    /// Names and colours this lane's series as one of several lanes (see [`SeriesStyle`]); if
    /// its static data is already out, the series styles are logged again (static data is
    /// replaced by a later static write).
    pub fn set_series_style(&mut self, style: Option<SeriesStyle>) -> Result<(), TelemetryError> {
        if self.series_style == style {
            return Ok(());
        }
        self.series_style = style;
        self.z_named = None;
        if self.static_logged {
            self.log_series_styles()?;
        }
        Ok(())
    }

    /// This lane's hue ([`palette::model`]): its family among several lanes, else the first.
    fn hue(&self) -> usize {
        self.series_style.as_ref().map_or(0, |s| s.family)
    }

    /// Draws this model's world (floor, goal, Ant) shifted by `offset` metres.
    pub fn with_world_offset(mut self, offset: [f32; 3]) -> Self {
        self.world_offset = offset;
        self
    }

    /// The same model's logger under another root (a rewind's branch): same offset and probe,
    /// the drawing state (trails, logged events) carried over.
    pub fn branch(&self, root: &str, env: &AntEnv) -> Self {
        let mut logger = AntLogger::new(self.rec.clone(), root, env, self.probe.clone())
            .with_world_offset(self.world_offset);
        logger.series_style = self.series_style.clone();
        logger.continue_from(self);
        logger
    }

    pub fn probe(&self) -> Option<&ProbeFile> {
        self.probe.as_deref()
    }

    fn path(&self, leaf: &str) -> String {
        format!("{}/{leaf}", self.root)
    }

    fn log_static(&mut self, env: &AntEnv) -> Result<(), TelemetryError> {
        let rec = &self.rec;
        // Stance tinted as the legs are: full torque, torque lost, dead, pinned.
        let stance_colors = LegTorque::ALL.map(|l| {
            let [r, g, b] = l.rgb();
            [r, g, b, 255]
        });
        for name in env.leg_names() {
            rec.log_static(
                self.path(&format!("gait/{name}")).as_str(),
                &rerun::StateConfiguration::new()
                    .with_values(GAIT_STATES)
                    .with_colors(stance_colors.map(color)),
            )?;
        }
        if self.world_offset != [0.0; 3] {
            rec.log_static(
                self.path("world").as_str(),
                &rerun::Transform3D::from_translation(self.world_offset),
            )?;
        }
        // Leg capsules: shape and names once; poses and colours per step only (static colours
        // would hide every per-step colour: in Rerun static data wins).
        rec.log_static(
            self.path("world/legs").as_str(),
            &rerun::Capsules3D::from_lengths_and_radii(
                self.capsules.iter().map(|c| 2.0 * c.half_length),
                self.capsules.iter().map(|c| c.radius),
            )
            .with_labels(self.capsules.iter().map(|c| c.name.clone()))
            .with_show_labels(false),
        )?;
        if let Some((_, radius)) = self.torso {
            rec.log_static(
                self.path("world/torso").as_str(),
                &rerun::Ellipsoids3D::from_radii([radius])
                    .with_colors([rerun::Color::from_rgb(204, 153, 102)])
                    .with_fill_mode(rerun::FillMode::Solid),
            )?;
        }
        if let Some(half) = self.floor_half {
            // The model's floor is 80 m wide; draw the patch around start and goal (within its
            // extent) so the default camera frames the Ant, not the horizon.
            let goal = env.config().env.goal;
            let center = [goal[0] as f32 / 2.0, goal[1] as f32 / 2.0];
            let reach =
                (center[0].abs().max(center[1].abs()) + 3.0).min(half[0].max(half[1]).max(1.0));
            rec.log_static(
                self.path("world/floor").as_str(),
                &rerun::Boxes3D::from_centers_and_half_sizes(
                    [[center[0], center[1], -0.005]],
                    [[reach, reach, 0.005]],
                )
                .with_colors([rerun::Color::from_rgb(205, 215, 205)])
                .with_fill_mode(rerun::FillMode::Solid),
            )?;
        }
        let goal = env.config().env.goal;
        let radius = env.config().env.success_radius;
        let gold = rerun::Color::from_rgb(250, 200, 0);
        rec.log_static(
            self.path("world/goal").as_str(),
            &rerun::Ellipsoids3D::from_centers_and_radii(
                [[goal[0] as f32, goal[1] as f32, 0.1]],
                [0.1],
            )
            .with_colors([gold])
            .with_fill_mode(rerun::FillMode::Solid),
        )?;
        let circle: Vec<[f32; 3]> = (0..=64)
            .map(|k| {
                let a = k as f64 / 64.0 * std::f64::consts::TAU;
                [
                    (goal[0] + radius * a.cos()) as f32,
                    (goal[1] + radius * a.sin()) as f32,
                    0.01,
                ]
            })
            .collect();
        rec.log_static(
            self.path("world/goal/radius").as_str(),
            &rerun::LineStrips3D::new([circle]).with_colors([gold]),
        )?;
        self.log_series_styles()?;
        self.static_logged = true;
        Ok(())
    }

    /// Series names (and, as one of several lanes, colours) of every plotted entity: static,
    /// as they never change within a recording except by being replaced whole.
    fn log_series_styles(&self) -> Result<(), TelemetryError> {
        let style = self.series_style.as_ref();
        let name = |n: &str| match style {
            Some(s) => format!("{}: {n}", s.label),
            None => n.to_string(),
        };
        let lines = |names: Vec<String>| {
            let n = names.len();
            let series = rerun::SeriesLines::new().with_names(names);
            match style {
                Some(s) => series.with_colors((0..n).map(|i| color(family_color(s.family, i, n)))),
                None => series,
            }
        };
        // The probe's joints, one colour each (shades of the lane's hue among several lanes):
        // the prediction a line, the truth crosses of the same colour.
        let joint_colors: Vec<rerun::Color> = (0..N_ACTUATORS)
            .map(|i| match style {
                Some(s) => color(family_color(s.family, i, N_ACTUATORS)),
                None => {
                    let [r, g, b] =
                        palette::hsl_to_rgb(360.0 * i as f64 / N_ACTUATORS as f64, 0.75, 0.45);
                    rerun::Color::from_rgb(r, g, b)
                }
            })
            .collect();
        let joints: Vec<String> = self.joint_names.iter().map(|j| name(j)).collect();
        let probed = self.probe.is_some();
        let mut entities: Vec<(&str, Vec<String>)> = vec![
            ("joints/fatigue", joints.clone()),
            ("joints/scale", joints.clone()),
            ("actions/commanded", joints.clone()),
            ("actions/applied", joints.clone()),
            (
                "reward",
                ["native", "progress", "success", "total"]
                    .iter()
                    .map(|n| name(n))
                    .collect(),
            ),
        ];
        if style.is_some() {
            // One line each: the lane's name says whose it is.
            entities.push(("joints/threshold", vec![name("threshold τ")]));
            entities.push(("goal/progress_rate", vec![name("progress rate")]));
        }
        for (leaf, names) in entities {
            self.rec
                .log_static(self.path(leaf).as_str(), &lines(names))?;
        }
        // Goal distance: one line per lane in the lane's own colour, named by its model (the
        // view's legend, shown, is the models' key).
        let [r, g, b] = palette::model(self.hue());
        self.rec.log_static(
            self.path("goal/distance").as_str(),
            &rerun::SeriesLines::new()
                .with_names([name("goal distance")])
                .with_colors([rerun::Color::from_rgb(r, g, b)]),
        )?;
        if probed {
            self.rec.log_static(
                self.path("probe/predicted").as_str(),
                &rerun::SeriesLines::new()
                    .with_names(joints.iter().map(|j| format!("P(damaged) {j}")))
                    .with_colors(joint_colors.clone()),
            )?;
            self.rec.log_static(
                self.path("probe/truth").as_str(),
                &rerun::SeriesPoints::new()
                    .with_names(joints.iter().map(|j| format!("truth {j}")))
                    .with_colors(joint_colors)
                    .with_markers([rerun::components::MarkerShape::Cross; N_ACTUATORS])
                    .with_marker_sizes([3.0; N_ACTUATORS]),
            )?;
        }
        Ok(())
    }

    /// Sets the timelines for global step `step` of episode `episode`.
    pub fn set_time(&mut self, step: u64, episode: u64) {
        self.now_step = step;
        self.rec.set_time_sequence("step", step as i64);
        self.rec
            .set_duration_secs("sim_time", step as f64 * self.dt);
        self.rec.set_time_sequence("episode", episode as i64);
    }

    /// Episode metadata at reset (and again with the outcome at the end).
    pub fn log_episode(
        &mut self,
        meta: &EpisodeMeta,
        env: &AntEnv,
        outcome: Option<&StepOutcome>,
    ) -> Result<(), TelemetryError> {
        if !self.static_logged {
            self.log_static(env)?;
        }
        if outcome.is_none() {
            self.trail.clear();
            self.pca_trail.clear();
            self.rec
                .log(self.path("world/ending").as_str(), &rerun::Clear::flat())?;
        }
        // The ending, in the 3-D view above the Ant, until the lane's next episode starts
        // (a side-by-side lane that goes on shows nothing there).
        if let Some(ending) = outcome.and_then(StepOutcome::ending) {
            let torso = env.physics().xpos()[env.torso_body()];
            let color = match ending {
                "success" => rerun::Color::from_rgb(40, 160, 60),
                _ => rerun::Color::from_rgb(220, 40, 40),
            };
            let steps = outcome.map_or(0, |o| o.step + 1);
            self.rec.log(
                self.path("world/ending").as_str(),
                &rerun::Points3D::new([[torso[0] as f32, torso[1] as f32, torso[2] as f32 + 0.8]])
                    .with_radii([rerun::Radius::new_ui_points(6.0)])
                    .with_colors([color])
                    .with_labels([format!("{} after {steps} steps", ending.to_uppercase())])
                    .with_show_labels(true),
            )?;
        }
        // τ at the episode's start and end: a flat line across the fatigue plot.
        self.rec.log(
            self.path("joints/threshold").as_str(),
            &rerun::Scalars::single(self.threshold),
        )?;
        let mut text = format!(
            "**checkpoint** {}  \n**encoder** {}  \n**condition** {}  \n**seed** {}",
            meta.checkpoint, meta.encoder, meta.condition, meta.seed
        );
        if let Some(out) = outcome {
            text += &format!(
                "  \n**success** {}  \n**steps** {}  \n**final distance** {:.2} m  \n**triggered joints** {}",
                out.success,
                out.step + 1,
                out.distance,
                env.damage().n_triggered()
            );
        }
        self.rec.log(
            self.path("episode").as_str(),
            &rerun::TextDocument::from_markdown(text),
        )?;
        Ok(())
    }

    /// After a rewind to `steps` steps of the episode: trails cut back, gait lanes re-logged.
    pub fn rewind_to(&mut self, steps: usize) {
        self.trail.truncate(steps);
        self.pca_trail.truncate(steps);
        self.gait_states = [None; crate::env::N_LEGS];
    }

    /// A fork's logger starts with the paths drawn so far by the lane it forks from.
    pub fn continue_from(&mut self, other: &AntLogger) {
        self.trail = other.trail.clone();
        self.pca_trail = other.pca_trail.clone();
    }

    /// A debugger note in this lane's event log, at the current time, with its own level.
    pub fn log_note(&mut self, level: NoteLevel, text: &str) -> Result<(), TelemetryError> {
        self.rec.log(
            self.path("events").as_str(),
            &rerun::TextLog::new(text).with_level(level.as_str()),
        )?;
        Ok(())
    }

    /// Ends every time series of this lane at the current time: the viewer breaks a line at a
    /// `Clear`, so a lane that waits for the others (its episode ended early) shows a gap until
    /// its next episode instead of a straight line across steps it never ran.
    pub fn log_series_gap(&mut self) -> Result<(), TelemetryError> {
        for entity in SERIES_ENTITIES {
            self.rec
                .log(self.path(entity).as_str(), &rerun::Clear::flat())?;
        }
        self.rec
            .log(self.path("gait").as_str(), &rerun::Clear::recursive())?;
        // The next logged state must go out even if it equals the one before the gap.
        self.gait_states = [None; crate::env::N_LEGS];
        Ok(())
    }

    /// Everything about one env step (timelines must be set first): `record` says what
    /// happened, `env` (in the state after the step) gives the geometry to draw.
    pub fn log_step(
        &mut self,
        env: &AntEnv,
        record: &crate::lane::StepRecord,
    ) -> Result<(), TelemetryError> {
        if !self.static_logged {
            self.log_static(env)?;
        }
        let out = &record.outcome;
        let physics = env.physics();
        // The Ant: poses from MuJoCo's geom frames (Rerun's capsule starts at its origin and runs
        // along +z, MuJoCo's is centred), leg colours from the damage state.
        let mut translations = Vec::with_capacity(self.capsules.len());
        let mut rotations = Vec::with_capacity(self.capsules.len());
        let mut colors = Vec::with_capacity(self.capsules.len());
        for c in &self.capsules {
            let (p, q) = geom_pose(env, c.id);
            let axis = q * rerun::external::glam::Vec3::Z;
            translations.push(p - axis * c.half_length);
            rotations.push(rerun::Quaternion::from_xyzw(q.to_array()));
            colors.push(match c.actuator {
                Some(i) => color(leg_color(record.scales[i], record.joint_states[i])),
                None => color(c.rgba),
            });
        }
        self.rec.log(
            self.path("world/legs").as_str(),
            &rerun::Capsules3D::update_fields()
                .with_translations(translations.iter().map(|t| t.to_array()))
                .with_quaternions(rotations)
                .with_colors(colors),
        )?;
        if let Some((g, _)) = self.torso {
            let (p, q) = geom_pose(env, g);
            self.rec.log(
                self.path("world/torso").as_str(),
                &rerun::Ellipsoids3D::update_fields()
                    .with_centers([p.to_array()])
                    .with_quaternions([rerun::Quaternion::from_xyzw(q.to_array())]),
            )?;
        }
        let torso = physics.xpos()[env.torso_body()];
        // The camera follows this ring: tracking the torso itself would frame a 0.25 m ball.
        let focus: Vec<[f32; 3]> = (0..=FOCUS_SEGMENTS)
            .map(|k| {
                let a = k as f32 / FOCUS_SEGMENTS as f32 * std::f32::consts::TAU;
                [
                    torso[0] as f32 + FOCUS_RADIUS * a.cos(),
                    torso[1] as f32 + FOCUS_RADIUS * a.sin(),
                    0.01,
                ]
            })
            .collect();
        self.rec.log(
            self.path("world/focus").as_str(),
            &rerun::LineStrips3D::new([focus])
                .with_colors([rerun::Color::from_unmultiplied_rgba(200, 200, 200, 60)]),
        )?;
        self.trail
            .push([torso[0] as f32, torso[1] as f32, torso[2] as f32]);
        if out.step.is_multiple_of(TRAIL_EVERY) || out.done() {
            let path: Vec<[f32; 3]> = self
                .trail
                .iter()
                .step_by(TRAIL_EVERY)
                .copied()
                .chain(self.trail.last().copied())
                .collect();
            let [r, g, b] = palette::model(self.hue());
            self.rec.log(
                self.path("world/trail").as_str(),
                &rerun::LineStrips3D::new([path]).with_colors([rerun::Color::from_rgb(r, g, b)]),
            )?;
        }
        // Joints and actions, one 8-wide batch each (series named by joint).
        let scalars = |v: &[f64]| rerun::Scalars::new(v.iter().copied());
        self.rec.log(
            self.path("joints/fatigue").as_str(),
            &scalars(&record.fatigue),
        )?;
        self.rec
            .log(self.path("joints/scale").as_str(), &scalars(&record.scales))?;
        self.rec.log(
            self.path("actions/commanded").as_str(),
            &scalars(&out.commanded_action),
        )?;
        self.rec.log(
            self.path("actions/applied").as_str(),
            &scalars(&out.applied_action),
        )?;
        // Gait diagram: per leg a state lane, "stance" states named by the leg's damage while the
        // foot is on the floor, a gap (an empty state) while it swings; logged on changes only.
        for (leg, name) in env.leg_names().iter().enumerate() {
            let state = if record.contacts[leg] {
                LegTorque::of(
                    (0..N_ACTUATORS)
                        .filter(|&i| env.leg_of_actuator()[i] == leg)
                        .map(|i| Torque::of(record.scales[i], record.joint_states[i])),
                )
                .stance_name()
            } else {
                GAIT_SWING
            };
            if self.gait_states[leg] != Some(state) {
                self.rec.log(
                    self.path(&format!("gait/{name}")).as_str(),
                    &rerun::StateChange::single(state),
                )?;
                self.gait_states[leg] = Some(state);
            }
        }
        // This step's events, as text (the state changes are in the series above).
        // The text's step is the row's (the `step` column), so the two never disagree.
        for e in &record.events {
            // A warning only where torque was lost: under the healthy condition a trigger
            // keeps scale 1 and is news, not damage.
            // A scenario's change is scripted damage, a warning like a trigger when it takes
            // torque; a hand's is INFO.
            let level = match &e.kind {
                DamageEventKind::Trigger | DamageEventKind::Dead if e.scale < 1.0 => {
                    rerun::TextLogLevel::WARN
                }
                DamageEventKind::Override { .. } if e.source.is_some() && e.scale < 1.0 => {
                    rerun::TextLogLevel::WARN
                }
                _ => rerun::TextLogLevel::INFO,
            };
            let text = format!("step {}: {}", self.now_step, e.describe());
            self.rec.log(
                self.path("events").as_str(),
                &rerun::TextLog::new(text).with_level(level),
            )?;
        }
        self.log_pushes(record)?;
        let r = out.reward;
        self.rec.log(
            self.path("reward").as_str(),
            &scalars(&[r.native, r.progress, r.success, r.total]),
        )?;
        self.rec.log(
            self.path("goal/distance").as_str(),
            &rerun::Scalars::single(out.distance),
        )?;
        self.rec.log(
            self.path("goal/progress_rate").as_str(),
            &rerun::Scalars::single(r.progress / self.dt),
        )?;
        // The latent, its PCA projection and the probes' readout.
        if let Some(z) = record.z.as_deref() {
            if let Some(style) = &self.series_style
                && self.z_named != Some(z.len())
            {
                let n = z.len();
                self.rec.log_static(
                    self.path("latent/z").as_str(),
                    &rerun::SeriesLines::new()
                        .with_names((0..n).map(|i| format!("{}: z{i}", style.label)))
                        .with_colors((0..n).map(|i| color(family_color(style.family, i, n)))),
                )?;
                self.z_named = Some(n);
            }
            self.rec.log(
                self.path("latent/z").as_str(),
                &rerun::Scalars::new(z.iter().map(|&v| v as f64)),
            )?;
            if let Some(probe) = &self.probe {
                let z64: Vec<f64> = z.iter().map(|&v| v as f64).collect();
                let p = probe.pca.project(&z64);
                let axis = |k: usize| p.get(k).copied().unwrap_or(0.0) as f32;
                // Coloured by the number of joints that have lost torque (the key says so).
                let n_lost = record.scales.iter().filter(|&&s| s < 1.0).count();
                let current = self.pca_palette[n_lost];
                self.pca_trail.push(([axis(0), axis(1), axis(2)], current));
                self.rec.log(
                    self.path("latent/pca").as_str(),
                    &rerun::Points2D::new([[axis(0), axis(1)]])
                        .with_radii([rerun::Radius::new_ui_points(7.0)])
                        .with_colors([current]),
                )?;
                self.rec.log(
                    self.path("latent/pca3").as_str(),
                    &rerun::Points3D::new([[axis(0), axis(1), axis(2)]])
                        .with_radii([rerun::Radius::new_ui_points(7.0)])
                        .with_colors([current]),
                )?;
                if out.step.is_multiple_of(TRAIL_EVERY) {
                    let trail: Vec<&([f32; 3], rerun::Color)> =
                        self.pca_trail.iter().step_by(TRAIL_EVERY).collect();
                    self.rec.log(
                        self.path("latent/pca_trail").as_str(),
                        &rerun::Points2D::new(trail.iter().map(|(p, _)| [p[0], p[1]]))
                            .with_radii([rerun::Radius::new_ui_points(2.5)])
                            .with_colors(trail.iter().map(|(_, c)| *c)),
                    )?;
                    self.rec.log(
                        self.path("latent/pca3_trail").as_str(),
                        &rerun::Points3D::new(trail.iter().map(|(p, _)| *p))
                            .with_radii([rerun::Radius::new_ui_points(2.5)])
                            .with_colors(trail.iter().map(|(_, c)| *c)),
                    )?;
                }
                if let Some(predicted) = &record.probe {
                    let truth: Vec<f64> = record
                        .damaged()
                        .iter()
                        .map(|&d| f64::from(u8::from(d)))
                        .collect();
                    self.rec
                        .log(self.path("probe/predicted").as_str(), &scalars(predicted))?;
                    self.rec
                        .log(self.path("probe/truth").as_str(), &scalars(&truth))?;
                }
            }
        }
        Ok(())
    }
}

impl AntLogger {
    /// A push that starts with this step is an event (level PUSH); while pushes act, an arrow
    /// per push points at the body's centre of mass (its head [`PUSH_ARROW_GAP`] short of it),
    /// its length the force (1 m per [`PUSH_NEWTONS_PER_METRE`] N); the step after the last one,
    /// the arrow is cleared.
    fn log_pushes(&mut self, record: &crate::lane::StepRecord) -> Result<(), TelemetryError> {
        for p in record.pushes.iter().filter(|p| p.starts_at(record.step())) {
            let text = format!("step {}: {}", self.now_step, p.describe());
            self.log_note(NoteLevel::Push, &text)?;
        }
        let path = self.path("world/push");
        if record.pushes.is_empty() {
            if self.push_drawn {
                self.rec.log(path.as_str(), &rerun::Clear::flat())?;
                self.push_drawn = false;
            }
            return Ok(());
        }
        let vectors: Vec<[f32; 3]> = record
            .pushes
            .iter()
            .map(|p| p.push.force.map(|f| (f / PUSH_NEWTONS_PER_METRE) as f32))
            .collect();
        // The head stops short of the centre of mass, outside the torso's 0.25 m sphere, so it
        // shows.
        let origins: Vec<[f32; 3]> = record
            .pushes
            .iter()
            .zip(&vectors)
            .map(|(p, v)| {
                let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-9);
                std::array::from_fn(|k| p.point[k] as f32 - v[k] - PUSH_ARROW_GAP * v[k] / norm)
            })
            .collect();
        self.rec.log(
            path.as_str(),
            &rerun::Arrows3D::from_vectors(vectors)
                .with_origins(origins)
                .with_colors([rerun::Color::from_rgb(255, 140, 0)])
                .with_radii([0.045])
                .with_labels(
                    record
                        .pushes
                        .iter()
                        .map(|p| format!("{:.0} N on {}", p.push.magnitude(), p.push.body)),
                ),
        )?;
        self.push_drawn = true;
        Ok(())
    }
}

/// Interpolation points of the live attribution.
pub const ATTRIBUTION_POINTS: usize = crate::explain::SHIFT_POINTS;

impl AntLogger {
    /// Why z moved at this step: the attribution of ‖z − z(0)‖ as a feature group × window slot
    /// heatmap (`latent/attribution`, a Tensor: 10 × 16; rows the eight joints in actuator
    /// order, torso, goal; columns the slots, oldest first) and each group's total as a series
    /// (`latent/attribution_groups`, named by group, a hue each).
    pub fn log_attribution(
        &mut self,
        a: &crate::explain::ShiftAttribution,
    ) -> Result<(), TelemetryError> {
        let groups = &self.feature_groups;
        let grid = a.by_group(groups);
        let names: Vec<&str> = groups.iter().map(|g| g.name.as_str()).collect();
        // Row-major, groups × slots: wide, as the view is.
        let values: Vec<f32> = (0..groups.len())
            .flat_map(|g| grid.iter().map(move |slot| slot[g] as f32))
            .collect();
        let data = rerun::datatypes::TensorData::new(
            vec![groups.len() as u64, grid.len() as u64],
            rerun::datatypes::TensorBuffer::F32(values.clone().into()),
        )
        .with_dim_names([
            format!("rows: {}", names.join(", ")),
            "window slot (oldest → newest)".to_string(),
        ]);
        self.rec.log(
            self.path("latent/attribution").as_str(),
            &rerun::Tensor::new(data),
        )?;
        // The same grid as a picture with its rows named (a tensor view names only its axes):
        // one pixel a cell, red where the cell raised ‖z − z(0)‖, blue where it lowered it.
        // From the tensor's own (f32) values, so the two agree to the pixel.
        let cells: Vec<f64> = values.iter().map(|&v| f64::from(v)).collect();
        let max_abs = cells.iter().fold(
            0.0f64,
            |m, v| if v.is_finite() { m.max(v.abs()) } else { m },
        );
        let pixels: Vec<u8> = cells
            .iter()
            .flat_map(|&v| palette::diverging(v, max_abs))
            .collect();
        let map = self.path("latent/attribution_map");
        self.rec.log(
            map.as_str(),
            &rerun::Image::from_rgb24(pixels, [grid.len() as u32, groups.len() as u32]),
        )?;
        let path = self.path("latent/attribution_groups");
        if !self.attribution_named {
            // Row names left of the grid, and which end of the window is which.
            let slots = grid.len() as f32;
            let rows = names.len() as f32;
            let labels = names
                .iter()
                .map(|n| n.to_string())
                .chain(["oldest".to_string(), "newest".to_string()]);
            let at = (0..names.len())
                .map(|g| (-2.0, g as f32 + 0.5))
                .chain([(0.5, rows + 0.8), (slots - 0.5, rows + 0.8)]);
            self.rec.log_static(
                format!("{map}/labels").as_str(),
                &rerun::Points2D::new(at)
                    .with_radii([0.05])
                    .with_labels(labels)
                    .with_show_labels(true),
            )?;
            let n = names.len();
            self.rec.log_static(
                path.as_str(),
                &rerun::SeriesLines::new()
                    // Short names: the view's title says what they add up to, and a legend
                    // of ten long names covered the lines.
                    .with_names(names.iter().map(|g| g.to_string()))
                    .with_colors((0..n).map(|i| {
                        let [r, g, b] = palette::hsl_to_rgb(360.0 * i as f64 / n as f64, 0.75, 0.6);
                        rerun::Color::from_rgb(r, g, b)
                    })),
            )?;
            self.attribution_named = true;
        }
        let totals = (0..groups.len()).map(|g| grid.iter().map(|slot| slot[g]).sum::<f64>());
        self.rec.log(path.as_str(), &rerun::Scalars::new(totals))?;
        Ok(())
    }
}

/// A push arrow's length: this many newtons per metre.
pub const PUSH_NEWTONS_PER_METRE: f64 = 50.0;
/// Metres between a push arrow's head and the body's centre of mass.
pub const PUSH_ARROW_GAP: f32 = 0.3;

/// Levels of the debugger's own notes in the event log (beside Rerun's WARN for triggers and
/// INFO for overrides), so the viewer can filter and colour them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NoteLevel {
    /// A breakpoint fired.
    Break,
    /// A rewind or a fork started a branch.
    Branch,
    /// A push (an external force) started.
    Push,
}

impl NoteLevel {
    pub fn as_str(self) -> &'static str {
        match self {
            NoteLevel::Break => "BREAK",
            NoteLevel::Branch => "BRANCH",
            NoteLevel::Push => "PUSH",
        }
    }
}

/// Checkpoint, encoder and seed of an episode, for the metadata document.
#[derive(Debug, Clone)]
pub struct EpisodeMeta {
    pub checkpoint: String,
    pub encoder: String,
    /// The condition as a person chose it (`manual` is not an env condition).
    pub condition: String,
    pub seed: u64,
}

/// World position and orientation of a geom (MuJoCo's xmat is row-major).
fn geom_pose(
    env: &AntEnv,
    geom: usize,
) -> (rerun::external::glam::Vec3, rerun::external::glam::Quat) {
    use rerun::external::glam::{Mat3, Quat, Vec3};
    let p = env.physics().geom_xpos()[geom];
    let m = env.physics().geom_xmat()[geom].map(|v| v as f32);
    let rotation = Mat3::from_cols(
        Vec3::new(m[0], m[3], m[6]),
        Vec3::new(m[1], m[4], m[7]),
        Vec3::new(m[2], m[5], m[8]),
    );
    (
        Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32),
        Quat::from_mat3(&rotation).normalize(),
    )
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
