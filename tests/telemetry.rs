//! Recordings decoded with Rerun's own decoder and checked against the env, step by step.

use gaitscope::damage::DamageEventKind;
use gaitscope::env::AntEnv;
use gaitscope::rollout::{BuiltinPolicy, policy_rng};
use gaitscope::telemetry::{Actor, RecordOptions, Sink, record};
use gaitscope::{Condition, ConditionChoice, GaitConfig};
use re_chunk::Chunk;
use std::collections::BTreeMap;
use std::sync::atomic::AtomicBool;

mod common;
use common::recording_chunks as chunks;

const SEED: u64 = 11;
const STEPS: usize = 80;

fn config() -> GaitConfig {
    let mut c = GaitConfig::default();
    c.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    c.env.max_episode_steps = STEPS;
    c
}

/// What the env reported at each step of the recorded episode, replayed independently.
struct Truth {
    fatigue: Vec<[f64; 8]>,
    torso_geom_xpos: Vec<[f64; 3]>,
    trigger_steps: Vec<(usize, String)>,
    joint_names: Vec<String>,
}

fn truth() -> Truth {
    let mut env = AntEnv::new(config(), SEED).unwrap();
    env.reset_with_seed(SEED);
    let mut rng = policy_rng(SEED);
    let (mut fatigue, mut xpos) = (Vec::new(), Vec::new());
    loop {
        let out = env.step(&BuiltinPolicy::Random.act(&mut rng)).unwrap();
        fatigue.push(*env.damage().fatigue());
        // Geom 1 is the torso sphere (geom 0 is the floor).
        xpos.push(env.physics().geom_xpos()[1]);
        if out.done() {
            break;
        }
    }
    let trigger_steps = env
        .damage()
        .events()
        .iter()
        .filter(|e| e.kind == DamageEventKind::Trigger)
        .map(|e| (e.step, e.joint.clone()))
        .collect();
    Truth {
        fatigue,
        torso_geom_xpos: xpos,
        trigger_steps,
        joint_names: env.actuators().iter().map(|a| a.joint.clone()).collect(),
    }
}

fn options(sink: Sink) -> RecordOptions {
    RecordOptions {
        actors: vec![Actor::Builtin(BuiltinPolicy::Random)],
        config: config(),
        episodes: 1,
        seed: SEED,
        sink,
        start: None,
        attribution: false,
        caption: None,
        fork: None,
    }
}

/// (step → value) of one component on one entity, across chunks.
fn by_step<T>(chunks: &[Chunk], entity: &str, read: impl Fn(&Chunk) -> Vec<T>) -> BTreeMap<i64, T> {
    common::per_step(chunks, entity, read).into_iter().collect()
}

fn check(chunks: &[Chunk], truth: &Truth) {
    let entities: std::collections::BTreeSet<String> =
        chunks.iter().map(|c| c.entity_path().to_string()).collect();
    for e in [
        "/ant/world/legs",
        "/ant/world/torso",
        "/ant/world/goal",
        "/ant/joints/fatigue",
        "/ant/events",
        "/ant/goal/distance",
        "/ant/episode",
    ] {
        assert!(entities.contains(e), "missing {e}; have {entities:?}");
    }
    let scalars = rerun::Scalars::descriptor_scalars().component;
    let fatigue = by_step(chunks, "/ant/joints/fatigue", |c| {
        c.iter_slices::<f64>(scalars)
            .map(|s| <[f64; 8]>::try_from(s).expect("8 joints per row"))
            .collect()
    });
    assert_eq!(fatigue.len(), truth.fatigue.len(), "one row per env step");
    for (t, f) in truth.fatigue.iter().enumerate() {
        // Env step t is logged at global step t + 1; series in actuator order.
        assert_eq!(
            &fatigue[&(t as i64 + 1)],
            f,
            "fatigue at step {t} ({:?})",
            truth.joint_names
        );
    }
    let centers = rerun::Ellipsoids3D::descriptor_centers().component;
    let torso = by_step(chunks, "/ant/world/torso", |c| {
        c.iter_slices::<[f32; 3]>(centers)
            .filter_map(|s| s.first().copied())
            .collect()
    });
    for (t, x) in truth.torso_geom_xpos.iter().enumerate() {
        assert_eq!(
            torso[&(t as i64 + 1)],
            [x[0] as f32, x[1] as f32, x[2] as f32],
            "torso position at step {t}"
        );
    }
    let events = common::text_log(chunks, "/ant/events");
    assert!(
        !truth.trigger_steps.is_empty(),
        "80 random steps trigger some joint"
    );
    assert_eq!(events.len(), truth.trigger_steps.len(), "{events:?}");
    for (step, joint) in &truth.trigger_steps {
        let at = *step as i64 + 1;
        assert!(
            events.iter().any(|(t, e)| *t == at
                && e.starts_with(&format!("step {at}: {joint} triggered at fatigue"))),
            "trigger of {joint} at step {step} not logged at global step {at}: {events:?}"
        );
    }
}

#[test]
fn file_recording_decodes_to_what_the_env_reported() {
    let truth = truth();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("episode.rrd");
    let summary = record(options(Sink::File(path.clone())), &AtomicBool::new(false)).unwrap();
    assert_eq!(summary.steps as usize, truth.fatigue.len());
    check(&common::read_rrd(&path), &truth);
}

