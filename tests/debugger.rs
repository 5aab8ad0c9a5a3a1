//! The debugger on the committed LSTM checkpoint, headless: breakpoints fire after the step an
//! independent run says they should and pause there, a rewind repeats the original steps bit for
//! bit, a fork runs beside the main lane, and the stream carries all of it.

use gaitscope::app::{Breakpoint, Command, LIVE_ROOTS, LiveCondition, LiveSetup, SimHandle};
use gaitscope::damage::{ConditionChoice, Edit, JointOverride};
use gaitscope::policy::{ActionMode, Policy};
use gaitscope::telemetry::{Sink, open};
use gaitscope::{AntEnv, Condition, ContextWindow, GaitConfig};
use re_chunk::Chunk;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Duration;

mod common;

const WAIT: Duration = Duration::from_secs(30);
const LIMIT: usize = 500;

fn lstm() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/checkpoints/encoder-lstm"
    ))
}

/// `rollout --jsonl` of the checkpoint (the headless path, not the live session).
fn reference(seed: u64) -> Vec<Value> {
    let (seed, limit) = (seed.to_string(), LIMIT.to_string());
    let checkpoint = lstm();
    let args: [&std::ffi::OsStr; 12] = [
        "rollout".as_ref(),
        "--checkpoint".as_ref(),
        checkpoint.as_os_str(),
        "--condition".as_ref(),
        "severe".as_ref(),
        "--episodes".as_ref(),
        "1".as_ref(),
        "--jsonl".as_ref(),
        "--seed".as_ref(),
        seed.as_ref(),
        "--max-steps".as_ref(),
        limit.as_ref(),
    ];
    common::gaitscope_json_lines(args).unwrap_or_else(|e| panic!("{e}"))
}

fn setup(seed: u64, breakpoints: Vec<Breakpoint>) -> LiveSetup {
    LiveSetup {
        checkpoint: lstm(),
        compare: None,
        condition: LiveCondition::Severe,
        seed,
        speed: 8.0,
        step_limit: LIMIT,
        mode: ActionMode::Deterministic,
        paused: true,
        breakpoints,
        start: None,
        attribution: false,
        fork: None,
        config: GaitConfig::default(),
    }
}

fn spawn(seed: u64, breakpoints: Vec<Breakpoint>) -> (SimHandle, rerun::sink::MemorySinkStorage) {
    let roots: Vec<String> = LIVE_ROOTS.iter().map(|r| r.to_string()).collect();
    let (rec, storage) = open(&Sink::Memory, "gaitscope-debugger-test", &roots).unwrap();
    let sim = SimHandle::spawn(rec, setup(seed, breakpoints)).unwrap();
    (sim, storage.unwrap())
}

/// Resumes and waits for a breakpoint; returns the episode steps when it paused.
fn run_to_break(sim: &SimHandle) -> usize {
    let before = sim.snapshot().global_step;
    assert!(sim.send(Command::Resume));
    let s = sim.wait_for(WAIT, |s| s.break_hit.is_some() && s.global_step > before);
    let hit = s.break_hit.clone().expect("a breakpoint fired");
    assert!(s.paused, "a hit pauses");
    assert_eq!(
        hit.step, s.lanes[0].step,
        "it paused after the step that hit"
    );
    // And it stays paused.
    std::thread::sleep(Duration::from_millis(150));
    assert_eq!(sim.snapshot().global_step, s.global_step);
    hit.step
}

