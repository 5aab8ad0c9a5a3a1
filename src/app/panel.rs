//! The control panel: a small egui window that sends [`Command`]s and shows the latest
//! [`Snapshot`]. It never touches the simulation directly.

use std::path::PathBuf;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use eframe::egui::{self, Color32, RichText};

use super::breakpoint::{Breakpoint, format_list};
use super::{Command, LiveCondition, MAX_SPEED, MIN_SPEED, PanelStats, SimHandle, Slot, Snapshot};
use crate::damage::Edit;
use crate::damage::{JointOverride, JointState, N_ACTUATORS};
use crate::palette::Torque;
use crate::policy::ActionMode;

/// The fatigue bar spans 0 … 1.5 τ so the threshold sits at two thirds, with room to overshoot.
const BAR_SPAN: f64 = 1.5;
/// The panel polls the snapshot this often (it repaints only then, or on input).
const REPAINT_EVERY: Duration = Duration::from_millis(33);

/// The panel's side of the simulation: a command sender and a way to read the snapshot.
#[derive(Clone)]
pub struct SimLink {
    tx: Sender<Command>,
    read: Arc<dyn Fn() -> Snapshot + Send + Sync>,
}

impl SimLink {
    pub fn new(tx: Sender<Command>, read: impl Fn() -> Snapshot + Send + Sync + 'static) -> Self {
        Self {
            tx,
            read: Arc::new(read),
        }
    }
}

impl SimHandle {
    /// A link for the panel (the handle stays with the caller, who shuts the thread down).
    pub fn link(&self) -> SimLink {
        let snapshot = self.shared_snapshot();
        SimLink::new(self.sender(), move || {
            snapshot.lock().unwrap_or_else(|p| p.into_inner()).clone()
        })
    }
}

/// The control panel's state: what the person is editing, plus the latest snapshot.
pub struct Panel {
    link: SimLink,
    view: Snapshot,
    /// Checkpoint folders offered in the pickers.
    checkpoints: Vec<PathBuf>,
    /// The "any folder" field.
    folder: String,
    /// Set when the sim thread is gone (commands can no longer be delivered).
    disconnected: bool,
    /// The "break on" list field (the `--break-on` syntax) and its parse error.
    break_text: String,
    break_error: Option<String>,
    /// The step to rewind to.
    rewind_to: usize,
    /// The fork's edits field (the `--fork` syntax) and its parse error.
    fork_text: String,
    fork_error: Option<String>,
    /// The scenario field (a built-in name or a file) and the save path.
    scenario_text: String,
    save_text: String,
    scenario_error: Option<String>,
    /// Where "Save state" writes.
    state_text: String,
    /// The push row: body, force (N, world frame), steps, and why the last push was refused.
    push_body: String,
    push_force: [f64; 3],
    push_steps: usize,
    push_error: Option<String>,
    /// A `gaitscope search` folder: its field, the held-out episodes its findings broke, the
    /// one shown last, and why the folder could not be read.
    search_text: String,
    failures: Vec<Failure>,
    failure_at: Option<usize>,
    search_error: Option<String>,
}

/// One held-out episode a search finding broke: replayed from a reset with its scenario and
/// seed ("Next failure", as on the web page).
struct Failure {
    name: String,
    description: String,
    scenario: crate::damage::scenario::Scenario,
    seed: u64,
}

impl Panel {
    pub fn new(link: SimLink, checkpoints: Vec<PathBuf>) -> Self {
        let view: Snapshot = (link.read)();
        let break_text = format_list(&view.breakpoints);
        Self {
            link,
            view,
            checkpoints,
            folder: String::new(),
            disconnected: false,
            break_text,
            break_error: None,
            rewind_to: 0,
            fork_text: "heal:all".into(),
            fork_error: None,
            scenario_text: String::new(),
            save_text: "scenarios/saved.json".into(),
            scenario_error: None,
            state_text: "saved-state.json".into(),
            push_body: "torso".into(),
            push_force: [0.0, 40.0, 0.0],
            push_steps: 5,
            push_error: None,
            search_text: String::new(),
            failures: Vec::new(),
            failure_at: None,
            search_error: None,
        }
    }