#[test]
fn memory_recording_matches_and_is_deterministic() {
    let truth = truth();
    let a = record(options(Sink::Memory), &AtomicBool::new(false)).unwrap();
    let chunks_a = chunks(a.storage.unwrap().take());
    check(&chunks_a, &truth);
    let b = record(options(Sink::Memory), &AtomicBool::new(false)).unwrap();
    let chunks_b = chunks(b.storage.unwrap().take());
    let rows = |cs: &[Chunk]| {
        cs.iter()
            .map(|c| (c.entity_path().to_string(), c.num_rows()))
            .collect::<Vec<_>>()
    };
    assert_eq!(
        rows(&chunks_a),
        rows(&chunks_b),
        "same inputs, same recording"
    );
}

#[test]
fn a_stop_request_still_leaves_a_readable_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("stopped.rrd");
    let summary = record(options(Sink::File(path.clone())), &AtomicBool::new(true)).unwrap();
    assert!(summary.interrupted);
    let file = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
    let msgs: Vec<_> = re_log_encoding::DecoderApp::decode_lazy(file).collect();
    assert!(
        msgs.iter().all(Result::is_ok),
        "the file decodes to the end"
    );
}

/// Run by `.ci/run` on a file the `gaitscope record` binary just exported headlessly:
/// `GAITSCOPE_RRD=FILE cargo test --release --test telemetry -- --ignored`.
#[test]
#[ignore = "needs GAITSCOPE_RRD, set by .ci/run"]
fn exported_file_decodes() {
    let path = std::env::var("GAITSCOPE_RRD").expect("GAITSCOPE_RRD names the exported .rrd");
    let chunks = common::read_rrd(std::path::Path::new(&path));
    let steps = common::rows(&chunks, "/ant/goal/distance");
    assert!(steps >= 1, "the exported recording has steps");
    eprintln!("{path}: {} chunks, {steps} steps", chunks.len());
}

/// Side by side, a lane whose episode ends first waits for the other: its series must show a
/// gap there (a `Clear` right after its last step, then nothing until its next episode), not a
/// line drawn across steps it never ran.
#[test]
fn a_lane_that_ends_early_leaves_a_gap_not_a_line() {
    let mut opts = options(Sink::Memory);
    opts.actors = vec![
        Actor::Builtin(BuiltinPolicy::Random),
        Actor::Builtin(BuiltinPolicy::Zero),
    ];
    opts.episodes = 2;
    // Episode lengths from independent rollouts of each policy on the recording's seed.
    let length = |policy: BuiltinPolicy| {
        let mut env = AntEnv::new(config(), SEED).unwrap();
        env.reset_with_seed(SEED);
        let mut rng = policy_rng(SEED);
        (1..)
            .find(|_| env.step(&policy.act(&mut rng)).unwrap().done())
            .unwrap() as i64
    };
    let (random_len, zero_len) = (length(BuiltinPolicy::Random), length(BuiltinPolicy::Zero));
    assert!(
        random_len < zero_len,
        "the random lane ends first ({random_len} vs {zero_len} steps)"
    );
    let summary = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(summary.storage.unwrap().take());
    let scalars = rerun::Scalars::descriptor_scalars().component;
    let clear = rerun::Clear::descriptor_is_recursive().component;
    for entity in gaitscope::telemetry::SERIES_ENTITIES {
        let path = format!("/random/{entity}");
        let data = steps_with(&chunks, &path, |c| {
            c.iter_slices::<f64>(scalars).map(|s| s.len()).collect()
        });
        let clears = steps_with(&chunks, &path, |c| {
            c.iter_slices::<bool>(clear).map(|s| s.len()).collect()
        });
        if data.is_empty() {
            continue; // latent/probe series: a built-in policy has no z
        }
        // Episode 0 runs global steps 1..=zero_len for the slower lane; episode 1 is reset at
        // zero_len (τ is logged there) and steps from zero_len + 1.
        assert!(
            data.iter().all(|&t| t <= random_len || t >= zero_len),
            "{path}: data inside the gap ({random_len}, {zero_len})"
        );
        assert!(
            data.contains(&random_len),
            "{path}: the lane's last step is logged"
        );
        assert_eq!(
            clears,
            [random_len + 1],
            "{path}: one gap, right after the last step"
        );
    }
    // The lane that ran to the end has no gap.
    let zero_clears = steps_with(&chunks, "/zero/joints/fatigue", |c| {
        c.iter_slices::<bool>(clear).map(|s| s.len()).collect()
    });
    assert!(zero_clears.is_empty(), "{zero_clears:?}");
}

/// Steps at which `entity` has a non-empty value; `count` gives each row's value count.
fn steps_with(chunks: &[Chunk], entity: &str, count: impl Fn(&Chunk) -> Vec<usize>) -> Vec<i64> {
    common::per_step(chunks, entity, count)
        .into_iter()
        .filter(|(_, n)| *n > 0)
        .map(|(t, _)| t)
        .collect()
}

