//! Dead actuators and the damage oracle (issue 47), against real MuJoCo: a dead actuator applies
//! exactly zero torque from its onset (bit-checked against a bare env told the same by hand);
//! the deaths survive snapshots, forks and saved states; the oracle's extra inputs are the true
//! scales at every step and never reach another model.

use gaitscope::config::GaitConfig;
use gaitscope::damage::{DamageEventKind, JointState, N_ACTUATORS};
use gaitscope::env::{ACT_DIM, AntEnv, OBS_DIM};
use gaitscope::lane::{Actor, Lane};
use gaitscope::policy::{ActionMode, EncoderKind, NetConfig, Privileged};
use gaitscope::{Condition, ConditionChoice, JointOverride};
use rand::{Rng, SeedableRng};

mod common;

fn dead_world(condition: Condition) -> GaitConfig {
    let mut c = GaitConfig::world("dead-joints").expect("shipped world");
    c.damage.condition = ConditionChoice::Fixed(condition);
    c.env.max_episode_steps = 200;
    c
}

fn actions(n: usize, seed: u64) -> Vec<[f64; ACT_DIM]> {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    (0..n)
        .map(|_| std::array::from_fn(|_| rng.random_range(-1.0..=1.0)))
        .collect()
}

/// An episode with at least one death, found by seed (about half of mild episodes' single
/// unit is a leg; every one has a death).
fn episode_with_deaths(world: &GaitConfig) -> (AntEnv, u64) {
    for seed in 0..50 {
        let mut env = AntEnv::new(world.clone(), 0).unwrap();
        env.reset_with_seed(seed);
        if !env.pending_deaths().is_empty() && env.pending_deaths()[0].step > 0 {
            return (env, seed);
        }
    }
    panic!("no episode with a death after step 0 in 50 seeds");
}

#[test]
fn a_dead_actuator_applies_zero_torque_from_its_onset_exactly_as_a_bare_env_told_by_hand() {
    let world = dead_world(Condition::Severe);
    let (mut env, seed) = episode_with_deaths(&world);
    let deaths = env.pending_deaths().to_vec();
    // The bare env: the same goal and no fatigue, no deaths of its own; the same reset draws
    // (the world's draw comes after the reset noise, so the start state is the same).
    let mut bare_config = world.clone();
    bare_config.damage.dead = None;
    let mut bare = AntEnv::new(bare_config, 0).unwrap();
    bare.reset_with_seed(seed);
    assert_eq!(env.qpos(), bare.qpos());

    let acts = actions(150, 5);
    for (t, a) in acts.iter().enumerate() {
        if env.is_done() {
            break;
        }
        // By hand, before the step the death is due at: the same scale pinned.
        for d in deaths.iter().filter(|d| d.step == t) {
            bare.apply_override(d.actuator, JointOverride::SetScale(d.scale))
                .unwrap();
        }
        // The env's scales after the previous step are those this step applies.
        let scales = *env.damage().scale();
        let out = env.step(a).unwrap();
        let bare_out = bare.step(a).unwrap();
        assert_eq!(env.qpos(), bare.qpos(), "step {t}: physics differs");
        assert_eq!(out.applied_action, bare_out.applied_action, "step {t}");
        for i in 0..N_ACTUATORS {
            assert_eq!(out.applied_action[i], scales[i] * a[i].clamp(-1.0, 1.0));
            if let Some(d) = deaths.iter().find(|d| d.actuator == i) {
                if t >= d.step {
                    assert_eq!(out.applied_action[i], 0.0, "step {t}: dead actuator {i}");
                } else {
                    assert_eq!(out.applied_action[i], a[i].clamp(-1.0, 1.0));
                }
            }
        }
    }
    // Each death is one event of its own kind, at its onset step, and the joint reads Dead.
    let dead_events: Vec<_> = env
        .damage()
        .events()
        .iter()
        .filter(|e| e.kind == DamageEventKind::Dead)
        .collect();
    // The deaths whose onset the episode reached (random actions may end it early).
    let happened: Vec<_> = deaths.iter().filter(|d| d.step < env.steps()).collect();
    assert!(!happened.is_empty(), "the episode reached a death");
    assert_eq!(dead_events.len(), happened.len());
    for (e, d) in dead_events.iter().zip(happened) {
        assert_eq!((e.step, e.actuator, e.scale), (d.step, d.actuator, 0.0));
        assert!(e.describe().contains("died"), "{}", e.describe());
        assert_eq!(env.damage().joint_state(d.actuator), JointState::Dead);
    }
    assert_eq!(env.damage().damage_onset(), Some(deaths[0].step));
    // No fatigue trigger in this world, however long the walk.
    assert!(
        env.damage()
            .events()
            .iter()
            .all(|e| e.kind != DamageEventKind::Trigger)
    );
}