    /// The panel with a search folder's findings loaded (`live --search DIR`).
    pub fn with_findings(mut self, findings: Vec<crate::search::Finding>) -> Self {
        self.set_findings(findings);
        self
    }

    fn set_findings(&mut self, findings: Vec<crate::search::Finding>) {
        self.failures.clear();
        self.failure_at = None;
        self.search_error = None;
        for f in findings {
            // The search wrote these files itself; one that does not parse is said, not skipped.
            let scenario = match crate::damage::scenario::Scenario::from_json(
                &f.scenario,
                &format!("search-{}", f.name),
            ) {
                Ok(s) => s,
                Err(e) => {
                    self.search_error = Some(e.to_string());
                    continue;
                }
            };
            for &seed in &f.failing_seeds {
                self.failures.push(Failure {
                    name: f.name.clone(),
                    description: f.description.clone(),
                    scenario: scenario.clone(),
                    seed,
                });
            }
        }
    }

    /// The next failing episode from a reset: its scenario, its seed.
    fn next_failure(&mut self) {
        if self.failures.is_empty() {
            return;
        }
        let at = self.failure_at.map_or(0, |i| (i + 1) % self.failures.len());
        self.failure_at = Some(at);
        let (scenario, seed) = (self.failures[at].scenario.clone(), self.failures[at].seed);
        self.send(Command::SetScenario(Some(scenario)));
        self.send(Command::SetSeed(seed));
        self.send(Command::Reset);
    }

