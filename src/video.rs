//! `gaitscope video`: an episode rendered with MuJoCo's own renderer (offscreen OpenGL on EGL,
//! no display) and encoded to H.264 MP4 by Debian's `ffmpeg` through a pipe (a well-kept
//! encoder with no build cost; the frames never touch the disk).
//!
//! The renderer draws a copy of the model, never the simulated one: each frame copies the
//! state in, runs `mj_forward`, tints each leg by its actuator's torque scale (the viewer's
//! palette) and renders from a camera that tracks the torso; a small text overlay says the
//! step, the distance to the goal, the condition and the triggered joints.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use mujoco_rs::prelude::{MjData, MjModel, MjtGeom, MjvCamera};
use mujoco_rs::renderer::MjRenderer;

use crate::damage::JointState;
use crate::env::AntEnv;
use crate::palette::Torque;

#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    #[error("width and height must be even numbers ≥ 16 (H.264 with yuv420p), got {0}×{1}")]
    BadSize(usize, usize),
    #[error("--fps must be between 1 and 240, got {0}")]
    BadFps(u32),
    #[error(
        "no OpenGL for offscreen rendering ({0}); on Debian: apt-get install libegl1 libgl1-mesa-dri"
    )]
    NoGl(#[source] crate::Cause),
    #[error("rendering failed: {0}")]
    Render(String),
    #[error("cannot start ffmpeg ({0}); on Debian: apt-get install ffmpeg")]
    NoEncoder(#[source] std::io::Error),
    #[error("ffmpeg failed: {0}")]
    Encoder(#[source] crate::Cause),
    #[error("cannot write {path}: {reason}")]
    Write {
        path: PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("--width {0} must be a multiple of 4 for two lanes side by side")]
    OddLanes(usize),
    #[error("--out {0} should end in .mp4")]
    NotMp4(PathBuf),
    #[error("MuJoCo's renderer failed")]
    Renderer(#[source] Box<dyn std::error::Error + Send + Sync>),
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error(transparent)]
    ForkBeyondEpisode(#[from] crate::lane::ForkBeyondEpisode),
}

/// How the camera moves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraMode {
    /// Follows the torso at 5 m, as the viewer's 3-D view does.
    Track,
    /// Still, framing the start and the goal.
    Fixed,
}

/// Frame size, rate and camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FrameSpec {
    pub width: usize,
    pub height: usize,
    pub fps: u32,
    pub camera: CameraMode,
}

impl FrameSpec {
    pub fn check(&self) -> Result<(), VideoError> {
        if self.width < 16 || self.height < 16 || self.width % 2 == 1 || self.height % 2 == 1 {
            return Err(VideoError::BadSize(self.width, self.height));
        }
        if !(1..=240).contains(&self.fps) {
            return Err(VideoError::BadFps(self.fps));
        }
        Ok(())
    }
}

/// Renders an env's current state to RGB frames.
pub struct FrameRenderer {
    data: MjData<Box<MjModel>>,
    renderer: MjRenderer,
    /// (geom, actuator) of every leg capsule, and each geom's own colour.
    leg_geoms: Vec<(usize, usize)>,
    spec: FrameSpec,
}

impl FrameRenderer {
    pub fn new(env: &AntEnv, spec: FrameSpec) -> Result<Self, VideoError> {
        spec.check()?;
        let mut model: MjModel = env.physics().model().clone();
        // The offscreen buffer is the model's (640 × 480 in the Ant's XML): make it the frame's.
        model.vis_mut().global.offwidth = spec.width as i32;
        model.vis_mut().global.offheight = spec.height as i32;
        let leg_geoms = (0..model.ngeom() as usize)
            .filter_map(|g| {
                let body = model.geom_bodyid()[g] as usize;
                env.actuators()
                    .iter()
                    .position(|a| a.body_id == body)
                    .map(|a| (g, a))
            })
            .collect();
        let [gx, gy] = env.config().env.goal;
        let camera = match spec.camera {
            CameraMode::Track => {
                let mut c = MjvCamera::new_tracking(env.torso_body());
                c.distance = 5.0;
                c.azimuth = 135.0;
                c.elevation = -30.0;
                c
            }
            CameraMode::Fixed => {
                // Above the side of the start–goal line, looking at its middle.
                let mut c = MjvCamera::new_free(&model);
                c.lookat = [gx / 2.0, gy / 2.0, 0.0];
                c.distance = 2.0 * gx.hypot(gy).max(2.0);
                c.azimuth = 225.0;
                c.elevation = -40.0;
                c
            }
        };
        let renderer = MjRenderer::builder()
            .width(spec.width as u32)
            .height(spec.height as u32)
            .camera(camera)
            .num_visual_user_geom(2)
            .build(&model)
            .map_err(|e| VideoError::NoGl(e.into()))?;
        let mut renderer = renderer;
        // The goal: its success disc and a marker (the user scene is drawn into every frame).
        let r = env.config().env.success_radius;
        let scene = renderer.user_scene_mut();
        // SAFETY: plain geoms with no material, texture or flex/skin index (all left at -1).
        unsafe {
            scene.create_geom(
                MjtGeom::mjGEOM_ELLIPSOID,
                Some([r, r, 0.01]),
                Some([gx, gy, 0.005]),
                None,
                Some([1.0, 0.8, 0.1, 0.45]),
            );
            scene.create_geom(
                MjtGeom::mjGEOM_SPHERE,
                Some([0.08, 0.08, 0.08]),
                Some([gx, gy, 0.08]),
                None,
                Some([1.0, 0.7, 0.0, 1.0]),
            );
        }
        Ok(Self {
            data: MjData::new(Box::new(model)),
            renderer,
            leg_geoms,
            spec,
        })
    }

    /// The frame of `env`'s current state, RGB, row-major, top row first.
    pub fn frame(&mut self, env: &AntEnv) -> Result<Vec<u8>, VideoError> {
        self.frame_with(env, "")
    }

    /// [`Self::frame`] with a label above the caption (side-by-side lanes).
    pub fn frame_with(&mut self, env: &AntEnv, label: &str) -> Result<Vec<u8>, VideoError> {
        self.data.qpos_mut().copy_from_slice(env.qpos());
        self.data.qvel_mut().copy_from_slice(env.qvel());
        let damage = env.damage();
        // SAFETY: only colours change; no array is resized and no index is touched.
        let rgba = unsafe { self.data.model_mut() }.geom_rgba_mut();
        for &(g, a) in &self.leg_geoms {
            // The torque the joint has left, as every view colours it.
            let c = Torque::of(damage.scale()[a], damage.joint_state(a)).rgba();
            rgba[g] = [c[0], c[1], c[2], c[3]].map(|v| f32::from(v) / 255.0);
        }
        self.data.forward();
        self.renderer
            .sync_data(&mut self.data)
            .map_err(|e| VideoError::Renderer(Box::new(e)))?;
        self.renderer
            .render()
            .map_err(|e| VideoError::Renderer(Box::new(e)))?;
        let mut rgb = self
            .renderer
            .rgb_flat()
            .ok_or_else(|| VideoError::Render("no RGB buffer".into()))?
            .to_vec();
        overlay(&mut rgb, self.spec, label, &caption(env)).map_err(VideoError::Render)?;
        Ok(rgb)
    }
}

/// The overlay's text: step, distance, condition, triggered joints.
fn caption(env: &AntEnv) -> String {
    let damage = env.damage();
    let broken: Vec<&str> = (0..crate::damage::N_ACTUATORS)
        .filter(|&i| damage.joint_state(i) != JointState::Healthy)
        .map(|i| damage.joint_names()[i].as_str())
        .collect();
    format!(
        "step {}  ·  {:.2} m to goal  ·  {}  ·  damaged: {}",
        env.steps(),
        env.goal_distance(),
        env.condition(),
        if broken.is_empty() {
            "none".to_string()
        } else {
            broken.join(", ")
        }
    )
}

fn overlay(rgb: &mut [u8], spec: FrameSpec, label: &str, text: &str) -> Result<(), String> {
    use plotters::prelude::*;
    crate::plots::register_font();
    let root = BitMapBackend::with_buffer(rgb, (spec.width as u32, spec.height as u32))
        .into_drawing_area();
    let size = (spec.height as f64 / 28.0).max(10.0);
    let style = ("sans-serif", size).into_font().color(&WHITE);
    // Wrapped to the frame's width (a lane's half in a side-by-side video), word by word.
    let max_width = spec.width.saturating_sub(12) as u32;
    let mut lines: Vec<String> = Vec::new();
    for paragraph in [label, text].into_iter().filter(|l| !l.is_empty()) {
        lines.extend(wrap(paragraph, max_width, |s| {
            root.estimate_text_size(s, &style).map_or(0, |(w, _)| w)
        }));
    }
    let strip = size * (0.3 + 1.3 * lines.len() as f64);
    root.draw(&Rectangle::new(
        [(0, 0), (spec.width as i32, strip as i32)],
        RGBAColor(0, 0, 0, 0.55).filled(),
    ))
    .map_err(|e| e.to_string())?;
    for (k, line) in lines.iter().enumerate() {
        let y = (size * (0.25 + 1.3 * k as f64)) as i32;
        root.draw(&Text::new(line.to_string(), (6, y), style.clone()))
            .map_err(|e| e.to_string())?;
    }
    root.present().map_err(|e| e.to_string())
}

/// Greedy word wrap of `text` into lines no wider than `max_width` by `width` (a single word
/// wider than that stays whole on its own line).
fn wrap(text: &str, max_width: u32, width: impl Fn(&str) -> u32) -> Vec<String> {
    let mut lines = Vec::new();
    let mut line = String::new();
    for word in text.split(' ') {
        let candidate = if line.is_empty() {
            word.to_string()
        } else {
            format!("{line} {word}")
        };
        if width(&candidate) <= max_width || line.is_empty() {
            line = candidate;
        } else {
            lines.push(std::mem::take(&mut line).trim_end().to_string());
            line = word.to_string();
        }
    }
    if !line.trim().is_empty() {
        lines.push(line.trim_end().to_string());
    }
    lines
}

/// An ffmpeg process taking raw RGB frames on stdin, writing `tmp`.
pub struct Encoder {
    child: Option<Child>,
    tmp: PathBuf,
    out: PathBuf,
}

impl Encoder {
    /// Starts ffmpeg on a temporary sibling of `out` (renamed at [`Self::finish`]).
    pub fn start(out: &Path, spec: FrameSpec) -> Result<Self, VideoError> {
        let tmp = out.with_extension("mp4.partial");
        // Fail on an unwritable folder here, with the OS's reason, not as a broken pipe later.
        std::fs::File::create(&tmp).map_err(|e| VideoError::Write {
            path: out.to_owned(),
            reason: e.into(),
        })?;
        let child = Command::new("ffmpeg")
            .args([
                "-loglevel",
                "error",
                "-y",
                "-f",
                "rawvideo",
                "-pix_fmt",
                "rgb24",
            ])
            .args(["-s", &format!("{}x{}", spec.width, spec.height)])
            .args(["-r", &spec.fps.to_string(), "-i", "-"])
            .args([
                "-c:v",
                "libx264",
                "-pix_fmt",
                "yuv420p",
                "-movflags",
                "+faststart",
            ])
            .args(["-f", "mp4"])
            .arg(&tmp)
            .stdin(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| {
                let _ = std::fs::remove_file(&tmp);
                VideoError::NoEncoder(e)
            })?;
        Ok(Self {
            child: Some(child),
            tmp,
            out: out.to_owned(),
        })
    }

    pub fn push(&mut self, frame: &[u8]) -> Result<(), VideoError> {
        let stdin = self
            .child
            .as_mut()
            .and_then(|c| c.stdin.as_mut())
            .ok_or_else(|| VideoError::Encoder("stdin closed".into()))?;
        let Err(e) = stdin.write_all(frame) else {
            return Ok(());
        };
        // ffmpeg quit: its own words say why better than the broken pipe does.
        let said = self
            .child
            .take()
            .and_then(|child| child.wait_with_output().ok())
            .map(|o| String::from_utf8_lossy(&o.stderr).trim().to_string())
            .filter(|s| !s.is_empty());
        Err(VideoError::Encoder(match said {
            Some(said) => said.into(),
            None => e.into(),
        }))
    }

    /// Closes the stream, waits for ffmpeg and moves the file into place.
    pub fn finish(mut self) -> Result<(), VideoError> {
        let Some(mut child) = self.child.take() else {
            return Err(VideoError::Encoder("already finished".into()));
        };
        drop(child.stdin.take()); // end of stream
        let output = child
            .wait_with_output()
            .map_err(|e| VideoError::Encoder(e.into()))?;
        if !output.status.success() {
            return Err(VideoError::Encoder(
                String::from_utf8_lossy(&output.stderr).trim().into(),
            ));
        }
        std::fs::rename(&self.tmp, &self.out).map_err(|e| VideoError::Write {
            path: self.out.clone(),
            reason: e.into(),
        })
    }
}

impl Drop for Encoder {
    /// An unfinished video leaves nothing behind: ffmpeg is stopped and its file removed.
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
        let _ = std::fs::remove_file(&self.tmp);
    }
}

