//! Damage scenarios through the env and the CLI: every edit kind at its exact step (applied =
//! scale × commanded, scales derived by hand), seeded draws, labelled events, bad files, and the
//! live "save overrides" → `rollout --scenario` round trip.

use gaitscope::app::{Command, LIVE_ROOTS, LiveCondition, LiveSetup, SimHandle};
use gaitscope::damage::scenario::Scenario;
use gaitscope::damage::{DamageEventKind, JointOverride};
use gaitscope::policy::ActionMode;
use gaitscope::rollout::BuiltinPolicy;
use gaitscope::telemetry::{Sink, open};
use gaitscope::{AntEnv, GaitConfig};
use serde_json::Value;
use std::path::PathBuf;
use std::process::Command as Process;
use std::time::Duration;

mod common;

fn env_with(scenario: &str, seed: u64) -> AntEnv {
    let mut config = GaitConfig::default();
    config.damage.scenario = Some(Scenario::from_json(scenario, "test").unwrap());
    let mut env = AntEnv::new(config, seed).unwrap();
    env.reset_with_seed(seed);
    env
}

/// Actuator index of a joint name.
fn joint(env: &AntEnv, name: &str) -> usize {
    env.damage()
        .joint_names()
        .iter()
        .position(|j| j == name)
        .unwrap()
}

#[test]
fn every_edit_kind_applies_at_its_exact_step() {
    let text = r#"{"name": "kinds", "fatigue": false, "edits": [
        {"step": 3, "joint": "ankle_3", "scale": 0.3},
        {"step": 5, "joint": "hip_1", "fail": 0.2},
        {"step": 8, "joint": "hip_1", "heal": true},
        {"step": 10, "until": 14, "joint": "hip_2", "ramp": [1.0, 0.0]},
        {"step": 4, "until": 9, "joint": "ankle_4", "intermittent": {"scales": [0.5, 1.0], "period": 2}},
        {"step": 6, "joint": "back_leg", "reset_fatigue": true}]}"#;
    let mut env = env_with(text, 11);
    let (a3, h1, h2, a4) = (
        joint(&env, "ankle_3"),
        joint(&env, "hip_1"),
        joint(&env, "hip_2"),
        joint(&env, "ankle_4"),
    );
    let h3 = joint(&env, "hip_3");
    // The scale each joint runs step t with, by hand.
    let expected = |j: usize, t: usize| -> f64 {
        match j {
            _ if j == a3 && t >= 3 => 0.3,
            _ if j == h1 && (5..8).contains(&t) => 0.2,
            _ if j == h2 && (10..=14).contains(&t) => 1.0 - (t - 10) as f64 / 4.0,
            _ if j == h2 && t > 14 => 0.0,
            // 0.5 at 4, 1.0 at 6, 0.5 at 8, then it stays (until 9).
            _ if j == a4 => match t {
                0..4 => 1.0,
                4 | 5 => 0.5,
                6 | 7 => 1.0,
                _ => 0.5,
            },
            _ => 1.0,
        }
    };
    let mut rng = gaitscope::rollout::policy_rng(11);
    let mut fatigue_before_6 = 0.0;
    for t in 0..20 {
        if t == 6 {
            fatigue_before_6 = env.damage().fatigue()[h3];
        }
        // Gentle random actions: the Ant stays up for the whole schedule.
        let action: Vec<f64> = BuiltinPolicy::Random
            .act(&mut rng)
            .iter()
            .map(|a| 0.3 * a)
            .collect();
        let out = env.step(&action).unwrap();
        for j in 0..8 {
            let s = expected(j, t);
            assert_eq!(
                out.applied_action[j],
                s * out.commanded_action[j],
                "joint {j}, step {t}"
            );
        }
        if t == 6 {
            // reset_fatigue zeroes hip_3's fatigue before step 6, which then adds one step's.
            assert!(fatigue_before_6 > 0.0 && env.damage().fatigue()[h3] < fatigue_before_6);
        }
    }
    assert!(
        env.damage()
            .first_trigger_steps()
            .iter()
            .all(Option::is_none),
        "fatigue off"
    );
    // Every change is an event at its step, labelled with the scenario.
    let events = env.damage().events();
    assert!(events.iter().all(|e| e.source.as_deref() == Some("kinds")));
    let at = |j: usize| -> Vec<usize> {
        events
            .iter()
            .filter(|e| e.actuator == j)
            .map(|e| e.step)
            .collect()
    };
    assert_eq!(at(a3), [3, 6], "scale, then back_leg's reset_fatigue");
    assert_eq!(at(h1), [5, 8]);
    assert_eq!(at(h2), [10, 11, 12, 13, 14]);
    assert_eq!(at(a4), [4, 6, 8]);
    assert!(matches!(
        events.iter().find(|e| e.actuator == h1).unwrap().kind,
        DamageEventKind::Override { change: JointOverride::FailTo(s) } if s == 0.2
    ));
}

