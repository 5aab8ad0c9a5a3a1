//! The simulation loop that `record` (headless) and `live` (interactive) share: one lane per
//! model, all lanes in lockstep on the same seeds and the same hand-made damage, every step
//! logged to Rerun.

use rerun::RecordingStream;

use super::{AntLogger, EpisodeMeta, TelemetryError};
use crate::config::GaitConfig;
use crate::damage::{Edit, JointOverride, N_ACTUATORS};
use crate::env::AntEnv;
use crate::lane::StepRecord;
use crate::policy::ActionMode;

pub use crate::lane::{Actor, LaneEnding};

/// An actor and where its entities go.
pub struct LaneSpec {
    pub actor: Actor,
    /// Entity root (`ant`, or one per model when several run side by side).
    pub root: String,
    /// Where this lane's world is drawn (metres), so side-by-side Ants do not overlap.
    pub world_offset: [f32; 3],
}

/// The world offset of the k-th of several side-by-side models: 12 m apart along x, which clears
/// the floor patch drawn around start and goal.
pub fn side_by_side_offset(k: usize) -> [f32; 3] {
    [12.0 * k as f32, 0.0, 0.0]
}

/// Entity root of the counterfactual lane a fork adds.
pub const FORK_ROOT: &str = "fork";

/// Keep at most this many steps of an episode for rewinding (a step is a few KB per lane:
/// MuJoCo's integration state, the damage state, the 16 × 37 window).
pub const HISTORY_CAP: usize = 10_000;

/// Everything that decides a lane's future: restoring it and stepping on repeats the original
/// steps bit for bit.
#[derive(Debug, Clone)]
pub struct LaneSnapshot {
    /// The stepping core's state (env, window, observation, RNG, latest step's record).
    state: crate::lane::LaneState,
}

impl LaneSnapshot {
    /// Env steps of the episode at the snapshot.
    pub fn steps(&self) -> usize {
        self.state.steps()
    }
}

/// One model driving one Ant.
pub struct Lane {
    actor: Actor,
    root: String,
    /// The root this lane started the episode under (a rewind's branch logs under another).
    base_root: String,
    /// That root's logger while a branch logs under its own.
    base_logger: Option<AntLogger>,
    /// The stepping core's lane: env, window, observation, RNG, latest step.
    core: crate::lane::Lane,
    logger: AntLogger,
    /// The probe's P(damaged) per joint before the latest step (after it: the step's record).
    probe_before: Option<[f64; N_ACTUATORS]>,
    /// For a fork lane: what it was forked from, in words.
    fork_of: Option<String>,
    /// The session's global step of this lane's latest step.
    stepped_at: u64,
    /// This episode's events in order, as the page lists them (see [`Self::event_log`]).
    log: Vec<LogEntry>,
}

/// One line of a lane's episode log: a damage event (with who made it), a push, an ending.
#[derive(Debug, Clone, PartialEq)]
pub struct LogEntry {
    /// Steps taken in the episode when it happened (the page's step counter).
    pub step: usize,
    pub kind: &'static str,
    pub text: String,
}

/// Entries a lane's log keeps (the oldest go first beyond it).
pub const LOG_CAP: usize = 500;

impl Lane {
    /// Its name in plot legends: the model, and whether this lane is a fork.
    fn series_label(&self) -> String {
        match self.fork_of {
            Some(_) => format!("{} (fork)", self.actor.label()),
            None => self.actor.label(),
        }
    }

    fn new(
        spec: LaneSpec,
        rec: &RecordingStream,
        config: &GaitConfig,
        seed: u64,
    ) -> Result<Self, RecordError> {
        // Its probe (probe.json) too: the logger draws its PCA, and each step's record carries
        // its readout, the value every view shows.
        let probe = match spec.actor.checkpoint_dir() {
            Some(dir) if dir.join(crate::probe::PROBE_FILE).exists() => {
                Some(std::sync::Arc::new(crate::probe::ProbeFile::load(dir)?))
            }
            _ => None,
        };
        let actor = match &probe {
            Some(p) => spec.actor.with_readout(p.clone()),
            None => spec.actor,
        };
        // Not started: done until the session's first episode resets it.
        let core = crate::lane::Lane::unstarted(&actor, config, seed)?;
        let logger = AntLogger::new(rec.clone(), &spec.root, core.env(), probe)
            .with_world_offset(spec.world_offset);
        Ok(Self {
            actor,
            base_root: spec.root.clone(),
            base_logger: None,
            root: spec.root,
            core,
            logger,
            probe_before: None,
            fork_of: None,
            stepped_at: 0,
            log: Vec::new(),
        })
    }

