//! One checkpoint, one world: a checkpoint trained in a non-default world (fatigue threshold
//! 10, window 8) runs in that world under every front-end — `rollout`, `record`, `live`,
//! `eval`, `probe` (and `video`, in tests/video.rs) — step for step the same episode, which an
//! independent replay of its actions on a bare env in that world reproduces.

use gaitscope::app::{Command, LIVE_ROOTS, LiveCondition, LiveSetup, SimHandle};
use gaitscope::damage::{Condition, ConditionChoice};
use gaitscope::lane::Actor;
use gaitscope::policy::ActionMode;
use gaitscope::telemetry::{RecordOptions, Sink, open, record};
use gaitscope::{AntEnv, GaitConfig};
use std::path::Path;
use std::time::Duration;

mod common;

const SEED: u64 = 5;
const MAX_STEPS: usize = 300;
const THRESHOLD: f64 = 10.0;

/// The request every front-end gets: severe, 300 steps, and otherwise the defaults (τ = 30).
fn requested() -> GaitConfig {
    let mut c = GaitConfig::default();
    c.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    c.env.max_episode_steps = MAX_STEPS;
    c
}

/// What each front-end shows of a step.
#[derive(Debug, Clone, PartialEq)]
struct Step {
    fatigue: [f64; 8],
    applied: [f64; 8],
}

/// The reference: `gaitscope rollout --checkpoint … --jsonl`, and its commanded actions.
fn rollout(dir: &Path) -> (Vec<Step>, Vec<[f64; 8]>, Vec<serde_json::Value>) {
    let lines = common::gaitscope_json_lines([
        "rollout",
        "--checkpoint",
        dir.to_str().unwrap(),
        "--condition",
        "severe",
        "--episodes",
        "1",
        "--seed",
        &SEED.to_string(),
        "--max-steps",
        &MAX_STEPS.to_string(),
        "--jsonl",
    ])
    .unwrap();
    let eight =
        |v: &serde_json::Value| -> [f64; 8] { std::array::from_fn(|i| v[i].as_f64().unwrap()) };
    let steps = lines
        .iter()
        .map(|l| Step {
            fatigue: eight(&l["fatigue"]),
            applied: eight(&l["applied_action"]),
        })
        .collect();
    let actions = lines.iter().map(|l| eight(&l["action"])).collect();
    (steps, actions, lines)
}

fn assert_same(front_end: &str, got: &[Step], want: &[Step]) {
    assert_eq!(got.len(), want.len(), "{front_end}: episode length");
    for (t, (g, w)) in got.iter().zip(want).enumerate() {
        assert_eq!(g, w, "{front_end}: step {t}");
    }
}

#[test]
fn a_checkpoint_runs_in_its_own_world_under_every_front_end() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("tau10");
    common::save_checkpoint_in_world(&dir, THRESHOLD, 8);
    let (reference, actions, lines) = rollout(&dir);

    // The world is the checkpoint's: the first trigger fires at fatigue 10 … 30, not past 30.
    let first = lines
        .iter()
        .find_map(|l| {
            let t = l["triggered"].as_array().unwrap();
            let i = t.iter().position(|v| v == true)?;
            Some(l["fatigue"][i].as_f64().unwrap())
        })
        .expect("300 severe steps trigger a joint at τ = 10");
    assert!((THRESHOLD..30.0).contains(&first), "triggered at {first}");

    // An independent replay: a bare env built in that world by hand, the same actions.
    let mut world = requested();
    world.damage.threshold = THRESHOLD;
    world.context.len = 8;
    let mut env = AntEnv::new(world, SEED).unwrap();
    env.reset_with_seed(SEED);
    let replayed: Vec<Step> = actions
        .iter()
        .map(|a| {
            let out = env.step(a).unwrap();
            Step {
                fatigue: *env.damage().fatigue(),
                applied: out.applied_action,
            }
        })
        .collect();
    assert_same("replay on a bare env", &replayed, &reference);

    // record: the recording's fatigue and applied-action series, read back.
    let actor = Actor::load(&dir).unwrap();
    let summary = record(
        RecordOptions {
            actors: vec![actor.clone()],
            config: requested(),
            episodes: 1,
            seed: SEED,
            sink: Sink::Memory,
            start: None,
            attribution: false,
            caption: None,
            fork: None,
        },
        &std::sync::atomic::AtomicBool::new(false),
    )
    .unwrap();
    let chunks = common::recording_chunks(summary.storage.unwrap().take());
    let fatigue = common::joint_series(&chunks, "/ant/joints/fatigue");
    let applied = common::joint_series(&chunks, "/ant/actions/applied");
    let recorded: Vec<Step> = fatigue
        .values()
        .zip(applied.values())
        .map(|(f, a)| Step {
            fatigue: *f,
            applied: *a,
        })
        .collect();
    assert_same("record", &recorded, &reference);

    // live: the simulation thread, stepped one step at a time, read from its snapshots.
    let (rec, _storage) = open(
        &Sink::Memory,
        "one-world",
        &LIVE_ROOTS.iter().map(|r| r.to_string()).collect::<Vec<_>>(),
    )
    .unwrap();
    let sim = SimHandle::spawn(
        rec,
        LiveSetup {
            checkpoint: dir.clone(),
            compare: None,
            condition: LiveCondition::Severe,
            seed: SEED,
            speed: 8.0,
            step_limit: MAX_STEPS,
            mode: ActionMode::Deterministic,
            paused: true,
            breakpoints: Vec::new(),
            start: None,
            attribution: false,
            fork: None,
            config: GaitConfig::default(),
        },
    )
    .unwrap();
    let mut live = Vec::new();
    let wait = Duration::from_secs(20);
    while live.len() < reference.len() {
        let before = sim.snapshot().global_step;
        assert!(sim.send(Command::StepOnce));
        let s = sim.wait_for(wait, |s| s.global_step == before + 1);
        assert_eq!(s.global_step, before + 1, "live took the step");
        assert_eq!(s.episode_seed, SEED);
        let lane = &s.lanes[0];
        live.push(Step {
            fatigue: lane.fatigue,
            applied: lane.applied,
        });
        if lane.done {
            break;
        }
    }
    assert_eq!(sim.snapshot().lanes[0].threshold, THRESHOLD);
    assert_same("live", &live, &reference);
    drop(sim);

    // eval: the episode's length, return and trigger steps.
    let report = gaitscope::eval::evaluate(&gaitscope::eval::EvalOptions {
        checkpoints: vec![dir.clone()],
        told_healthy: Vec::new(),
        episodes: 1,
        seed_base: SEED,
        conditions: vec![gaitscope::eval::Case::Condition(Condition::Severe)],
        scenarios: Vec::new(),
        max_steps: MAX_STEPS,
        threads: 1,
    })
    .unwrap();
    let episode = &report.episodes[0];
    assert_eq!(episode.steps, reference.len(), "eval: episode length");
    let rollout_return: f64 = lines.iter().map(|l| l["reward"].as_f64().unwrap()).sum();
    assert!(
        (episode.episode_return - rollout_return).abs() < 1e-9,
        "eval return {} vs rollout {rollout_return}",
        episode.episode_return
    );
    let first_triggers: [Option<usize>; 8] =
        std::array::from_fn(|i| lines.iter().position(|l| l["triggered"][i] == true));
    assert_eq!(episode.trigger_steps, first_triggers, "eval: trigger steps");

    // probe: its collector's episode under severe (seed + condition index) is this episode.
    let steps = gaitscope::probe::collect(
        &actor,
        1,
        MAX_STEPS,
        SEED - Condition::Severe.index() as u64,
        0,
    )
    .unwrap();
    let severe: Vec<_> = steps
        .iter()
        .filter(|s| s.condition == Condition::Severe)
        .collect();
    assert_eq!(severe.len(), reference.len(), "probe: episode length");
    for (t, s) in severe.iter().enumerate() {
        assert_eq!(s.fatigue, reference[t].fatigue, "probe: step {t}");
        // The observation the policy decided from: the previous step's.
        if t > 0 {
            let obs: Vec<f64> = serde_json::from_value(lines[t - 1]["obs"].clone()).unwrap();
            assert_eq!(s.obs, obs, "probe: observation before step {t}");
        }
    }
}