/// The gait diagram: each leg's state lane is a stance state exactly at the steps where MuJoCo's
/// contact list (read here by geom name) has that leg's foot on the floor, and a gap at the others;
/// states are logged only when they change.
#[test]
fn the_gait_diagram_follows_mujoco_foot_contacts() {
    let mut env = AntEnv::new(config(), SEED).unwrap();
    env.reset_with_seed(SEED);
    let mut rng = policy_rng(SEED);
    let feet = [
        "left_ankle_geom",
        "right_ankle_geom",
        "third_ankle_geom",
        "fourth_ankle_geom",
    ];
    let mut stance: Vec<Vec<i64>> = vec![Vec::new(); 4];
    for t in 1.. {
        let out = env.step(&BuiltinPolicy::Random.act(&mut rng)).unwrap();
        let model = env.physics().model();
        let id = |n: &str| {
            model
                .name_to_id(mujoco_rs::prelude::MjtObjBase::mjOBJ_GEOM, n)
                .unwrap() as i32
        };
        let floor = id("floor");
        for (leg, foot) in feet.iter().enumerate() {
            let foot = id(foot);
            if env
                .physics()
                .contact()
                .iter()
                .any(|c| c.geom == [foot, floor] || c.geom == [floor, foot])
            {
                stance[leg].push(t);
            }
        }
        if out.done() {
            break;
        }
    }
    let summary = record(options(Sink::Memory), &AtomicBool::new(false)).unwrap();
    let chunks = chunks(summary.storage.unwrap().take());
    let state = rerun::StateChange::descriptor_state().component;
    let legs = [
        "front_left_leg",
        "front_right_leg",
        "back_leg",
        "right_back_leg",
    ];
    let last_step = *stance.iter().flatten().max().unwrap_or(&0);
    let mut swing_seen = false;
    for (leg, name) in legs.iter().enumerate() {
        let path = format!("/ant/gait/{name}");
        // (step, stance?) at every change; a null or empty state is a swing.
        let changes: Vec<(i64, bool)> = common::per_step(&chunks, &path, |c| {
            c.iter_slices::<String>(state)
                .map(|s| s.iter().any(|v| !v.to_string().is_empty()))
                .collect()
        });
        assert!(!changes.is_empty(), "{path}: no state logged");
        assert!(
            changes.windows(2).all(|w| w[0].1 != w[1].1),
            "{path}: a state logged twice in a row"
        );
        // Forward-fill the changes over the episode's steps.
        let mut on = false;
        let mut logged = Vec::new();
        for t in 1..=last_step.max(changes.last().map_or(0, |c| c.0)) {
            if let Some(&(_, s)) = changes.iter().find(|(at, _)| *at == t) {
                on = s;
            }
            if on && t <= STEPS as i64 {
                logged.push(t);
            }
        }
        assert_eq!(logged, stance[leg], "{path}");
        swing_seen |= logged.len() < STEPS;
    }
    assert!(
        swing_seen,
        "some foot must leave the floor in {STEPS} steps"
    );
}

/// The layout's view properties travel on the blueprint stream, before its activation: every
/// 3-D view follows its model's floor ring, every time-series legend is hidden.
#[test]
fn the_blueprint_makes_cameras_follow_keys_the_models_and_hides_crowded_legends() {
    use rerun::log::LogMsg;
    let roots = vec!["ant".to_string(), "fork".to_string()];
    let (_rec, storage) = gaitscope::telemetry::open(&Sink::Memory, "bp-test", &roots).unwrap();
    let msgs = storage.unwrap().take();
    let activation = msgs
        .iter()
        .position(|m| matches!(m, LogMsg::BlueprintActivationCommand(_)))
        .expect("the blueprint is activated");
    let mut tracked = Vec::new();
    let (mut hidden_legends, mut shown_legends) = (0, 0);
    let mut event_columns = None;
    for (i, msg) in msgs.iter().enumerate() {
        let LogMsg::ArrowMsg(store, arrow) = msg else {
            continue;
        };
        if !store.is_blueprint() {
            continue;
        }
        let chunk = Chunk::from_arrow_msg(arrow).unwrap();
        let path = chunk.entity_path().to_string();
        if path.ends_with("/EyeControls3D") {
            assert!(i < activation, "sent before the activation");
            let component = rerun::external::re_sdk_types::blueprint::archetypes::EyeControls3D::descriptor_tracking_entity().component;
            for s in chunk.iter_slices::<String>(component) {
                tracked.extend(s.iter().map(|t| t.to_string()));
            }
            // A starting eye close behind the Ant (0.41's default frames the whole scene, so
            // the Ant came out a few pixels tall); tracking keeps the offset.
            let eye = rerun::external::re_sdk_types::blueprint::archetypes::EyeControls3D::descriptor_position().component;
            let eyes: Vec<_> = chunk
                .iter_component::<rerun::components::Position3D>(eye)
                .flat_map(|p| p.to_vec())
                .collect();
            assert_eq!(eyes.len(), 1, "one starting eye per view");
            let [x, y, z] = eyes[0].0.0;
            let distance = (x * x + y * y + (z - 0.4) * (z - 0.4)).sqrt();
            assert!(
                (3.0..8.0).contains(&distance),
                "eye {distance} m from the Ant"
            );
        }
        if path.ends_with("/PlotLegend") {
            let component = rerun::external::re_sdk_types::blueprint::archetypes::PlotLegend::descriptor_visible().component;
            for s in chunk.iter_slices::<bool>(component) {
                match s.iter().collect::<Vec<bool>>()[..] {
                    [false] => hidden_legends += 1,
                    [true] => shown_legends += 1,
                    ref other => panic!("{other:?}"),
                }
            }
        }
        if path.ends_with("/TextLogColumns") {
            // The event text before the entity path (a narrow view cut both to "/enc…").
            let component = rerun::external::re_sdk_types::blueprint::archetypes::TextLogColumns::descriptor_text_log_columns().component;
            let raw = chunk
                .raw_component_array(component)
                .expect("columns")
                .to_data();
            event_columns = Some(format!("{raw:?}"));
        }
    }
    tracked.sort();
    assert_eq!(tracked, ["/ant/world/focus", "/fork/world/focus"]);
    // Eight or sixteen lines would cover the plot: fatigue, scale, z and probe keep the key
    // entity instead; the goal distance (a line per model) shows its legend.
    assert_eq!(hidden_legends, 4, "fatigue, scale, z, probe");
    assert_eq!(shown_legends, 1, "goal distance");
    assert!(event_columns.is_some(), "the event log's columns are set");
    let views = common::blueprint_view_names(&msgs);
    assert!(
        views.contains(&"Key: what each colour means".to_string()),
        "{views:?}"
    );
    assert!(
        views.contains(&"Goal distance (m)".to_string()),
        "{views:?}"
    );
}