    /// The lane's state now (see [`LaneSnapshot`]).
    pub fn snapshot(&self) -> LaneSnapshot {
        LaneSnapshot {
            state: self.core.state(),
        }
    }

    /// Puts the lane back into `snapshot`'s state, its drawing state (trails, logged events)
    /// with it.
    fn restore(&mut self, snapshot: &LaneSnapshot) -> Result<(), RecordError> {
        self.core.restore(&snapshot.state)?;
        self.probe_before = self.probe_now().copied();
        self.logger.rewind_to(snapshot.steps());
        self.log.retain(|e| e.step <= snapshot.steps());
        Ok(())
    }

    pub fn actor(&self) -> &Actor {
        &self.actor
    }
    pub fn root(&self) -> &str {
        &self.root
    }
    pub fn env(&self) -> &AntEnv {
        self.core.env()
    }
    /// The stepping core's lane, to read (only the session changes it).
    pub fn core(&self) -> &crate::lane::Lane {
        &self.core
    }
    /// The record of this episode's latest step (none right after a reset).
    pub fn last(&self) -> Option<&StepRecord> {
        self.core.last()
    }
    /// The latent the policy produced for the latest step (encoder policies).
    pub fn z(&self) -> Option<&[f32]> {
        self.core.z()
    }
    pub fn probe(&self) -> Option<&crate::probe::ProbeFile> {
        self.logger.probe()
    }
    pub fn is_done(&self) -> bool {
        self.core.is_done()
    }
    /// The probe's P(damaged) per joint before the latest step.
    pub fn probe_before(&self) -> Option<&[f64; N_ACTUATORS]> {
        self.probe_before.as_ref()
    }
    /// The probe's P(damaged) per joint after the latest step.
    pub fn probe_now(&self) -> Option<&[f64; N_ACTUATORS]> {
        self.core.last()?.probe.as_ref()
    }
    /// The session's global step (the `step` timeline) of this lane's latest step.
    pub fn stepped_at(&self) -> u64 {
        self.stepped_at
    }
    /// For a fork lane: what it was forked from.
    /// The lane's state before its next step, as a file saves it (`seed`: the episode's).
    pub fn save_state(&self, seed: u64) -> crate::lane::SavedState {
        self.core.save_state(&self.actor, seed)
    }

    pub fn fork_of(&self) -> Option<&str> {
        self.fork_of.as_deref()
    }

    /// This episode's events, oldest first (at most [`LOG_CAP`]): damage with its cause,
    /// pushes, the ending.
    pub fn event_log(&self) -> &[LogEntry] {
        &self.log
    }

    /// Notes what the latest step brought into the log.
    fn note_step(&mut self) {
        let Some(record) = self.core.last() else {
            return;
        };
        let steps = record.step() + 1;
        let mut entries: Vec<LogEntry> = record
            .events
            .iter()
            .map(|e| LogEntry {
                step: steps,
                kind: match e.kind {
                    crate::damage::DamageEventKind::Trigger => "triggered",
                    crate::damage::DamageEventKind::Dead => "died",
                    crate::damage::DamageEventKind::Override { .. } => "manual",
                },
                text: format!("{} ({})", e.describe(), e.cause()),
            })
            .collect();
        entries.extend(
            record
                .pushes
                .iter()
                .filter(|p| p.starts_at(record.step()))
                .map(|p| LogEntry {
                    step: steps,
                    kind: "push",
                    text: p.describe(),
                }),
        );
        if let Some(ending) = record.outcome.ending {
            entries.push(LogEntry {
                step: steps,
                kind: "ending",
                text: format!(
                    "ended: {ending} ({}), {:.2} m from the goal",
                    ending.meaning(),
                    record.outcome.distance
                ),
            });
        }
        self.log.extend(entries);
        if self.log.len() > LOG_CAP {
            let extra = self.log.len() - LOG_CAP;
            self.log.drain(..extra);
        }
    }
}

