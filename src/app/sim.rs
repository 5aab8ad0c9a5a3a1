//! The simulation thread: commands in, paced env steps, a snapshot out.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex, MutexGuard};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use rerun::RecordingStream;

use super::breakpoint::{BreakHit, Breakpoint, LaneStep};
use super::{Command, LiveCondition, LiveError, MAX_SPEED, MIN_SPEED, Slot, live_specs};
use crate::config::GaitConfig;
use crate::damage::{ConditionChoice, JointState, N_ACTUATORS};
use crate::policy::ActionMode;
use crate::telemetry::{Actor, Lane, Session};

/// How long a finished episode stays on screen before the next one starts (wall time).
const HOLD_FINISHED: Duration = Duration::from_millis(1500);
/// Behind schedule by more than this, the sim stops trying to catch up (it would only burst).
const MAX_LAG: Duration = Duration::from_millis(250);
/// How long the end of a session waits for the viewer to take the last data.
const FLUSH_TIMEOUT: Duration = Duration::from_secs(5);
/// While paused, the thread still wakes this often (to notice a closed panel).
const IDLE_WAIT: Duration = Duration::from_millis(100);
/// Single steps queued at most; more are refused with a message (a flood of step requests
/// must not grow without bound).
pub const MAX_PENDING_STEPS: usize = 10_000;

/// How a live session starts.
#[derive(Debug, Clone)]
pub struct LiveSetup {
    pub checkpoint: PathBuf,
    /// A second model, side by side from the start.
    pub compare: Option<PathBuf>,
    pub condition: LiveCondition,
    pub seed: u64,
    /// Multiple of real time (real time = 1 / dt env steps per second, 20 for the Ant).
    pub speed: f64,
    pub step_limit: usize,
    pub mode: ActionMode,
    pub paused: bool,
    /// Pause after any step where one of these holds.
    pub breakpoints: Vec<Breakpoint>,
    /// Fork the main model in every episode before this step, with these edits (as the
    /// panel's "Fork here" would).
    pub fork: Option<crate::rollout::Fork>,
    /// Env settings (model, weights); a checkpoint's own task settings take precedence.
    pub config: GaitConfig,
    /// Every episode (each reset) starts from this state (`--init-state`).
    pub start: Option<crate::lane::StartState>,
    /// Start with the attribution view on (why z moved; the panel toggles it).
    pub attribution: bool,
}

impl LiveSetup {
    fn check_settings(&self) -> Result<(), LiveError> {
        if !(self.speed.is_finite() && (MIN_SPEED..=MAX_SPEED).contains(&self.speed)) {
            return Err(LiveError::BadSpeed(self.speed));
        }
        if self.step_limit == 0 {
            return Err(LiveError::BadStepLimit);
        }
        Ok(())
    }

    /// Checks the settings and that the checkpoints load, before any window or viewer opens.
    pub fn validate(&self) -> Result<(), LiveError> {
        self.check_settings()?;
        let main = Actor::load(&self.checkpoint)?;
        if let Some(dir) = &self.compare {
            crate::policy::Policy::load(dir, None)?;
        }
        let env = crate::env::AntEnv::new(self.world(&main), 0)
            .map_err(|e| LiveError::Record(crate::telemetry::RecordError::Env(e)))?;
        let has_probe = self.checkpoint.join(crate::probe::PROBE_FILE).exists();
        for b in &self.breakpoints {
            b.validate(env.damage().joint_names(), has_probe)?;
        }
        self.check_fork(&main)
    }

    /// The main model's world for the first episode (see [`Actor::world`]).
    fn world(&self, main: &Actor) -> GaitConfig {
        main.world(&episode_config(
            &self.config,
            self.condition,
            self.step_limit,
        ))
    }

    /// `--fork-at K --fork EDITS`, checked once, before any step (lane::Fork::validate).
    fn check_fork(&self, main: &Actor) -> Result<(), LiveError> {
        match &self.fork {
            Some(fork) => fork
                .validate(&self.world(main))
                .map_err(|e| LiveError::Record(e.into())),
            None => Ok(()),
        }
    }
}