/// The probe's first flip on this episode, from the policy, probe and env directly: the steps
/// after which P(damaged) of some joint has crossed 0.5 since the step before.
fn first_probe_flip(seed: u64) -> usize {
    let policy = Policy::load(&lstm(), None).unwrap();
    let probe = gaitscope::probe::ProbeFile::load(&lstm()).unwrap();
    let mut config = policy.meta.env.clone();
    config.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    config.env.max_episode_steps = LIMIT;
    let mut env = AntEnv::new(config, seed).unwrap();
    let mut obs = env.reset_with_seed(seed);
    let mut window = ContextWindow::new(policy.net().context_len);
    let mut before: Option<Vec<f64>> = None;
    for t in 0..LIMIT {
        let d = policy
            .act_one(&obs, &[1.0; 8], &window, ActionMode::Deterministic, None)
            .unwrap();
        let p = probe.joint_damage_probabilities(d.z.as_deref().unwrap());
        if let Some(b) = &before
            && b.iter().zip(&p).any(|(x, y)| (*x >= 0.5) != (*y >= 0.5))
        {
            return t + 1;
        }
        before = Some(p);
        let out = env.step(&d.action).unwrap();
        window.push(&obs, &d.action);
        obs = out.obs;
        assert!(!out.done(), "the episode ended before the probe flipped");
    }
    panic!("no flip within {LIMIT} steps");
}

fn first_trigger(rows: &[Value], joint: Option<usize>) -> usize {
    let idx = rows
        .iter()
        .position(|r| {
            let t = r["triggered"].as_array().unwrap();
            match joint {
                Some(j) => t[j] == true,
                None => t.iter().any(|v| *v == true),
            }
        })
        .expect("a joint triggers");
    idx + 1
}

#[test]
fn each_breakpoint_fires_after_its_step_and_pauses() {
    let seed0 = reference(0); // ends at the goal
    let seed1 = reference(1); // ends unhealthy
    let goal_distance = |row: &Value| {
        let xy = row["torso_xy"].as_array().unwrap();
        let d = |k: usize| xy[k].as_f64().unwrap() - 5.0;
        d(0).hypot(d(1))
    };
    let (end0, end1) = (seed0.last().unwrap(), seed1.last().unwrap());
    assert!(
        end0["terminated"] == true && goal_distance(end0) <= 1.0,
        "seed 0 succeeds"
    );
    assert!(
        end1["terminated"] == true && goal_distance(end1) > 1.0,
        "seed 1 falls"
    );
    let names = [
        "hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3",
    ];
    let ankle_2 = names.iter().position(|n| *n == "ankle_2").unwrap();
    let cases = [
        ("trigger", 0, first_trigger(&seed0, None)),
        ("trigger:ankle_2", 0, first_trigger(&seed0, Some(ankle_2))),
        ("termination", 1, seed1.len()),
        ("success", 0, seed0.len()),
        ("step:7", 0, 7),
        ("probe-flip", 0, first_probe_flip(0)),
    ];
    for (text, seed, expected) in cases {
        let (sim, _storage) = spawn(seed, Breakpoint::parse_list(text).unwrap());
        let s = sim.snapshot();
        assert_eq!(s.breakpoints, Breakpoint::parse_list(text).unwrap());
        assert_eq!(run_to_break(&sim), expected, "{text} on seed {seed}");
        sim.shutdown().unwrap();
    }
    // A hand-made change: fires after the step it first shapes.
    let (sim, _storage) = spawn(0, vec![Breakpoint::Override, Breakpoint::Step(40)]);
    assert!(sim.send(Command::Override {
        actuator: 2,
        change: JointOverride::FailNow
    }));
    assert_eq!(run_to_break(&sim), 1);
    let hit = sim.snapshot().break_hit.unwrap();
    assert_eq!(hit.breakpoint, Breakpoint::Override);
    // Running on reaches the next one.
    assert_eq!(run_to_break(&sim), 40);
    sim.shutdown().unwrap();
}

/// One 8-wide series (or the first value of a scalar one) per `step`.
fn series(chunks: &[Chunk], entity: &str) -> BTreeMap<i64, Vec<f64>> {
    let scalars = rerun::Scalars::descriptor_scalars().component;
    common::per_step(chunks, entity, |c| {
        c.iter_slices::<f64>(scalars).map(|s| s.to_vec()).collect()
    })
    .into_iter()
    .collect()
}