    fn search_rows(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            let label = ui.label("Search folder").id;
            ui.add(
                egui::TextEdit::singleline(&mut self.search_text)
                    .hint_text("a gaitscope search --out folder")
                    .desired_width(150.0),
            )
            .labelled_by(label);
            if ui.button("Load findings").clicked() {
                match crate::search::findings(std::path::Path::new(self.search_text.trim())) {
                    Ok(findings) => self.set_findings(findings),
                    Err(e) => self.search_error = Some(e.to_string()),
                }
            }
        });
        if self.failures.is_empty() {
            return;
        }
        ui.horizontal(|ui| {
            if ui
                .button("Next failure")
                .on_hover_text(
                    "the next held-out episode a search finding broke: its scenario and seed, \
                     from a reset",
                )
                .clicked()
            {
                self.next_failure();
            }
            let text = match self.failure_at {
                Some(i) => {
                    let f = &self.failures[i];
                    format!(
                        "{} of {}: {}, seed {} — {}",
                        i + 1,
                        self.failures.len(),
                        f.name,
                        f.seed,
                        f.description
                    )
                }
                None => format!(
                    "{} failing episodes in the search's findings",
                    self.failures.len()
                ),
            };
            ui.label(text);
        });
    }

    /// The snapshot the panel last drew.
    pub fn view(&self) -> &Snapshot {
        &self.view
    }

    fn send(&mut self, command: Command) {
        if self.link.tx.send(command).is_err() {
            self.disconnected = true;
        }
    }

    /// Draws the whole panel (also what the headless tests drive).
    pub fn ui(&mut self, ui: &mut egui::Ui) {
        self.view = (self.link.read)();
        if ui.input(|i| i.key_pressed(egui::Key::Space)) {
            let c = if self.view.paused {
                Command::Resume
            } else {
                Command::Pause
            };
            self.send(c);
        }
        self.status_line(ui);
        ui.separator();
        self.policy_section(ui);
        ui.separator();
        self.episode_section(ui);
        ui.separator();
        self.joints_section(ui);
        ui.separator();
        self.debugger_section(ui);
        ui.separator();
        self.readouts(ui);
        if let Some(message) = &self.view.message {
            ui.colored_label(Color32::from_rgb(230, 90, 60), message);
        }
        if self.disconnected || self.view.stopped {
            ui.colored_label(Color32::RED, "the simulation has stopped");
        }
    }

    fn status_line(&self, ui: &mut egui::Ui) {
        let v = &self.view;
        ui.horizontal(|ui| {
            ui.heading("gaitscope live");
            let state = if v.paused { "paused" } else { "running" };
            ui.label(format!(
                "{state} · {:.0} / {:.0} steps/s",
                v.steps_per_s, v.target_steps_per_s
            ));
        });
    }

    fn policy_section(&mut self, ui: &mut egui::Ui) {
        let main = self.view.lanes.first().and_then(|l| l.checkpoint.clone());
        ui.horizontal(|ui| {
            let label = ui.label("Model").id;
            if let Some(dir) = self.pick_checkpoint(ui, "model", label, main.as_ref()) {
                self.send(Command::Load {
                    slot: Slot::Main,
                    dir,
                });
            }
        });
        ui.horizontal(|ui| {
            ui.label("Folder");
            ui.add(
                egui::TextEdit::singleline(&mut self.folder)
                    .hint_text("any checkpoint folder")
                    .desired_width(200.0),
            );
            let folder = PathBuf::from(self.folder.trim());
            if ui.button("Load").clicked() && !self.folder.trim().is_empty() {
                self.send(Command::Load {
                    slot: Slot::Main,
                    dir: folder.clone(),
                });
            }
            if ui.button("Compare").clicked() && !self.folder.trim().is_empty() {
                self.send(Command::Load {
                    slot: Slot::Compare,
                    dir: folder,
                });
            }
        });
        ui.horizontal(|ui| {
            ui.label("Actions");
            let mut mode = self.view.mode;
            ui.radio_value(&mut mode, ActionMode::Deterministic, "deterministic");
            ui.radio_value(&mut mode, ActionMode::Sampled, "sampled");
            if mode != self.view.mode {
                self.send(Command::SetActionMode(mode));
            }
        });
        ui.horizontal(|ui| {
            let mut compare = self.view.compare;
            let check = ui.checkbox(&mut compare, "Side by side with");
            if check.changed() {
                self.send(Command::SetCompare(compare));
            }
            let current = self.view.compare_checkpoint.clone();
            if let Some(dir) = self.pick_checkpoint(ui, "compare", check.id, current.as_ref()) {
                self.send(Command::Load {
                    slot: Slot::Compare,
                    dir,
                });
            }
        });
    }

    /// A combo box of the known checkpoints (named by the widget `label`, for screen readers);
    /// returns a newly picked one.
    fn pick_checkpoint(
        &self,
        ui: &mut egui::Ui,
        id: &str,
        label: egui::Id,
        current: Option<&PathBuf>,
    ) -> Option<PathBuf> {
        let name = |p: &PathBuf| crate::eval::model_label(p);
        let mut picked = None;
        egui::ComboBox::from_id_salt(id)
            .selected_text(current.map_or_else(|| "none".to_string(), name))
            .width(200.0)
            .show_ui(ui, |ui| {
                for dir in &self.checkpoints {
                    let selected = current == Some(dir);
                    if ui.selectable_label(selected, name(dir)).clicked() && !selected {
                        picked = Some(dir.clone());
                    }
                }
            })
            .response
            .labelled_by(label);
        picked
    }

    fn episode_section(&mut self, ui: &mut egui::Ui) {
        let v = self.view.clone();
        ui.horizontal(|ui| {
            let label = ui.label("Condition").id;
            let mut condition = v.condition;
            egui::ComboBox::from_id_salt("condition")
                .selected_text(condition.name())
                .show_ui(ui, |ui| {
                    for (c, meaning) in LiveCondition::ALL.into_iter().zip(&v.condition_meanings) {
                        ui.selectable_value(&mut condition, c, c.name())
                            .on_hover_text(meaning);
                    }
                })
                .response
                .labelled_by(label);
            if condition != v.condition {
                self.send(Command::SetCondition(condition));
            }
            let label = ui.label("Seed").id;
            let mut seed = v.seed;
            if ui
                .add(egui::DragValue::new(&mut seed))
                .labelled_by(label)
                .changed()
            {
                self.send(Command::SetSeed(seed));
            }
            let label = ui.label("Step limit").id;
            let mut limit = v.step_limit;
            if ui
                .add(egui::DragValue::new(&mut limit).range(1..=100_000))
                .labelled_by(label)
                .changed()
            {
                self.send(Command::SetStepLimit(limit));
            }
        });
        // What the chosen condition does in the main model's world (a `dead-legs` "severe" is
        // two dead legs, the paper's a 0.1× fatigue trigger).
        if let Some(meaning) = LiveCondition::ALL
            .iter()
            .position(|&c| c == v.condition)
            .map(|i| &v.condition_meanings[i])
        {
            ui.weak(format!("world {}: {} = {meaning}", v.world, v.condition));
        }
        ui.horizontal(|ui| {
            if ui.button("Reset").clicked() {
                self.send(Command::Reset);
            }
            let (label, command) = if v.paused {
                ("Resume", Command::Resume)
            } else {
                ("Pause", Command::Pause)
            };
            if ui.button(label).clicked() {
                self.send(command);
            }
            if ui
                .add_enabled(v.paused, egui::Button::new("Step"))
                .clicked()
            {
                self.send(Command::StepOnce);
            }
            let label = ui.label("Speed").id;
            let mut speed = v.speed;
            let slider = egui::Slider::new(&mut speed, MIN_SPEED..=MAX_SPEED)
                .logarithmic(true)
                .suffix("×")
                .max_decimals(2);
            if ui.add(slider).labelled_by(label).changed() {
                self.send(Command::SetSpeed(speed));
            }
        });
        ui.horizontal(|ui| {
            ui.label("Scenario");
            ui.add(
                egui::TextEdit::singleline(&mut self.scenario_text)
                    .hint_text("ood-leg or a .json file")
                    .desired_width(150.0),
            );
            if ui.button("Use").clicked() {
                match crate::damage::scenario::Scenario::load(self.scenario_text.trim()) {
                    Ok(scenario) => {
                        self.scenario_error = None;
                        self.send(Command::SetScenario(Some(scenario)));
                    }
                    Err(e) => self.scenario_error = Some(e.to_string()),
                }
            }
            if ui
                .add_enabled(v.scenario.is_some(), egui::Button::new("No scenario"))
                .clicked()
            {
                self.send(Command::SetScenario(None));
            }
            ui.label(v.scenario.as_deref().unwrap_or("none"));
        });
        ui.horizontal(|ui| {
            let label = ui.label("Save overrides to").id;
            ui.add(egui::TextEdit::singleline(&mut self.save_text).desired_width(150.0))
                .labelled_by(label);
            if ui
                .button("Save")
                .on_hover_text("this episode's hand-made overrides as a scenario file (re-run with rollout --scenario)")
                .clicked()
            {
                self.send(Command::SaveScenario(PathBuf::from(self.save_text.trim())));
            }
        });
        ui.horizontal(|ui| {
            let label = ui.label("Save state to").id;
            ui.add(egui::TextEdit::singleline(&mut self.state_text).desired_width(150.0))
                .labelled_by(label);
            if ui
                .button("Save state")
                .on_hover_text(
                    "the main model's state before its next step: physics, damage, window, and an \
                     MJCF <key> (start from it with --init-state)",
                )
                .clicked()
            {
                self.send(Command::SaveState(PathBuf::from(self.state_text.trim())));
            }
        });
        self.search_rows(ui);
        for e in [&self.scenario_error, &self.search_error]
            .into_iter()
            .flatten()
        {
            ui.colored_label(Color32::from_rgb(230, 90, 60), e);
        }
        ui.label(
            RichText::new("Condition, seed, step limit and scenario apply at the next reset.")
                .small()
                .weak(),
        );
    }

    fn joints_section(&mut self, ui: &mut egui::Ui) {
        let Some(lane) = self.view.lanes.first().cloned() else {
            ui.label("no model loaded");
            return;
        };
        // Fatigue still accumulates where it triggers nothing (a world of dead actuators,
        // manual): then the bars are grey and the heading says so, not a threshold to fear.
        let heading = if lane.fatigue_triggers {
            format!(
                "Joints of {} — fatigue, τ = {:.0}",
                lane.label, lane.threshold
            )
        } else {
            format!("Joints of {} — fatigue triggers nothing here", lane.label)
        };
        ui.label(RichText::new(heading).strong());
        egui::Grid::new("joints")
            .num_columns(6)
            .spacing([6.0, 4.0])
            .striped(true)
            .show(ui, |ui| {
                ui.spacing_mut().slider_width = 80.0;
                for i in 0..N_ACTUATORS {
                    let name = ui
                        .label(&lane.joint_names[i])
                        .on_hover_text(&lane.joint_legs[i])
                        .id;
                    fatigue_bar(ui, lane.fatigue[i], lane.threshold, lane.fatigue_triggers);
                    let (text, color) =
                        state_text(lane.scale[i], lane.states[i], lane.causes[i].as_deref());
                    ui.colored_label(color, text);
                    let mut scale = lane.scale[i];
                    let slider = egui::Slider::new(&mut scale, 0.0..=1.0)
                        .max_decimals(2)
                        .show_value(true);
                    if ui.add(slider).labelled_by(name).changed() {
                        self.send(Command::Override {
                            actuator: i,
                            change: JointOverride::SetScale(scale),
                        });
                    }
                    if ui.button("fail now").clicked() {
                        self.send(Command::Override {
                            actuator: i,
                            change: JointOverride::FailNow,
                        });
                    }
                    if ui.button("heal").clicked() {
                        self.send(Command::Override {
                            actuator: i,
                            change: JointOverride::Heal,
                        });
                    }
                    ui.end_row();
                }
            });
        self.push_row(ui, &lane.body_names);
    }

    /// Push a body of every model: an external force for a few steps (`push:BODY=F@N`).
    fn push_row(&mut self, ui: &mut egui::Ui, bodies: &[String]) {
        ui.horizontal(|ui| {
            egui::ComboBox::from_id_salt("push body")
                .selected_text(&self.push_body)
                .width(110.0)
                .show_ui(ui, |ui| {
                    for b in bodies {
                        ui.selectable_value(&mut self.push_body, b.clone(), b);
                    }
                })
                .response
                .accessible_name("push body");
            for (axis, f) in ["x", "y", "z"].iter().zip(&mut self.push_force) {
                ui.add(
                    egui::DragValue::new(f)
                        .prefix(format!("{axis} "))
                        .suffix(" N")
                        .speed(1.0)
                        .range(-crate::damage::MAX_PUSH_NEWTONS..=crate::damage::MAX_PUSH_NEWTONS),
                )
                .accessible_name(format!("push force {axis} (N)"));
            }
            ui.add(
                egui::DragValue::new(&mut self.push_steps)
                    .range(1..=crate::damage::MAX_PUSH_STEPS)
                    .suffix(" steps"),
            )
            .accessible_name("push steps");
            if ui
                .button("Push")
                .on_hover_text("an external force on the body's centre of mass, world frame")
                .clicked()
            {
                match crate::damage::Push::new(&self.push_body, self.push_force, self.push_steps) {
                    Ok(push) => {
                        self.push_error = None;
                        self.send(Command::Push(push));
                    }
                    Err(e) => self.push_error = Some(e.to_string()),
                }
            }
        });
        if let Some(e) = &self.push_error {
            ui.colored_label(Color32::from_rgb(230, 90, 60), e);
        }
    }

    /// Breakpoints, time travel and forks.
    fn debugger_section(&mut self, ui: &mut egui::Ui) {
        let v = self.view.clone();
        ui.label(RichText::new("Break on").strong());
        ui.horizontal_wrapped(|ui| {
            let kinds = [
                (Breakpoint::Trigger(None), "trigger", true),
                (Breakpoint::Override, "override", true),
                (Breakpoint::Termination, "termination", true),
                (Breakpoint::Success, "success", true),
                (Breakpoint::ProbeFlip, "probe-flip", v.has_probe),
            ];
            for (kind, label, enabled) in kinds {
                let mut on = v.breakpoints.contains(&kind);
                let hint = if enabled {
                    "pause after the step where this happens"
                } else {
                    "needs a probe.json beside the checkpoint (gaitscope probe)"
                };
                if ui
                    .add_enabled(enabled, egui::Checkbox::new(&mut on, label))
                    .on_hover_text(hint)
                    .changed()
                {
                    let mut list: Vec<Breakpoint> = v
                        .breakpoints
                        .iter()
                        .filter(|b| **b != kind)
                        .cloned()
                        .collect();
                    if on {
                        list.push(kind);
                    }
                    self.break_text = format_list(&list);
                    self.send(Command::SetBreakpoints(list));
                }
            }
        });
        ui.horizontal(|ui| {
            ui.label("list");
            let field = ui.add(
                egui::TextEdit::singleline(&mut self.break_text)
                    .hint_text("trigger:ankle_3,step:120")
                    .desired_width(200.0),
            );
            let apply = ui.button("Set").clicked()
                || (field.lost_focus() && ui.input(|i| i.key_pressed(egui::Key::Enter)));
            if apply {
                match Breakpoint::parse_list(&self.break_text) {
                    Ok(list) => {
                        self.break_error = None;
                        self.send(Command::SetBreakpoints(list));
                    }
                    Err(e) => self.break_error = Some(e.to_string()),
                }
            }
        });
        if let Some(e) = &self.break_error {
            ui.colored_label(Color32::from_rgb(230, 90, 60), e);
        }
        if let Some(hit) = &v.break_hit {
            ui.colored_label(Color32::from_rgb(240, 180, 40), format!("⏸ {hit}"));
        }
        let mut attribution = v.attribution;
        if ui
            .checkbox(&mut attribution, "Why z moved (attribution)")
            .on_hover_text(
                "integrated gradients of ‖z − z(0)‖ over the window, every step: a window slot × \
                 joint heatmap and per-group series in the viewer (encoder models)",
            )
            .changed()
        {
            self.send(Command::SetAttribution(attribution));
        }

        ui.label(RichText::new("Time travel and forks").strong());
        ui.horizontal(|ui| {
            let label = ui.label("rewind to step").id;
            self.rewind_to = self.rewind_to.min(v.rewindable);
            ui.add_enabled(
                v.rewindable > 0,
                egui::Slider::new(&mut self.rewind_to, 0..=v.rewindable.max(1)),
            )
            .labelled_by(label);
            if ui
                .add_enabled(v.rewindable > 0, egui::Button::new("Rewind"))
                .on_hover_text("go back to that step and continue from there (a new branch)")
                .clicked()
            {
                self.send(Command::Rewind(self.rewind_to));
            }
        });
        ui.horizontal(|ui| {
            ui.label("fork with");
            ui.add(
                egui::TextEdit::singleline(&mut self.fork_text)
                    .hint_text("heal:all, fail:ankle_3, scale:hip_1=0.5")
                    .desired_width(160.0),
            );
            if ui
                .button("Fork here")
                .on_hover_text(
                    "a second lane of this model from the identical state, with these edits",
                )
                .clicked()
            {
                match Edit::parse_list(&self.fork_text) {
                    Ok(edits) => {
                        self.fork_error = None;
                        self.send(Command::Fork(edits));
                    }
                    Err(e) => self.fork_error = Some(e.to_string()),
                }
            }
            let forked = v.lanes.iter().any(|l| l.fork_of.is_some());
            if ui
                .add_enabled(forked, egui::Button::new("End fork"))
                .clicked()
            {
                self.send(Command::EndFork);
            }
        });
        if let Some(e) = &self.fork_error {
            ui.colored_label(Color32::from_rgb(230, 90, 60), e);
        }
        let branch = if v.branches > 0 {
            format!(" · branch {}", v.branches)
        } else {
            String::new()
        };
        ui.label(
            RichText::new(format!(
                "{} steps of this episode kept for rewinding{branch}",
                v.rewindable
            ))
            .small()
            .weak(),
        );
    }

    fn readouts(&self, ui: &mut egui::Ui) {
        let v = &self.view;
        for lane in &v.lanes {
            // Joints that have lost torque (a trigger that took nothing is not damage).
            let triggered: Vec<&str> = (0..N_ACTUATORS)
                .filter(|&i| Torque::of(lane.scale[i], lane.states[i]).lost())
                .map(|i| lane.joint_names[i].as_str())
                .collect();
            let title = match &lane.fork_of {
                Some(of) => of.clone(),
                None => format!("{} ({})", lane.label, lane.encoder),
            };
            ui.label(RichText::new(title).strong());
            if let Some(ending) = lane.ending {
                let color = if ending == "success" {
                    egui::Color32::from_rgb(40, 160, 60)
                } else {
                    egui::Color32::from_rgb(220, 40, 40)
                };
                ui.label(
                    RichText::new(format!("episode ended: {ending} after {} steps", lane.step))
                        .color(color)
                        .strong(),
                );
            }
            ui.label(format!(
                "step {} / {} · goal distance {:.2} m · success {} · damaged joints {}{}",
                lane.step,
                v.step_limit,
                lane.distance,
                if lane.success { "yes" } else { "no" },
                triggered.len(),
                if triggered.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", triggered.join(", "))
                }
            ));
            if let Some(p) = &lane.probe {
                ui.horizontal_wrapped(|ui| {
                    ui.label("probe on z, P(damaged):");
                    let joints = p.iter().zip(&lane.damaged).zip(&lane.joint_names);
                    for ((&prob, &damaged), name) in joints {
                        let says = prob >= 0.5;
                        let color = if says == damaged {
                            Color32::from_rgb(80, 170, 90)
                        } else {
                            Color32::from_rgb(220, 80, 60)
                        };
                        // Plain words: egui's bundled fonts have no ■/□ (they drew empty boxes).
                        let mark = if damaged { " lost" } else { " ok" };
                        let word = |d: bool| if d { "damaged" } else { "healthy" };
                        ui.colored_label(color, format!("{} {prob:.2}{mark}", short_name(name)))
                            .on_hover_text(format!(
                                "{name}: z says {} (p = {prob:.2}); truth: {}",
                                word(says),
                                word(damaged)
                            ));
                    }
                });
            }
            if let Some(e) = &lane.last_event {
                // egui's bundled fonts have no "→".
                let e = &e.replace('→', "->");
                ui.label(RichText::new(format!("last event: {e}")).weak());
            }
        }
        ui.label(
            RichText::new(format!(
                "episode {} · seed {} · recording step {}",
                v.episodes, v.episode_seed, v.global_step
            ))
            .weak(),
        );
    }
}