/// One model's episode in a video: a lane of the stepping core and its renderer.
pub struct VideoLane {
    pub label: String,
    actor: crate::lane::Actor,
    lane: crate::lane::Lane,
    renderer: FrameRenderer,
    /// The last frame (shown frozen once this lane's episode ended).
    frame: Vec<u8>,
}

impl VideoLane {
    /// A lane of `actor` in its own world (see [`crate::lane::Actor::world`]: a checkpoint's
    /// task with `requested`'s condition, scenario and step limit), reset with `seed`, rendered
    /// at `spec`.
    pub fn new(
        label: String,
        actor: crate::lane::Actor,
        requested: &crate::config::GaitConfig,
        seed: u64,
        spec: FrameSpec,
    ) -> Result<Self, VideoError> {
        let lane = crate::lane::Lane::new(&actor, requested, seed)?;
        let renderer = FrameRenderer::new(lane.env(), spec)?;
        Ok(Self {
            label,
            actor,
            lane,
            renderer,
            frame: Vec::new(),
        })
    }

    /// A second lane from this one's exact state with `edits` applied (a counterfactual fork).
    pub fn fork(&self, edits: &[crate::damage::Edit], spec: FrameSpec) -> Result<Self, VideoError> {
        let lane = self.lane.fork(edits)?;
        let renderer = FrameRenderer::new(lane.env(), spec)?;
        let edits: Vec<String> = edits.iter().map(ToString::to_string).collect();
        Ok(Self {
            label: format!("fork at step {}: {}", lane.steps(), edits.join(",")),
            actor: self.actor.clone(),
            lane,
            renderer,
            frame: self.frame.clone(),
        })
    }

