//! The blueprint: which views a recording opens with, their titles, and sending it.

use super::*;

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
pub(super) fn view_path(view: &rerun::blueprint::ContainerLike) -> Option<String> {
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
    layout_for(world_roots, titles, plot_roots, ViewOptions::default())
}

/// Which views a layout shows beyond the fixed ones.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewOptions {
    /// The tabs holding the attribution views come up on them.
    pub attribution: bool,
    /// The fatigue view: only where some lane's world triggers damage by fatigue. Fatigue
    /// accumulates in every world, but where nothing triggers on it (dead-legs: actuators die
    /// by draw) its rising lines under "τ = threshold" would promise a damage that never comes.
    pub fatigue: bool,
    /// The z, z-in-PCA and probe views: only where some lane's model has an encoder. A
    /// memoryless model has no z, and three views saying "No data available" read as a broken
    /// recording; its third column shows the actions instead, commanded beside applied (where
    /// a joint lost torque the two part).
    pub latent: bool,
}

impl Default for ViewOptions {
    /// The paper's world and an encoder: fatigue and z shown, attribution not up front.
    fn default() -> Self {
        Self {
            attribution: false,
            fatigue: true,
            latent: true,
        }
    }
}

impl ViewOptions {
    /// The views for lanes in `worlds`: the fatigue view where any of them damages by fatigue.
    pub fn for_worlds<W: std::borrow::Borrow<crate::config::GaitConfig>>(
        worlds: impl IntoIterator<Item = W>,
    ) -> Self {
        Self {
            fatigue: worlds.into_iter().any(|w| w.borrow().damage.fatigue),
            ..Self::default()
        }
    }

    /// These views, with the latent ones where any of the lanes' models has an encoder.
    pub fn with_latent(self, encoders: impl IntoIterator<Item = bool>) -> Self {
        Self {
            latent: encoders.into_iter().any(|e| e),
            ..self
        }
    }
}

/// [`layout_with`], with the views `views` asks for.
pub fn layout_for(
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
    views: ViewOptions,
) -> Layout {
    let attribution = views.attribution;
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
    let fatigue = views.fatigue.then(|| {
        series(
            TimeSeriesView::new("Fatigue per joint (τ = threshold)")
                .with_contents(paths(&["joints/fatigue", "joints/threshold"])),
        )
    });
    let scale = series(TimeSeriesView::new("Torque scale").with_contents(paths(&["joints/scale"])));
    // The third column: the models' z (why it moved, where it sits, what a probe reads from
    // it), or, where no lane's model has an encoder, the actions it would have shown beside.
    let third: rerun::blueprint::ContainerLike = if views.latent {
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
        let pca = Spatial2DView::new("z in PCA basis")
            .with_contents(paths(&["latent/pca", "latent/pca_trail"]));
        let pca3 = Spatial3DView::new("z in PCA basis, 3-D")
            .with_contents(paths(&["latent/pca3", "latent/pca3_trail"]));
        Vertical::new([
            tabs(vec![latent, why], why_path).into(),
            tabs(vec![pca.into(), pca3.into(), why_grid], grid_path).into(),
            probe,
        ])
        .into()
    } else {
        Vertical::new([
            series(
                TimeSeriesView::new("Action commanded per joint (the policy's output)")
                    .with_contents(paths(&["actions/commanded"])),
            ),
            series(
                TimeSeriesView::new("Action applied per joint (× torque scale)")
                    .with_contents(paths(&["actions/applied"])),
            ),
        ])
        .into()
    };
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
            match fatigue {
                Some(fatigue) => Vertical::new([gait.into(), fatigue, scale, progress])
                    .with_row_shares([1.5, 1.0, 1.0, 1.0]),
                None => {
                    Vertical::new([gait.into(), scale, progress]).with_row_shares([1.5, 1.0, 1.0])
                }
            }
            .into(),
            third,
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
    send_layout_for(rec, world_roots, titles, plot_roots, ViewOptions::default())
}

/// [`send_layout_with`], with the views `views` asks for (see [`layout_for`]).
pub fn send_layout_for(
    rec: &RecordingStream,
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
    views: ViewOptions,
) -> Result<(), TelemetryError> {
    let key = format!("{world_roots:?} {titles:?} {plot_roots:?} {views:?}");
    let cached = LAYOUTS.lock().ok().and_then(|cache| {
        cache
            .iter()
            .find(|(k, _)| *k == key)
            .map(|(_, v)| v.clone())
    });
    let (messages, activation) = match cached {
        Some(built) => built,
        None => {
            let built = build_layout(world_roots, titles, plot_roots, views)?;
            if let Ok(mut cache) = LAYOUTS.lock()
                && cache.len() < MAX_CACHED_LAYOUTS
            {
                cache.push((key, built.clone()));
            }
            built
        }
    };
    rec.send_blueprint(messages, activation);
    Ok(())
}

/// A built layout: the blueprint store's messages and the command that activates it.
type BuiltLayout = (
    Vec<rerun::log::LogMsg>,
    rerun::external::re_log_msg::BlueprintActivationCommand,
);

/// Layouts built so far, by their inputs. Rerun builds a blueprint's messages on a memory
/// stream of its own (`Blueprint::to_log_msgs`) whose sink holds the stream, so it never drops:
/// each build leaves a recording thread and a batcher thread behind. `live` sends a layout on
/// every view change (attribution, fork, compare), a handful of distinct ones per session, so
/// each is built once and sent again from here (issue 49: 1,000 toggles had left 6,000 threads).
static LAYOUTS: std::sync::Mutex<Vec<(String, BuiltLayout)>> = std::sync::Mutex::new(Vec::new());
/// Distinct layouts kept, at most (beyond it each new one is built afresh).
const MAX_CACHED_LAYOUTS: usize = 64;

fn build_layout(
    world_roots: &[String],
    titles: &[String],
    plot_roots: &[String],
    views: ViewOptions,
) -> Result<BuiltLayout, TelemetryError> {
    use rerun::log::LogMsg;
    let layout = layout_for(world_roots, titles, plot_roots, views);
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
    // A memory stream's sink holds a handle to the stream itself, so it would never drop (nor
    // end its two threads): swapping the sink out breaks that cycle.
    scratch.disconnect();
    drop((scratch, storage));
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
    props.disconnect();
    drop((props, props_storage));
    Ok((messages, activation))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each distinct layout is built once, however often it is sent (the thread count of a
    /// whole `live --web` process is checked in tests/web.rs; here other tests share the
    /// process, so the cache is what is checked).
    #[test]
    fn a_layout_is_built_once_however_often_it_is_sent() {
        let (rec, _storage) = RecordingStreamBuilder::new(APP_ID).memory().unwrap();
        let roots = vec!["built-once-test".to_string()];
        for i in 0..20 {
            let views = ViewOptions {
                attribution: i % 2 == 0,
                ..ViewOptions::default()
            };
            send_layout_for(&rec, &roots, &default_titles(&roots), &roots, views).unwrap();
        }
        let cache = LAYOUTS.lock().unwrap();
        let ours = cache
            .iter()
            .filter(|(k, _)| k.contains("built-once-test"))
            .count();
        assert_eq!(ours, 2, "one build per layout (attribution on, off)");
    }
}