fn short_name(joint: &str) -> String {
    joint.replace("hip_", "h").replace("ankle_", "a")
}

/// A joint's torque in words and in the colour its leg has in every view (palette): what it
/// has lost, and who took it (a fatigue trigger, the world, a hand).
fn state_text(scale: f64, state: JointState, cause: Option<&str>) -> (String, Color32) {
    let torque = Torque::of(scale, state);
    let mut text = torque.describe();
    match (cause, torque.lost()) {
        (Some(cause), true) => text += &format!(" ({cause})"),
        (Some(cause), false) if state == JointState::Triggered => {
            text += &format!(" ({cause}, nothing lost)")
        }
        _ => {}
    }
    let [r, g, b] = torque.rgb();
    (text, Color32::from_rgb(r, g, b))
}

/// Fatigue as a bar over 0 … 1.5 τ, with the threshold marked: green, amber from 0.8 τ (the
/// torque column beside it says what the joint has lost); grey where it triggers nothing.
fn fatigue_bar(ui: &mut egui::Ui, fatigue: f64, threshold: f64, triggers: bool) {
    let size = egui::vec2(96.0, ui.spacing().interact_size.y * 0.8);
    let (rect, response) = ui.allocate_exact_size(size, egui::Sense::hover());
    let span = (threshold * BAR_SPAN).max(f64::EPSILON);
    let frac = (fatigue / span).clamp(0.0, 1.0) as f32;
    let painter = ui.painter();
    painter.rect_filled(rect, 2.0, ui.visuals().extreme_bg_color);
    let fill = if !triggers {
        Color32::from_gray(120)
    } else if fatigue < threshold * 0.8 {
        Color32::from_rgb(90, 160, 90)
    } else {
        Color32::from_rgb(230, 170, 40)
    };
    let mut filled = rect;
    filled.set_width(rect.width() * frac);
    painter.rect_filled(filled, 2.0, fill);
    let x = rect.left() + rect.width() * (1.0 / BAR_SPAN) as f32;
    painter.line_segment(
        [egui::pos2(x, rect.top()), egui::pos2(x, rect.bottom())],
        egui::Stroke::new(2.0, ui.visuals().strong_text_color()),
    );
    painter.text(
        rect.left_center() + egui::vec2(4.0, 0.0),
        egui::Align2::LEFT_CENTER,
        format!("{fatigue:.1}"),
        egui::FontId::monospace(11.0),
        ui.visuals().strong_text_color(),
    );
    response.on_hover_text(if triggers {
        format!("fatigue {fatigue:.2}; the joint triggers at τ = {threshold:.1} (the mark)")
    } else {
        format!("fatigue {fatigue:.2}; it triggers nothing in this episode (τ = {threshold:.1})")
    });
}

