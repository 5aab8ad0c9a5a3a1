//! The env against real MuJoCo: layout, reward terms, fatigue, triggers, overrides, window,
//! determinism and bad inputs. Expected values are derived by hand from the spec.

use gaitscope::config::GaitConfig;
use gaitscope::damage::{DamageEventKind, JointState, N_ACTUATORS};
use gaitscope::env::{ACT_DIM, AntEnv, EnvError, NQ, NV, OBS_DIM};
use gaitscope::lane::{Actor, Lane, StepRecord};
use gaitscope::rollout::{self, BuiltinPolicy};
use gaitscope::window::{ContextWindow, ENTRY_DIM};
use gaitscope::{Condition, ConditionChoice, JointOverride};

fn env_with(condition: Condition, tweak: impl FnOnce(&mut GaitConfig)) -> AntEnv {
    let mut config = GaitConfig::default();
    config.damage.condition = ConditionChoice::Fixed(condition);
    tweak(&mut config);
    AntEnv::new(config, 7).expect("bundled Ant loads")
}

/// Upright Ant at (x, y, z), joints at the given hinge angles, at rest.
fn standing_state(x: f64, y: f64, z: f64) -> (Vec<f64>, Vec<f64>) {
    let mut qpos = vec![0.0; NQ];
    qpos[..7].copy_from_slice(&[x, y, z, 1.0, 0.0, 0.0, 0.0]);
    (qpos, vec![0.0; NV])
}

#[test]
fn actuator_joint_body_table_matches_ant_v4() {
    let env = env_with(Condition::Healthy, |_| {});
    let joints: Vec<&str> = env.actuators().iter().map(|a| a.joint.as_str()).collect();
    assert_eq!(
        joints,
        [
            "hip_4", "ankle_4", "hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3", "ankle_3"
        ]
    );
    // Body ids in ant.xml's depth-first order: world 0, torso 1, then per leg
    // (thigh-aux, aux_i, ankle body) = (2,3,4), (5,6,7), (8,9,10), (11,12,13).
    let bodies: Vec<usize> = env.actuators().iter().map(|a| a.body_id).collect();
    assert_eq!(bodies, [12, 13, 3, 4, 6, 7, 9, 10]);
    assert_eq!(env.actuators()[2].body, "aux_1");
    assert_eq!(env.torso_body(), 1);
    // dt = frame_skip × timestep = 5 × 0.01.
    assert!((env.dt() - 0.05).abs() < 1e-15);
}

#[test]
fn observation_is_qpos_tail_qvel_and_goal_offset() {
    let mut env = env_with(Condition::Healthy, |_| {});
    env.reset_with_seed(3);
    let out = env.step(&[0.3; ACT_DIM]).unwrap();
    let (qpos, qvel) = (env.qpos().to_vec(), env.qvel().to_vec());
    assert_eq!(out.obs.len(), OBS_DIM);
    assert_eq!(&out.obs[..13], &qpos[2..15]);
    assert_eq!(&out.obs[13..27], &qvel[..]);
    let xy = env.torso_xy();
    assert_eq!(out.obs[27], 5.0 - xy[0]);
    assert_eq!(out.obs[28], 5.0 - xy[1]);
    // torso_xy is the torso body's xpos, which MuJoCo computed before the last integration, so
    // it sits within one substep's travel of qpos[0..2].
    assert!((xy[0] - qpos[0]).abs() < 0.05 && (xy[1] - qpos[1]).abs() < 0.05);
}

#[test]
fn reset_noise_stays_in_its_bounds() {
    let mut env = env_with(Condition::Healthy, |_| {});
    env.reset_with_seed(11);
    // qpos = qpos0 + U(−0.1, 0.1): torso at 0.75 m, unit quaternion, joints at 0.
    let qpos0 = [
        0.0, 0.0, 0.75, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    ];
    for (q, q0) in env.qpos().iter().zip(qpos0) {
        assert!((q - q0).abs() <= 0.1, "qpos {q} vs init {q0}");
    }
    assert!(
        env.qpos().iter().zip(qpos0).any(|(q, q0)| q != &q0),
        "noise was applied"
    );
    assert!(env.qvel().iter().any(|&v| v != 0.0));
}