/// Models in lockstep, logged to one recording stream.
pub struct Session {
    rec: RecordingStream,
    lanes: Vec<Lane>,
    /// Requested settings (condition, step limit); each lane derives its own from them.
    config: GaitConfig,
    /// Settings changed since the lanes' envs were built: rebuilt at the next episode.
    config_changed: bool,
    /// Fatigue triggers and the world's deaths on (off: the live viewer's manual condition).
    world_damage: bool,
    mode: ActionMode,
    global_step: u64,
    episodes_started: u64,
    seed: u64,
    /// Keep every step's state for rewinding ([`Self::keep_history`]).
    keep_history: bool,
    /// The model lanes' states before each step of this episode: index k = after k steps.
    history: Vec<Vec<LaneSnapshot>>,
    /// Rewinds in this recording (each starts a new branch under its own roots).
    branches: u64,
    /// The global step the current episode started at, and the furthest any branch reached.
    episode_start: u64,
    global_max: u64,
    /// Roots overlaid in the plots: the lanes', and this episode's earlier branches.
    plot_roots: Vec<String>,
    /// Where every episode starts (`--init-state`), instead of the reset's state.
    start: Option<std::sync::Arc<crate::lane::StartState>>,
    /// Log why z moved (integrated gradients of ‖z − z(0)‖) with every step of encoder lanes.
    attribution: bool,
    /// Shown under the key ([`Self::set_caption`]).
    caption: Option<String>,
}

impl Session {
    /// Builds the lanes; call [`Self::start_episode`] before stepping.
    pub fn new(
        rec: RecordingStream,
        specs: Vec<LaneSpec>,
        config: GaitConfig,
    ) -> Result<Self, RecordError> {
        let lanes: Vec<Lane> = specs
            .into_iter()
            .map(|spec| Lane::new(spec, &rec, &config, 0))
            .collect::<Result<Vec<_>, _>>()?;
        let plot_roots = lanes.iter().map(|l| l.root.clone()).collect();
        let mut session = Self {
            rec,
            lanes,
            config,
            config_changed: false,
            world_damage: true,
            mode: ActionMode::Deterministic,
            global_step: 0,
            episodes_started: 0,
            seed: 0,
            keep_history: false,
            history: Vec::new(),
            branches: 0,
            episode_start: 0,
            global_max: 0,
            plot_roots,
            start: None,
            attribution: false,
            caption: None,
        };
        session.style_lanes()?;
        Ok(session)
    }

    /// With several lanes in the same plots, each gets its name in every series name and a hue
    /// family of its own (one lane alone keeps plain joint names and distinct colours).
    fn style_lanes(&mut self) -> Result<(), RecordError> {
        let several = self.lanes.len() > 1;
        let labels: Vec<String> = self.lanes.iter().map(Lane::series_label).collect();
        let mut keyed = Vec::new();
        for (k, lane) in self.lanes.iter_mut().enumerate() {
            // The model's name; with the lane's root where two lanes share a model.
            let shared = labels.iter().filter(|l| **l == labels[k]).count() > 1;
            let label = if shared {
                format!("{} ({})", labels[k], lane.base_root)
            } else {
                labels[k].clone()
            };
            keyed.push((label.clone(), k));
            let style = several.then_some(super::SeriesStyle { label, family: k });
            lane.logger.set_series_style(style)?;
        }
        let probe = self.lanes.iter().any(|l| l.logger.probe().is_some());
        super::log_key(&self.rec, &keyed, probe, self.caption.as_deref())?;
        Ok(())
    }

    /// What the recording shows and why (under the key), e.g. how its episode was chosen.
    pub fn set_caption(&mut self, caption: Option<String>) -> Result<(), RecordError> {
        if caption == self.caption {
            return Ok(());
        }
        self.caption = caption;
        self.style_lanes()
    }

