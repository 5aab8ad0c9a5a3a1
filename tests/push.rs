//! Pushes (issue 32, part 2): an external force on a body through MuJoCo's `xfrc_applied`,
//! applied like a damage edit, checked against Newton's second law.

use gaitscope::GaitConfig;
use gaitscope::damage::scenario::Scenario;
use gaitscope::damage::{Condition, ConditionChoice, Edit};
use gaitscope::lane::{Actor, BuiltinPolicy, Fork, Lane, LaneError};
use gaitscope::policy::ActionMode;

fn world(limit: usize) -> GaitConfig {
    let mut c = GaitConfig::default();
    c.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    c.env.max_episode_steps = limit;
    c
}

fn edits(text: &str) -> Vec<Edit> {
    Edit::parse_list(text).unwrap()
}

#[test]
fn a_zero_push_is_no_push_bit_for_bit() {
    let actor = Actor::Builtin(BuiltinPolicy::Random);
    let mut lane = Lane::new(&actor, &world(300), 5).unwrap();
    for _ in 0..10 {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
    }
    let mut plain = lane.fork(&[]).unwrap();
    let mut zero = lane.fork(&edits("push:torso=0,0,0@5")).unwrap();
    for k in 0..40 {
        if plain.is_done() {
            assert!(zero.is_done() && k > 5, "ended at step {k}");
            break;
        }
        let a = plain
            .advance(&actor, ActionMode::Deterministic)
            .unwrap()
            .clone();
        let b = zero
            .advance(&actor, ActionMode::Deterministic)
            .unwrap()
            .clone();
        assert_eq!(b.pushes.len(), usize::from(k < 5), "step {k}");
        assert_eq!(a.outcome, b.outcome, "step {k}");
        assert_eq!((a.qpos, a.qvel), (b.qpos, b.qvel), "step {k}");
        assert_eq!(a.fatigue, b.fatigue, "step {k}");
    }
}

#[test]
fn a_push_moves_the_ant_as_newton_says() {
    // In the air (4 m up, zero torques): no contact, so the Ant's centre of mass gains exactly
    // F·T of momentum relative to the unpushed lane — Δy = ½aT² + aT(t − T), a = F / M.
    let mut w = world(200);
    w.env.healthy_z_range = [0.2, 100.0];
    let actor = Actor::Builtin(BuiltinPolicy::Zero);
    let mut lane = Lane::new(&actor, &w, 3).unwrap();
    let mut qpos = lane.env().qpos().to_vec();
    qpos[2] += 4.0;
    lane.reset_to_state(&qpos, &[0.0; 14], Condition::Healthy)
        .unwrap();
    let torso = lane.env().torso_body();
    let mass = lane.env().physics().model().body_subtreemass()[torso];
    assert!((mass - 0.91).abs() < 0.01, "the Ant weighs {mass} kg");
    let (force, steps) = (20.0, 4);
    let mut pushed = lane
        .fork(&edits(&format!("push:torso=0,{force},0@{steps}")))
        .unwrap();
    let dt = lane.env().dt();
    let a = force / mass;
    for k in 1..=10 {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
        let record = pushed.advance(&actor, ActionMode::Deterministic).unwrap();
        assert_eq!(record.pushes.len(), usize::from(k <= steps));
        let (t, push_t) = (k as f64 * dt, (steps.min(k)) as f64 * dt);
        let predicted = 0.5 * a * push_t * push_t + a * push_t * (t - push_t);
        let com = |l: &Lane| l.env().physics().subtree_com()[torso];
        let (cp, cl) = (com(&pushed), com(&lane));
        let com_dy = cp[1] - cl[1];
        assert!(
            (com_dy - predicted).abs() < 1e-3 * predicted,
            "step {k}: centre of mass moved {com_dy} m, F/M predicts {predicted} m"
        );
        assert!(
            (cp[0] - cl[0]).abs() < 1e-3 * predicted && (cp[2] - cl[2]).abs() < 1e-3 * predicted,
            "step {k}: the centre of mass moved off the push's line: {cp:?} vs {cl:?}"
        );
        // The torso itself swings a little against its legs: within 5 %.
        let torso_dy = pushed.env().qpos()[1] - lane.env().qpos()[1];
        assert!(
            (torso_dy - predicted).abs() < 0.05 * predicted,
            "step {k}: torso moved {torso_dy} m, F/M predicts {predicted} m"
        );
    }
}

#[test]
fn on_the_floor_a_push_moves_the_torso_its_way() {
    // Standing, friction takes part of the impulse: the torso still moves +y, and no further
    // than the frictionless prediction.
    let actor = Actor::Builtin(BuiltinPolicy::Zero);
    let mut lane = Lane::new(&actor, &world(300), 8).unwrap();
    for _ in 0..20 {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
    }
    let mut pushed = lane.fork(&edits("push:torso=0,30,0@5")).unwrap();
    for _ in 0..5 {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
        pushed.advance(&actor, ActionMode::Deterministic).unwrap();
    }
    let dy = pushed.env().qpos()[1] - lane.env().qpos()[1];
    let t = 5.0 * lane.env().dt();
    let frictionless = 0.5 * 30.0 / 0.9109 * t * t;
    assert!(
        dy > 0.2 * frictionless && dy < 1.05 * frictionless,
        "torso moved {dy} m in +y; frictionless {frictionless} m"
    );
}