#[test]
fn reward_terms_follow_the_task_formula() {
    let mut env = env_with(Condition::Severe, |_| {});
    let (qpos, qvel) = standing_state(0.0, 0.0, 0.55);
    env.reset_to_state(&qpos, &qvel, Condition::Severe).unwrap();
    let d0 = env.goal_distance();
    assert!(
        (d0 - 50f64.sqrt()).abs() < 1e-12,
        "reset distance is |(5,5) − (0,0)|"
    );
    // Fail actuator 0 by hand: its applied command becomes 0.1 × 0.5.
    env.apply_override(0, JointOverride::FailNow).unwrap();
    let xy0 = env.torso_xy();
    let out = env.step(&[0.5; ACT_DIM]).unwrap();
    let xy1 = env.torso_xy();
    let r = out.reward;
    assert_eq!(out.applied_action[0], 0.05);
    // ctrl cost = 0.5 × (0.05² + 7 × 0.5²) on the *applied* action.
    assert!((r.ctrl_cost - 0.5 * (0.0025 + 7.0 * 0.25)).abs() < 1e-12);
    assert_eq!(r.forward, (xy1[0] - xy0[0]) / 0.05);
    assert_eq!(r.healthy, 1.0);
    assert_eq!(r.native, r.forward + 1.0 - r.ctrl_cost);
    let d1 = (5.0 - xy1[0]).hypot(5.0 - xy1[1]);
    assert!((r.progress - (d0 - d1)).abs() < 1e-12);
    assert_eq!(r.success, 0.0);
    assert!((r.total - (0.5 * r.native + 50.0 * r.progress)).abs() < 1e-12);
    assert!(!out.terminated && !out.truncated);
}

#[test]
fn success_pays_the_bonus_and_terminates() {
    let mut env = env_with(Condition::Healthy, |_| {});
    let (qpos, qvel) = standing_state(4.6, 5.0, 0.55);
    env.reset_to_state(&qpos, &qvel, Condition::Healthy)
        .unwrap();
    let out = env.step(&[0.0; ACT_DIM]).unwrap();
    assert!(out.success && out.terminated && out.distance < 1.0);
    assert_eq!(out.reward.success, 1.0);
    let expected = 0.5 * out.reward.native + 50.0 * out.reward.progress + 200.0;
    assert!((out.reward.total - expected).abs() < 1e-12);
    assert!(matches!(
        env.step(&[0.0; ACT_DIM]),
        Err(EnvError::EpisodeOver)
    ));
}

#[test]
fn unhealthy_height_terminates_but_still_pays_the_healthy_bonus() {
    // Too high (falls only ~1 cm in one step from 1.5 m), and too low for a raised floor of the
    // healthy range (standing at 0.55 m cannot reach 0.8 m in 0.05 s).
    for (z, z_range) in [(1.5, [0.2, 1.0]), (0.55, [0.8, 1.0])] {
        let mut env = env_with(Condition::Healthy, |c| c.env.healthy_z_range = z_range);
        let (qpos, qvel) = standing_state(0.0, 0.0, z);
        env.reset_to_state(&qpos, &qvel, Condition::Healthy)
            .unwrap();
        let out = env.step(&[0.0; ACT_DIM]).unwrap();
        assert!(!out.healthy && out.terminated, "z = {z}");
        assert_eq!(
            out.reward.healthy, 1.0,
            "Ant-v4 pays the bonus on the final step too"
        );
    }
}

#[test]
fn truncates_at_the_step_limit() {
    let mut env = env_with(Condition::Healthy, |c| c.env.max_episode_steps = 3);
    let (qpos, qvel) = standing_state(0.0, 0.0, 0.55);
    env.reset_to_state(&qpos, &qvel, Condition::Healthy)
        .unwrap();
    let done: Vec<bool> = (0..3)
        .map(|_| env.step(&[0.0; ACT_DIM]).unwrap().truncated)
        .collect();
    assert_eq!(done, [false, false, true]);
}