/// The fatigue view opens only where fatigue can damage a joint: in the paper's world, not in
/// dead-legs, where fatigue accumulates but actuators die by the world's draw.
#[test]
fn the_fatigue_view_opens_only_in_a_world_where_fatigue_damages() {
    for (world, shown) in [("paper", true), ("dead-legs", false)] {
        let mut opts = options(Sink::Memory);
        opts.config = GaitConfig::world(world).unwrap();
        opts.config.env.max_episode_steps = 5;
        let run = record(opts, &AtomicBool::new(false)).unwrap();
        let views = common::active_blueprint_view_names(&run.storage.unwrap().take());
        assert!(
            views.contains(&"Torque scale".to_string()),
            "{world}: {views:?}"
        );
        assert_eq!(
            views.contains(&"Fatigue per joint (τ = threshold)".to_string()),
            shown,
            "{world}: {views:?}"
        );
    }
}

/// The z, PCA and probe views open only where some lane's model has an encoder: a memoryless
/// model's third column shows its actions, commanded and applied, instead of three empty views.
#[test]
fn the_latent_views_open_only_for_a_model_with_an_encoder() {
    let lstm = Actor::load(std::path::Path::new("checkpoints/encoder-lstm")).unwrap();
    let baseline = Actor::load(std::path::Path::new("checkpoints/baseline")).unwrap();
    let random = Actor::Builtin(BuiltinPolicy::Random);
    let cases = [
        ("baseline", vec![baseline.clone()], false),
        ("random", vec![random], false),
        ("lstm", vec![lstm.clone()], true),
        ("baseline beside lstm", vec![baseline, lstm], true),
    ];
    for (name, actors, latent) in cases {
        let mut opts = options(Sink::Memory);
        opts.actors = actors;
        opts.config.env.max_episode_steps = 5;
        let run = record(opts, &AtomicBool::new(false)).unwrap();
        let views = common::active_blueprint_view_names(&run.storage.unwrap().take());
        for view in ["z", "z in PCA basis", "Probe: P(damaged) vs truth"] {
            assert_eq!(
                views.contains(&view.to_string()),
                latent,
                "{name}: {view} in {views:?}"
            );
        }
        for view in [
            "Action commanded per joint (the policy's output)",
            "Action applied per joint (× torque scale)",
        ] {
            assert_eq!(
                views.contains(&view.to_string()),
                !latent,
                "{name}: {view} in {views:?}"
            );
        }
        assert!(
            views.contains(&"Torque scale".to_string()),
            "{name}: {views:?}"
        );
    }
}

/// The key every recording carries: which colour is which model, and what the legs', gait's,
/// probe's and PCA's colours and the endings' words mean.
#[test]
fn the_key_names_each_model_and_every_colour() {
    use gaitscope::rollout::BuiltinPolicy;
    let mut opts = options(Sink::Memory);
    opts.actors = vec![
        Actor::Builtin(BuiltinPolicy::Random),
        Actor::Builtin(BuiltinPolicy::Zero),
    ];
    let run = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(run.storage.unwrap().take());
    let text = rerun::TextDocument::descriptor_text().component;
    let docs: Vec<String> = chunks
        .iter()
        .filter(|c| c.is_static() && c.entity_path().to_string() == "/key")
        .flat_map(|c| c.iter_slices::<String>(text).collect::<Vec<_>>())
        .flat_map(|s| s.iter().map(|l| l.to_string()).collect::<Vec<_>>())
        .collect();
    assert_eq!(docs.len(), 1, "one static key");
    let key = &docs[0];
    for line in [
        "**orange**: random",
        "**blue**: zero",
        "**green**: full torque",
        "**amber → red**: torque lost",
        "**slate**: dead",
        "**violet**: pinned by hand",
        "LEAPT = the torso leapt above the healthy height band",
        "TIMEOUT UPSIDE DOWN",
        "FLIPPED = the torso turned upside down, in a world that ends episodes there",
    ] {
        assert!(key.contains(line), "{line:?} in {key}");
    }
    // The colours the key names are the ones drawn: each lane's trail and goal-distance line
    // in its model's hue (orange, blue: hues 24° and 212° at 80 % saturation, 45 % light).
    let strips = rerun::LineStrips3D::descriptor_colors().component;
    for (root, rgb) in [("random", [207u8, 96, 23]), ("zero", [23, 109, 207])] {
        let trail: Vec<[u8; 4]> = common::per_step(&chunks, &format!("/{root}/world/trail"), |c| {
            c.iter_slices::<u32>(strips)
                .flat_map(|s| s.iter().map(|c| c.to_be_bytes()).collect::<Vec<_>>())
                .collect()
        })
        .into_iter()
        .map(|(_, c)| c)
        .collect();
        assert!(!trail.is_empty());
        assert!(trail.iter().all(|c| c[..3] == rgb), "{root}: {trail:?}");
        let line = common::series_colors(&chunks, &format!("/{root}/goal/distance"));
        assert_eq!(line, [[rgb[0], rgb[1], rgb[2], 255]], "{root}");
        let names = common::series_names(&chunks, &format!("/{root}/goal/distance"));
        assert_eq!(names, [format!("{root}: goal distance")]);
    }
}