#[test]
fn random_draws_repeat_per_episode_seed_and_vary_across_seeds() {
    let scenario = Scenario::load("ood-late-fault").unwrap();
    let text = scenario.to_json();
    let plan = |seed: u64| env_with(&text, seed).scenario_plan().unwrap().starts();
    assert_eq!(plan(5), plan(5));
    let plans: Vec<_> = (0..16).map(plan).collect();
    let distinct: std::collections::BTreeSet<_> = plans.iter().collect();
    assert!(distinct.len() >= 12, "{plans:?}");
    for p in &plans {
        assert!((50..=150).contains(&p[0].0) && p[0].1.len() == 1);
    }
    // The draw comes after the reset noise: the start state is the scenario-free one.
    let mut plain = AntEnv::new(GaitConfig::default(), 5).unwrap();
    assert_eq!(plain.reset_with_seed(5), env_with(&text, 5).observation());
}

#[test]
fn bad_scenarios_are_refused_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (
            r#"{"name": "x", "edits": [{"step": 0, "joint": "ankle_9", "scale": 0.1}]}"#,
            "unknown joint or leg 'ankle_9'",
        ),
        (
            r#"{"name": "x", "edits": [{"step": 0, "joint": "ankle_3", "scale": 2}]}"#,
            "edits[0].scale: 2 is outside [0, 1]",
        ),
        (
            r#"{"name": "x", "edits": [{"step": -1, "joint": "ankle_3", "scale": 0.5}]}"#,
            "edits[0].step: -1 is negative",
        ),
        (
            r#"{"name": "x", "edits": [{"step": 0, "joint": "ankle_3", "scael": 0.5}]}"#,
            "unknown field `scael`",
        ),
        ("{\"name\": ", "EOF"),
    ];
    for (k, (text, expected)) in cases.iter().enumerate() {
        let path = dir.path().join(format!("bad{k}.json"));
        std::fs::write(&path, text).unwrap();
        let out = Process::new(env!("CARGO_BIN_EXE_gaitscope"))
            .args([
                "rollout",
                "--policy",
                "zero",
                "--episodes",
                "1",
                "--scenario",
            ])
            .arg(&path)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            !out.status.success() && err.contains(expected),
            "{text}: {err}"
        );
    }
}

fn lstm() -> PathBuf {
    PathBuf::from(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/checkpoints/encoder-lstm"
    ))
}

