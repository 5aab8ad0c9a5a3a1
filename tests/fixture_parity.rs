//! Our physics, reward and fatigue against Gymnasium 1.4.0's Ant-v4 (MuJoCo 3.17.0) with the
//! goal task and fatigue model written in Python from the spec (`tests/fixtures/`).

#[path = "common/gymnasium.rs"]
mod gymnasium;

use gaitscope::{AntEnv, Condition, GaitConfig};
use serde::Deserialize;

#[derive(Deserialize)]
struct Fixture {
    condition: Condition,
    damage_scale: f64,
    init_qpos: Vec<f64>,
    init_qvel: Vec<f64>,
    init_obs: Vec<f64>,
    steps: Vec<FixtureStep>,
}

#[derive(Deserialize)]
struct FixtureStep {
    step: usize,
    action: Vec<f64>,
    applied_action: Vec<f64>,
    obs: Vec<f64>,
    reward: f64,
    terminated: bool,
    truncated: bool,
    fatigue: Vec<f64>,
    triggered: Vec<bool>,
    torso_xy: Vec<f64>,
    qpos: Vec<f64>,
    qvel: Vec<f64>,
}

fn assert_close(what: &str, step: usize, ours: &[f64], theirs: &[f64], tol: f64) {
    assert_eq!(ours.len(), theirs.len(), "{what} length at step {step}");
    for (i, (a, b)) in ours.iter().zip(theirs).enumerate() {
        let err = (a - b).abs() / b.abs().max(1.0);
        assert!(
            err <= tol,
            "{what}[{i}] at step {step}: ours {a}, Gymnasium {b} (rel err {err:e})"
        );
    }
}

#[test]
fn reproduces_gymnasium_ant_v4_under_mild_damage() {
    reproduces_fixture(Condition::Mild);
}

#[test]
fn reproduces_gymnasium_ant_v4_under_severe_damage_with_clipped_actions() {
    reproduces_fixture(Condition::Severe);
}

fn reproduces_fixture(condition: Condition) {
    let (_, path) = gymnasium::fixtures()
        .into_iter()
        .find(|(c, _)| *c == condition.name())
        .expect("a fixture per condition");
    let fx: Fixture = serde_json::from_str(&gymnasium::read(&path)).expect("fixture parses");
    assert_eq!(fx.condition, condition);
    let config = GaitConfig::default();
    assert_eq!(condition.scale(&config.damage.scales), fx.damage_scale);
    let mut env = AntEnv::new(config, 0).unwrap();
    let obs = env
        .reset_to_state(&fx.init_qpos, &fx.init_qvel, fx.condition)
        .unwrap();
    const TOL: f64 = 1e-9;
    assert_close("init obs", 0, &obs, &fx.init_obs, TOL);
    let mut clipped = false;
    for s in &fx.steps {
        clipped |= s.action.iter().any(|a| a.abs() > 1.0);
        let out = env.step(&s.action).unwrap();
        assert_eq!(out.step, s.step);
        assert_close("qpos", s.step, env.qpos(), &s.qpos, TOL);
        assert_close("qvel", s.step, env.qvel(), &s.qvel, TOL);
        assert_close("obs", s.step, &out.obs, &s.obs, TOL);
        assert_close("torso_xy", s.step, &env.torso_xy(), &s.torso_xy, TOL);
        assert_close(
            "applied_action",
            s.step,
            &out.applied_action,
            &s.applied_action,
            TOL,
        );
        assert_close("reward", s.step, &[out.reward.total], &[s.reward], TOL);
        assert_close("fatigue", s.step, env.damage().fatigue(), &s.fatigue, TOL);
        assert_eq!(
            env.damage().triggered().as_slice(),
            s.triggered.as_slice(),
            "triggered at {}",
            s.step
        );
        assert_eq!(
            (out.terminated, out.truncated),
            (s.terminated, s.truncated),
            "done at {}",
            s.step
        );
        if out.terminated || out.truncated {
            break;
        }
    }
    let last = fx.steps.last().expect("the fixture has steps");
    assert!(
        last.triggered.iter().all(|&t| t),
        "the fixture exercises every joint's trigger"
    );
    assert_eq!(
        clipped,
        condition == Condition::Severe,
        "the severe fixture exercises clipping"
    );
}