/// A leg's colour is the torque its joint has left, whatever fatigue does: under `healthy`
/// joints trigger and keep scale 1, and every leg stays green; under mild and severe a trigger
/// takes torque and the leg turns orange (mild, 0.5) or red (severe, 0.1); a dead joint
/// (the dead-joints world) is slate. Colours decoded from the recording, against the key's end
/// points applied by hand to the env's own account of each joint's scale.
#[test]
fn leg_colours_are_the_torque_each_joint_has_left() {
    let run_condition = |config: GaitConfig| {
        let mut opts = options(Sink::Memory);
        opts.config = config;
        let run = record(opts, &AtomicBool::new(false)).unwrap();
        chunks(run.storage.unwrap().take())
    };
    // Healthy: the random policy triggers joints (fatigue passes τ), yet nothing turns colour.
    let mut healthy = config();
    healthy.damage.condition = ConditionChoice::Fixed(Condition::Healthy);
    let chunks_h = run_condition(healthy.clone());
    common::assert_no_static_shadowing(&chunks_h);
    let events = common::text_log_levels(&chunks_h, "/ant/events");
    assert!(
        events
            .iter()
            .any(|(_, level, text)| text.contains("triggered") && level == "INFO"),
        "a healthy trigger is news (INFO), not a warning: {events:?}"
    );
    assert!(
        events.iter().all(|(_, level, _)| level != "WARN"),
        "{events:?}"
    );
    assert_eq!(common::check_leg_colors(&chunks_h, "/ant", &[]), 0);
    let green = common::expected_leg_color(1.0, false);
    for (step, row) in common::leg_colors(&chunks_h, "/ant") {
        for (_, geom) in common::JOINT_GEOMS {
            assert_eq!(row[geom], green, "{geom} at step {step}");
        }
    }
    // Mild (0.5) and severe (0.1): a triggered joint halfway down the ramp, and near red.
    for (condition, want) in [
        (Condition::Mild, common::expected_leg_color(0.5, false)),
        (Condition::Severe, common::expected_leg_color(0.1, false)),
    ] {
        let mut c = config();
        c.damage.condition = ConditionChoice::Fixed(condition);
        let chunks = run_condition(c);
        assert!(
            common::check_leg_colors(&chunks, "/ant", &[]) > 0,
            "{condition}"
        );
        let seen: std::collections::BTreeSet<[u8; 4]> = common::leg_colors(&chunks, "/ant")
            .values()
            .flat_map(|row| row.values().copied().collect::<Vec<_>>())
            .collect();
        assert!(seen.contains(&want), "{condition}: {seen:?}");
        let events = common::text_log_levels(&chunks, "/ant/events");
        assert!(
            events
                .iter()
                .any(|(_, l, t)| l == "WARN" && t.contains("triggered"))
        );
    }
    // A dead joint: slate from its onset, its stance named so in the gait view.
    let mut dead = GaitConfig::world("dead-joints").unwrap();
    dead.damage.condition = ConditionChoice::Fixed(Condition::Severe);
    dead.env.max_episode_steps = 150;
    let chunks_d = run_condition(dead);
    assert!(common::check_leg_colors(&chunks_d, "/ant", &[]) > 0);
    let slate = common::expected_leg_color(0.0, false);
    assert_eq!(slate, [55, 60, 75, 255]);
    assert!(
        common::leg_colors(&chunks_d, "/ant")
            .values()
            .any(|row| row.values().any(|c| *c == slate))
    );
    let events = common::text_log_levels(&chunks_d, "/ant/events");
    assert!(
        events
            .iter()
            .any(|(_, l, t)| l == "WARN" && t.contains("died; scale → 0")),
        "{events:?}"
    );
}