    pub fn steps(&self) -> usize {
        self.lane.steps()
    }

    pub fn is_done(&self) -> bool {
        self.lane.is_done()
    }

    /// The world this lane runs in.
    pub fn world(&self) -> &crate::config::GaitConfig {
        self.lane.env().config()
    }

    /// One env step (deterministic policy, or the built-in one) and its frame; the step's
    /// record (none once the lane's episode has ended: it holds its last frame).
    pub fn step(&mut self) -> Result<Option<&crate::lane::StepRecord>, VideoError> {
        if self.lane.is_done() {
            return Ok(None);
        }
        let record = self
            .lane
            .advance(&self.actor, crate::policy::ActionMode::Deterministic)?;
        // The lane's last frame says how its episode ended; it stays up while others go on.
        let label = match record.outcome.ending() {
            Some(ending) => format!("{}  ·  ENDED: {}", self.label, ending.to_uppercase()),
            None => self.label.clone(),
        };
        self.frame = self.renderer.frame_with(self.lane.env(), &label)?;
        Ok(self.lane.last())
    }
}

/// What `gaitscope video` renders.
pub struct VideoOptions {
    pub out: PathBuf,
    pub spec: FrameSpec,
    /// The model (a checkpoint or a built-in policy), and a second one side by side.
    pub actor: crate::lane::Actor,
    pub compare: Option<crate::lane::Actor>,
    /// The requested world: condition and step limit (each model runs in its own world).
    pub config: crate::config::GaitConfig,
    pub seed: u64,
    pub fork: Option<crate::lane::Fork>,
    /// Every lane starts from this state (`--init-state`).
    pub start: Option<crate::lane::StartState>,
}

