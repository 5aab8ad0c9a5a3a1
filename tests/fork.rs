//! `rollout --checkpoint ... --fork-at K --fork EDITS`: a counterfactual lane from the exact
//! state before step K, through the CLI.

use serde_json::Value;
use std::process::Command;

mod common;

const CHECKPOINTS: [&str; 3] = [
    concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-lstm"),
    concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/baseline"),
    concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-mlp"),
];

fn rollout(extra: &[&str]) -> Result<Vec<Value>, String> {
    rollout_of(CHECKPOINTS[0], extra)
}

fn rollout_of(checkpoint: &str, extra: &[&str]) -> Result<Vec<Value>, String> {
    let base = [
        "rollout",
        "--checkpoint",
        checkpoint,
        "--episodes",
        "1",
        "--seed",
        "3",
    ];
    let tail = ["--condition", "severe", "--max-steps", "150", "--jsonl"];
    common::gaitscope_json_lines(base.iter().chain(&tail).chain(extra))
}

fn lane<'a>(rows: &'a [Value], name: &str) -> Vec<&'a Value> {
    rows.iter().filter(|r| r["lane"] == name).collect()
}

fn without_lane(v: &Value) -> Value {
    let mut v = v.clone();
    v.as_object_mut().unwrap().remove("lane");
    v
}

/// Every encoder kind: the fork restores physics, damage and the policy's window exactly.
#[test]
fn a_fork_with_no_edit_repeats_the_main_lane_bit_for_bit() {
    for checkpoint in CHECKPOINTS {
        let rows = rollout_of(checkpoint, &["--fork-at", "12", "--fork", "none"]).unwrap();
        let (main, fork) = (lane(&rows, "main"), lane(&rows, "fork"));
        assert!(main.len() > 20, "{checkpoint}: {} steps", main.len());
        assert_eq!(fork.len(), main.len() - 12);
        assert_eq!(fork[0]["step"], 12, "steps count from the episode start");
        for (m, f) in main[12..].iter().zip(&fork) {
            // serde_json prints f64s exactly (shortest round-trip): equal values are equal bits.
            assert_eq!(without_lane(m), without_lane(f), "{checkpoint}");
        }
    }
}

/// A push of zero newtons through the CLI is `--fork none`, bit for bit (its lines only say
/// which push acted).
#[test]
fn a_zero_push_fork_is_a_fork_with_no_edit() {
    let none = rollout(&["--fork-at", "12", "--fork", "none"]).unwrap();
    let zero = rollout(&["--fork-at", "12", "--fork", "push:torso=0,0,0@5"]).unwrap();
    assert_eq!(none.len(), zero.len());
    let mut pushed = 0;
    for (a, b) in none.iter().zip(&zero) {
        let mut b = b.clone();
        if let Some(p) = b.as_object_mut().unwrap().remove("pushes") {
            assert_eq!(b["lane"], "fork");
            assert_eq!(p[0]["push"]["body"], "torso");
            pushed += 1;
        }
        assert_eq!(*a, b);
    }
    assert_eq!(pushed, 5, "the push acts for its 5 steps");
}

#[test]
fn a_heal_all_fork_applies_what_it_commands_and_leaves_the_main_lane_alone() {
    let plain = rollout(&[]).unwrap();
    let k = 35;
    let rows = rollout(&["--fork-at", &k.to_string(), "--fork", "heal:all"]).unwrap();
    let (main, fork) = (lane(&rows, "main"), lane(&rows, "fork"));
    // The main lane is the run without a fork.
    assert_eq!(main.len(), plain.len());
    for (a, b) in main.iter().zip(&plain) {
        assert_eq!(*a, b);
    }
    // Under severe damage the main lane had joints triggered by step K, so its applied action
    // is scaled down there.
    let before = main[k - 1]["triggered"].as_array().unwrap();
    assert!(
        before.iter().any(|t| t == true),
        "no joint triggered by step {k}"
    );
    // From K on the fork applies exactly what it commands, until fatigue triggers a joint anew.
    let mut checked = 0;
    for row in &fork {
        if row["triggered"]
            .as_array()
            .unwrap()
            .iter()
            .any(|t| t == true)
        {
            break;
        }
        assert_eq!(row["applied_action"], row["action"], "step {}", row["step"]);
        checked += 1;
    }
    assert!(checked >= 5, "only {checked} healed steps");
    assert_eq!(fork[0]["step"], k);
}