#[test]
fn overrides_saved_from_live_replay_step_for_step_in_rollout() {
    let roots: Vec<String> = LIVE_ROOTS.iter().map(|r| r.to_string()).collect();
    let (rec, storage) = open(&Sink::Memory, "scenario-round-trip", &roots).unwrap();
    let setup = LiveSetup {
        checkpoint: lstm(),
        compare: None,
        condition: LiveCondition::Manual,
        seed: 4,
        speed: 8.0,
        step_limit: 500,
        mode: ActionMode::Deterministic,
        paused: true,
        breakpoints: Vec::new(),
        start: None,
        attribution: false,
        fork: None,
        config: GaitConfig::default(),
    };
    let sim = SimHandle::spawn(rec, setup).unwrap();
    let wait = Duration::from_secs(20);
    let step_to = |n: u64| {
        while sim.snapshot().global_step < n {
            let before = sim.snapshot().global_step;
            assert!(sim.send(Command::StepOnce));
            sim.wait_for(wait, |s| s.global_step == before + 1);
        }
    };
    let over = |actuator: usize, change: JointOverride| {
        assert!(sim.send(Command::Override { actuator, change }));
    };
    over(7, JointOverride::FailNow);
    step_to(5);
    over(2, JointOverride::SetScale(0.4));
    step_to(12);
    over(7, JointOverride::Heal);
    over(0, JointOverride::ResetFatigue);
    step_to(20);
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("found-by-hand.json");
    assert!(sim.send(Command::SaveScenario(file.clone())));
    let s = sim.wait_for(wait, |s| {
        s.message.as_deref().is_some_and(|m| m.contains("saved"))
    });
    assert!(s.message.unwrap().contains("saved"));
    sim.shutdown().unwrap();
    let saved: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    assert_eq!(saved["fatigue"], false, "manual: no fatigue triggers");
    assert_eq!(saved["edits"].as_array().unwrap().len(), 4);
    let chunks = common::recording_chunks(storage.unwrap().take());
    let scalars = rerun::Scalars::descriptor_scalars().component;
    let live: Vec<(i64, Vec<f64>)> = common::per_step(&chunks, "/ant/actions/applied", |c| {
        c.iter_slices::<f64>(scalars).map(|s| s.to_vec()).collect()
    });
    let checkpoint = lstm();
    let mut args: Vec<&std::ffi::OsStr> = vec!["rollout".as_ref(), "--checkpoint".as_ref()];
    args.push(checkpoint.as_os_str());
    for a in [
        "--condition",
        "severe",
        "--seed",
        "4",
        "--episodes",
        "1",
        "--max-steps",
        "20",
    ] {
        args.push(a.as_ref());
    }
    args.extend(["--scenario".as_ref(), file.as_os_str(), "--jsonl".as_ref()]);
    let rows = common::gaitscope_json_lines(args).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(rows.len(), 20);
    assert_eq!(live.len(), 20);
    for ((step, applied), row) in live.iter().zip(&rows) {
        let replayed: Vec<f64> = row["applied_action"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(applied, &replayed, "step {step}");
    }
    // The damage really was in force: ankle_3 at 0.1 before the heal, hip_1 at 0.4 after step 5.
    let scale = |t: usize, j: usize| {
        rows[t]["applied_action"][j].as_f64().unwrap() / rows[t]["action"][j].as_f64().unwrap()
    };
    assert!((scale(3, 7) - 0.1).abs() < 1e-12 && (scale(8, 2) - 0.4).abs() < 1e-12);
    assert!((scale(15, 7) - 1.0).abs() < 1e-12);
}

#[test]
fn eval_runs_the_ood_suite_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let baseline = concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/baseline");
    let out = Process::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["eval", "--checkpoint", baseline])
        .arg(lstm())
        .args([
            "--suite",
            "ood",
            "--scenario",
            "ood-leg",
            "--episodes",
            "2",
            "--out",
        ])
        .arg(dir.path())
        .output()
        .unwrap();
    // ood-leg twice (the suite has it) is refused: each column needs its own name.
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("two scenarios are named 'ood-leg'"));
    let out = Process::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["eval", "--checkpoint", baseline])
        .arg(lstm())
        .args(["--suite", "ood", "--episodes", "2", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("eval.json")).unwrap())
            .unwrap();
    let episodes = report["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 2 * 2 * 8, "2 models × 8 cases × 2 episodes");
    let cases: std::collections::BTreeSet<&str> = episodes
        .iter()
        .map(|e| e["condition"].as_str().unwrap())
        .collect();
    assert!(cases.contains("healthy") && cases.contains("ood-diagonal") && cases.len() == 8);
    assert_eq!(report["comparisons"].as_array().unwrap().len(), 8);
}

/// eval's cases and scenario checks are library calls: the case list, and scenarios refused
/// before any episode when two share a name or one names a joint the model does not have.
#[test]
fn eval_checks_its_scenarios_before_any_episode() {
    use gaitscope::damage::Condition;
    use gaitscope::eval::{Case, EvalOptions, cases, evaluate};
    let ankle = Scenario::load("ood-ankle").unwrap();
    assert_eq!(
        cases(&[], &[]),
        Condition::ALL.map(Case::from).to_vec(),
        "all three conditions by default"
    );
    assert_eq!(
        cases(&[], std::slice::from_ref(&ankle)),
        vec![Case::from(Condition::Healthy), Case::scenario("ood-ankle")]
    );
    assert_eq!(
        cases(&[Condition::Mild], std::slice::from_ref(&ankle)),
        vec![Case::from(Condition::Mild), Case::scenario("ood-ankle")]
    );
    let knee = Scenario::from_json(
        r#"{"name": "knee", "fatigue": false, "edits": [{"step": 0, "joint": "knee_9", "scale": 0.1}]}"#,
        "test",
    )
    .unwrap();
    for (scenarios, message) in [
        (
            vec![ankle.clone(), ankle.clone()],
            "two scenarios are named 'ood-ankle'",
        ),
        (vec![knee], "knee_9"),
    ] {
        let opts = EvalOptions {
            checkpoints: vec![lstm()],
            told_healthy: Vec::new(),
            episodes: 1,
            seed_base: 0,
            conditions: cases(&[], &scenarios),
            scenarios,
            max_steps: 5,
            threads: 1,
        };
        let err = evaluate(&opts).unwrap_err().to_string();
        assert!(err.contains(message), "{err}");
    }
}