/// Renders one episode to `opts.out`: every check (size, name, fork in the model's world)
/// before the file is created; two lanes (a comparison or a fork) side by side, each half the
/// width and captioned with its model's name. Returns the frame count and each lane's ending.
pub fn render(opts: VideoOptions) -> Result<VideoSummary, VideoError> {
    let VideoOptions {
        out,
        spec,
        actor,
        compare,
        config,
        seed,
        fork,
        start,
    } = opts;
    spec.check()?;
    if out.extension().and_then(|e| e.to_str()) != Some("mp4") {
        return Err(VideoError::NotMp4(out));
    }
    if let Some(f) = &fork {
        f.validate(&actor.world(&config))?;
    }
    let two = compare.is_some() || fork.is_some();
    let lane_spec = if two {
        if !spec.width.is_multiple_of(4) {
            return Err(VideoError::OddLanes(spec.width));
        }
        FrameSpec {
            width: spec.width / 2,
            ..spec
        }
    } else {
        spec
    };
    // A lane alone needs no caption; side by side each says which model it is.
    let caption = |a: &crate::lane::Actor| match a {
        _ if !two => String::new(),
        crate::lane::Actor::Checkpoint { .. } => a.label(),
        other => format!("{} policy", other.label()),
    };
    let mut lanes = vec![VideoLane::new(
        caption(&actor),
        actor,
        &config,
        seed,
        lane_spec,
    )?];
    if let Some(other) = compare {
        lanes.push(VideoLane::new(
            caption(&other),
            other,
            &config,
            seed,
            lane_spec,
        )?);
    }
    if let Some(start) = &start {
        for lane in &mut lanes {
            lane.lane.start_from(start)?;
        }
    }
    let mut encoder = Encoder::start(&out, spec)?;
    let summary = render_episode(lanes, fork.as_ref(), spec, lane_spec, &mut encoder, seed)?;
    encoder.finish()?;
    Ok(summary)
}

