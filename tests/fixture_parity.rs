//! Our physics, reward and fatigue against Gymnasium 1.4.0's Ant-v4 (MuJoCo 3.17.0) with the
//! goal task and fatigue model, from `../shared/fixtures/` (see its README).

use gaitscope::{AntEnv, Condition, GaitConfig};
use serde::Deserialize;
use std::path::PathBuf;

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

fn fixture() -> Fixture {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/fixtures/gymnasium_ant_v4_mild_parity.json");
    let text = std::fs::read_to_string(&path)
        .unwrap_or_else(|e| panic!("fixture {} unreadable: {e}", path.display()));
    serde_json::from_str(&text).expect("fixture parses")
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
fn reproduces_gymnasium_ant_v4_with_goal_and_fatigue() {
    let fx = fixture();
    assert_eq!(fx.condition, Condition::Mild);
    let config = GaitConfig::default();
    assert_eq!(config.damage.scales.mild, fx.damage_scale);
    let mut env = AntEnv::new(config, 0).unwrap();
    let obs = env
        .reset_to_state(&fx.init_qpos, &fx.init_qvel, fx.condition)
        .unwrap();
    const TOL: f64 = 1e-9;
    assert_close("init obs", 0, &obs, &fx.init_obs, TOL);
    let mut any_trigger = false;
    for s in &fx.steps {
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
        any_trigger |= s.triggered.iter().any(|&t| t);
        if out.terminated || out.truncated {
            break;
        }
    }
    assert!(any_trigger, "the fixture exercises at least one trigger");
}
