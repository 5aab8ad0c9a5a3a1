//! The live viewer without a display: the simulation thread driven by scripted commands, the
//! recorded stream read back, and the egui panel clicked through its AccessKit tree.

use candle_core::Device;
use gaitscope::GaitConfig;
use gaitscope::app::{
    Command, LIVE_ROOTS, LiveCondition, LiveError, LiveSetup, SimHandle, Snapshot,
};
use gaitscope::damage::{JointOverride, JointState};
use gaitscope::policy::checkpoint::TrainingRecord;
use gaitscope::policy::{ActionMode, EncoderKind, NetConfig, SacConfig, SacModel};
use gaitscope::telemetry::{Sink, TelemetryError, open};
use std::path::Path;
use std::time::Duration;

mod common;

const WAIT: Duration = Duration::from_secs(20);

/// A small untrained LSTM-encoder checkpoint: the loop's behaviour does not depend on skill.
fn checkpoint(dir: &Path) {
    checkpoint_in(dir, GaitConfig::default());
}

/// [`checkpoint`], trained in `world`.
fn checkpoint_in(dir: &Path, world: GaitConfig) {
    let net = NetConfig {
        hidden: vec![16, 16],
        z_dim: 4,
        ..NetConfig::ant(EncoderKind::Lstm)
    };
    let model = SacModel::new(net, 1.0, 7, &Device::Cpu).unwrap();
    let record = TrainingRecord {
        env: world,
        sac: SacConfig::default(),
        seed: 7,
        steps_done: 0,
        episodes_done: 0,
        wall_time_s: 0.0,
        imported_from: None,
    };
    model.save(dir, &record).unwrap();
}

fn setup(dir: &Path, condition: LiveCondition) -> LiveSetup {
    LiveSetup {
        checkpoint: dir.to_path_buf(),
        compare: None,
        condition,
        seed: 3,
        speed: 8.0,
        step_limit: 200,
        mode: ActionMode::Deterministic,
        paused: true,
        breakpoints: Vec::new(),
        start: None,
        attribution: false,
        fork: None,
        config: GaitConfig::default(),
    }
}

/// Every lane's entity root, as the live command streams them.
fn live_roots() -> Vec<String> {
    LIVE_ROOTS.iter().map(|r| r.to_string()).collect()
}

fn memory_stream() -> (rerun::RecordingStream, rerun::sink::MemorySinkStorage) {
    let (rec, storage) = open(&Sink::Memory, "gaitscope-live-test", &live_roots()).unwrap();
    (rec, storage.unwrap())
}

/// A paused simulation thread on a fresh checkpoint, streaming to memory. Keep the folder alive.
fn started(
    condition: LiveCondition,
) -> (tempfile::TempDir, SimHandle, rerun::sink::MemorySinkStorage) {
    let dir = tempfile::tempdir().unwrap();
    checkpoint(dir.path());
    let (rec, storage) = memory_stream();
    let sim = SimHandle::spawn(rec, setup(dir.path(), condition)).unwrap();
    (dir, sim, storage)
}

/// A loopback port that was free a moment ago (bound, then released).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .unwrap()
        .port()
}

/// Sends one single-step command and waits until the simulation has taken it.
fn step_once(sim: &SimHandle) -> Snapshot {
    let before = sim.snapshot().global_step;
    assert!(sim.send(Command::StepOnce));
    let s = sim.wait_for(WAIT, |s| s.global_step == before + 1);
    assert_eq!(s.global_step, before + 1, "the step happened");
    s
}