fn text_logs(chunks: &[Chunk], entity: &str) -> Vec<(String, String)> {
    let text = rerun::TextLog::descriptor_text().component;
    let level = rerun::TextLog::descriptor_level().component;
    let mut out = Vec::new();
    for c in chunks
        .iter()
        .filter(|c| c.entity_path().to_string() == entity)
    {
        let texts: Vec<String> = c
            .iter_slices::<String>(text)
            .flat_map(|s| s.iter().map(|t| t.to_string()).collect::<Vec<_>>())
            .collect();
        let levels: Vec<String> = c
            .iter_slices::<String>(level)
            .flat_map(|s| s.iter().map(|t| t.to_string()).collect::<Vec<_>>())
            .collect();
        out.extend(levels.into_iter().zip(texts));
    }
    out
}

fn chunks_of(sim: SimHandle, storage: rerun::sink::MemorySinkStorage) -> Vec<Chunk> {
    sim.shutdown().unwrap();
    common::recording_chunks(storage.take())
}

#[test]
fn rewinding_repeats_the_original_steps_bit_for_bit_under_a_branch_root() {
    let (sim, storage) = spawn(0, vec![Breakpoint::Step(30)]);
    assert_eq!(run_to_break(&sim), 30);
    let original = sim.snapshot();
    assert_eq!(original.rewindable, 30);
    assert!(sim.send(Command::Rewind(10)));
    let s = sim.wait_for(WAIT, |s| s.lanes[0].step == 10);
    assert_eq!((s.lanes[0].step, s.branches, s.rewindable), (10, 1, 10));
    assert!(s.paused, "a rewind keeps the sim paused");
    // Out of range: said, nothing changed.
    assert!(sim.send(Command::Rewind(11)));
    let s = sim.wait_for(WAIT, |s| s.message.is_some());
    assert!(s.message.unwrap().contains("not in this episode's history"));
    assert_eq!(run_to_break(&sim), 30);
    let again = sim.snapshot();
    assert_eq!(again.lanes[0].fatigue, original.lanes[0].fatigue);
    assert_eq!(again.lanes[0].distance, original.lanes[0].distance);
    assert_eq!(again.lanes[0].commanded, original.lanes[0].commanded);
    assert_eq!(again.lanes[0].root, "ant_b1");
    // A new episode goes back to the model's own root, after the furthest step logged.
    assert!(sim.send(Command::Reset));
    assert!(sim.send(Command::StepOnce));
    let s = sim.wait_for(WAIT, |s| s.lanes[0].step == 1 && s.episodes == 2);
    assert_eq!((s.lanes[0].root.as_str(), s.global_step), ("ant", 31));
    // The stream: the original history under /ant, the branch under /ant_b1 at the same steps
    // (overlaid in the plots), bit for bit the same values from step 11 on.
    let chunks = chunks_of(sim, storage);
    for leaf in ["joints/fatigue", "goal/distance", "actions/applied"] {
        let original = series(&chunks, &format!("/ant/{leaf}"));
        let branch = series(&chunks, &format!("/ant_b1/{leaf}"));
        assert_eq!(
            original.len(),
            31,
            "{leaf}: the history stays (and episode 2's step)"
        );
        let steps: Vec<i64> = branch.keys().copied().collect();
        assert_eq!(
            steps,
            (11..=30).collect::<Vec<_>>(),
            "{leaf}: the branch's steps"
        );
        for step in 11..=30i64 {
            assert_eq!(original[&step], branch[&step], "{leaf}, step {step}");
        }
    }
    let notes = text_logs(&chunks, "/ant_b1/events");
    assert!(
        notes
            .iter()
            .any(|(level, text)| level == "BRANCH"
                && text.contains("branch 1: ant rewound to step 10")),
        "{notes:?}"
    );
    let breaks: usize = ["/ant/events", "/ant_b1/events"]
        .iter()
        .map(|e| {
            text_logs(&chunks, e)
                .iter()
                .filter(|(l, _)| l == "BREAK")
                .count()
        })
        .sum();
    assert_eq!(breaks, 2, "each hit is an event");
}