/// `base` with the panel's condition and step limit.
pub fn episode_config(
    base: &GaitConfig,
    condition: LiveCondition,
    step_limit: usize,
) -> GaitConfig {
    let mut config = base.clone();
    config.env.max_episode_steps = step_limit;
    config.damage.condition = ConditionChoice::Fixed(condition.env_condition());
    config
}

/// One model as the panel shows it.
#[derive(Debug, Clone, PartialEq)]
pub struct LaneView {
    pub label: String,
    pub root: String,
    pub encoder: String,
    pub checkpoint: Option<PathBuf>,
    /// Env steps taken in this episode.
    pub step: usize,
    pub distance: f64,
    pub success: bool,
    pub done: bool,
    /// How the episode ended ("success", "leapt", "timeout", … : [`crate::env::Ending`]), once it has.
    pub ending: Option<&'static str>,
    pub joint_names: [String; N_ACTUATORS],
    /// The model's named bodies, what a push may name.
    pub body_names: Vec<String>,
    /// The leg each joint moves (the gait view's lane names: `front_left_leg`, …).
    pub joint_legs: [String; N_ACTUATORS],
    pub fatigue: [f64; N_ACTUATORS],
    pub threshold: f64,
    /// Whether fatigue reaching the threshold triggers a joint this episode (not in a world
    /// whose damage is dead actuators alone, nor in the manual condition).
    pub fatigue_triggers: bool,
    pub states: [JointState; N_ACTUATORS],
    pub scale: [f64; N_ACTUATORS],
    /// P(joint damaged) from the probe on z, when the checkpoint has `probe.json`.
    pub probe: Option<[f64; N_ACTUATORS]>,
    /// Whether each joint is effectively damaged (triggered with a scale below 1): the probe's truth.
    pub damaged: [bool; N_ACTUATORS],
    /// The latest step's commanded and applied (scaled) actions.
    pub commanded: [f64; N_ACTUATORS],
    pub applied: [f64; N_ACTUATORS],
    pub events: usize,
    pub last_event: Option<String>,
    /// This episode's events, oldest first: damage (with who made it), pushes, the ending.
    pub event_log: Vec<crate::telemetry::LogEntry>,
    /// Who last changed each joint's torque: fatigue, the world, a scenario, manual.
    pub causes: [Option<String>; N_ACTUATORS],
    /// For the fork lane: what it was forked from.
    pub fork_of: Option<String>,
}

impl LaneView {
    fn of(lane: &Lane) -> Self {
        let env = lane.env();
        let damage = env.damage();
        let states = std::array::from_fn(|i| damage.joint_state(i));
        let damaged = std::array::from_fn(|i| damage.triggered()[i] && damage.scale()[i] < 1.0);
        // The readout the session computed once for this step (and logged).
        let probe = lane.probe_now().copied();
        let last = lane.last().map(|r| &r.outcome);
        Self {
            label: lane.actor().label(),
            root: lane.root().to_string(),
            encoder: lane.actor().encoder(),
            checkpoint: lane.actor().checkpoint_dir().map(|d| d.to_path_buf()),
            step: env.steps(),
            distance: last.map_or_else(|| env.goal_distance(), |o| o.distance),
            success: last.is_some_and(|o| o.success),
            done: lane.is_done(),
            ending: last.and_then(crate::env::StepOutcome::ending),
            joint_names: damage.joint_names().clone(),
            body_names: env.body_names().iter().map(|n| n.to_string()).collect(),
            joint_legs: std::array::from_fn(|i| env.leg_names()[env.leg_of_actuator()[i]].clone()),
            fatigue: *damage.fatigue(),
            threshold: damage.config().threshold,
            fatigue_triggers: damage.fatigue_triggers(),
            states,
            scale: *damage.scale(),
            probe,
            damaged,
            commanded: last.map_or([0.0; N_ACTUATORS], |o| o.commanded_action),
            applied: last.map_or([0.0; N_ACTUATORS], |o| o.applied_action),
            fork_of: lane.fork_of().map(str::to_string),
            events: damage.events().len(),
            event_log: lane.event_log().to_vec(),
            causes: damage.causes(),
            // Counted as the page's step counter counts: steps taken in this episode.
            last_event: damage
                .events()
                .last()
                .map(|e| format!("step {}: {}", e.step + 1, e.describe())),
        }
    }
}