#[test]
fn scripted_commands_reach_the_sim_at_the_next_step_and_the_stream() {
    // Manual: fatigue never triggers, so every scale change below is ours.
    let (_dir, sim, storage) = started(LiveCondition::Manual);
    let names = sim.snapshot().lanes[0].joint_names.clone();
    for _ in 0..5 {
        step_once(&sim);
    }
    // Before env step 5 (recorded at global step 6): joint 2 fails (manual → severe scale 0.1).
    sim.send(Command::Override {
        actuator: 2,
        change: JointOverride::FailNow,
    });
    let s = step_once(&sim);
    assert_eq!(s.lanes[0].states[2], JointState::Triggered);
    assert_eq!(s.lanes[0].applied[2], 0.1 * s.lanes[0].commanded[2]);
    for _ in 0..4 {
        step_once(&sim);
    }
    // Before env step 10: joint 5 pinned at 0.3 by hand.
    sim.send(Command::Override {
        actuator: 5,
        change: JointOverride::SetScale(0.3),
    });
    let s = step_once(&sim);
    assert_eq!(s.lanes[0].states[5], JointState::Manual);
    assert_eq!(s.lanes[0].applied[5], 0.3 * s.lanes[0].commanded[5]);
    // A state saved now calls the session what it is: manual (severe's thresholds underneath).
    let saved = s.saved_state.as_ref().expect("a model is loaded");
    assert_eq!(saved.condition.as_deref(), Some("manual"));
    assert_eq!(saved.env.damage.condition.name(), "severe");
    assert!(!saved.env.damage.fatigue_triggers);
    // Before env step 11: joint 2 healed.
    sim.send(Command::Override {
        actuator: 2,
        change: JointOverride::Heal,
    });
    let s = step_once(&sim);
    assert_eq!(s.lanes[0].states[2], JointState::Healthy);
    assert_eq!(s.lanes[0].applied[2], s.lanes[0].commanded[2]);
    // A bad value is refused with a message, and nothing changes.
    sim.send(Command::Override {
        actuator: 1,
        change: JointOverride::SetScale(1.5),
    });
    let s = sim.wait_for(WAIT, |s| s.message.is_some());
    assert!(
        s.message.as_deref().unwrap_or("").contains("[0, 1]"),
        "{:?}",
        s.message
    );
    let s = step_once(&sim);
    assert_eq!(s.global_step, 13);
    assert_eq!(s.lanes[0].scale[1], 1.0);
    sim.shutdown().unwrap();

    let chunks = common::recording_chunks(storage.take());
    let commanded = common::joint_series(&chunks, "/ant/actions/commanded");
    let applied = common::joint_series(&chunks, "/ant/actions/applied");
    assert_eq!(applied.len(), 13, "one row per env step");
    // Env step t is recorded at global step t + 1. Expected scale per (joint, env step):
    let expected = |joint: usize, t: i64| match joint {
        2 if (5..11).contains(&t) => 0.1,
        5 if t >= 10 => 0.3,
        _ => 1.0,
    };
    for t in 0..13i64 {
        for j in 0..8 {
            assert_eq!(
                applied[&(t + 1)][j],
                expected(j, t) * commanded[&(t + 1)][j],
                "joint {j} at env step {t}"
            );
        }
    }
    let events = common::text_log(&chunks, "/ant/events");
    let expect = [
        (
            6,
            format!("step 6: {} failed by hand; scale → 0.1", names[2]),
        ),
        (11, format!("step 11: {} scale → 0.3 (manual)", names[5])),
        (12, format!("step 12: {} healed; scale → 1", names[2])),
    ];
    assert_eq!(
        events,
        expect.map(|(t, s)| (t, s)).to_vec(),
        "exactly the three overrides, each text naming its row's step"
    );
}