/// How the panel window opens.
pub struct PanelOptions {
    pub checkpoints: Vec<PathBuf>,
    /// A search folder's findings, for "Next failure" (`live --search DIR`).
    pub findings: Vec<crate::search::Finding>,
    /// Close after this long (scripted runs and measurements).
    pub exit_after: Option<Duration>,
}

/// The panel window's size (logical points).
const PANEL_SIZE: [f32; 2] = [520.0, 1000.0];

/// Where the panel goes on a monitor of `monitor` points: its top-right corner, wholly on
/// screen (a fixed x once put it half off a 1600-point screen), the left of the screen for the
/// viewer.
fn panel_position(monitor: egui::Vec2) -> egui::Pos2 {
    egui::pos2((monitor.x - PANEL_SIZE[0]).max(0.0), 0.0)
}

struct LiveApp {
    panel: Panel,
    /// Moved to its place once the monitor's size is known (the first frames).
    placed: bool,
    started: Instant,
    exit_after: Option<Duration>,
    cpu_total: f64,
    stats: Arc<Mutex<PanelStats>>,
}

impl eframe::App for LiveApp {
    fn ui(&mut self, ui: &mut egui::Ui, frame: &mut eframe::Frame) {
        let elapsed = self.started.elapsed();
        {
            let mut stats = self.stats.lock().unwrap_or_else(|p| p.into_inner());
            stats.frames += 1;
            stats.seconds = elapsed.as_secs_f64();
            self.cpu_total += f64::from(frame.info().cpu_usage.unwrap_or(0.0));
            stats.mean_frame_cpu_ms = 1000.0 * self.cpu_total / stats.frames as f64;
        }
        if !self.placed
            && let Some(monitor) = ui.ctx().input(|i| i.viewport().monitor_size)
        {
            let at = panel_position(monitor);
            ui.ctx()
                .send_viewport_cmd(egui::ViewportCommand::OuterPosition(at));
            self.placed = true;
        }
        egui::CentralPanel::default().show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| self.panel.ui(ui));
        });
        if self.exit_after.is_some_and(|limit| elapsed >= limit) {
            ui.ctx().send_viewport_cmd(egui::ViewportCommand::Close);
        }
        ui.ctx().request_repaint_after(REPAINT_EVERY);
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PanelError {
    #[error(
        "could not open the control panel window: {0}. Is the display reachable (DISPLAY / \
         WAYLAND_DISPLAY)? Headless, use `gaitscope record` instead"
    )]
    // eframe's error holds window-system handles that are neither Send nor Sync: its text is
    // all that can travel with the error.
    Window(String),
}

