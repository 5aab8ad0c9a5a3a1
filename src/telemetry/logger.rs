//! `AntLogger`: the Rerun sink of one lane — its static world, and every step's record drawn
//! from MuJoCo's own state.

use super::*;

/// A capsule of the model: MuJoCo's capsule is centred on its frame, axis along local z.
#[derive(Debug, Clone)]
pub(super) struct CapsuleGeom {
    pub(super) id: usize,
    pub(super) name: String,
    pub(super) radius: f32,
    pub(super) half_length: f32,
    /// The actuator whose joint moves this geom's body (leg segments), for damage colours.
    pub(super) actuator: Option<usize>,
    pub(super) rgba: [u8; 4],
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

pub(super) fn color([r, g, b, a]: [u8; 4]) -> rerun::Color {
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
    pub(super) fn hue(&self) -> usize {
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

    pub(super) fn path(&self, leaf: &str) -> String {
        format!("{}/{leaf}", self.root)
    }

    pub(super) fn log_static(&mut self, env: &AntEnv) -> Result<(), TelemetryError> {
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
    pub(super) fn log_series_styles(&self) -> Result<(), TelemetryError> {
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
    pub(super) fn log_pushes(
        &mut self,
        record: &crate::lane::StepRecord,
    ) -> Result<(), TelemetryError> {
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
pub(super) fn geom_pose(
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