#[test]
fn pause_speed_condition_and_reset_are_obeyed() {
    let (dir, sim, _storage) = started(LiveCondition::Severe);
    // Paused: nothing moves.
    std::thread::sleep(Duration::from_millis(200));
    assert_eq!(sim.snapshot().global_step, 0);
    // Speed is clamped to 0.25×…8×; running at 8× (160 steps/s) moves on its own.
    sim.send(Command::SetSpeed(100.0));
    sim.send(Command::Resume);
    let s = sim.wait_for(WAIT, |s| s.global_step >= 20);
    assert!(s.global_step >= 20 && !s.paused);
    assert_eq!(s.speed, 8.0);
    assert_eq!(s.target_steps_per_s, 160.0);
    sim.send(Command::Pause);
    let paused = sim.wait_for(WAIT, |s| s.paused);
    std::thread::sleep(Duration::from_millis(100));
    assert_eq!(
        sim.snapshot().global_step,
        paused.global_step,
        "paused stays put"
    );
    // Condition, seed and step limit apply at the reset.
    sim.send(Command::SetCondition(LiveCondition::Mild));
    sim.send(Command::SetSeed(42));
    sim.send(Command::SetStepLimit(3));
    sim.send(Command::Reset);
    let s = sim.wait_for(WAIT, |s| s.episode_seed == 42);
    assert_eq!((s.episodes, s.episode_seed), (2, 42));
    assert_eq!(s.lanes[0].step, 0);
    assert_eq!(s.condition, LiveCondition::Mild);
    sim.send(Command::Override {
        actuator: 0,
        change: JointOverride::FailNow,
    });
    let s = step_once(&sim);
    assert_eq!(s.lanes[0].applied[0], 0.5 * s.lanes[0].commanded[0], "mild");
    // The step limit of 3 ends the episode after 3 steps; a step then starts the next seed.
    step_once(&sim);
    let s = step_once(&sim);
    assert!(s.lanes[0].done && s.lanes[0].step == 3);
    sim.send(Command::StepOnce);
    let s = sim.wait_for(WAIT, |s| s.episode_seed == 43);
    assert_eq!(s.lanes[0].step, 0);
    // A missing checkpoint is a message, and the current model keeps running.
    sim.send(Command::Load {
        slot: gaitscope::app::Slot::Compare,
        dir: dir.path().join("nope"),
    });
    let s = sim.wait_for(WAIT, |s| s.message.is_some());
    assert!(!s.compare && s.lanes.len() == 1, "{:?}", s.message);
    // A real second model runs side by side under the same damage.
    sim.send(Command::Load {
        slot: gaitscope::app::Slot::Compare,
        dir: dir.path().to_path_buf(),
    });
    let s = sim.wait_for(WAIT, |s| s.lanes.len() == 2);
    assert!(s.compare && s.lanes[1].root == "compare");
    sim.send(Command::Override {
        actuator: 4,
        change: JointOverride::SetScale(0.2),
    });
    let s = step_once(&sim);
    for lane in &s.lanes {
        assert_eq!(lane.applied[4], 0.2 * lane.commanded[4], "{}", lane.root);
    }
    sim.send(Command::SetCompare(false));
    let s = sim.wait_for(WAIT, |s| s.lanes.len() == 1);
    assert!(!s.compare);
    sim.shutdown().unwrap();
}

/// A model loaded from a world that ends elsewhere brings that world's step limit, unless the
/// limit was moved off the old model's own.
#[test]
fn a_model_from_another_world_brings_its_step_limit() {
    let dir = tempfile::tempdir().unwrap();
    let (paper, short) = (dir.path().join("paper"), dir.path().join("short"));
    checkpoint(&paper);
    let mut world = GaitConfig::world("dead-legs").unwrap();
    world.env.max_episode_steps = 40;
    checkpoint_in(&short, world);
    let (rec, _storage) =
        gaitscope::telemetry::open(&gaitscope::telemetry::Sink::Memory, "limit", &live_roots())
            .unwrap();
    let sim = SimHandle::spawn(
        rec,
        LiveSetup {
            step_limit: 500,
            ..setup(&paper, LiveCondition::Severe)
        },
    )
    .unwrap();
    let load = |dir: &Path| {
        let episodes = sim.snapshot().episodes;
        sim.send(Command::Load {
            slot: gaitscope::app::Slot::Main,
            dir: dir.to_path_buf(),
        });
        sim.wait_for(WAIT, |s| s.episodes > episodes)
    };
    // The paper's own 500 → the short world's 40, and back.
    assert_eq!(load(&short).step_limit, 40);
    assert_eq!(load(&paper).step_limit, 500);
    // A limit set by hand stays.
    sim.send(Command::SetStepLimit(77));
    assert_eq!(load(&short).step_limit, 77);
    sim.shutdown().unwrap();
}

#[test]
fn bad_settings_are_refused_before_anything_starts() {
    let dir = tempfile::tempdir().unwrap();
    let missing = setup(&dir.path().join("absent"), LiveCondition::Severe);
    let e = missing.validate().unwrap_err().to_string();
    assert!(e.contains("absent"), "{e}");
    checkpoint(dir.path());
    let fast = LiveSetup {
        speed: 16.0,
        ..setup(dir.path(), LiveCondition::Severe)
    };
    assert!(
        fast.validate()
            .unwrap_err()
            .to_string()
            .contains("between 0.25× and 8×")
    );
    let none = LiveSetup {
        step_limit: 0,
        ..setup(dir.path(), LiveCondition::Severe)
    };
    assert!(none.validate().is_err());
    assert!(setup(dir.path(), LiveCondition::Severe).validate().is_ok());
}