    /// Keep every step's state of the current episode (up to [`HISTORY_CAP`]), so
    /// [`Self::rewind`] can go back to it.
    pub fn keep_history(&mut self, on: bool) {
        self.keep_history = on;
        if !on {
            self.history.clear();
        }
    }

    /// Episode steps the session can rewind to: 0 ..= this (the current step included).
    pub fn rewindable(&self) -> usize {
        self.history.len()
    }

    /// Rewinds in this recording so far.
    pub fn branches(&self) -> u64 {
        self.branches
    }

    fn model_lanes(&self) -> usize {
        self.lanes.iter().filter(|l| l.fork_of.is_none()).count()
    }

    /// Sends the layout for the lanes now, with this episode's earlier branches in the plots.
    fn send_current_layout(&self) -> Result<(), TelemetryError> {
        let roots: Vec<String> = self.lanes.iter().map(|l| l.root.clone()).collect();
        let mut plots = self.plot_roots.clone();
        plots.extend(
            roots
                .iter()
                .filter(|r| !self.plot_roots.contains(r))
                .cloned(),
        );
        let labels: Vec<String> = self.lanes.iter().map(Lane::series_label).collect();
        let titles = super::view_titles(&labels, &roots);
        let views = super::ViewOptions {
            attribution: self.attribution,
            ..super::ViewOptions::for_worlds(self.lanes.iter().map(|l| l.core.env().config()))
                .with_latent(self.lanes.iter().map(|l| l.actor().has_z()))
        };
        super::send_layout_for(&self.rec, &roots, &titles, &plots, views)
    }

    fn drop_fork(&mut self) -> Result<bool, RecordError> {
        let before = self.lanes.len();
        self.lanes.retain(|l| l.fork_of.is_none());
        if self.lanes.len() == before {
            return Ok(false);
        }
        self.send_current_layout()?;
        Ok(true)
    }

    /// Ends the fork lane, if any (its data stays in the recording).
    pub fn end_fork(&mut self) -> Result<bool, RecordError> {
        self.drop_fork()
    }

    /// Goes back to the state after `step` steps of this episode and continues from there as a
    /// new branch: each model logs under a new root (`ant_b1`, …) at the same `step` times as
    /// the history it leaves, which stays in the recording, overlaid in the plots to compare.
    /// A fork lane ends.
    pub fn rewind(&mut self, step: usize) -> Result<(), RewindError> {
        let now = self.lanes.first().map_or(0, |l| l.core.steps());
        if step == now && step == self.history.len() {
            return Ok(());
        }
        let Some(states) = self.history.get(step).cloned() else {
            return Err(RewindError::OutOfRange {
                step,
                available: self.history.len(),
            });
        };
        self.drop_fork()?;
        self.branches += 1;
        let branch = self.branches;
        let episode = self.episodes_started.saturating_sub(1);
        self.global_step = self.episode_start + step as u64;
        let mut new_roots = Vec::new();
        for (lane, state) in self.lanes.iter_mut().zip(&states) {
            lane.restore(state)?;
            let root = format!("{}_b{branch}", lane.base_root);
            let mut logger = lane.logger.branch(&root, lane.core.env());
            logger.set_time(self.global_step, episode);
            let mut meta = episode_meta(self.world_damage, self.seed, &lane.actor, lane.core.env());
            meta.checkpoint = format!(
                "{} (branch {branch}: rewound to step {step})",
                meta.checkpoint
            );
            logger.log_episode(&meta, lane.core.env(), None)?;
            logger.continue_from(&lane.logger);
            logger.log_note(
                super::NoteLevel::Branch,
                &format!(
                    "branch {branch}: {} rewound to step {step} of episode {episode}",
                    lane.root
                ),
            )?;
            let previous = std::mem::replace(&mut lane.logger, logger);
            if lane.base_logger.is_none() {
                lane.base_logger = Some(previous);
            }
            lane.root = root.clone();
            new_roots.push(root);
        }
        self.plot_roots.extend(new_roots);
        self.send_current_layout()?;
        self.history.truncate(step);
        Ok(())
    }