#[test]
fn a_push_in_a_scenario_lands_at_its_step() {
    let scenario = Scenario::from_json(
        r#"{"name": "shove", "fatigue": false,
            "edits": [{"step": 12, "push": {"body": "torso", "force": [0, -60, 0], "steps": 3}}]}"#,
        "test",
    )
    .unwrap();
    let mut w = world(60);
    w.env.healthy_z_range = [0.2, 100.0];
    w.damage.scenario = Some(scenario);
    let actor = Actor::Builtin(BuiltinPolicy::Zero);
    let mut lane = Lane::new(&actor, &w, 2).unwrap();
    // The same episode by hand: the push applied before step 12.
    let mut plain = world(60);
    plain.env.healthy_z_range = [0.2, 100.0];
    plain.damage.scenario =
        Some(Scenario::from_json(r#"{"name": "shove", "fatigue": false}"#, "test").unwrap());
    let mut by_hand = Lane::new(&actor, &plain, 2).unwrap();
    for step in 0..30 {
        if step == 12 {
            by_hand
                .apply_edit(&edits("push:torso=0,-60,0@3")[0])
                .unwrap();
        }
        let a = lane
            .advance(&actor, ActionMode::Deterministic)
            .unwrap()
            .clone();
        let b = by_hand
            .advance(&actor, ActionMode::Deterministic)
            .unwrap()
            .clone();
        assert_eq!(a.qpos, b.qpos, "step {step}");
        let acting = (12..15).contains(&step);
        assert_eq!(a.pushes.len(), usize::from(acting), "step {step}");
        if acting {
            assert_eq!(a.pushes[0].start, 12);
            assert_eq!(a.pushes[0].source.as_deref(), Some("shove"));
            assert_eq!(a.pushes[0].push.force, [0.0, -60.0, 0.0]);
        }
    }
}

#[test]
fn bad_pushes_are_refused_before_any_step() {
    let w = world(100);
    let err = Fork {
        at: 5,
        edits: edits("push:tail=1,0,0"),
    }
    .validate(&w)
    .unwrap_err();
    assert!(matches!(err, LaneError::Env(_)));
    let text = err.to_string();
    assert!(text.contains("tail") && text.contains("torso"), "{text}");
    for bad in [
        "push:torso=NaN,0,0",
        "push:torso=5000,0,0",
        "push:torso=1,2",
    ] {
        assert!(Edit::parse_list(bad).is_err(), "{bad}");
    }
}

/// Issue 49 #11: one push's 1,000 N cap holds for pushes stacked on one body (before, a
/// thousand 1,000 N pushes at once were accepted); pushes on other bodies, or that cancel, are
/// fine; and no more than 64 act at once.
#[test]
fn stacked_pushes_are_held_to_one_push_cap() {
    let actor = Actor::Builtin(BuiltinPolicy::Zero);
    let mut lane = Lane::new(&actor, &world(50), 3).unwrap();
    lane.apply_edit(&edits("push:torso=800,0,0@10")[0]).unwrap();
    let err = lane
        .apply_edit(&edits("push:torso=300,0,0@10")[0])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("torso") && err.contains("1100 N") && err.contains("1000 N"),
        "{err}"
    );
    // Another body, and a push that brings the torso's total back down, are accepted.
    lane.apply_edit(&edits("push:front_left_leg=800,0,0@10")[0])
        .unwrap();
    lane.apply_edit(&edits("push:torso=-800,0,0@10")[0])
        .unwrap();
    lane.apply_edit(&edits("push:torso=0,900,0@10")[0]).unwrap();
    // The refused push never acted: the torso's force this step is the sum of the accepted.
    lane.advance(&actor, ActionMode::Deterministic).unwrap();
    let on_torso: Vec<[f64; 3]> = lane
        .env()
        .last_pushes()
        .iter()
        .filter(|p| p.push.body == "torso")
        .map(|p| p.push.force)
        .collect();
    assert_eq!(
        on_torso,
        vec![[800.0, 0.0, 0.0], [-800.0, 0.0, 0.0], [0.0, 900.0, 0.0]]
    );

    // At most 64 pushes at once, however small.
    let mut lane = Lane::new(&actor, &world(50), 3).unwrap();
    for _ in 0..32 {
        lane.apply_edit(&edits("push:torso=1,0,0@5")[0]).unwrap();
        lane.apply_edit(&edits("push:torso=-1,0,0@5")[0]).unwrap();
    }
    let err = lane
        .apply_edit(&edits("push:aux_1=1,0,0")[0])
        .unwrap_err()
        .to_string();
    assert!(err.contains("at most 64"), "{err}");
}