/// What a rendered video shows: its frames and how each lane's episode ended.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoSummary {
    pub frames: usize,
    pub endings: Vec<crate::lane::LaneEnding>,
}

/// Runs the lanes in lockstep to the end of every episode, one frame per step: lanes side by
/// side, each `lane_width` wide (a finished lane holds its last frame). `fork` adds a lane from
/// the first one before step K. Returns the frame count and each lane's ending (episode 1 of
/// `seed`).
pub fn render_episode(
    mut lanes: Vec<VideoLane>,
    fork: Option<&crate::rollout::Fork>,
    spec: FrameSpec,
    lane_spec: FrameSpec,
    encoder: &mut Encoder,
    seed: u64,
) -> Result<VideoSummary, VideoError> {
    let mut frames = 0;
    let mut forked = false;
    // Frames up to the longest step limit (an episode can end sooner).
    let limit = lanes
        .iter()
        .map(|l| l.world().env.max_episode_steps)
        .max()
        .unwrap_or(0);
    let progress = crate::progress::bar(limit as u64, "video frames");
    while lanes.iter().any(|l| !l.is_done()) {
        if let Some(f) = fork
            && !forked
            && f.due(&lanes[0].lane)
        {
            let lane = lanes[0].fork(&f.edits, lane_spec)?;
            lanes.push(lane);
            forked = true;
        }
        for lane in &mut lanes {
            lane.step()?;
        }
        encoder.push(&stitch(&lanes, spec, lane_spec))?;
        frames += 1;
        progress.set_position(frames as u64);
    }
    progress.finish_and_clear();
    if let Some(f) = fork
        && !forked
    {
        return Err(f.beyond(&lanes[0].lane).into());
    }
    let endings = lanes
        .iter()
        .map(|l| {
            // A lane alone has no caption: its model names it.
            let label = match (&l.label, &l.actor) {
                (c, _) if !c.is_empty() => c.clone(),
                (_, a @ crate::lane::Actor::Checkpoint { .. }) => a.label(),
                (_, a) => format!("{} policy", a.label()),
            };
            l.lane.ending(label, 1, seed)
        })
        .collect();
    Ok(VideoSummary { frames, endings })
}

/// The lanes' frames side by side in one `spec`-sized frame (black where a lane has none yet).
fn stitch(lanes: &[VideoLane], spec: FrameSpec, lane_spec: FrameSpec) -> Vec<u8> {
    if lanes.len() == 1 && lane_spec == spec {
        return lanes[0].frame.clone();
    }
    let mut out = vec![0u8; spec.width * spec.height * 3];
    for (k, lane) in lanes.iter().enumerate() {
        if lane.frame.len() != lane_spec.width * lane_spec.height * 3 {
            continue;
        }
        for row in 0..lane_spec.height {
            let src = &lane.frame[row * lane_spec.width * 3..(row + 1) * lane_spec.width * 3];
            let at = (row * spec.width + k * lane_spec.width) * 3;
            out[at..at + src.len()].copy_from_slice(src);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn captions_wrap_at_the_lanes_width() {
        // Ten units a character: a 60-unit line holds six.
        let width = |s: &str| 10 * s.chars().count() as u32;
        let text = "damaged: hip_1, ankle_2, hip_3";
        let lines = super::wrap(text, 160, width);
        assert_eq!(lines, ["damaged: hip_1,", "ankle_2, hip_3"]);
        assert!(lines.iter().all(|l| width(l) <= 160));
        // A word longer than the line keeps a line of its own.
        assert_eq!(
            super::wrap("a verylongword b", 60, width),
            ["a", "verylongword", "b"]
        );
        assert_eq!(super::wrap("fits", 60, width), ["fits"]);
    }
}