    /// Starts a counterfactual lane of the main model (root [`FORK_ROOT`], drawn beside the
    /// others) from its exact current state with `edits` applied; it steps in lockstep until it
    /// ends, the episode ends, or [`Self::end_fork`]. A previous fork is replaced.
    pub fn fork(&mut self, edits: &[Edit]) -> Result<(), RecordError> {
        self.drop_fork()?;
        let Some(main) = self.lanes.first() else {
            return Ok(());
        };
        let main_log = main.log.clone();
        let described = format!(
            "fork of {} at step {}: {}",
            main.root,
            main.core.steps(),
            edits
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(",")
        );
        let spec = LaneSpec {
            actor: main.actor.clone(),
            root: FORK_ROOT.to_string(),
            world_offset: side_by_side_offset(self.lanes.len()),
        };
        let mut lane = Lane::new(spec, &self.rec, &self.config, self.seed)?;
        // The stepping core's fork: the main lane's exact state, the edits applied.
        lane.core = main.core.fork(edits)?;
        lane.probe_before = lane.probe_now().copied();
        lane.log = main_log;
        lane.fork_of = Some(described.clone());
        let episode = self.episodes_started.saturating_sub(1);
        lane.logger.set_time(self.global_step, episode);
        let mut meta = episode_meta(self.world_damage, self.seed, &lane.actor, lane.core.env());
        meta.checkpoint = format!("{} ({described})", meta.checkpoint);
        lane.logger.log_episode(&meta, lane.core.env(), None)?;
        // After the episode metadata, which starts a logger's trails afresh.
        lane.logger.continue_from(&self.lanes[0].logger);
        lane.logger.log_note(super::NoteLevel::Branch, &described)?;
        self.lanes.push(lane);
        self.style_lanes()?;
        self.send_current_layout()?;
        Ok(())
    }

    /// Writes a breakpoint hit (or any debugger note) into a lane's event log at the current
    /// time, as its own level.
    pub fn log_break(&mut self, root: &str, text: &str) -> Result<(), RecordError> {
        if let Some(lane) = self.lanes.iter_mut().find(|l| l.root == root) {
            lane.logger.log_note(super::NoteLevel::Break, text)?;
        }
        Ok(())
    }

    /// Deterministic (evaluation) or sampled actions, from the next step on.
    pub fn set_action_mode(&mut self, mode: ActionMode) {
        self.mode = mode;
    }

    /// New requested settings, in force from the next episode.
    pub fn set_config(&mut self, config: GaitConfig) {
        self.config = config;
        self.config_changed = true;
    }

    /// Whether the world damages joints by itself (fatigue triggers, a world's deaths), from the
    /// next episode (off: only a person damages joints).
    pub fn set_world_damage(&mut self, on: bool) {
        self.world_damage = on;
    }

    /// Replaces the models (e.g. another checkpoint picked in the panel); start an episode next.
    /// The recording and its timelines go on.
    pub fn replace_lanes(&mut self, specs: Vec<LaneSpec>) -> Result<(), RecordError> {
        let roots: Vec<String> = specs.iter().map(|s| s.root.clone()).collect();
        self.lanes = specs
            .into_iter()
            .map(|spec| Lane::new(spec, &self.rec, &self.config, self.seed))
            .collect::<Result<Vec<_>, _>>()?;
        self.style_lanes()?;
        self.plot_roots = roots;
        self.config_changed = false;
        // The layout follows the models: one 3-D view each.
        self.send_current_layout()?;
        Ok(())
    }

    /// Every later episode starts from `start` (a saved state: its physics, damage and, for the
    /// model that saved it, window) after the reset with its seed.
    pub fn set_start_state(&mut self, start: Option<std::sync::Arc<crate::lane::StartState>>) {
        self.start = start;
    }

    /// Turns the attribution view on or off (from the next step); the layout brings its tabs
    /// up front while it is on.
    pub fn set_attribution(&mut self, on: bool) -> Result<(), TelemetryError> {
        if self.attribution != on {
            self.attribution = on;
            self.send_current_layout()?;
        }
        Ok(())
    }

    pub fn attribution(&self) -> bool {
        self.attribution
    }