/// Opens the panel window and runs it until it is closed; returns its frame statistics.
pub fn run_panel(link: SimLink, options: PanelOptions) -> Result<PanelStats, PanelError> {
    let stats = Arc::new(Mutex::new(PanelStats::default()));
    let native = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_title("gaitscope — live")
            .with_inner_size(PANEL_SIZE),
        ..Default::default()
    };
    let app_stats = stats.clone();
    let panel = Panel::new(link, options.checkpoints).with_findings(options.findings);
    eframe::run_native(
        "gaitscope live",
        native,
        Box::new(move |_cc| {
            Ok(Box::new(LiveApp {
                panel,
                placed: false,
                started: Instant::now(),
                exit_after: options.exit_after,
                cpu_total: 0.0,
                stats: app_stats,
            }))
        }),
    )
    .map_err(|e| PanelError::Window(e.to_string()))?;
    let stats = stats.lock().unwrap_or_else(|p| p.into_inner()).clone();
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::{PANEL_SIZE, egui, panel_position};

    #[test]
    fn the_panel_sits_wholly_on_screen_at_the_top_right() {
        // 1600 points wide: x = 1600 − 520 = 1080, its right edge on the screen's.
        assert_eq!(
            panel_position(egui::vec2(1600.0, 1000.0)),
            egui::pos2(1080.0, 0.0)
        );
        assert_eq!(
            panel_position(egui::vec2(1920.0, 1080.0)).x + PANEL_SIZE[0],
            1920.0
        );
        // Narrower than the panel: its left edge stays on screen.
        assert_eq!(
            panel_position(egui::vec2(400.0, 300.0)),
            egui::pos2(0.0, 0.0)
        );
    }
}