#[test]
fn a_heal_all_fork_runs_beside_the_unchanged_main_lane() {
    let reference = reference(0);
    let (sim, storage) = spawn(0, vec![Breakpoint::Step(40), Breakpoint::Step(60)]);
    assert_eq!(run_to_break(&sim), 40);
    assert!(sim.send(Command::Fork(Edit::parse_list("heal:all").unwrap())));
    let s = sim.wait_for(WAIT, |s| s.lanes.len() == 2);
    assert_eq!(s.lanes[1].root, "fork");
    assert!(
        s.lanes[1]
            .fork_of
            .as_deref()
            .unwrap()
            .contains("at step 40: heal:all")
    );
    assert!(s.lanes[1].scale.iter().all(|&x| x == 1.0), "healed");
    assert_eq!(run_to_break(&sim), 60);
    assert!(sim.send(Command::EndFork));
    assert_eq!(sim.wait_for(WAIT, |s| s.lanes.len() == 1).lanes.len(), 1);
    let chunks = chunks_of(sim, storage);
    let main = series(&chunks, "/ant/actions/applied");
    let applied = series(&chunks, "/fork/actions/applied");
    let commanded = series(&chunks, "/fork/actions/commanded");
    // Global steps equal episode steps here (one episode, no rewind).
    for step in 1..=60i64 {
        let row = &reference[step as usize - 1];
        let expected: Vec<f64> = row["applied_action"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(
            main[&step], expected,
            "the main lane is the plain run at {step}"
        );
    }
    let (d_main, d_fork) = (
        series(&chunks, "/ant/goal/distance"),
        series(&chunks, "/fork/goal/distance"),
    );
    let parted = (41..=60).filter(|k| d_main[k] != d_fork[k]).count();
    eprintln!(
        "distance differs at {parted} of 20 fork steps; at 60: {:?} vs {:?}",
        d_main[&60], d_fork[&60]
    );
    assert!(parted > 0, "healing changes the fork's path");
    assert_eq!(
        applied.keys().min(),
        Some(&41),
        "the fork starts after step 40"
    );
    assert_eq!(applied.len(), 20);
    for (step, a) in &applied {
        assert_eq!(a, &commanded[step], "healed: applied = commanded at {step}");
    }
}

/// `record --fork-at`: the recording holds the fork lane from step K on.
#[test]
fn a_recording_holds_the_fork_lane() {
    use gaitscope::rollout::Fork;
    use gaitscope::telemetry::{Actor, RecordOptions, record};
    let mut config = GaitConfig::default();
    config.env.max_episode_steps = 80;
    config.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    let opts = RecordOptions {
        actors: vec![Actor::load(&lstm()).unwrap()],
        config,
        episodes: 1,
        seed: 0,
        sink: Sink::Memory,
        start: None,
        attribution: false,
        caption: None,
        fork: Some(Fork {
            at: 30,
            edits: Edit::parse_list("fail:hip_1").unwrap(),
        }),
    };
    let stop = std::sync::atomic::AtomicBool::new(false);
    let summary = record(opts, &stop).unwrap();
    let chunks = common::recording_chunks(summary.storage.unwrap().take());
    let main = series(&chunks, "/ant/joints/scale");
    let fork = series(&chunks, "/fork/joints/scale");
    assert_eq!(main.len(), 80);
    assert_eq!(fork.keys().min(), Some(&31));
    let hip_1 = 2;
    for (step, scale) in &fork {
        assert_eq!(scale[hip_1], 0.1, "hip_1 failed in the fork at {step}");
    }
    assert_eq!(main[&31][hip_1], 1.0, "the main lane's hip_1 is untouched");
    let notes = text_logs(&chunks, "/fork/events");
    assert!(
        notes
            .iter()
            .any(|(l, t)| l == "BRANCH" && t.contains("fork of ant at step 30: fail:hip_1")),
        "{notes:?}"
    );
}