/// What the panel shows: the simulation's state after the latest step or command.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    pub paused: bool,
    pub speed: f64,
    /// Condition, seed and step limit the next reset uses.
    pub condition: LiveCondition,
    /// The main model's world (`paper`, `dead-legs`, …): what the conditions mean.
    pub world: String,
    /// What each condition does in that world, in [`LiveCondition::ALL`]'s order.
    pub condition_meanings: [String; 4],
    pub seed: u64,
    pub step_limit: usize,
    pub mode: ActionMode,
    pub compare: bool,
    /// The second model's folder, once one is loaded.
    pub compare_checkpoint: Option<PathBuf>,
    pub episode_seed: u64,
    pub episodes: u64,
    /// The recording's `step` timeline.
    pub global_step: u64,
    pub lanes: Vec<LaneView>,
    /// Env steps per second over the last second, and what the speed asks for.
    pub steps_per_s: f64,
    pub target_steps_per_s: f64,
    /// The last problem (a checkpoint that did not load, a rejected change), for the panel.
    pub message: Option<String>,
    pub breakpoints: Vec<Breakpoint>,
    /// The breakpoint that paused the sim, until it runs on.
    pub break_hit: Option<BreakHit>,
    /// Steps of this episode the sim can rewind to: 0 ..= this.
    pub rewindable: usize,
    /// Rewinds so far (each a new branch on the timeline).
    pub branches: u64,
    /// Whether the main model's checkpoint has a probe.json (for `probe-flip`).
    pub has_probe: bool,
    /// The scenario episodes run under (from the next reset once changed).
    pub scenario: Option<String>,
    /// This episode's hand-made overrides (main model) as a scenario file's JSON: what
    /// "save" writes, and what the web page downloads.
    pub recorded_scenario: Option<serde_json::Value>,
    /// The main model's state before its next step: what "Save state" writes and the page
    /// downloads (`--init-state` starts from it).
    pub saved_state: Option<Arc<crate::lane::SavedState>>,
    /// Whether the attribution view (why z moved) is on.
    pub attribution: bool,
    /// Commands the sim thread has taken so far, in the order they were sent.
    pub commands_handled: u64,
    /// When it took the latest of them (a front-end times its command from its own send).
    pub last_command_at: Option<Instant>,
    /// The simulation thread has stopped.
    pub stopped: bool,
}

/// How far the simulation kept up with real time at each speed it ran at.
#[derive(Debug, Clone, PartialEq)]
pub struct SpeedReport {
    pub speed: f64,
    pub seconds: f64,
    pub steps: u64,
    pub target_steps_per_s: f64,
}

impl SpeedReport {
    pub fn steps_per_s(&self) -> f64 {
        self.steps as f64 / self.seconds.max(1e-9)
    }
    /// Achieved over asked-for rate (1.0 = keeps up).
    pub fn keeps_up(&self) -> f64 {
        self.steps_per_s() / self.target_steps_per_s
    }
}

/// What a finished live session did.
#[derive(Debug, Clone, Default)]
pub struct SimReport {
    pub steps: u64,
    pub episodes: u64,
    /// Time spent running (not paused, not holding a finished episode) per speed.
    pub speeds: Vec<SpeedReport>,
}

/// The panel's end of the simulation thread.
pub struct SimHandle {
    tx: Sender<Command>,
    snapshot: Arc<Mutex<Snapshot>>,
    thread: Option<JoinHandle<Result<SimReport, LiveError>>>,
}