    /// Takes the models out, leaving no lanes until [`Self::replace_lanes`].
    pub fn take_actors(&mut self) -> Vec<Actor> {
        self.lanes.drain(..).map(|l| l.actor).collect()
    }

    /// Resets every lane with `seed` and logs the episode's metadata.
    pub fn start_episode(&mut self, seed: u64) -> Result<(), RecordError> {
        self.drop_fork()?;
        self.history.clear();
        // After branches: back to the models' own roots, on after the furthest step logged.
        let branched = self.lanes.iter().any(|l| l.base_logger.is_some());
        for lane in &mut self.lanes {
            if let Some(base) = lane.base_logger.take() {
                lane.logger = base;
                lane.root = lane.base_root.clone();
            }
        }
        self.plot_roots = self.lanes.iter().map(|l| l.root.clone()).collect();
        if branched {
            self.send_current_layout()?;
        }
        self.global_step = self.global_step.max(self.global_max);
        self.episode_start = self.global_step;
        if self.config_changed {
            for lane in &mut self.lanes {
                lane.core = crate::lane::Lane::unstarted(&lane.actor, &self.config, seed)?;
            }
            self.config_changed = false;
        }
        self.seed = seed;
        let episode = self.episodes_started;
        self.episodes_started += 1;
        for lane in &mut self.lanes {
            lane.core.set_world_damage(self.world_damage);
            lane.core.reset(seed);
            lane.log.clear();
            if let Some(start) = &self.start {
                lane.core.start_from(start)?;
            }
            lane.probe_before = None;
            lane.logger.set_time(self.global_step, episode);
            let meta = episode_meta(self.world_damage, seed, &lane.actor, lane.core.env());
            lane.logger.log_episode(&meta, lane.core.env(), None)?;
        }
        Ok(())
    }

    /// One env step for every lane still running. Returns whether every lane's episode is over.
    pub fn step(&mut self) -> Result<bool, RecordError> {
        if self.is_over() {
            return Ok(true);
        }
        if self.keep_history && self.history.len() < HISTORY_CAP {
            let models = self.model_lanes();
            self.history
                .push(self.lanes[..models].iter().map(Lane::snapshot).collect());
        }
        self.global_step += 1;
        self.global_max = self.global_max.max(self.global_step);
        let episode = self.episodes_started.saturating_sub(1);
        let mut ended = Vec::new();
        for i in 0..self.lanes.len() {
            let lane = &mut self.lanes[i];
            if lane.core.is_done() {
                continue;
            }
            lane.probe_before = lane.probe_now().copied();
            // Why z moves: from the window this step's decision reads, before it is pushed.
            let attribution = match (self.attribution, lane.actor.policy()) {
                (true, Some(policy)) if policy.net().encoder.uses_window() => Some(
                    crate::explain::z_shift_attribution(
                        policy,
                        lane.core.window().as_slice(),
                        super::ATTRIBUTION_POINTS,
                    )
                    .map_err(RecordError::Attribution)?,
                ),
                _ => None,
            };
            // The stepping core steps; the sinks only read its record.
            lane.core.advance(&lane.actor, self.mode)?;
            lane.note_step();
            let Some(record) = lane.core.last() else {
                continue;
            };
            lane.stepped_at = self.global_step;
            lane.logger.set_time(self.global_step, episode);
            lane.logger.log_step(lane.core.env(), record)?;
            if let Some(a) = &attribution {
                lane.logger.log_attribution(a)?;
            }
            let out = &record.outcome;
            if out.done() {
                let meta = episode_meta(self.world_damage, self.seed, &lane.actor, lane.core.env());
                lane.logger.log_episode(&meta, lane.core.env(), Some(out))?;
                ended.push(i);
            }
        }
        // A lane that ended while others run waits for them: its series stop here.
        if !self.is_over() {
            for i in ended {
                let logger = &mut self.lanes[i].logger;
                logger.set_time(self.global_step + 1, episode);
                logger.log_series_gap()?;
            }
        }
        Ok(self.is_over())
    }

    /// Whether every lane's episode has ended (true before the first episode too).
    pub fn is_over(&self) -> bool {
        self.lanes.iter().all(|l| l.core.is_done())
    }