/// With no --max-steps a checkpoint runs to its own world's limit (the paper's 500 in the
/// paper's world, a new world's own end elsewhere), never past it; the flag still wins, and
/// models whose worlds end at different steps need it.
#[test]
fn a_checkpoint_runs_to_its_worlds_step_limit_unless_told() {
    let tmp = tempfile::tempdir().unwrap();
    let net = gaitscope::policy::NetConfig {
        hidden: vec![16, 16],
        ..gaitscope::policy::NetConfig::ant(gaitscope::policy::EncoderKind::None)
    };
    // A short world (dead-legs, ending after 40 steps) and the paper's, each with a height
    // band no untrained Ant leaves, so only the step limit ends an episode.
    let unbounded = |mut world: GaitConfig| {
        world.env.healthy_z_range = [-100.0, 100.0];
        world
    };
    let short = tmp.path().join("short");
    let mut world = unbounded(GaitConfig::world("dead-legs").unwrap());
    world.env.max_episode_steps = 40;
    common::save_untrained(&short, net.clone(), &world);
    let paper = tmp.path().join("paper");
    common::save_untrained(&paper, net, &unbounded(GaitConfig::default()));
    let steps = |dir: &Path, extra: &[&str]| -> usize {
        let mut args = vec![
            "rollout",
            "--checkpoint",
            dir.to_str().unwrap(),
            "--condition",
            "healthy",
            "--episodes",
            "1",
            "--json",
        ];
        args.extend_from_slice(extra);
        let lines = common::gaitscope_json_lines(&args).unwrap();
        assert_eq!(lines[0]["truncated"], true, "{}", lines[0]);
        lines[0]["steps"].as_u64().unwrap() as usize
    };
    assert_eq!(steps(&short, &[]), 40, "the short world's own end");
    assert_eq!(steps(&short, &["--max-steps", "25"]), 25, "the flag wins");
    assert_eq!(
        steps(&paper, &[]),
        500,
        "the paper's evaluation limit, not training's 1000"
    );

    // eval records the limit it judged at: the world's.
    let out_dir = tmp.path().join("eval");
    let eval = |models: &[&Path]| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"));
        cmd.args([
            "eval",
            "--episodes",
            "1",
            "--conditions",
            "healthy",
            "--threads",
            "1",
        ]);
        for m in models {
            cmd.arg("--checkpoint").arg(m);
        }
        cmd.arg("--out").arg(&out_dir).output().unwrap()
    };
    let out = eval(&[&short]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let saved: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out_dir.join("eval.json")).unwrap()).unwrap();
    assert_eq!(saved["max_steps"], 40);
    assert_eq!(saved["episodes"][0]["steps"], 40);
    // Two worlds with two limits: said, with both, before any episode runs.
    let out = eval(&[&short, &paper]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("runs to 40 steps in its world (dead-legs)")
            && err.contains("paper to 500 in its own (paper)")
            && err.contains("give --max-steps"),
        "{err}"
    );
}