impl SimHandle {
    /// Loads the checkpoints (errors surface here, before any window opens), then starts the
    /// simulation thread streaming to `rec`.
    pub fn spawn(rec: RecordingStream, setup: LiveSetup) -> Result<Self, LiveError> {
        setup.check_settings()?;
        let main = Actor::load(&setup.checkpoint)?;
        setup.check_fork(&main)?;
        let compare = setup.compare.as_deref().map(Actor::load).transpose()?;
        let compare_on = compare.is_some();
        let config = episode_config(&setup.config, setup.condition, setup.step_limit);
        let mut session = Session::new(rec, live_specs(main, compare), config)?;
        session.keep_history(true);
        session.set_action_mode(setup.mode);
        session.set_world_damage(setup.condition.world_damage());
        session.set_start_state(setup.start.clone().map(Arc::new));
        session.set_attribution(setup.attribution)?;
        session.start_episode(setup.seed)?;

        let dt = session.lanes()[0].env().dt();
        let sim = Sim {
            session,
            spare: None,
            compare_dir: setup.compare.clone(),
            compare_on,
            condition: setup.condition,
            seed: setup.seed,
            step_limit: setup.step_limit,
            mode: setup.mode,
            paused: setup.paused,
            speed: setup.speed,
            dt,
            steps_pending: 0,
            commands_handled: 0,
            last_command_at: None,
            over_since: None,
            message: None,
            breakpoints: setup.breakpoints.clone(),
            break_hit: None,
            auto_fork: setup.fork.clone(),
            forked_episode: None,
            recent: Vec::new(),
            speeds: BTreeMap::new(),
        };
        let snapshot = Arc::new(Mutex::new(sim.snapshot()));
        let (tx, rx) = mpsc::channel();
        let shared = snapshot.clone();
        let thread = std::thread::Builder::new()
            .name("gaitscope-sim".into())
            .spawn(move || sim.run(rx, shared))
            .map_err(LiveError::ThreadStart)?;
        Ok(Self {
            tx,
            snapshot,
            thread: Some(thread),
        })
    }

    /// Queues a command; false once the simulation thread has stopped.
    pub fn send(&self, command: Command) -> bool {
        self.tx.send(command).is_ok()
    }

    pub fn sender(&self) -> Sender<Command> {
        self.tx.clone()
    }

    /// The snapshot the thread publishes into.
    pub fn shared_snapshot(&self) -> Arc<Mutex<Snapshot>> {
        self.snapshot.clone()
    }

    /// The latest state (a copy; the lock is held only to clone).
    pub fn snapshot(&self) -> Snapshot {
        lock(&self.snapshot).clone()
    }