#[test]
fn fatigue_is_recomputed_from_cfrc_ext() {
    let mut env = env_with(Condition::Mild, |_| {});
    env.reset_with_seed(5);
    let action = [0.9, -0.8, 0.7, -0.6, 0.5, -0.4, 0.3, -0.2];
    let mut expected = [0.0; N_ACTUATORS];
    for _ in 0..10 {
        env.step(&action).unwrap();
        let cfrc = env.physics().cfrc_ext();
        for (i, info) in env.actuators().iter().enumerate() {
            let norm = cfrc[info.body_id].iter().map(|v| v * v).sum::<f64>().sqrt();
            expected[i] += 1.0 * f64::abs(action[i]) + 0.1 * norm;
        }
    }
    for (ours, hand) in env.damage().fatigue().iter().zip(expected) {
        assert!((ours - hand).abs() < 1e-9, "{ours} vs {hand}");
    }
    // The ankles touch the floor, so after ten steps some ankle has seen contact force.
    let ankle_contact: f64 = [1, 3, 5, 7]
        .iter()
        .map(|&i| env.damage().fatigue()[i] - action[i].abs() * 10.0)
        .sum();
    assert!(ankle_contact > 0.0);
}

#[test]
fn triggers_persist_and_scale_the_next_steps() {
    // A low threshold so an |a| = 1 command alone triggers on step 4 (fatigue ≥ 5 after 5 steps).
    let mut env = env_with(Condition::Severe, |c| {
        c.damage.threshold = 5.0;
        c.damage.beta = 0.0;
        c.env.healthy_z_range = [0.0, 10.0]; // this test is about damage, not falling
    });
    let (qpos, qvel) = standing_state(0.0, 0.0, 0.55);
    env.reset_to_state(&qpos, &qvel, Condition::Severe).unwrap();
    let action = [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
    for t in 0..12 {
        let out = env.step(&action).unwrap();
        let expected_applied = if t <= 4 { 1.0 } else { 0.1 };
        assert_eq!(out.applied_action[0], expected_applied, "step {t}");
        assert_eq!(out.new_triggers, usize::from(t == 4), "step {t}");
        assert_eq!(out.commanded_action[0], 1.0);
    }
    let events = env.damage().events();
    assert_eq!(events.len(), 1);
    assert_eq!(
        (events[0].step, events[0].actuator, events[0].joint.as_str()),
        (4, 0, "hip_4")
    );
    assert_eq!(events[0].fatigue, 5.0);
    assert_eq!(env.damage().joint_state(0), JointState::Triggered);
}

#[test]
fn manual_overrides_apply_at_the_next_step_and_are_events() {
    let mut env = env_with(Condition::Mild, |_| {});
    env.reset_with_seed(1);
    env.step(&[0.5; ACT_DIM]).unwrap();
    env.step(&[0.5; ACT_DIM]).unwrap();
    env.apply_override(3, JointOverride::SetScale(0.2)).unwrap();
    env.apply_override(6, JointOverride::FailNow).unwrap();
    let out = env.step(&[0.5; ACT_DIM]).unwrap();
    assert_eq!(out.applied_action[3], 0.1);
    assert_eq!(
        out.applied_action[6], 0.25,
        "fail now uses the condition's scale (mild 0.5)"
    );
    let overrides: Vec<_> = env
        .damage()
        .events()
        .iter()
        .filter(|e| matches!(e.kind, DamageEventKind::Override { .. }))
        .map(|e| (e.step, e.actuator))
        .collect();
    assert_eq!(overrides, [(2, 3), (2, 6)]);
    env.apply_override(3, JointOverride::Heal).unwrap();
    assert_eq!(env.step(&[0.5; ACT_DIM]).unwrap().applied_action[3], 0.5);
    assert!(matches!(
        env.apply_override(9, JointOverride::Heal),
        Err(EnvError::Damage(_))
    ));
}

#[test]
fn context_window_follows_the_episode() {
    let mut env = env_with(Condition::Healthy, |_| {});
    let mut window = ContextWindow::new(16);
    let mut obs = env.reset_with_seed(2);
    let mut history = Vec::new();
    for t in 0..20 {
        let action = [0.1 * (t % 5) as f64 - 0.2; ACT_DIM];
        let out = env.step(&action).unwrap();
        window.push(&obs, &action);
        history.push((obs, action));
        obs = out.obs;
        // Window = the last min(t+1, 16) pairs, oldest first, zeros in front.
        let flat = window.as_slice();
        let real = history.len().min(16);
        let pad = 16 - real;
        assert!(flat[..pad * ENTRY_DIM].iter().all(|&v| v == 0.0));
        for (k, (o, a)) in history[history.len() - real..].iter().enumerate() {
            let entry = &flat[(pad + k) * ENTRY_DIM..(pad + k + 1) * ENTRY_DIM];
            let want: Vec<f32> = o.iter().chain(a).map(|&v| v as f32).collect();
            assert_eq!(entry, want.as_slice(), "t = {t}, entry {k}");
        }
    }
    window.clear();
    assert!(window.as_slice().iter().all(|&v| v == 0.0));
}

/// A severe episode of a fixed action list, through the stepping core (a scripted actor).
fn trajectory(seed: u64) -> Vec<StepRecord> {
    let env = env_with(Condition::Severe, |_| {});
    let actions: Vec<[f64; ACT_DIM]> = (0..300)
        .map(|t| [((t * 7 + seed as usize) % 13) as f64 / 6.5 - 1.0; ACT_DIM])
        .collect();
    let actor = Actor::Scripted(actions.into());
    let mut lane = Lane::new(&actor, env.config(), seed).unwrap();
    let mut records = Vec::new();
    while !lane.is_done() && records.len() < 300 {
        let record = lane
            .advance(&actor, gaitscope::policy::ActionMode::Deterministic)
            .unwrap();
        records.push(record.clone());
    }
    records
}

#[test]
fn same_seed_gives_a_bit_identical_trajectory() {
    let a = trajectory(42);
    let b = trajectory(42);
    assert_eq!(a, b);
    assert_ne!(a[0].qpos, trajectory(43)[0].qpos);
    let mut env1 = env_with(Condition::Healthy, |c| {
        c.damage.condition = ConditionChoice::Random
    });
    let mut env2 = env_with(Condition::Healthy, |c| {
        c.damage.condition = ConditionChoice::Random
    });
    for seed in 0..5 {
        let s1 = rollout::run_builtin_episode(&mut env1, BuiltinPolicy::Random, 0, seed).unwrap();
        let s2 = rollout::run_builtin_episode(&mut env2, BuiltinPolicy::Random, 0, seed).unwrap();
        assert_eq!(s1, s2);
    }
}

#[test]
fn random_conditions_cover_all_three() {
    let mut env = env_with(Condition::Healthy, |c| {
        c.damage.condition = ConditionChoice::Random
    });
    let mut seen = [0usize; 3];
    for seed in 0..60 {
        env.reset_with_seed(seed);
        seen[env.condition().index()] += 1;
    }
    assert!(
        seen.iter().all(|&n| n >= 10),
        "uniform over three conditions: {seen:?}"
    );
}

#[test]
fn ankles_trigger_well_before_hips_under_random_actions() {
    // |a| ~ U(0, 1) has mean 0.5, so the action term alone reaches τ = 30 after ~60 steps: that
    // is the hips' pace. Ankles also carry the floor contact, so they must get there far sooner.
    let mut env = env_with(Condition::Mild, |c| {
        c.damage.condition = ConditionChoice::Random
    });
    let (mut hips, mut ankles) = (Vec::new(), Vec::new());
    for seed in 0..60 {
        let summary =
            rollout::run_builtin_episode(&mut env, BuiltinPolicy::Random, 0, seed).unwrap();
        for (joint, step) in summary.trigger_steps {
            if let Some(s) = step {
                if joint.starts_with("hip") {
                    hips.push(s as f64)
                } else {
                    ankles.push(s as f64)
                }
            }
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (hip, ankle) = (mean(&hips), mean(&ankles));
    assert!(
        hips.len() >= 20 && ankles.len() >= 20,
        "{} hip, {} ankle triggers",
        hips.len(),
        ankles.len()
    );
    assert!((45.0..=75.0).contains(&hip), "mean hip trigger step {hip}");
    assert!(ankle < 0.75 * hip, "ankles {ankle} vs hips {hip}");
}

#[test]
fn bad_actions_are_errors_not_clips() {
    let mut env = env_with(Condition::Healthy, |_| {});
    env.reset_with_seed(0);
    let err = env.step(&[0.0; 7]).unwrap_err();
    assert_eq!(
        err.to_string(),
        "action has 7 values, the Ant has 8 actuators"
    );
    let mut action = [0.0; ACT_DIM];
    action[5] = f64::NAN;
    assert_eq!(
        env.step(&action).unwrap_err().to_string(),
        "action[5] is NaN; actions must be finite"
    );
    action[5] = f64::INFINITY;
    assert!(matches!(
        env.step(&action),
        Err(EnvError::NonFiniteAction { index: 5, .. })
    ));
    // Out-of-range but finite values are clipped to [−1, 1].
    let out = env
        .step(&[3.0, -3.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        .unwrap();
    assert_eq!(&out.applied_action[..2], &[1.0, -1.0]);
}

#[test]
fn stepping_before_reset_is_an_error() {
    let mut env = env_with(Condition::Healthy, |_| {});
    assert!(matches!(
        env.step(&[0.0; ACT_DIM]),
        Err(EnvError::EpisodeOver)
    ));
}

#[test]
fn bad_initial_states_are_named() {
    let mut env = env_with(Condition::Healthy, |_| {});
    let err = env
        .reset_to_state(&[0.0; 14], &[0.0; NV], Condition::Healthy)
        .unwrap_err();
    assert_eq!(
        err.to_string(),
        "initial state: qpos has 14 values, the Ant needs 15"
    );
    let mut qvel = [0.0; NV];
    qvel[2] = f64::NEG_INFINITY;
    let (qpos, _) = standing_state(0.0, 0.0, 0.55);
    let err = env
        .reset_to_state(&qpos, &qvel, Condition::Healthy)
        .unwrap_err();
    assert!(err.to_string().contains("qvel[2] is -inf"), "{err}");
}

#[test]
fn unreadable_or_wrong_model_files_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let load = |path: std::path::PathBuf| {
        let mut config = GaitConfig::default();
        config.env.model_path = Some(path);
        AntEnv::new(config, 0).err().expect("load fails")
    };
    let missing = load(dir.path().join("nope.xml"));
    assert!(matches!(missing, EnvError::ModelRead { .. }));
    assert!(missing.to_string().contains("nope.xml"), "{missing}");

    let garbage = dir.path().join("garbage.xml");
    std::fs::write(&garbage, "<mujoco><worldbody><body></mujoco>").unwrap();
    assert!(matches!(load(garbage), EnvError::ModelLoad { .. }));

    let pendulum = dir.path().join("pendulum.xml");
    std::fs::write(
        &pendulum,
        r#"<mujoco><worldbody><body><joint name="j" type="hinge"/><geom size="0.1"/></body></worldbody>
           <actuator><motor joint="j"/></actuator></mujoco>"#,
    )
    .unwrap();
    let err = load(pendulum);
    assert!(matches!(err, EnvError::NotAnAnt { .. }), "{err}");
    assert!(err.to_string().contains("expected nq=15"), "{err}");
}