#[test]
fn bad_forks_are_clear_errors() {
    for (args, message) in [
        (
            vec!["--fork-at", "5", "--fork", "fail:ankle_9"],
            "unknown joint 'ankle_9'",
        ),
        (
            vec!["--fork-at", "5", "--fork", "scale:ankle_3=1.5"],
            "torque scale 1.5",
        ),
        (
            vec!["--fork-at", "5", "--fork", "break:ankle_3"],
            "bad damage edit 'break:ankle_3'",
        ),
        (
            vec!["--fork-at", "5", "--fork", "heal:"],
            "bad damage edit 'heal:'",
        ),
        (
            vec!["--fork-at", "100000", "--fork", "none"],
            "is beyond the episode",
        ),
        (vec!["--fork-at", "5"], "--fork"),
        (
            vec!["--fork-at", "5", "--fork", "push:tail=1,0,0"],
            "unknown body 'tail' to push",
        ),
        (
            vec!["--fork-at", "5", "--fork", "push:torso=inf,0,0"],
            "must be three finite numbers",
        ),
        (
            vec!["--fork-at", "5", "--fork", "push:torso=0,4000,0@2"],
            "4000 N is more than the 1000 N",
        ),
        (
            vec!["--fork-at", "5", "--fork", "push:torso=0,40"],
            "bad push 'push:torso=0,40'",
        ),
    ] {
        let err = rollout(&args).unwrap_err();
        assert!(err.contains(message), "{args:?}: {err}");
    }
}

/// A policy episode from a given state is the replay of its own actions from that state: the
/// same records, step for step.
#[test]
fn a_policy_from_a_state_matches_the_replay_of_its_actions() {
    let tmp = tempfile::tempdir().unwrap();
    let init = tmp.path().join("init.json");
    // Ant-v4's standing pose with a small lean and push.
    let mut qpos = vec![0.0, 0.0, 0.75, 1.0, 0.0, 0.0, 0.0];
    qpos.extend(
        [0.0, 1.0, 0.0, -1.0, 0.0, -1.0, 0.0, 1.0]
            .iter()
            .map(|v| v * 0.1),
    );
    let qvel: Vec<f64> = (0..14).map(|i| 0.05 * (i as f64 - 7.0)).collect();
    std::fs::write(
        &init,
        serde_json::json!({"qpos": qpos, "qvel": qvel}).to_string(),
    )
    .unwrap();
    let run = |args: &[&str]| -> Vec<Value> {
        let out = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
            .args([
                "rollout",
                "--condition",
                "mild",
                "--max-steps",
                "60",
                "--jsonl",
            ])
            .args(["--init-state", init.to_str().unwrap()])
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout)
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let policy = run(&["--checkpoint", CHECKPOINTS[0]]);
    assert!(policy.len() > 10);
    let actions: Vec<Value> = policy.iter().map(|r| r["action"].clone()).collect();
    let actions_file = tmp.path().join("actions.json");
    std::fs::write(&actions_file, Value::Array(actions).to_string()).unwrap();
    let replay = run(&["--actions", actions_file.to_str().unwrap()]);
    assert_eq!(replay.len(), policy.len());
    for (p, r) in policy.iter().zip(&replay) {
        let mut p = without_lane(p);
        // A policy's lines name their episode and seed; a replay's are one given episode.
        assert_eq!(
            (p["episode"].as_u64(), p["seed"].as_u64()),
            (Some(0), Some(0))
        );
        for key in ["action", "episode", "seed"] {
            p.as_object_mut().unwrap().remove(key);
        }
        assert_eq!(&p, r);
    }
}

/// One rule for the world a checkpoint runs in, in every command: a checkpoint trained with
/// joints that trigger at fatigue 10 triggers them at 10 under `rollout` (it ran in the default
/// world, τ = 30, before the lane core).
#[test]
fn rollout_runs_a_checkpoint_in_its_own_world() {
    let tmp = tempfile::tempdir().unwrap();
    common::save_checkpoint_in_world(tmp.path(), 10.0, 16);
    let lines = common::gaitscope_json_lines([
        "rollout",
        "--checkpoint",
        tmp.path().to_str().unwrap(),
        "--condition",
        "severe",
        "--episodes",
        "1",
        "--max-steps",
        "300",
        "--jsonl",
    ])
    .unwrap();
    // The first step at which any joint is triggered: its fatigue crossed 10, not 30.
    let first = lines
        .iter()
        .find(|l| l["triggered"].as_array().unwrap().iter().any(|t| t == true))
        .expect("a severe episode of 300 steps triggers a joint at τ = 10");
    let i = first["triggered"]
        .as_array()
        .unwrap()
        .iter()
        .position(|t| t == true)
        .unwrap();
    let fatigue = first["fatigue"][i].as_f64().unwrap();
    assert!(
        (10.0..30.0).contains(&fatigue),
        "triggered at fatigue {fatigue}"
    );
}