/// Two models side by side: each root's legs show its own damage, and each model's plot lines
/// carry its name and a hue family of their own (not 16 lines under 8 names).
#[test]
fn compared_models_have_their_own_leg_colours_names_and_hues() {
    use gaitscope::rollout::BuiltinPolicy;
    let mut opts = options(Sink::Memory);
    opts.actors = vec![
        Actor::Builtin(BuiltinPolicy::Random),
        Actor::Builtin(BuiltinPolicy::Zero),
    ];
    let run = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(run.storage.unwrap().take());
    common::assert_no_static_shadowing(&chunks);
    assert!(
        common::check_leg_colors(&chunks, "/random", &[]) > 0,
        "the random policy's severe episode triggers a joint"
    );
    common::check_leg_colors(&chunks, "/zero", &[]);
    let mut hues = Vec::new();
    for root in ["random", "zero"] {
        let names = common::series_names(&chunks, &format!("/{root}/joints/fatigue"));
        assert_eq!(names.len(), 8, "{names:?}");
        assert!(
            names.iter().all(|n| n.starts_with(&format!("{root}: "))),
            "{names:?}"
        );
        let colors = common::series_colors(&chunks, &format!("/{root}/joints/fatigue"));
        assert_eq!(colors.len(), 8);
        assert_eq!(
            colors
                .iter()
                .collect::<std::collections::BTreeSet<_>>()
                .len(),
            8,
            "joints differ in shade"
        );
        for (leaf, n) in [("goal/distance", 1), ("reward", 4)] {
            let names = common::series_names(&chunks, &format!("/{root}/{leaf}"));
            assert_eq!(names.len(), n, "{leaf}: {names:?}");
            assert!(names.iter().all(|s| s.starts_with(root)), "{names:?}");
        }
        hues.push(colors);
    }
    // Each lane's ending is written in its 3-D view, at its last step, with its step count.
    let labels = rerun::Points3D::descriptor_labels().component;
    for root in ["random", "zero"] {
        // Rows with a distance (a lane that ended also has a Clear row after its last step).
        let scalars = rerun::Scalars::descriptor_scalars().component;
        let steps: Vec<(i64, usize)> =
            common::per_step(&chunks, &format!("/{root}/goal/distance"), |c| {
                c.iter_slices::<f64>(scalars).map(|s| s.len()).collect()
            })
            .into_iter()
            .filter(|(_, n)| *n > 0)
            .collect();
        let last = steps.iter().map(|(t, _)| *t).max().unwrap();
        let endings: Vec<(i64, Vec<String>)> =
            common::per_step(&chunks, &format!("/{root}/world/ending"), |c| {
                c.iter_slices::<String>(labels)
                    .map(|s| s.iter().map(|l| l.to_string()).collect())
                    .collect()
            });
        let shown: Vec<_> = endings.iter().filter(|(_, l)| !l.is_empty()).collect();
        assert_eq!(shown.len(), 1, "{root}: {endings:?}");
        assert_eq!(shown[0].0, last, "{root}: at its last step");
        let text = &shown[0].1[0];
        assert!(
            text.ends_with(&format!("after {} steps", steps.len())),
            "{root}: {text}"
        );
        assert!(
            gaitscope::env::Ending::ALL
                .iter()
                .any(|e| text.starts_with(&e.name().to_uppercase())),
            "{text}"
        );
    }
    // Orange family vs blue family: every line of the first is redder than any of the second.
    let max_blue_red = hues[1].iter().map(|c| c[0]).max().unwrap();
    let min_orange_red = hues[0].iter().map(|c| c[0]).min().unwrap();
    assert!(min_orange_red > max_blue_red, "{hues:?}");
}

/// A push is a PUSH event at its first step and an arrow while it acts, ending at the pushed
/// body's centre of mass, cleared the step after (issue 32).
#[test]
fn a_push_is_an_event_and_an_arrow_while_it_acts() {
    let scenario = gaitscope::damage::scenario::Scenario::from_json(
        r#"{"name": "shove", "edits": [
            {"step": 20, "push": {"body": "torso", "force": [0, 40, 0], "steps": 3}}]}"#,
        "test",
    )
    .unwrap();
    let mut opts = options(Sink::Memory);
    opts.config.damage.scenario = Some(scenario);
    let out = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(out.storage.unwrap().take());
    common::assert_no_static_shadowing(&chunks);
    // Env step t is logged at global step t + 1.
    let events = common::text_log(&chunks, "/ant/events");
    let pushes: Vec<&(i64, String)> = events.iter().filter(|(_, t)| t.contains("push")).collect();
    assert_eq!(
        pushes,
        [&(
            21,
            "step 21: scenario shove: push torso by (0, 40, 0) N for 3 steps".to_string()
        )]
    );
    let level = rerun::TextLog::descriptor_level().component;
    let levels = by_step(&chunks, "/ant/events", |c| {
        c.iter_slices::<String>(level)
            .map(|s| s.first().map(|v| v.to_string()).unwrap_or_default())
            .collect()
    });
    assert_eq!(levels[&21], "PUSH");
    let vectors = rerun::Arrows3D::descriptor_vectors().component;
    let arrows = common::per_step(&chunks, "/ant/world/push", |c| {
        c.iter_slices::<[f32; 3]>(vectors)
            .map(|s| s.to_vec())
            .collect()
    });
    let drawn: Vec<(i64, Vec<[f32; 3]>)> =
        arrows.into_iter().filter(|(_, v)| !v.is_empty()).collect();
    // 40 N at 50 N per metre: 0.8 m along +y, on env steps 20, 21, 22.
    assert_eq!(
        drawn,
        (21..=23)
            .map(|t| (t, vec![[0.0, 0.8, 0.0]]))
            .collect::<Vec<_>>()
    );
    // Cleared at the next step: a Clear on the entity at step 24.
    let cleared = chunks.iter().any(|c| {
        c.entity_path().to_string() == "/ant/world/push"
            && c.timelines()
                .get(&"step".into())
                .is_some_and(|t| t.times_raw().contains(&24))
            && c.components()
                .keys()
                .any(|k| k.to_string().contains("Clear"))
    });
    assert!(cleared, "the arrow is cleared after the push");
}