#[test]
fn the_death_count_follows_the_condition() {
    for (condition, units) in [
        (Condition::Healthy, 0..=0),
        (Condition::Mild, 1..=2),
        (Condition::Severe, 2..=4),
    ] {
        let mut env = AntEnv::new(dead_world(condition), 0).unwrap();
        for seed in 0..30 {
            env.reset_with_seed(seed);
            let n = env.pending_deaths().len() + env.damage().dead().iter().filter(|&&d| d).count();
            assert!(units.contains(&n), "{condition}: {n} deaths");
        }
    }
    // The paper's world draws none and keeps its fatigue.
    let mut paper = AntEnv::new(GaitConfig::default(), 0).unwrap();
    paper.reset_with_seed(3);
    assert!(paper.pending_deaths().is_empty() && paper.damage().fatigue_triggers());
}

/// A scenario with the rule off damages the Ant alone (docs/scenarios.md: "only the scenario
/// damages joints"): a dead world draws no deaths beside it. With the rule on, the world's
/// deaths come as without a scenario, under the rule's condition.
#[test]
fn a_scenario_with_its_rule_off_is_the_only_damage_in_a_dead_world() {
    let scenario = |fatigue: &str| {
        gaitscope::damage::scenario::Scenario::from_json(
            &format!(
                r#"{{"name": "t", "fatigue": {fatigue}, "edits": [{{"step": 5, "joint": "hip_2", "scale": 0.0}}]}}"#
            ),
            "test",
        )
        .unwrap()
    };
    let mut world = dead_world(Condition::Severe);
    world.damage.scenario = Some(scenario("false"));
    let mut alone = AntEnv::new(world.clone(), 0).unwrap();
    for seed in 0..20 {
        alone.reset_with_seed(seed);
        assert!(
            alone.pending_deaths().is_empty(),
            "seed {seed}: the world drew deaths"
        );
        for _ in 0..10 {
            alone.step(&[0.5; N_ACTUATORS]).unwrap();
        }
        // Only hip_2, from step 5.
        let dead: Vec<&str> = (0..N_ACTUATORS)
            .filter(|&a| alone.damage().scale()[a] == 0.0)
            .map(|a| alone.damage().joint_names()[a].as_str())
            .collect();
        assert_eq!(dead, ["hip_2"], "seed {seed}");
    }
    // The rule on, under severe: the world's deaths again (two to four units' worth each).
    for rule in ["true", r#""severe""#] {
        world.damage.scenario = Some(scenario(rule));
        let mut with_world = AntEnv::new(world.clone(), 0).unwrap();
        for seed in 0..20 {
            with_world.reset_with_seed(seed);
            let n = with_world.pending_deaths().len();
            assert!((2..=4).contains(&n), "{rule}, seed {seed}: {n} deaths");
        }
    }
    // Healthy under the rule: none drawn, as without a scenario.
    world.damage.scenario = Some(scenario(r#""healthy""#));
    let mut healthy = AntEnv::new(world, 0).unwrap();
    healthy.reset_with_seed(0);
    assert!(healthy.pending_deaths().is_empty());
}

/// A death is a damage onset for the probes (`first_onset_steps`), at the step the draw gave
/// it, where fatigue triggers nothing: a world of dead actuators has no fatigue triggers.
#[test]
fn a_death_is_the_joints_damage_onset() {
    let mut world = GaitConfig::world("dead-legs").expect("shipped world");
    world.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    let mut env = AntEnv::new(world, 0).unwrap();
    env.reset_with_seed(3);
    let deaths = env.pending_deaths().to_vec();
    for _ in 0..70 {
        env.step(&[0.0; N_ACTUATORS]).unwrap();
    }
    let mut want = [None; N_ACTUATORS];
    for d in &deaths {
        want[d.actuator] = Some(d.step);
    }
    assert_eq!(deaths.len(), 4, "two legs die under severe");
    assert_eq!(env.damage().first_onset_steps(), want);
    assert_eq!(env.damage().first_trigger_steps(), [None; N_ACTUATORS]);
}

#[test]
fn in_the_dead_legs_world_whole_legs_die_by_step_60() {
    for (condition, legs) in [
        (Condition::Healthy, 0),
        (Condition::Mild, 1),
        (Condition::Severe, 2),
    ] {
        let mut world = GaitConfig::world("dead-legs").expect("shipped world");
        world.damage.condition = ConditionChoice::Fixed(condition);
        let mut env = AntEnv::new(world, 0).unwrap();
        for seed in 0..40 {
            env.reset_with_seed(seed);
            let deaths = env.pending_deaths().to_vec();
            assert_eq!(
                deaths.len(),
                2 * legs,
                "{condition}, seed {seed}: {deaths:?}"
            );
            // A leg dies whole (hip and ankle at the same onset, in [10, 60]) or not at all.
            let onset = |a: usize| deaths.iter().find(|d| d.actuator == a).map(|d| d.step);
            let mut dead_legs = 0;
            for [hip, ankle] in env.leg_actuators() {
                assert_eq!(
                    onset(hip),
                    onset(ankle),
                    "{condition}, seed {seed}: {deaths:?}"
                );
                if let Some(step) = onset(hip) {
                    assert!((10..=60).contains(&step), "{deaths:?}");
                    dead_legs += 1;
                }
            }
            assert_eq!(dead_legs, legs);
        }
    }
}

#[test]
fn an_episode_names_what_its_draw_kills_before_and_after_the_deaths() {
    // dead-legs: whole legs, named by leg; dead-joints: a joint or a leg, each by its own name.
    for (world_name, condition) in [
        ("dead-legs", Condition::Severe),
        ("dead-joints", Condition::Severe),
        ("dead-joints", Condition::Mild),
    ] {
        let mut world = GaitConfig::world(world_name).expect("shipped world");
        world.damage.condition = ConditionChoice::Fixed(condition);
        let mut env = AntEnv::new(world, 0).unwrap();
        let mut saw_leg_and_joint = (false, false);
        for seed in 0..30 {
            env.reset_with_seed(seed);
            let plan = env.pending_deaths().to_vec();
            // Expected by hand from the plan: a leg whose hip and ankle die at one step is
            // named as the leg, any other dying actuator by its joint.
            let onset = |a: usize| plan.iter().find(|d| d.actuator == a).map(|d| d.step);
            let mut want = Vec::new();
            let mut by_leg = Vec::new();
            for (leg, [hip, ankle]) in env.leg_actuators().into_iter().enumerate() {
                if onset(hip).is_some() && onset(hip) == onset(ankle) {
                    want.push(env.leg_names()[leg].clone());
                    by_leg.extend([hip, ankle]);
                }
            }
            for d in &plan {
                if !by_leg.contains(&d.actuator) {
                    want.push(env.damage().joint_names()[d.actuator].clone());
                }
            }
            let mut named = env.drawn_deaths();
            named.sort();
            want.sort();
            assert_eq!(
                named, want,
                "{world_name} {condition} seed {seed}: {plan:?}"
            );
            saw_leg_and_joint.0 |= !by_leg.is_empty();
            saw_leg_and_joint.1 |= by_leg.len() < plan.len();
            // Walk past every death: the names stay (the deaths moved from plan to past).
            let before = env.drawn_deaths();
            let last = plan.iter().map(|d| d.step).max().unwrap_or(0);
            for _ in 0..=last {
                if env.is_done() {
                    break;
                }
                env.step(&[0.0; ACT_DIM]).unwrap();
            }
            if !env.is_done() {
                assert!(env.pending_deaths().is_empty());
            }
            assert_eq!(env.drawn_deaths(), before, "{world_name} seed {seed}");
        }
        assert!(
            saw_leg_and_joint.0,
            "{world_name}: no leg died whole in 30 seeds"
        );
        if world_name == "dead-legs" {
            assert!(!saw_leg_and_joint.1, "dead-legs kills whole legs only");
        } else {
            assert!(
                saw_leg_and_joint.1,
                "{world_name}: no single joint died in 30 seeds"
            );
        }
    }
    // Nothing dies in the paper's world.
    let mut paper = AntEnv::new(GaitConfig::default(), 0).unwrap();
    paper.reset_with_seed(1);
    assert!(paper.drawn_deaths().is_empty());
}

#[test]
fn deaths_to_come_survive_snapshots_forks_and_saved_states() {
    let world = dead_world(Condition::Severe);
    let (mut env, _) = episode_with_deaths(&world);
    let first = env.pending_deaths()[0];
    let acts = actions(first.step + 20, 9);
    // Stop one step before the first death.
    for a in &acts[..first.step - 1] {
        env.step(a).unwrap();
    }
    let snapshot = env.snapshot();
    let saved = env.save();
    assert_eq!(saved.dead_plan, env.pending_deaths());
    let text = serde_json::to_string(&saved).unwrap();
    let mut continued = Vec::new();
    for a in &acts[first.step - 1..] {
        continued.push(env.step(a).unwrap().applied_action);
    }
    // Restore: the same deaths at the same steps.
    let mut restored = AntEnv::new(world.clone(), 0).unwrap();
    restored.restore(&snapshot).unwrap();
    let from_snapshot: Vec<_> = acts[first.step - 1..]
        .iter()
        .map(|a| restored.step(a).unwrap().applied_action)
        .collect();
    assert_eq!(from_snapshot, continued);
    // A saved state (through JSON): the same.
    let mut from_file = AntEnv::new(world.clone(), 0).unwrap();
    from_file
        .start_from_save(&serde_json::from_str(&text).unwrap())
        .unwrap();
    let from_save: Vec<_> = acts[first.step - 1..]
        .iter()
        .map(|a| from_file.step(a).unwrap().applied_action)
        .collect();
    assert_eq!(from_save, continued);
    assert_eq!(from_file.damage().dead(), env.damage().dead());
    // A saved state whose pending death names no actuator, or lies in its past, is refused.
    let mut bad = saved.clone();
    bad.dead_plan[0].actuator = 8;
    let err = AntEnv::new(world.clone(), 0)
        .unwrap()
        .start_from_save(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("actuator 8"), "{err}");
    let mut bad = saved.clone();
    bad.dead_plan[0].step = 0;
    let err = AntEnv::new(world, 0)
        .unwrap()
        .start_from_save(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("before the state's step"), "{err}");
}

#[test]
fn without_world_damage_no_world_death_comes() {
    // The live viewer's manual condition: only a hand damages joints, in every world.
    let mut world = GaitConfig::world("dead-legs").expect("shipped world");
    world.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    let dir = tempfile::tempdir().unwrap();
    save_model(dir.path(), NetConfig::ant(EncoderKind::None), &world);
    let actor = Actor::load(dir.path()).unwrap();
    let mut lane = Lane::new(&actor, &world, 4).unwrap();
    assert_eq!(lane.env().pending_deaths().len(), 4, "severe: two legs");
    let start = lane.env().qpos().to_vec();
    lane.set_world_damage(false);
    lane.reset(4);
    assert!(lane.env().pending_deaths().is_empty());
    // The same start: the deaths' draw is made and dropped, not skipped.
    assert_eq!(lane.env().qpos(), &start[..]);
    while lane.steps() < 80 && !lane.is_done() {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
    }
    assert!(lane.env().damage().dead().iter().all(|&d| !d));
    assert_eq!(lane.env().damage().scale(), &[1.0; N_ACTUATORS]);
    lane.set_world_damage(true);
    lane.reset(4);
    assert_eq!(
        lane.env().pending_deaths().len(),
        4,
        "on again from the next reset"
    );
}

#[test]
fn a_fork_heals_a_dead_joint_by_hand() {
    let world = dead_world(Condition::Mild);
    let dir = tempfile::tempdir().unwrap();
    save_model(dir.path(), NetConfig::ant(EncoderKind::None), &world);
    let actor = Actor::load(dir.path()).unwrap();
    let (_, seed) = episode_with_deaths(&world);
    let mut lane = Lane::new(&actor, &world, seed).unwrap();
    let death = lane.env().pending_deaths()[0];
    while lane.steps() <= death.step && !lane.is_done() {
        lane.advance(&actor, ActionMode::Deterministic).unwrap();
    }
    assert_eq!(lane.env().damage().scale()[death.actuator], 0.0);
    let joint = lane.env().damage().joint_names()[death.actuator].clone();
    let healed = lane
        .fork(&gaitscope::damage::Edit::parse_list(&format!("heal:{joint}")).unwrap())
        .unwrap();
    assert_eq!(healed.env().damage().scale()[death.actuator], 1.0);
    assert_eq!(
        healed.env().damage().joint_state(death.actuator),
        JointState::Healthy
    );
}

fn save_model(dir: &std::path::Path, net: NetConfig, world: &GaitConfig) {
    let net = NetConfig {
        hidden: vec![16, 16],
        ..net
    };
    common::save_untrained(dir, net, world);
}

#[test]
fn the_oracle_reads_the_true_scales_at_every_step_and_no_other_model_does() {
    the_oracle_reads(Privileged::Damage, |scale| scale);
}

#[test]
fn the_torque_lost_oracle_reads_one_minus_the_true_scales_at_every_step() {
    the_oracle_reads(Privileged::TorqueLost, |scale| 1.0 - scale);
}

/// An oracle of `kind` reads `told(scale)` per actuator after its observation, in training and
/// in every lane, and no other model reads anything but its observation.
fn the_oracle_reads(kind: Privileged, told: fn(f64) -> f64) {
    let world = dead_world(Condition::Severe);
    let net = NetConfig::ant_oracle(kind);
    assert_eq!(net.obs_dim, OBS_DIM + N_ACTUATORS);
    net.check_inputs().unwrap();
    // A privileged encoder model makes no sense and is refused.
    let bad = NetConfig {
        privileged: kind,
        ..NetConfig::ant(EncoderKind::Lstm)
    };
    assert!(bad.check_inputs().unwrap_err().contains("memoryless"));

    // The trainer's task: observation, then the scales the next action is applied with.
    let (probe_env, seed) = episode_with_deaths(&world);
    drop(probe_env);
    let env = AntEnv::new(world.clone(), 0).unwrap();
    let mut task = gaitscope::train::AntTask::new(env, kind);
    use gaitscope::train::Task;
    assert_eq!(task.obs_dim(), OBS_DIM + N_ACTUATORS);
    let mut obs = task.reset_with_seed(seed);
    let mut saw_dead = false;
    for a in actions(140, 2) {
        let scales = *task.env.damage().scale();
        let want: Vec<f64> = scales.iter().map(|&s| told(s)).collect();
        assert_eq!(&obs[OBS_DIM..], &want[..]);
        saw_dead |= scales.contains(&0.0);
        let out = task.step(&a).unwrap();
        obs = out.obs;
        if out.terminated || out.truncated {
            break;
        }
    }
    assert!(saw_dead, "the episode's deaths reached the oracle's input");
    // A baseline's task is the observation alone.
    let mut plain =
        gaitscope::train::AntTask::new(AntEnv::new(world.clone(), 0).unwrap(), Privileged::None);
    assert_eq!(plain.reset_with_seed(seed).len(), OBS_DIM);

    // A lane: the oracle checkpoint decides from [obs, true scales], lane by lane and in
    // lockstep alike; the world and the privileged inputs round-trip through checkpoint.json.
    let dir = tempfile::tempdir().unwrap();
    save_model(dir.path(), net, &world);
    let actor = Actor::load(dir.path()).unwrap();
    let policy = actor.policy().unwrap();
    assert_eq!(policy.net().privileged, kind);
    assert_eq!(policy.meta.env.world.0, "dead-joints");
    // Asked for in the paper's world, the checkpoint runs in its own (the caller's condition and
    // step limit apply).
    let mut requested = GaitConfig::default();
    requested.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    requested.env.max_episode_steps = 200;
    let mut lane = Lane::new(&actor, &requested, seed).unwrap();
    assert_eq!(lane.env().config().world.0, "dead-joints", "its own world");
    assert_eq!(lane.env().config().env.goal, [10.0, 10.0]);
    let mut lockstep = vec![Lane::new(&actor, &requested, seed).unwrap()];
    let mut saw_dead = false;
    while !lane.is_done() && lane.steps() < 140 {
        let mut input = Vec::new();
        input.extend(lane.obs().iter().map(|&v| v as f32));
        input.extend(lane.env().damage().scale().iter().map(|&v| told(v) as f32));
        saw_dead |= lane.env().damage().scale().contains(&0.0);
        let want = policy
            .act_batch(&input, None, ActionMode::Deterministic, None)
            .unwrap()
            .remove(0)
            .action;
        let got = lane
            .advance(&actor, ActionMode::Deterministic)
            .unwrap()
            .outcome
            .commanded_action;
        gaitscope::lane::advance_lockstep(&actor, &mut lockstep, ActionMode::Deterministic)
            .unwrap();
        let batched = lockstep[0].last().unwrap().outcome.commanded_action;
        for i in 0..ACT_DIM {
            assert_eq!(got[i], want[i].clamp(-1.0, 1.0));
            assert_eq!(batched[i], got[i]);
        }
    }
    assert!(saw_dead);
    // Its input differs from the observation alone once a joint is dead: the scales matter.
    let mut obs_only = Vec::new();
    obs_only.extend(lane.obs().iter().map(|&v| v as f32));
    obs_only.extend([told(1.0) as f32; N_ACTUATORS]);
    assert_ne!(
        policy
            .act_batch(&obs_only, None, ActionMode::Deterministic, None)
            .unwrap()[0]
            .action,
        {
            let mut input = Vec::new();
            input.extend(lane.obs().iter().map(|&v| v as f32));
            input.extend(lane.env().damage().scale().iter().map(|&v| told(v) as f32));
            policy
                .act_batch(&input, None, ActionMode::Deterministic, None)
                .unwrap()
                .remove(0)
                .action
        }
    );
    // A hand-edited checkpoint.json whose input size disagrees with its privileged inputs.
    let meta_path = dir.path().join("checkpoint.json");
    let text = std::fs::read_to_string(&meta_path).unwrap();
    std::fs::write(
        &meta_path,
        text.replace("\"obs_dim\": 37", "\"obs_dim\": 29"),
    )
    .unwrap();
    let err = Actor::load(dir.path()).err().unwrap().to_string();
    assert!(err.contains("obs_dim 29 does not fit"), "{err}");
}

/// The ablation that asks what knowing the damage is worth: an oracle told every joint is
/// healthy decides, at every step of a dead-joint episode, exactly as the same network does
/// from [observation, 1 × 8] (lane by lane and in lockstep); a model without privileged inputs
/// cannot be told anything; and in eval the told-healthy oracle is its own model whose healthy
/// episodes are the oracle's own, bit for bit (all scales are 1 there anyway), while its
/// severe episodes are not.
#[test]
fn an_oracle_told_healthy_reads_ones_and_eval_pairs_it_with_the_truth() {
    use gaitscope::eval::{Case, EvalOptions, evaluate};
    use gaitscope::policy::OracleView;
    let world = dead_world(Condition::Severe);
    let root = tempfile::tempdir().unwrap();
    let oracle_dir = root.path().join("oracle-s3");
    save_model(
        &oracle_dir,
        NetConfig::ant_oracle(Privileged::Damage),
        &world,
    );
    let baseline_dir = root.path().join("baseline-s3");
    save_model(&baseline_dir, NetConfig::ant(EncoderKind::None), &world);

    let baseline = gaitscope::policy::Policy::load(&baseline_dir, None).unwrap();
    let err = baseline
        .with_oracle_view(OracleView::ToldHealthy)
        .unwrap_err();
    assert!(err.to_string().contains("only an oracle"), "{err}");

    let truth = Actor::load(&oracle_dir).unwrap();
    let told = gaitscope::policy::Policy::load(&oracle_dir, None)
        .unwrap()
        .with_oracle_view(OracleView::ToldHealthy)
        .unwrap();
    let network = told.clone().with_oracle_view(OracleView::Truth).unwrap();
    let told = Actor::from_policy(&oracle_dir, told);
    let (probe_env, seed) = episode_with_deaths(&world);
    drop(probe_env);
    let mut lane = Lane::new(&told, &world, seed).unwrap();
    let mut lockstep = vec![Lane::new(&told, &world, seed).unwrap()];
    let (mut saw_dead, mut differs) = (false, false);
    while !lane.is_done() && lane.steps() < 140 {
        let scales = *lane.env().damage().scale();
        saw_dead |= scales.contains(&0.0);
        let decide = |told: &[f64; N_ACTUATORS]| {
            let mut input: Vec<f32> = lane.obs().iter().map(|&v| v as f32).collect();
            input.extend(told.iter().map(|&v| v as f32));
            network
                .act_batch(&input, None, ActionMode::Deterministic, None)
                .unwrap()
                .remove(0)
                .action
        };
        let want = decide(&[1.0; N_ACTUATORS]);
        differs |= want != decide(&scales);
        let got = lane
            .advance(&told, ActionMode::Deterministic)
            .unwrap()
            .outcome
            .commanded_action;
        gaitscope::lane::advance_lockstep(&told, &mut lockstep, ActionMode::Deterministic).unwrap();
        let batched = lockstep[0].last().unwrap().outcome.commanded_action;
        for i in 0..ACT_DIM {
            assert_eq!(got[i], want[i].clamp(-1.0, 1.0));
            assert_eq!(batched[i], got[i]);
        }
    }
    assert!(
        saw_dead && differs,
        "a death reached the episode and the truth would have differed"
    );
    drop(truth);

    let options = |told_healthy: Vec<std::path::PathBuf>| EvalOptions {
        checkpoints: vec![oracle_dir.clone()],
        told_healthy,
        episodes: 4,
        seed_base: 40,
        conditions: vec![
            Case::Condition(Condition::Healthy),
            Case::Condition(Condition::Severe),
        ],
        scenarios: Vec::new(),
        max_steps: 150,
        threads: 1,
    };
    let err = evaluate(&options(vec![baseline_dir.clone()]))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("--told-healthy") && err.contains("baseline-s3"),
        "{err}"
    );
    let report = evaluate(&options(vec![oracle_dir.clone()])).unwrap();
    let of = |model: &str, case: Condition| -> Vec<(usize, u64)> {
        report
            .episodes
            .iter()
            .filter(|e| e.model == model && e.condition == Case::Condition(case))
            .map(|e| (e.steps, e.episode_return.to_bits()))
            .collect()
    };
    assert_eq!(of("oracle-told-healthy-s3", Condition::Healthy).len(), 4);
    assert_eq!(
        of("oracle-told-healthy-s3", Condition::Healthy),
        of("oracle-s3", Condition::Healthy)
    );
    assert_ne!(
        of("oracle-told-healthy-s3", Condition::Severe),
        of("oracle-s3", Condition::Severe)
    );
    assert!(
        report
            .episodes
            .iter()
            .any(|e| e.group == "oracle-told-healthy")
    );
    assert_eq!(
        gaitscope::eval::told_healthy_label("oracle-s12"),
        "oracle-told-healthy-s12"
    );
    assert_eq!(
        gaitscope::eval::told_healthy_label("oracle"),
        "oracle-told-healthy"
    );
}

/// `train --init-from`: a fresh oracle started from a trained baseline acts exactly as that
/// baseline, whatever damage it is told, and a fresh encoder model whatever its window holds,
/// until they update; the run names its source; a source that cannot start it is refused
/// before anything is written.
#[test]
fn a_warm_started_oracle_or_encoder_acts_as_its_baseline_whatever_it_is_told() {
    use gaitscope::policy::Policy;
    use gaitscope::train;
    use std::sync::Arc;
    use std::sync::atomic::AtomicBool;

    let world = GaitConfig::world("dead-legs").expect("shipped world");
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().join("baseline");
    save_model(&base, NetConfig::ant(EncoderKind::None), &world);
    let warm_options = |out: &str, net: NetConfig, world: &GaitConfig, from: &std::path::Path| {
        let mut opts = train::ant_options(net.encoder, 60, 5, dir.path().join(out));
        opts.net = NetConfig {
            hidden: vec![16, 16],
            context_len: world.context.len,
            ..net
        };
        opts.env = world.clone();
        // No update within the run: its weights stay the ones it started from.
        opts.sac.learning_starts = 60;
        opts.progress_bar = false;
        opts.init_from = Some(from.to_path_buf());
        opts
    };
    let stop = || Arc::new(AtomicBool::new(false));
    let oracle_opts = warm_options(
        "oracle",
        NetConfig::ant_oracle(Privileged::Damage),
        &world,
        &base,
    );
    train::train_ant(oracle_opts, false, stop()).unwrap();
    let oracle_dir = dir.path().join("oracle");
    let baseline = Policy::load(&base, None).unwrap();
    let oracle = Policy::load(&oracle_dir, None).unwrap();
    assert_eq!(oracle.net().privileged, Privileged::Damage);
    let window = gaitscope::window::ContextWindow::new(world.context.len);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
    for _ in 0..20 {
        let obs: Vec<f64> = (0..OBS_DIM).map(|_| rng.random_range(-2.0..2.0)).collect();
        let scales: [f64; N_ACTUATORS] = std::array::from_fn(|_| rng.random_range(0.0..=1.0));
        let act = |p: &Policy| {
            p.act_one(&obs, &scales, &window, ActionMode::Deterministic, None)
                .unwrap()
                .action
        };
        assert_eq!(act(&oracle), act(&baseline), "told {scales:?}");
    }
    let state: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(oracle_dir.join("train_state.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(state["warm_start"]["from"], base.to_str().unwrap());
    assert_eq!(state["warm_start"]["steps_done"], 0);

    // An encoder model: z's first-layer rows at zero, so whatever the window holds (a random,
    // full one here) it acts as the baseline; its encoders are its own fresh ones, so z itself
    // is not zero.
    for encoder in [EncoderKind::Lstm, EncoderKind::MlpWindow] {
        let name = format!("warm-{encoder}");
        let opts = warm_options(&name, NetConfig::ant(encoder), &world, &base);
        train::train_ant(opts, false, stop()).unwrap();
        let model = Policy::load(&dir.path().join(&name), None).unwrap();
        assert_eq!(model.net().encoder, encoder);
        for _ in 0..10 {
            let mut window = gaitscope::window::ContextWindow::new(world.context.len);
            for _ in 0..world.context.len {
                let o: Vec<f64> = (0..OBS_DIM).map(|_| rng.random_range(-2.0..2.0)).collect();
                let a: Vec<f64> = (0..N_ACTUATORS)
                    .map(|_| rng.random_range(-1.0..1.0))
                    .collect();
                window.push(&o, &a);
            }
            let obs: Vec<f64> = (0..OBS_DIM).map(|_| rng.random_range(-2.0..2.0)).collect();
            let healthy = [1.0; N_ACTUATORS];
            let act = |p: &Policy| {
                p.act_one(&obs, &healthy, &window, ActionMode::Deterministic, None)
                    .unwrap()
            };
            let (warm, source) = (act(&model), act(&baseline));
            assert_eq!(warm.action, source.action, "{encoder}");
            let z = warm.z.expect("an encoder model reports its z");
            assert!(z.iter().any(|v| *v != 0.0), "{encoder}: z {z:?}");
        }
    }

    // Refused, with nothing written: an oracle as source (of an oracle or an encoder model),
    // another world, an encoder model told the damage.
    let oracle_as_source =
        warm_options("a", NetConfig::ant(EncoderKind::None), &world, &oracle_dir);
    let paper = GaitConfig::default();
    let other_world = warm_options("b", NetConfig::ant(EncoderKind::None), &paper, &base);
    let encoder_from_oracle =
        warm_options("c", NetConfig::ant(EncoderKind::Lstm), &world, &oracle_dir);
    for (opts, want) in [
        (oracle_as_source, "reads privileged inputs 'damage'"),
        (
            other_world,
            "trained in world 'dead-legs', this run is in 'paper'",
        ),
        (encoder_from_oracle, "reads privileged inputs 'damage'"),
    ] {
        let out = opts.out.clone();
        let err = train::train_ant(opts, false, stop())
            .unwrap_err()
            .to_string();
        assert!(err.contains(want) && err.contains("--init-from"), "{err}");
        assert!(!out.exists(), "{} was written", out.display());
    }
}