    /// How each lane's current episode has ended so far (a lane still running: `ending` none).
    pub fn endings(&self, episode: usize) -> Vec<LaneEnding> {
        self.lanes
            .iter()
            .map(|l| l.core.ending(l.series_label(), episode, self.seed))
            .collect()
    }

    /// The same hand-made change to every lane (forks included); it applies from the next step
    /// and is logged as an event with it.
    pub fn apply_override(
        &mut self,
        actuator: usize,
        change: JointOverride,
    ) -> Result<(), RecordError> {
        for lane in &mut self.lanes {
            lane.core.apply_override(actuator, change)?;
        }
        Ok(())
    }

    /// The same push on every running lane (forks included), from the next step on. Checked
    /// against every lane's model first, so a bad body changes nothing.
    pub fn push(&mut self, push: &crate::damage::Push) -> Result<(), RecordError> {
        let edit = Edit::Push(push.clone());
        for lane in &self.lanes {
            lane.core.env().check_edit(&edit)?;
        }
        for lane in self.lanes.iter_mut().filter(|l| !l.core.is_done()) {
            lane.core.apply_edit(&edit)?;
        }
        Ok(())
    }

    pub fn lanes(&self) -> &[Lane] {
        &self.lanes
    }
    /// Env steps since the recording started (the `step` timeline).
    pub fn global_step(&self) -> u64 {
        self.global_step
    }
    pub fn episodes_started(&self) -> u64 {
        self.episodes_started
    }
    /// The current episode's seed.
    pub fn seed(&self) -> u64 {
        self.seed
    }
    pub fn config(&self) -> &GaitConfig {
        &self.config
    }
    pub fn recording(&self) -> &RecordingStream {
        &self.rec
    }

    /// Waits up to `timeout` for everything logged so far to reach the sinks.
    pub fn flush_within(&self, timeout: std::time::Duration) -> Result<(), TelemetryError> {
        match self.rec.flush_with_timeout(timeout) {
            Ok(()) => Ok(()),
            Err(rerun::sink::SinkFlushError::Timeout) => Err(TelemetryError::FlushTimeout(timeout)),
            Err(e) => Err(TelemetryError::Flush(e)),
        }
    }

    /// Blocks until everything logged so far has reached the sinks.
    pub fn flush(&self) -> Result<(), TelemetryError> {
        self.rec.flush_blocking().map_err(TelemetryError::Flush)
    }
}

fn episode_meta(world_damage: bool, seed: u64, actor: &Actor, env: &AntEnv) -> EpisodeMeta {
    let condition = env.condition();
    EpisodeMeta {
        checkpoint: actor.label(),
        encoder: actor.encoder(),
        condition: if world_damage {
            condition.to_string()
        } else {
            format!(
                "manual (only hand-made damage: no fatigue triggers, no world deaths; fail now → {condition} scale)"
            )
        },
        seed,
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RewindError {
    #[error("step {step} is not in this episode's history (0 ..= {available})")]
    OutOfRange { step: usize, available: usize },
    #[error(transparent)]
    Record(#[from] RecordError),
    #[error(transparent)]
    Telemetry(#[from] TelemetryError),
    #[error(transparent)]
    Env(#[from] crate::env::EnvError),
}

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error(transparent)]
    Telemetry(#[from] TelemetryError),
    #[error(transparent)]
    Lane(#[from] crate::lane::LaneError),
    #[error(transparent)]
    Env(#[from] crate::env::EnvError),
    #[error(transparent)]
    Probe(#[from] crate::probe::ProbeError),
    #[error("policy inference failed: {0}")]
    Policy(#[from] candle_core::Error),
    #[error("the attribution view failed")]
    Attribution(#[source] crate::explain::ExplainError),

    #[error(
        "the recording {path} could not be written completely: {reason}; nothing was left under that name"
    )]
    Incomplete {
        path: std::path::PathBuf,
        #[source]
        reason: crate::Cause,
    },
    #[error("episode {episode}: {source}")]
    ForkBeyondEpisode {
        episode: usize,
        #[source]
        source: crate::lane::ForkBeyondEpisode,
    },
}