/// `record --attribution`: each step's slot × group heatmap and group totals, which add up
/// (completeness) to how far z is from z(0) — checked against the recording's own z series and
/// z(0) from the policy (issue 32).
#[test]
fn the_attribution_view_adds_up_to_how_far_z_moved() {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-lstm");
    let actor = Actor::load(std::path::Path::new(dir)).unwrap();
    let policy = actor.policy().unwrap().clone();
    let mut opts = options(Sink::Memory);
    opts.actors = vec![actor];
    opts.attribution = true;
    let out = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(out.storage.unwrap().take());
    common::assert_no_static_shadowing(&chunks);
    let net = policy.net();
    let zeros = vec![0.0f32; net.context_len * net.entry_dim()];
    let z0 = gaitscope::explain::integrated_gradients(
        &policy,
        &zeros,
        &vec![0.0; net.obs_dim],
        gaitscope::explain::Target::Z,
        1,
    )
    .unwrap()
    .baseline_output;
    let scalars = rerun::Scalars::descriptor_scalars().component;
    let z = by_step(&chunks, "/ant/latent/z", |c| {
        c.iter_slices::<f64>(scalars).map(|s| s.to_vec()).collect()
    });
    let totals = by_step(&chunks, "/ant/latent/attribution_groups", |c| {
        c.iter_slices::<f64>(scalars).map(|s| s.to_vec()).collect()
    });
    let shapes = by_step(&chunks, "/ant/latent/attribution", |c| {
        c.iter_component::<rerun::components::TensorData>(
            rerun::Tensor::descriptor_data().component,
        )
        .map(|t| t.first().map(|t| t.0.shape.to_vec()).unwrap_or_default())
        .collect()
    });
    assert_eq!(totals.len(), z.len(), "one attribution per step");
    assert!(z.len() > 50);
    let mut worst: f64 = 0.0;
    for (step, z) in &z {
        assert_eq!(shapes[step], [10, 16], "step {step}: groups × window slots");
        let t = &totals[step];
        assert_eq!(t.len(), 10);
        let shift = z
            .iter()
            .zip(&z0)
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f64>()
            .sqrt();
        let sum: f64 = t.iter().sum();
        // f32 network, 32 midpoints: within 1 % of the shift.
        worst = worst.max((sum - shift).abs() / shift);
        assert!(
            (sum - shift).abs() <= 0.01 * shift + 1e-4,
            "step {step}: Σ attribution {sum}, ‖z − z(0)‖ {shift}"
        );
    }
    eprintln!(
        "largest completeness error: {:.3} % of the shift",
        100.0 * worst
    );
    // The series are named by group (joints in actuator order, torso, goal).
    let names = common::series_names(&chunks, "/ant/latent/attribution_groups");
    assert_eq!(names.len(), 10);
    assert!(
        names[0].starts_with("hip_4") && names[8].starts_with("torso"),
        "{names:?}"
    );
    // The picture of the grid: its rows named, its cells the tensor's values on the diverging
    // scale (red raised ‖z − z(0)‖, blue lowered it), pixel for pixel.
    let labels: Vec<String> = chunks
        .iter()
        .filter(|c| {
            c.is_static() && c.entity_path().to_string() == "/ant/latent/attribution_map/labels"
        })
        .flat_map(|c| {
            c.iter_slices::<String>(rerun::Points2D::descriptor_labels().component)
                .flat_map(|s| s.iter().map(|l| l.to_string()).collect::<Vec<_>>())
                .collect::<Vec<_>>()
        })
        .collect();
    let groups: Vec<String> = names
        .iter()
        .map(|n| n.split(" →").next().unwrap().to_string())
        .collect();
    assert_eq!(labels[..10], groups[..], "{labels:?}");
    assert_eq!(labels[10..], ["oldest", "newest"]);
    let grids = by_step(&chunks, "/ant/latent/attribution", |c| {
        c.iter_component::<rerun::components::TensorData>(
            rerun::Tensor::descriptor_data().component,
        )
        .map(|t| match &t.first().unwrap().0.buffer {
            rerun::datatypes::TensorBuffer::F32(v) => v.to_vec(),
            other => panic!("{other:?}"),
        })
        .collect()
    });
    let pictures = by_step(&chunks, "/ant/latent/attribution_map", |c| {
        c.iter_component::<rerun::components::ImageBuffer>(
            rerun::Image::descriptor_buffer().component,
        )
        .map(|b| b.first().unwrap().0.to_vec())
        .collect()
    });
    assert_eq!(pictures.len(), grids.len(), "one picture per step");
    for (step, grid) in &grids {
        let max_abs = grid.iter().fold(0.0f64, |m, v| m.max(f64::from(*v).abs()));
        let expected: Vec<u8> = grid
            .iter()
            .flat_map(|v| gaitscope::palette::diverging(f64::from(*v), max_abs))
            .collect();
        assert_eq!(pictures[step], expected, "step {step}");
    }
}