    /// Waits (up to `timeout`) until `ready` holds for the snapshot; returns the last one seen.
    pub fn wait_for(&self, timeout: Duration, ready: impl Fn(&Snapshot) -> bool) -> Snapshot {
        let deadline = Instant::now() + timeout;
        loop {
            let s = self.snapshot();
            if ready(&s) || s.stopped || Instant::now() >= deadline {
                return s;
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }

    /// Stops the thread, flushes the stream and reports.
    pub fn shutdown(mut self) -> Result<SimReport, LiveError> {
        let _ = self.tx.send(Command::Quit);
        match self.thread.take().map(|t| t.join()) {
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(LiveError::SimThreadPanicked),
            None => Ok(SimReport::default()),
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        if let Some(thread) = self.thread.take() {
            let _ = self.tx.send(Command::Quit);
            let _ = thread.join();
        }
    }
}

fn lock(m: &Mutex<Snapshot>) -> MutexGuard<'_, Snapshot> {
    // A panic elsewhere while holding the lock leaves a valid snapshot: keep using it.
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// The simulation thread's state.
struct Sim {
    session: Session,
    /// The second model while side-by-side is off (kept loaded so it can be switched back on).
    spare: Option<Actor>,
    compare_dir: Option<PathBuf>,
    compare_on: bool,
    condition: LiveCondition,
    seed: u64,
    step_limit: usize,
    mode: ActionMode,
    paused: bool,
    speed: f64,
    dt: f64,
    /// Single steps asked for while paused, not yet taken.
    steps_pending: usize,
    /// Commands taken off the channel so far (a front-end's receipt: its n-th command applied).
    commands_handled: u64,
    last_command_at: Option<Instant>,
    /// When every model's episode ended (the next starts after [`HOLD_FINISHED`]).
    over_since: Option<Instant>,
    message: Option<String>,
    breakpoints: Vec<Breakpoint>,
    break_hit: Option<BreakHit>,
    /// `--fork-at K --fork EDITS`, and the episode it last forked.
    auto_fork: Option<crate::rollout::Fork>,
    forked_episode: Option<u64>,
    /// Wall times of the steps in the last second (the achieved rate).
    recent: Vec<Instant>,
    /// Per speed (in 1/1000 ×): running seconds and steps.
    speeds: BTreeMap<u64, (f64, u64)>,
}

/// Commands taken from the queue between two snapshots at most.
const MAX_COMMAND_BATCH: usize = 4_096;

impl Sim {
    fn target_rate(&self) -> f64 {
        self.speed / self.dt
    }

    fn run(
        mut self,
        rx: Receiver<Command>,
        shared: Arc<Mutex<Snapshot>>,
    ) -> Result<SimReport, LiveError> {
        let mut next_tick = Instant::now();
        let mut last_tick = Instant::now();
        loop {
            // Commands first; wait for one until the next step is due (or idle while paused).
            let running = !self.paused || self.steps_pending > 0;
            let wait = if running {
                next_tick.saturating_duration_since(Instant::now())
            } else {
                IDLE_WAIT
            };
            match rx.recv_timeout(wait) {
                Ok(Command::Quit) | Err(RecvTimeoutError::Disconnected) => break,
                Ok(command) => {
                    // And everything queued behind it (a request's commands arrive together):
                    // one snapshot for the batch, not one per command, which made a long edit
                    // list quadratic (each snapshot carries every override so far).
                    self.handle(command);
                    let mut quit = false;
                    for _ in 0..MAX_COMMAND_BATCH {
                        match rx.try_recv() {
                            Ok(Command::Quit) => {
                                quit = true;
                                break;
                            }
                            Ok(command) => self.handle(command),
                            Err(_) => break,
                        }
                    }
                    *lock(&shared) = self.snapshot();
                    if quit {
                        break;
                    }
                    continue;
                }
                Err(RecvTimeoutError::Timeout) => {}
            }
            if self.paused && self.steps_pending == 0 {
                next_tick = Instant::now();
                last_tick = next_tick;
                continue;
            }
            let stepping_once = self.steps_pending > 0;
            self.steps_pending = self.steps_pending.saturating_sub(1);
            let now = Instant::now();
            let since_last_tick = (now - last_tick).min(MAX_LAG);
            last_tick = now;
            match self.advance(stepping_once) {
                // Paced running time per speed: a single step or a finished episode on show
                // is not.
                Ok(true) if !stepping_once => {
                    let key = (self.speed * 1000.0).round() as u64;
                    let entry = self.speeds.entry(key).or_insert((0.0, 0));
                    entry.0 += since_last_tick.as_secs_f64();
                    entry.1 += 1;
                }
                Ok(_) => {}
                Err(e) => {
                    // Keep the panel alive: pause and say what went wrong.
                    self.paused = true;
                    self.message = Some(format!("simulation paused: {e}"));
                }
            }
            *lock(&shared) = self.snapshot();
            next_tick += Duration::from_secs_f64(1.0 / self.target_rate());
            if Instant::now().saturating_duration_since(next_tick) > MAX_LAG {
                next_tick = Instant::now();
            }
        }
        let flushed = self.session.flush_within(FLUSH_TIMEOUT);
        let mut snapshot = self.snapshot();
        snapshot.stopped = true;
        *lock(&shared) = snapshot;
        let report = self.report();
        match flushed {
            Ok(()) => Ok(report),
            Err(source) => {
                // Rerun's stream blocks on drop until a viewer takes its data; a viewer that is
                // gone never will. Leave the stream to process exit rather than hang the program.
                std::mem::forget(self.session);
                // The report travels with the error: what the session did is still worth saying.
                Err(LiveError::Unflushed {
                    report: Box::new(report),
                    source,
                })
            }
        }
    }

    fn report(&self) -> SimReport {
        SimReport {
            steps: self.session.global_step(),
            episodes: self.session.episodes_started(),
            speeds: self
                .speeds
                .iter()
                .map(|(&k, &(seconds, steps))| SpeedReport {
                    speed: k as f64 / 1000.0,
                    seconds,
                    steps,
                    target_steps_per_s: k as f64 / 1000.0 / self.dt,
                })
                .collect(),
        }
    }

    /// One tick: a step, or the next episode once a finished one has been shown long enough.
    /// Returns whether an env step was taken.
    fn advance(&mut self, stepping_once: bool) -> Result<bool, LiveError> {
        if self.session.is_over() {
            let since = *self.over_since.get_or_insert_with(Instant::now);
            if stepping_once || since.elapsed() >= HOLD_FINISHED {
                self.seed = self.seed.wrapping_add(1);
                self.new_episode()?;
            }
            return Ok(false);
        }
        self.break_hit = None;
        if let Some(fork) = &self.auto_fork
            && self.forked_episode != Some(self.session.episodes_started())
            && self
                .session
                .lanes()
                .first()
                .is_some_and(|l| fork.due(l.core()))
        {
            let edits = fork.edits.clone();
            self.forked_episode = Some(self.session.episodes_started());
            self.session.fork(&edits)?;
        }
        self.session.step()?;
        if let Some(hit) = self.check_breakpoints() {
            self.session.log_break(&hit.lane, &hit.to_string())?;
            self.paused = true;
            self.break_hit = Some(hit);
        }
        let now = Instant::now();
        self.recent.push(now);
        self.recent
            .retain(|t| now.duration_since(*t) < Duration::from_secs(1));
        Ok(true)
    }

    /// The first breakpoint that holds for the step just taken, lane by lane (main first).
    fn check_breakpoints(&self) -> Option<BreakHit> {
        for lane in self.session.lanes() {
            let Some(record) = lane.last() else {
                continue;
            };
            let outcome = &record.outcome;
            // A lane that ended earlier did not step now.
            if lane.stepped_at() != self.session.global_step() {
                continue;
            }
            let step = LaneStep {
                outcome,
                events: &record.events,
                probe_before: lane.probe_before(),
                probe_after: record.probe.as_ref(),
                joint_names: lane.env().damage().joint_names(),
            };
            for b in &self.breakpoints {
                if let Some(reason) = b.hit(&step) {
                    return Some(BreakHit {
                        breakpoint: b.clone(),
                        lane: lane.root().to_string(),
                        step: outcome.step + 1,
                        reason,
                    });
                }
            }
        }
        None
    }

    fn new_episode(&mut self) -> Result<(), LiveError> {
        let config = episode_config(self.session.config(), self.condition, self.step_limit);
        self.session.set_config(config);
        self.session.set_world_damage(self.condition.world_damage());
        self.session.start_episode(self.seed)?;
        self.over_since = None;
        Ok(())
    }

    fn handle(&mut self, command: Command) {
        self.message = None;
        self.commands_handled += 1;
        self.last_command_at = Some(Instant::now());
        let result = match command {
            Command::Override { actuator, change } => self
                .session
                .apply_override(actuator, change)
                .map_err(LiveError::from),
            Command::Push(push) => self.session.push(&push).map_err(LiveError::from),
            Command::SetAttribution(on) => {
                self.session.set_attribution(on).map_err(LiveError::from)
            }
            Command::SetCondition(c) => {
                self.condition = c;
                Ok(())
            }
            Command::SetSeed(s) => {
                self.seed = s;
                Ok(())
            }
            Command::SetStepLimit(n) => {
                if n == 0 {
                    Err(LiveError::BadStepLimit)
                } else {
                    self.step_limit = n;
                    Ok(())
                }
            }
            // Pause and reset take effect before steps still queued: those are dropped.
            Command::Reset => {
                self.steps_pending = 0;
                self.new_episode()
            }
            Command::Pause => {
                self.paused = true;
                self.steps_pending = 0;
                Ok(())
            }
            Command::Resume => {
                self.paused = false;
                self.break_hit = None;
                Ok(())
            }
            Command::StepOnce => {
                if self.steps_pending >= MAX_PENDING_STEPS {
                    self.message = Some(format!(
                        "step refused: {MAX_PENDING_STEPS} steps are already queued"
                    ));
                } else {
                    self.steps_pending += 1;
                }
                self.break_hit = None;
                Ok(())
            }
            Command::SetSpeed(s) => {
                if s.is_finite() {
                    self.speed = s.clamp(MIN_SPEED, MAX_SPEED);
                    Ok(())
                } else {
                    Err(LiveError::BadSpeed(s))
                }
            }
            Command::SetActionMode(mode) => {
                self.mode = mode;
                self.session.set_action_mode(mode);
                Ok(())
            }
            Command::Load { slot, dir } => self.load(slot, dir),
            Command::SetCompare(on) => self.set_compare(on),
            Command::SetBreakpoints(list) => self.set_breakpoints(list),
            Command::Rewind(step) => {
                self.break_hit = None;
                self.over_since = None;
                self.session.rewind(step).map_err(LiveError::from)
            }
            Command::Fork(edits) => {
                if self.session.is_over() {
                    Err(LiveError::ForkAfterEnd)
                } else {
                    self.session.fork(&edits).map_err(LiveError::from)
                }
            }
            Command::EndFork => self.session.end_fork().map(|_| ()).map_err(LiveError::from),
            Command::SetScenario(scenario) => {
                // Checked against this model's joints now, as the CLI does: a scenario naming a
                // joint the Ant lacks is refused, not left to break every later reset.
                let checked = match (&scenario, self.session.lanes().first()) {
                    (Some(s), Some(lane)) => s.check(&lane.env().joint_map()),
                    _ => Ok(()),
                };
                match checked {
                    Ok(()) => {
                        let mut config = self.session.config().clone();
                        config.damage.scenario = scenario;
                        self.session.set_config(config);
                        Ok(())
                    }
                    Err(e) => {
                        self.message = Some(format!("scenario refused: {e}"));
                        Ok(())
                    }
                }
            }
            Command::SaveScenario(path) => self.save_scenario(&path),
            Command::SaveState(path) => self.save_state(&path),
            Command::Quit => Ok(()),
        };
        if let Err(e) = result {
            self.message = Some(e.to_string());
        }
    }

    /// The main model's state before its next step, as `--init-state` reads it.
    fn save_state(&mut self, path: &std::path::Path) -> Result<(), LiveError> {
        let Some(lane) = self.session.lanes().first() else {
            return Ok(());
        };
        let state = lane.save_state(self.session.seed());
        crate::policy::checkpoint::write_atomic(path, state.to_json().as_bytes()).map_err(|e| {
            LiveError::SaveState {
                path: path.to_owned(),
                reason: e.into(),
            }
        })?;
        self.message = Some(format!(
            "saved the state before step {} to {}",
            state.env.step,
            path.display()
        ));
        Ok(())
    }

    /// The main lane's hand-made overrides of this episode, as a scenario file that replays
    /// them (`rollout --scenario`), with this session's fatigue rule.
    fn save_scenario(&mut self, path: &std::path::Path) -> Result<(), LiveError> {
        let name = path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "live-session".into());
        let Some(value) = self.recorded_scenario(&name) else {
            return Ok(());
        };
        let text = serde_json::to_string_pretty(&value).map_err(|e| LiveError::SaveScenario {
            path: path.to_owned(),
            reason: e.into(),
        })?;
        crate::policy::checkpoint::write_atomic(path, format!("{text}\n").as_bytes()).map_err(
            |e| LiveError::SaveScenario {
                path: path.to_owned(),
                reason: e.into(),
            },
        )?;
        self.message = Some(format!("saved the overrides to {}", path.display()));
        Ok(())
    }

    /// The world the main model runs in: its checkpoint's, not the session's default (a
    /// `dead-legs` checkpoint runs in `dead-legs` whatever the session started with).
    fn main_world(&self) -> &GaitConfig {
        self.session
            .lanes()
            .first()
            .map_or(self.session.config(), |l| l.env().config())
    }

    /// The main lane's hand-made overrides of this episode as a scenario named `name`.
    fn recorded_scenario(&self, name: &str) -> Option<serde_json::Value> {
        let env = self.session.lanes().first()?.env();
        let fatigue = env.damage().fatigue_triggers().then(|| env.condition());
        Some(crate::damage::scenario::from_events(
            name,
            fatigue,
            env.damage().events(),
        ))
    }

    fn set_breakpoints(&mut self, list: Vec<Breakpoint>) -> Result<(), LiveError> {
        let Some(main) = self.session.lanes().first() else {
            return Ok(());
        };
        let has_probe = main.probe().is_some();
        for b in &list {
            b.validate(main.env().damage().joint_names(), has_probe)?;
        }
        self.breakpoints = list;
        Ok(())
    }

    /// Replaces a model; the old one stays if the new one does not load.
    fn load(&mut self, slot: Slot, dir: PathBuf) -> Result<(), LiveError> {
        let actor = Actor::load(&dir)?;
        let mut actors = self.session.take_actors();
        if slot == Slot::Main {
            // A model from a world that ends elsewhere brings its world's limit, unless the
            // limit had been moved off the old model's own (by hand or --max-steps).
            let own = |a: &Actor| a.trained_world().map(GaitConfig::run_step_limit);
            if let (Some(old), Some(new)) = (actors.first().and_then(own), own(&actor))
                && self.step_limit == old
            {
                self.step_limit = new;
            }
        }
        match slot {
            Slot::Main if actors.is_empty() => actors.push(actor),
            Slot::Main => actors[0] = actor,
            Slot::Compare => {
                self.compare_dir = Some(dir);
                self.compare_on = true;
                actors.truncate(1);
                actors.push(actor);
            }
        }
        self.rebuild(actors)
    }

    fn set_compare(&mut self, on: bool) -> Result<(), LiveError> {
        if on == self.compare_on {
            return Ok(());
        }
        let actors = if on {
            let second = match (self.spare.take(), &self.compare_dir) {
                (Some(actor), _) => actor,
                (None, Some(dir)) => Actor::load(dir)?,
                (None, None) => {
                    self.message = Some("pick a checkpoint to compare with first".into());
                    return Ok(());
                }
            };
            let mut actors = self.session.take_actors();
            actors.truncate(1);
            actors.push(second);
            actors
        } else {
            let mut actors = self.session.take_actors();
            if actors.len() > 1 {
                self.spare = actors.pop();
            }
            actors
        };
        self.compare_on = on;
        self.rebuild(actors)
    }

    fn rebuild(&mut self, actors: Vec<Actor>) -> Result<(), LiveError> {
        let mut actors = actors.into_iter();
        let Some(main) = actors.next() else {
            return Ok(());
        };
        self.session
            .replace_lanes(live_specs(main, actors.next()))?;
        self.session.set_action_mode(self.mode);
        self.new_episode()
    }

    fn snapshot(&self) -> Snapshot {
        let lanes: Vec<LaneView> = self.session.lanes().iter().map(LaneView::of).collect();
        let world = self.main_world();
        Snapshot {
            paused: self.paused,
            speed: self.speed,
            condition: self.condition,
            seed: self.seed,
            step_limit: self.step_limit,
            world: world.world.to_string(),
            condition_meanings: LiveCondition::ALL.map(|c| c.meaning(&world.damage)),
            mode: self.mode,
            compare: self.compare_on,
            compare_checkpoint: self.compare_dir.clone(),
            episode_seed: self.session.seed(),
            episodes: self.session.episodes_started(),
            global_step: self.session.global_step(),
            lanes,
            steps_per_s: self.recent.len() as f64,
            target_steps_per_s: self.target_rate(),
            message: self.message.clone(),
            breakpoints: self.breakpoints.clone(),
            break_hit: self.break_hit.clone(),
            rewindable: self.session.rewindable(),
            branches: self.session.branches(),
            scenario: self
                .session
                .config()
                .damage
                .scenario
                .as_ref()
                .map(|s| s.name.clone()),
            has_probe: self
                .session
                .lanes()
                .first()
                .is_some_and(|l| l.probe().is_some()),
            recorded_scenario: self.recorded_scenario("live-session"),
            saved_state: self
                .session
                .lanes()
                .first()
                .map(|l| Arc::new(l.save_state(self.session.seed()))),
            attribution: self.session.attribution(),
            commands_handled: self.commands_handled,
            last_command_at: self.last_command_at,
            stopped: false,
        }
    }
}