/// A viewer that vanished (here: never listened) cannot take the last data; the session still
/// reports what it did, and the `--save` file has every step.
#[test]
fn a_vanished_viewer_still_yields_the_report_and_the_saved_file() {
    let dir = tempfile::tempdir().unwrap();
    checkpoint(dir.path());
    // Nothing listens on a free port.
    let port = free_port();
    let save = dir.path().join("session.rrd");
    let sink = Sink::Viewer {
        url: format!("rerun+http://127.0.0.1:{port}/proxy"),
        save: Some(save.clone()),
    };
    let (rec, _) = open(&sink, "gaitscope-live-unflushed", &live_roots()).unwrap();
    let sim = SimHandle::spawn(rec, setup(dir.path(), LiveCondition::Severe)).unwrap();
    for _ in 0..3 {
        step_once(&sim);
    }
    match sim.shutdown() {
        Err(LiveError::Unflushed { report, source }) => {
            assert_eq!(report.steps, 3, "the report survives the failed flush");
            assert_eq!(report.episodes, 1);
            // Which gives up first is a race of two 5 s clocks: the flush's timeout, or the gRPC
            // client's connect retries (an error naming the viewer's address).
            match &source {
                TelemetryError::FlushTimeout(_) => {
                    assert!(source.to_string().contains("viewer"), "{source}")
                }
                TelemetryError::Flush(cause) => {
                    // The sink's own error, kept as the source.
                    assert!(
                        cause.to_string().contains(&format!("127.0.0.1:{port}")),
                        "{cause}"
                    )
                }
                other => panic!("expected a failed flush, got {other:?}"),
            }
        }
        other => panic!("expected an unflushed-session error, got {other:?}"),
    }
    // Read once, up to the first message that does not decode.
    let chunks = common::recording_chunks({
        let file = std::io::BufReader::new(std::fs::File::open(&save).unwrap());
        re_log_encoding::DecoderApp::decode_lazy(file)
            .map_while(Result::ok)
            .collect::<Vec<_>>()
    });
    let distance = common::rows(&chunks, &format!("/{}/goal/distance", LIVE_ROOTS[0]));
    assert_eq!(distance, 3, "every step reached the file");
    // The saved file's legs: per-step colours only, each the damage palette of its step.
    common::assert_no_static_shadowing(&chunks);
    common::check_leg_colors(&chunks, &format!("/{}", LIVE_ROOTS[0]), &[]);
}