/// A recording gaitscope made with Rerun 0.36 (committed before the move to 0.41) still reads:
/// our 0.41 decoder finds its legs turning red exactly where its own fatigue and torque-scale
/// series say, and the stock 0.41 CLI verifies it and migrates it (what its viewer does on
/// load) to the same leg colours.
#[test]
fn a_recording_made_with_rerun_0_36_still_reads() {
    let fixture = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/rerun-0.36-encoder-lstm-severe.rrd");
    let old = common::read_rrd(&fixture);
    let threshold = config().damage.threshold;
    let red = check_0_36_leg_colors(&old, threshold);
    assert!(red > 0, "the severe episode shows triggered (red) joints");
    let viewer = common::stock_viewer();
    let dir = tempfile::tempdir().unwrap();
    let copy = dir.path().join("old.rrd");
    std::fs::copy(&fixture, &copy).unwrap();
    let run = |args: &[&std::ffi::OsStr]| {
        let out = std::process::Command::new(viewer)
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "rerun {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    run(&["rrd".as_ref(), "verify".as_ref(), copy.as_os_str()]);
    run(&["rrd".as_ref(), "migrate".as_ref(), copy.as_os_str()]);
    let migrated = common::read_rrd(&copy);
    assert_ne!(
        std::fs::read(&copy).unwrap(),
        std::fs::read(&fixture).unwrap(),
        "migrate rewrote the file"
    );
    assert_eq!(check_0_36_leg_colors(&migrated, threshold), red);
    assert_eq!(
        common::leg_colors(&migrated, "/ant"),
        common::leg_colors(&old, "/ant")
    );
}

/// The 0.36-era leg colours (before colour meant torque lost): red [220, 40, 40] once a joint's
/// scale fell below 1, else green shading to amber by fatigue in tenths of τ. Returns the red
/// (step, joint) pairs.
fn check_0_36_leg_colors(chunks: &[Chunk], threshold: f64) -> usize {
    let fatigue = common::joint_series(chunks, "/ant/joints/fatigue");
    let scale = common::joint_series(chunks, "/ant/joints/scale");
    // Series and colours in actuator order (hip_4, ankle_4, hip_1, …: assets/ant.xml).
    let joints: Vec<String> = AntEnv::new(GaitConfig::default(), 0)
        .unwrap()
        .actuators()
        .iter()
        .map(|a| a.joint.clone())
        .collect();
    let mut red = 0;
    for (step, row) in common::leg_colors(chunks, "/ant") {
        let (Some(f), Some(s)) = (fatigue.get(&step), scale.get(&step)) else {
            continue;
        };
        for (i, joint) in joints.iter().enumerate() {
            let geom = &common::JOINT_GEOMS
                .iter()
                .find(|(j, _)| j == joint)
                .unwrap()
                .1;
            let want = if s[i] < 1.0 {
                red += 1;
                [220, 40, 40, 255]
            } else {
                let k = ((f[i] / threshold).clamp(0.0, 1.0) * 10.0).floor() as f32 / 10.0;
                let lerp = |a: f32, b: f32| (a + (b - a) * k) as u8;
                [lerp(60.0, 240.0), 170, lerp(90.0, 30.0), 255]
            };
            assert_eq!(row[*geom], want, "{geom} at step {step}");
        }
    }
    red
}

/// A scenario's damage is scripted damage, not a hand's: a leg it kills turns slate (and one it
/// weakens follows the ramp), never the violet of a pin by hand, and its events are warnings.
#[test]
fn a_scenario_kills_a_leg_in_slate_with_warnings() {
    let scenario = gaitscope::damage::scenario::Scenario::from_json(
        r#"{"name": "dead-leg", "fatigue": false,
            "edits": [{"step": 10, "joint": "front_left_leg", "scale": 0.0},
                      {"step": 10, "joint": "hip_2", "scale": 0.5}]}"#,
        "test",
    )
    .unwrap();
    let mut opts = options(Sink::Memory);
    opts.config.damage.scenario = Some(scenario);
    let run = record(opts, &AtomicBool::new(false)).unwrap();
    let chunks = chunks(run.storage.unwrap().take());
    // No joint counted as pinned by hand: every colour is its scale's.
    assert!(common::check_leg_colors(&chunks, "/ant", &[]) > 0);
    let colors = common::leg_colors(&chunks, "/ant");
    let last = colors.values().last().unwrap();
    assert_eq!(
        last["left_leg_geom"],
        common::expected_leg_color(0.0, false)
    );
    assert_eq!(
        last["left_ankle_geom"],
        common::expected_leg_color(0.0, false)
    );
    assert_eq!(
        last["right_leg_geom"],
        common::expected_leg_color(0.5, false)
    );
    let events = common::text_log_levels(&chunks, "/ant/events");
    let scripted: Vec<_> = events
        .iter()
        .filter(|(_, _, t)| t.contains("scenario dead-leg"))
        .collect();
    assert_eq!(scripted.len(), 3, "{events:?}");
    assert!(scripted.iter().all(|(_, l, _)| l == "WARN"), "{events:?}");
}