/// A `--config` given to a checkpoint command is not silently half-applied: what the
/// checkpoint's own task overrides is named, by every command that runs a checkpoint.
#[test]
fn a_config_on_a_checkpoint_command_says_what_it_does_not_set() {
    let tmp = tempfile::tempdir().unwrap();
    common::save_checkpoint_in_world(tmp.path(), 10.0, 16);
    let config = tmp.path().join("c.json");
    std::fs::write(&config, r#"{"damage": {"threshold": 50}}"#).unwrap();
    let out_dir = tempfile::tempdir().unwrap();
    let run = |command: &str, with_config: bool| {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"));
        cmd.args([command, "--checkpoint", tmp.path().to_str().unwrap()])
            .args(["--max-steps", "3"])
            // live stops at "no display" right after its checks: the note comes before.
            .env_remove("DISPLAY")
            .env_remove("WAYLAND_DISPLAY");
        if with_config {
            cmd.arg("--config").arg(&config);
        }
        match command {
            "rollout" => {
                cmd.args(["--episodes", "1"]);
            }
            "record" => {
                cmd.args(["--episodes", "1", "--out"])
                    .arg(out_dir.path().join("r.rrd"));
            }
            "video" => {
                cmd.args(["--width", "64", "--height", "48", "--out"])
                    .arg(out_dir.path().join("v.mp4"));
            }
            _ => {}
        }
        String::from_utf8_lossy(&cmd.output().unwrap().stderr).into_owned()
    };
    for command in ["rollout", "record", "live", "video"] {
        let e = run(command, true);
        assert!(
            e.contains("runs in the task it was trained in: the damage settings"),
            "{command}: {e}"
        );
        // Without --config nothing is said, whatever the checkpoint's task.
        assert!(!run(command, false).contains("note:"), "{command}");
    }
}

/// Every front-end that takes `--fork-at K --fork EDITS` checks it once, the same way, before
/// any step: a joint the model does not have, or K at or past the step limit, is an error and
/// nothing is written.
#[test]
fn every_front_end_refuses_a_bad_fork_before_any_step() {
    use gaitscope::app::{LiveCondition, LiveSetup, SimHandle};
    let tmp = tempfile::tempdir().unwrap();
    let cases = [
        ("5", "fail:knee_9", "unknown joint 'knee_9'"),
        ("60", "heal:all", "beyond the episodes' step limit (60)"),
    ];
    for (at, edits, message) in cases {
        let fork = ["--fork-at", at, "--fork", edits, "--max-steps", "60"];
        for (command, out) in [
            ("rollout", None),
            ("record", Some("r.rrd")),
            ("video", Some("v.mp4")),
        ] {
            let mut cmd = Command::new(env!("CARGO_BIN_EXE_gaitscope"));
            cmd.args([command, "--checkpoint", CHECKPOINTS[0]])
                .args(["--condition", "severe"])
                .args(fork);
            if command == "rollout" {
                cmd.arg("--jsonl");
            }
            if let Some(name) = out {
                cmd.arg("--out").arg(tmp.path().join(name));
            }
            let result = cmd.output().unwrap();
            let err = String::from_utf8_lossy(&result.stderr);
            assert!(!result.status.success(), "{command} {fork:?}");
            assert!(err.contains(message), "{command} {fork:?}: {err}");
            assert!(result.stdout.is_empty(), "{command}: no step printed");
            let left: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
            assert!(left.is_empty(), "{command} wrote {left:?}");
        }
        // live: the simulation thread refuses to start (and the pre-window check says so).
        let setup = LiveSetup {
            checkpoint: CHECKPOINTS[0].into(),
            compare: None,
            condition: LiveCondition::Severe,
            seed: 0,
            speed: 1.0,
            step_limit: 60,
            mode: gaitscope::policy::ActionMode::Deterministic,
            paused: true,
            breakpoints: Vec::new(),
            start: None,
            attribution: false,
            fork: Some(gaitscope::rollout::Fork {
                at: at.parse().unwrap(),
                edits: gaitscope::damage::Edit::parse_list(edits).unwrap(),
            }),
            config: gaitscope::GaitConfig::default(),
        };
        let err = setup.validate().unwrap_err().to_string();
        assert!(err.contains(message), "live: {err}");
        let (rec, _storage) = gaitscope::telemetry::open(
            &gaitscope::telemetry::Sink::Memory,
            "bad-fork",
            &["ant".to_string()],
        )
        .unwrap();
        let Err(err) = SimHandle::spawn(rec, setup) else {
            panic!("live started with a bad fork");
        };
        assert!(err.to_string().contains(message), "live: {err}");
    }
}