/// `live --connect` to a viewer a person started themselves, of the current Rerun: the stock
/// 0.41 binary (`rerun --port P --save FILE`, which listens like a viewer and writes what it
/// receives) takes the stream, and what it wrote has every step, the legs coloured by damage.
#[test]
fn live_streams_to_a_stock_viewer_started_by_the_test() {
    let viewer = common::stock_viewer();
    gaitscope::app::viewer::check_viewer(viewer)
        .expect("the viewer matches the SDK's minor version");
    let dir = tempfile::tempdir().unwrap();
    checkpoint(dir.path());
    let port = free_port();
    let received = dir.path().join("received.rrd");
    /// The viewer process, killed if the test fails before it is stopped.
    struct Server(std::process::Child);
    impl Drop for Server {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut server = Server(
        std::process::Command::new(viewer)
            .args(["--bind", "127.0.0.1", "--port", &port.to_string(), "--save"])
            .arg(&received)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let url = format!("rerun+http://127.0.0.1:{port}/proxy");
    let deadline = std::time::Instant::now() + WAIT;
    while gaitscope::app::viewer::check_reachable(&url).is_err() {
        assert!(
            std::time::Instant::now() < deadline,
            "the viewer never listened on {port}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let sink = Sink::Viewer { url, save: None };
    let (rec, _) = open(&sink, "gaitscope-live-connect", &live_roots()).unwrap();
    let sim = SimHandle::spawn(rec, setup(dir.path(), LiveCondition::Severe)).unwrap();
    let steps = 30;
    for _ in 0..steps {
        step_once(&sim);
    }
    let report = sim.shutdown().expect("every step reached the viewer");
    assert_eq!(report.steps, steps);
    // The viewer writes what it ingests as it goes, behind its socket: a SIGINT sent the moment
    // our side has flushed could stop it before it wrote the last steps (0 of 30 once, under
    // load). Give it up to 10 s to have them in the file.
    let root = format!("/{}", LIVE_ROOTS[0]);
    let written = || {
        received.exists()
            && common::rows(
                &common::read_rrd(&received),
                &format!("{root}/goal/distance"),
            ) >= steps as usize
    };
    let settle = std::time::Instant::now() + Duration::from_secs(10);
    while !written() && std::time::Instant::now() < settle {
        std::thread::sleep(Duration::from_millis(100));
    }
    // SIGINT: the viewer closes its file as a person's Ctrl-C would.
    let _ = std::process::Command::new("kill")
        .args(["-INT", &server.0.id().to_string()])
        .status();
    let deadline = std::time::Instant::now() + WAIT;
    while server.0.try_wait().unwrap().is_none() {
        assert!(
            std::time::Instant::now() < deadline,
            "the viewer did not exit on SIGINT"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let chunks = common::read_rrd(&received);
    let distance = common::rows(&chunks, &format!("{root}/goal/distance"));
    assert_eq!(distance as u64, steps, "every step reached the viewer");
    common::assert_no_static_shadowing(&chunks);
    common::check_leg_colors(&chunks, &root, &[]);
}

/// Two models live under severe damage, one joint pinned by hand: the stream's legs show each
/// model's own damage (red when triggered, purple when pinned), nothing is shadowed by static
/// data, and every plot line names its checkpoint and lane.
#[test]
fn live_legs_show_each_models_damage_and_lines_name_the_model() {
    let dir = tempfile::tempdir().unwrap();
    checkpoint(dir.path());
    let label = gaitscope::eval::model_label(dir.path());
    let (rec, storage) = memory_stream();
    let mut live = setup(dir.path(), LiveCondition::Severe);
    live.compare = Some(dir.path().to_path_buf());
    let sim = SimHandle::spawn(rec, live).unwrap();
    for _ in 0..5 {
        step_once(&sim);
    }
    // Pinned before the next step: from that step's frame on, the joint is "manual".
    assert!(sim.send(Command::Override {
        actuator: 2,
        change: JointOverride::SetScale(0.4),
    }));
    let pinned_at = step_once(&sim).global_step as i64;
    for _ in 0..54 {
        step_once(&sim);
    }
    sim.shutdown().unwrap();
    let chunks = common::recording_chunks(storage.take());
    common::assert_no_static_shadowing(&chunks);
    let mut red = 0;
    for root in LIVE_ROOTS {
        red += common::check_leg_colors(&chunks, &format!("/{root}"), &[(pinned_at, 2)]);
        // One checkpoint twice: its name and the lane in every series name.
        let names = common::series_names(&chunks, &format!("/{root}/joints/fatigue"));
        assert_eq!(names.len(), 8);
        assert!(
            names
                .iter()
                .all(|n| n.starts_with(&format!("{label} ({root}): "))),
            "{names:?}"
        );
    }
    assert!(red > 0, "60 severe steps trigger a joint");
}

/// Pause takes effect before steps still queued: a burst of single steps followed by Pause
/// stops the sim where it is, and it stays there.
#[test]
fn pause_drops_the_steps_still_queued() {
    let (_dir, sim, _storage) = started(LiveCondition::Severe);
    let before = sim.snapshot().global_step;
    for _ in 0..50 {
        assert!(sim.send(Command::StepOnce));
    }
    assert!(sim.send(Command::Pause));
    std::thread::sleep(Duration::from_millis(300));
    let paused_at = sim.snapshot().global_step;
    assert!(
        paused_at < before + 50,
        "the queued steps were dropped: {before} → {paused_at}"
    );
    std::thread::sleep(Duration::from_millis(700));
    assert_eq!(
        sim.snapshot().global_step,
        paused_at,
        "nothing moves while paused"
    );
    sim.shutdown().unwrap();
}

/// A scenario naming a joint the Ant lacks is refused when it is set (as the CLI refuses it),
/// with a message; the next reset and steps still work.
#[test]
fn a_scenario_with_an_unknown_joint_is_refused_and_resets_still_work() {
    let (_dir, sim, _storage) = started(LiveCondition::Severe);
    let bad = gaitscope::damage::scenario::Scenario::from_json(
        r#"{"name": "bad", "fatigue": false, "edits": [{"step": 0, "joint": "knee_9", "scale": 0.1}]}"#,
        "test",
    )
    .unwrap();
    assert!(sim.send(Command::SetScenario(Some(bad))));
    let s = sim.wait_for(WAIT, |s| s.message.is_some());
    let message = s.message.unwrap_or_default();
    assert!(
        message.contains("scenario refused") && message.contains("knee_9"),
        "{message}"
    );
    assert!(sim.send(Command::Reset));
    step_once(&sim);
    step_once(&sim);
    sim.shutdown().unwrap();
}

#[cfg(feature = "live")]
mod panel {
    use super::*;
    use egui_kittest::Harness;
    use egui_kittest::kittest::Queryable;
    use gaitscope::app::panel::Panel;

    fn harness(sim: &SimHandle) -> Harness<'static, Panel> {
        let panel = Panel::new(sim.link(), Vec::new());
        Harness::builder()
            .with_size([560.0, 1300.0])
            .build_ui_state(|ui, panel: &mut Panel| panel.ui(ui), panel)
    }

    #[test]
    fn clicking_fail_now_damages_that_joint_from_the_next_step() {
        let (_dir, sim, _storage) = started(LiveCondition::Severe);
        let mut ui = harness(&sim);
        ui.run();
        assert_eq!(ui.get_all_by_label("fail now").count(), 8, "one per joint");
        assert_eq!(ui.get_all_by_label("full torque").count(), 8);
        ui.get_all_by_label("fail now")
            .nth(3)
            .expect("a fourth joint")
            .click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.lanes[0].states[3] == JointState::Triggered);
        assert_eq!(s.lanes[0].states[3], JointState::Triggered);
        assert_eq!(s.global_step, 0, "paused: not applied to a step yet");
        // The panel shows it, and Step runs exactly one env step with the joint at 0.1.
        ui.run();
        // In the torque's words, with who took it: a hand, not fatigue.
        assert_eq!(ui.get_all_by_label("scale 0.10 (manual)").count(), 1);
        ui.get_by_label("Step").click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.global_step == 1);
        assert_eq!(s.global_step, 1);
        let lane = &s.lanes[0];
        assert_eq!(lane.applied[3], 0.1 * lane.commanded[3]);
        for j in (0..8).filter(|&j| j != 3) {
            assert_eq!(lane.applied[j], lane.commanded[j], "joint {j} untouched");
        }
        // Heal from the panel.
        ui.get_all_by_label("heal")
            .nth(3)
            .expect("a fourth joint")
            .click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.lanes[0].states[3] == JointState::Healthy);
        assert_eq!(s.lanes[0].scale[3], 1.0);
        sim.shutdown().unwrap();
    }

    #[test]
    fn break_on_fork_and_rewind_controls_drive_the_sim() {
        use gaitscope::app::Breakpoint;
        let (_dir, sim, _storage) = started(LiveCondition::Severe);
        let mut ui = harness(&sim);
        ui.run();
        // Break on: a checkbox per kind; probe-flip is off without a probe.json.
        ui.get_by_label("trigger").click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| !s.breakpoints.is_empty());
        assert_eq!(s.breakpoints, [Breakpoint::Trigger(None)]);
        assert!(!s.has_probe);
        // Three steps, then fork with the field's default edit (heal:all).
        for k in 1..=3 {
            ui.get_by_label("Step").click();
            ui.run();
            assert_eq!(sim.wait_for(WAIT, |s| s.global_step == k).global_step, k);
        }
        ui.get_by_label("Fork here").click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.lanes.len() == 2);
        assert_eq!(s.lanes[1].root, "fork");
        assert!(
            s.lanes[1]
                .fork_of
                .as_deref()
                .unwrap()
                .contains("at step 3: heal:all")
        );
        ui.run();
        ui.get_by_label("End fork").click();
        ui.run();
        assert_eq!(sim.wait_for(WAIT, |s| s.lanes.len() == 1).lanes.len(), 1);
        // Rewind with the slider at 0: back to the episode's start, a new branch.
        ui.run();
        ui.get_by_label("Rewind").click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.branches == 1);
        assert_eq!((s.lanes[0].step, s.branches), (0, 1));
        sim.shutdown().unwrap();
    }

    #[test]
    fn the_push_button_pushes_and_save_state_writes_what_init_state_reads() {
        let (dir, sim, _storage) = started(LiveCondition::Severe);
        let mut ui = harness(&sim);
        ui.run();
        // The push row's defaults: torso, 40 N along +y, 5 steps.
        let handled = sim.snapshot().commands_handled;
        ui.get_by_label("Push").click();
        ui.run();
        sim.wait_for(WAIT, |s| s.commands_handled > handled);
        step_once(&sim);
        let s = step_once(&sim);
        let saved = s.saved_state.expect("a model is loaded");
        assert_eq!(saved.condition.as_deref(), Some("severe"));
        assert_eq!(saved.env.step, 2);
        assert_eq!(saved.env.pushes.len(), 1);
        assert_eq!(saved.env.pushes[0].push.force, [0.0, 40.0, 0.0]);
        assert_eq!(saved.env.pushes[0].remaining, 3, "5-step push, 2 taken");
        // The attribution checkbox turns the view on.
        assert!(!s.attribution);
        ui.get_by_label("Why z moved (attribution)").click();
        ui.run();
        assert!(sim.wait_for(WAIT, |s| s.attribution).attribution);
        // "Save state" (the command the button sends, to the path beside it) writes the file
        // --init-state reads back.
        let path = dir.path().join("state.json");
        assert!(sim.send(Command::SaveState(path.clone())));
        let s = sim.wait_for(WAIT, |s| {
            s.message
                .as_deref()
                .is_some_and(|m| m.contains("saved the state"))
        });
        assert!(s.message.unwrap().contains("before step 2"));
        match gaitscope::lane::StartState::read(&path).unwrap() {
            gaitscope::lane::StartState::Saved(read) => assert_eq!(*read, *saved),
            other => panic!("{other:?}"),
        }
        sim.shutdown().unwrap();
    }

    /// Issue 48: the panel loads a search folder and "Next failure" replays each held-out
    /// episode a finding broke, from a reset with its scenario and seed (as the page does).
    #[test]
    fn the_panel_loads_a_search_folder_and_steps_through_its_failures() {
        let out = tempfile::tempdir().unwrap();
        let found = out.path().join("search");
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args([
                "search",
                "--checkpoint",
                "checkpoints/encoder-lstm",
                "--budget",
                "3",
            ])
            .args([
                "--evaluations",
                "6",
                "--episodes",
                "4",
                "--held-out",
                "8",
                "--top",
                "1",
            ])
            .args([
                "--shrink-evaluations",
                "0",
                "--max-steps",
                "150",
                "--latest-onset",
                "10",
            ])
            .arg("--out")
            .arg(&found)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let findings = gaitscope::search::findings(&found).unwrap();
        let failing: Vec<(String, u64)> = findings
            .iter()
            .flat_map(|f| f.failing_seeds.iter().map(|&s| (f.name.clone(), s)))
            .collect();
        assert!(failing.len() >= 2, "{failing:?}");

        let (_dir, sim, _storage) = started(LiveCondition::Severe);
        // A folder that is not a search: said in the panel, nothing offered.
        let mut other = harness(&sim);
        other.run();
        other.get_by_label("Search folder").focus();
        other.run();
        other
            .get_by_label("Search folder")
            .type_text(&out.path().to_string_lossy());
        other.run();
        other.get_by_label("Load findings").click();
        other.run();
        assert!(other.query_by_label("Next failure").is_none());
        assert!(other.query_by_label_contains("search.json").is_some());
        drop(other);
        // The search folder itself.
        let mut ui = harness(&sim);
        ui.run();
        ui.get_by_label("Search folder").focus();
        ui.run();
        ui.get_by_label("Search folder")
            .type_text(&found.to_string_lossy());
        ui.run();
        ui.get_by_label("Load findings").click();
        ui.run();
        let count = format!(
            "{} failing episodes in the search's findings",
            failing.len()
        );
        assert!(ui.query_by_label(&count).is_some(), "{count}");
        for (k, (name, seed)) in failing[..2].iter().enumerate() {
            let handled = sim.snapshot().commands_handled;
            ui.get_by_label("Next failure").click();
            ui.run();
            let s = sim.wait_for(WAIT, |s| s.commands_handled >= handled + 3);
            assert_eq!(s.episode_seed, *seed);
            assert_eq!(
                s.scenario.as_deref(),
                Some(format!("search-{name}").as_str())
            );
            assert_eq!(s.lanes[0].step, 0, "from a reset");
            ui.run();
            let shown = format!("{} of {}: {name}, seed {seed} — ", k + 1, failing.len());
            assert!(ui.query_by_label_contains(&shown).is_some(), "{shown}");
        }
        sim.shutdown().unwrap();
    }

    #[test]
    fn resume_and_pause_buttons_drive_the_sim() {
        let (_dir, sim, _storage) = started(LiveCondition::Severe);
        let mut ui = harness(&sim);
        ui.run();
        ui.get_by_label("Resume").click();
        ui.run();
        let s = sim.wait_for(WAIT, |s| s.global_step >= 5);
        assert!(!s.paused && s.global_step >= 5);
        ui.run();
        ui.get_by_label("Pause").click();
        ui.run();
        assert!(sim.wait_for(WAIT, |s| s.paused).paused);
        sim.shutdown().unwrap();
    }
}

/// The lane's episode log (what the page lists in full): a hand-failed joint reads "manual"
/// and its cause is "manual", not "triggered"; a push and the ending are there; fatigue
/// triggers name fatigue; the web snapshot carries the same list.
#[test]
fn the_episode_log_lists_every_event_with_its_cause() {
    let (_dir, sim, _storage) = started(LiveCondition::Severe);
    step_once(&sim);
    assert!(sim.send(Command::Override {
        actuator: 5,
        change: JointOverride::FailNow,
    }));
    assert!(sim.send(Command::Push(
        gaitscope::damage::Push::new("torso", [0.0, 40.0, 0.0], 3).unwrap()
    )));
    let mut s = step_once(&sim);
    let lane = &s.lanes[0];
    let joint = lane.joint_names[5].clone();
    assert_eq!(
        lane.causes[5].as_deref(),
        Some("manual"),
        "{:?}",
        lane.causes
    );
    let manual: Vec<_> = lane
        .event_log
        .iter()
        .filter(|e| e.kind == "manual")
        .collect();
    assert_eq!(manual.len(), 1, "{:?}", lane.event_log);
    assert!(
        manual[0].text.contains(&format!("{joint} failed by hand"))
            && manual[0].text.ends_with("(manual)"),
        "{:?}",
        manual[0]
    );
    assert!(
        lane.event_log
            .iter()
            .any(|e| e.kind == "push" && e.text.contains("torso")),
        "{:?}",
        lane.event_log
    );
    // On to the end: fatigue triggers say so, and the ending closes the list.
    while !s.lanes[0].done {
        s = step_once(&sim);
    }
    let log = &s.lanes[0].event_log;
    // Any fatigue trigger (the untrained test policy may leap first) names fatigue.
    assert!(
        log.iter()
            .filter(|e| e.kind == "triggered")
            .all(|e| e.text.ends_with("(fatigue)")),
        "{log:?}"
    );
    let last = log.last().unwrap();
    assert_eq!(last.kind, "ending", "{log:?}");
    assert!(last.text.starts_with("ended: "), "{last:?}");
    assert!(
        log.windows(2).all(|w| w[0].step <= w[1].step),
        "in step order"
    );
    let page = gaitscope::app::web::snapshot_json(&s);
    let listed = page["lanes"][0]["event_log"].as_array().unwrap();
    assert_eq!(listed.len(), log.len());
    assert_eq!(listed[0]["text"], log[0].text.as_str());
    sim.shutdown().unwrap();
}
