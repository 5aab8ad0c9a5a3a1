//! The `gaitscope` binary: summaries, the replay formats (checked against the Gymnasium
//! fixture), and clear errors for bad files and flags.

mod common;
#[path = "common/gymnasium.rs"]
mod gymnasium;

use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn gaitscope(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(args)
        .output()
        .expect("binary runs")
}

fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.to_string_lossy().into_owned()
}

#[test]
fn json_summaries_have_one_object_per_episode() {
    let out = gaitscope(&[
        "rollout",
        "--episodes",
        "3",
        "--seed",
        "5",
        "--condition",
        "severe",
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let lines: Vec<Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    for (k, line) in lines.iter().enumerate() {
        assert_eq!(line["episode"], k);
        assert_eq!(line["seed"], 5 + k);
        assert_eq!(line["condition"], "severe");
        let triggers = line["trigger_steps"].as_object().unwrap();
        assert_eq!(triggers.len(), 8);
        assert!(triggers.contains_key("hip_1") && triggers.contains_key("ankle_4"));
        assert!(line["steps"].as_u64().unwrap() >= 1);
    }
    // Deterministic: the same command prints the same bytes.
    let again = gaitscope(&[
        "rollout",
        "--episodes",
        "3",
        "--seed",
        "5",
        "--condition",
        "severe",
        "--json",
    ]);
    assert_eq!(out.stdout, again.stdout);
    // The default step limit is the evaluation's 500 (a standing Ant never ends sooner).
    let out = gaitscope(&["rollout", "--policy", "zero", "--episodes", "1", "--json"]);
    let line: Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(
        (line["steps"].as_u64(), line["truncated"].as_bool()),
        (Some(500), Some(true))
    );
}

#[test]
fn text_summary_names_condition_and_triggers() {
    let out = gaitscope(&[
        "rollout",
        "--policy",
        "zero",
        "--episodes",
        "1",
        "--condition",
        "mild",
        "--max-steps",
        "20",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    // 20 steps of the zero policy trigger nothing: the line says so in words, and how the
    // episode ended (the step limit).
    assert!(
        text.contains("mild") && text.contains("20 steps") && text.contains("timeout"),
        "{text}"
    );
    assert!(
        text.trim_end().ends_with("fatigue triggers: none"),
        "{text}"
    );
}

#[test]
fn replay_reproduces_the_gymnasium_fixtures() {
    for (condition, path) in gymnasium::fixtures() {
        let fx: Value = serde_json::from_str(&gymnasium::read(&path)).unwrap();
        replay_reproduces(condition, &fx);
    }
}

fn replay_reproduces(condition: &str, fx: &Value) {
    let dir = tempfile::tempdir().unwrap();
    let init = serde_json::json!({"qpos": fx["init_qpos"], "qvel": fx["init_qvel"]});
    let actions: Vec<Value> = fx["steps"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["action"].clone())
        .collect();
    let init_path = write(dir.path(), "init.json", &init.to_string());
    let actions_path = write(
        dir.path(),
        "actions.json",
        &Value::from(actions).to_string(),
    );
    let out = gaitscope(&[
        "rollout",
        "--condition",
        condition,
        "--init-state",
        &init_path,
        "--actions",
        &actions_path,
        "--jsonl",
    ]);
    assert!(out.status.success(), "{condition}: {}", stderr(&out));
    let ours: Vec<Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let theirs = fx["steps"].as_array().unwrap();
    assert_eq!(ours.len(), theirs.len(), "{condition}: steps");
    for (o, t) in ours.iter().zip(theirs) {
        for field in [
            "obs",
            "fatigue",
            "applied_action",
            "torso_xy",
            "qpos",
            "qvel",
            "reward",
        ] {
            let flat = |v: &Value| -> Vec<f64> {
                match v {
                    Value::Array(a) => a.iter().map(|x| x.as_f64().unwrap()).collect(),
                    x => vec![x.as_f64().unwrap()],
                }
            };
            for (a, b) in flat(&o[field]).iter().zip(flat(&t[field])) {
                assert!(
                    (a - b).abs() <= 1e-9 * b.abs().max(1.0),
                    "{condition}: {field} at step {}: {a} vs {b}",
                    o["step"]
                );
            }
        }
        for field in ["step", "terminated", "truncated", "triggered"] {
            assert_eq!(o[field], t[field], "{condition}: {field}");
        }
    }
}

#[test]
fn replay_stops_when_the_episode_ends() {
    let dir = tempfile::tempdir().unwrap();
    // Torso 0.4 m from the goal: success (and termination) on the first step.
    let mut qpos = vec![0.0; 15];
    qpos[..4].copy_from_slice(&[4.6, 5.0, 0.55, 1.0]);
    let init = write(
        dir.path(),
        "init.json",
        &serde_json::json!({"qpos": qpos, "qvel": vec![0.0; 14]}).to_string(),
    );
    let actions = write(
        dir.path(),
        "a.json",
        &serde_json::json!(vec![vec![0.0; 8]; 3]).to_string(),
    );
    let out = gaitscope(&[
        "rollout",
        "--condition",
        "healthy",
        "--init-state",
        &init,
        "--actions",
        &actions,
        "--jsonl",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let lines: Vec<Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 1);
    assert_eq!(lines[0]["terminated"], true);
}

fn replay_error(init: &str, actions: &str) -> String {
    let dir = tempfile::tempdir().unwrap();
    let init = write(dir.path(), "init.json", init);
    let actions = write(dir.path(), "actions.json", actions);
    let out = gaitscope(&[
        "rollout",
        "--condition",
        "mild",
        "--init-state",
        &init,
        "--actions",
        &actions,
        "--jsonl",
    ]);
    assert!(!out.status.success());
    assert!(out.stdout.is_empty(), "nothing half-written on stdout");
    let err = stderr(&out);
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn malformed_replay_files_name_the_problem() {
    let good_init =
        serde_json::json!({"qpos": [0,0,0.55,1,0,0,0,0,0,0,0,0,0,0,0], "qvel": vec![0.0; 14]})
            .to_string();
    let good_actions = "[[0,0,0,0,0,0,0,0]]";
    let err = replay_error("{\"qpos\": [1, 2], \"qvel\": []}", good_actions);
    assert!(
        err.contains("init-state") && err.contains("qpos has 2 numbers, expected 15"),
        "{err}"
    );
    let err = replay_error("not json", good_actions);
    assert!(
        err.contains("init-state") && err.contains("malformed"),
        "{err}"
    );
    let err = replay_error("{\"qpos\": [], \"qvel\": [], \"extra\": 1}", good_actions);
    assert!(err.contains("unknown field"), "{err}");
    let err = replay_error(&good_init, "[[0,0,0,0,0,0,0,0], [0,0,0]]");
    assert!(
        err.contains("actions[1] has 3 numbers, expected 8"),
        "{err}"
    );
    let err = replay_error(&good_init, "[[0,0,0,0,0,0,0,\"x\"]]");
    assert!(
        err.contains("actions") && err.contains("malformed"),
        "{err}"
    );
    let err = replay_error(&good_init, "[]");
    assert!(err.contains("no actions"), "{err}");
}

#[test]
fn missing_files_and_bad_flags_are_clear() {
    let out = gaitscope(&[
        "rollout",
        "--condition",
        "mild",
        "--init-state",
        "/no/such/init.json",
        "--actions",
        "/no/such/a.json",
    ]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("cannot read init-state file /no/such/init.json"),
        "{}",
        stderr(&out)
    );

    // A bare state (qpos, qvel) brings no damage state: the replay needs a condition.
    let dir = tempfile::tempdir().unwrap();
    let bare = dir.path().join("bare.json");
    let actions = dir.path().join("actions.json");
    let mut qpos = vec![0.0; 15];
    (qpos[2], qpos[3]) = (0.75, 1.0);
    std::fs::write(
        &bare,
        serde_json::json!({"qpos": qpos, "qvel": vec![0.0; 14]}).to_string(),
    )
    .unwrap();
    std::fs::write(&actions, "[[0, 0, 0, 0, 0, 0, 0, 0]]").unwrap();
    let out = gaitscope(&[
        "rollout",
        "--init-state",
        bare.to_str().unwrap(),
        "--actions",
        actions.to_str().unwrap(),
    ]);
    assert!(
        stderr(&out).contains("needs --condition healthy|mild|severe"),
        "{}",
        stderr(&out)
    );

    let out = gaitscope(&["rollout", "--condition", "broken"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("unknown condition 'broken'"),
        "{}",
        stderr(&out)
    );

    let out = gaitscope(&["rollout", "--episodes", "0"]);
    assert!(
        stderr(&out).contains("--episodes must be at least 1"),
        "{}",
        stderr(&out)
    );

    // A built-in policy's steps as JSON lines (the random policy's commanded action included).
    let out = gaitscope(&["rollout", "--jsonl", "--episodes", "1", "--max-steps", "3"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3);
    assert!(
        lines
            .iter()
            .all(|l| l["lane"] == "main" && l["action"].as_array().unwrap().len() == 8)
    );

    let out = gaitscope(&["rollout", "--model", "/no/such/ant.xml"]);
    assert!(
        stderr(&out).contains("cannot read model file /no/such/ant.xml"),
        "{}",
        stderr(&out)
    );

    let dir = tempfile::tempdir().unwrap();
    let config = write(
        dir.path(),
        "c.json",
        r#"{"damage": {"scales": {"severe": 2.0}}}"#,
    );
    let out = gaitscope(&["rollout", "--config", &config]);
    assert!(
        stderr(&out).contains("damage.scales.severe must lie in [0, 1]"),
        "{}",
        stderr(&out)
    );

    // A camera the renderer has no mode for: the flag's own values, before anything renders.
    let out = gaitscope(&["video", "--camera", "orbit", "--out", "/tmp/never.mp4"]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("possible values: track, fixed"),
        "{}",
        stderr(&out)
    );
}

/// `gaitscope` with a chosen display environment (the live viewer's checks come first).
fn gaitscope_display(args: &[&str], display: Option<&str>) -> Output {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_gaitscope"));
    cmd.args(args)
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY");
    if let Some(d) = display {
        cmd.env("DISPLAY", d);
    }
    cmd.output().expect("binary runs")
}

#[test]
fn live_and_view_explain_what_is_missing() {
    let dir = tempfile::tempdir().unwrap();
    // No display: name the headless alternative.
    let out = gaitscope_display(&["live"], None);
    assert!(!out.status.success());
    let e = stderr(&out);
    assert!(
        e.contains("no display") && e.contains("gaitscope record"),
        "{e}"
    );
    // ... and for `live`, the browser first.
    let web = e.find("live --web").expect("mentions live --web");
    assert!(web < e.find("gaitscope record").unwrap(), "{e}");
    // Bad settings are refused before any window or viewer opens (a display is "set" here, but
    // nothing gets far enough to use it).
    let out = gaitscope_display(&["live", "--speed", "20"], Some(":12345"));
    assert!(
        stderr(&out).contains("between 0.25× and 8×"),
        "{}",
        stderr(&out)
    );
    let out = gaitscope_display(
        &["live", "--checkpoint", dir.path().to_str().unwrap()],
        Some(":12345"),
    );
    assert!(stderr(&out).contains("checkpoint.json"), "{}", stderr(&out));
    let out = gaitscope_display(&["live", "--condition", "broken"], Some(":12345"));
    assert!(stderr(&out).contains("manual"), "{}", stderr(&out));
    // No viewer binary: say how to get one.
    let missing = dir.path().join("no-rerun");
    let out = gaitscope_display(
        &["live", "--viewer", missing.to_str().unwrap()],
        Some(":12345"),
    );
    let e = stderr(&out);
    assert!(
        e.contains("no Rerun viewer found") && e.contains("make viewer"),
        "{e}"
    );
    // view: the file is checked first, then the display.
    let out = gaitscope_display(&["view", "nowhere.rrd"], None);
    assert!(
        stderr(&out).contains("nowhere.rrd not found"),
        "{}",
        stderr(&out)
    );
    let text = write(dir.path(), "notes.rrd", "not a recording");
    let out = gaitscope_display(&["view", &text], None);
    assert!(
        stderr(&out).contains("not a Rerun recording"),
        "{}",
        stderr(&out)
    );
    let rrd = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("recordings/baseline-severe.rrd");
    let out = gaitscope_display(&["view", rrd.to_str().unwrap()], None);
    assert!(stderr(&out).contains("no display"), "{}", stderr(&out));
    assert!(!stderr(&out).contains("not whole"), "{}", stderr(&out));
    // A recording cut short (or with a damaged byte) still opens, but says so first.
    let bytes = std::fs::read(&rrd).unwrap();
    let cut = dir.path().join("cut.rrd");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let out = gaitscope_display(&["view", cut.to_str().unwrap()], None);
    let e = stderr(&out);
    assert!(
        e.contains("cut.rrd is not whole: it breaks off after")
            && e.contains("bytes into the next")
            && e.contains("no display"),
        "{e}"
    );
}

/// The paths a newcomer passes where a checkpoint folder belongs get told what they are.
#[test]
fn a_checkpoint_flag_given_an_sb3_zip_or_a_folder_of_runs_says_what_to_pass() {
    let dir = tempfile::tempdir().unwrap();
    let zip = dir.path().join("sac_ant.zip");
    // A zip's local-file magic is enough to recognise the archive.
    std::fs::write(&zip, b"PK\x03\x04 rest of an archive").unwrap();
    let zip_s = zip.to_str().unwrap();
    for args in [
        vec!["record", "--checkpoint", zip_s, "--out", "/tmp/never.rrd"],
        vec!["eval", "--checkpoint", zip_s],
    ] {
        let e = stderr(&gaitscope(&args));
        assert!(
            e.contains("Stable-Baselines3 archive")
                && e.contains(&format!("gaitscope import-sb3 {zip_s}")),
            "{args:?}: {e}"
        );
    }
    let runs = dir.path().join("seeds");
    for run in ["a-s1", "b-s2"] {
        std::fs::create_dir_all(runs.join(run)).unwrap();
        std::fs::write(runs.join(run).join("checkpoint.json"), "{}").unwrap();
    }
    let e = stderr(&gaitscope(&[
        "eval",
        "--checkpoint",
        runs.to_str().unwrap(),
    ]));
    assert!(e.contains("is a folder of runs"), "{e}");
    assert!(e.contains("seeds/a-s1") && e.contains("seeds/b-s2"), "{e}");
    // import-sb3 wants the zip, not a folder.
    let e = stderr(&gaitscope(&[
        "import-sb3",
        runs.to_str().unwrap(),
        "--out",
        "/tmp/never",
    ]));
    assert!(e.contains("it is a folder") && e.contains(".zip"), "{e}");
}

/// A fork prints its own summary line after the main lane's, text and JSON alike.
#[test]
fn rollout_prints_the_fork_lanes_summary_too() {
    let dir = env!("CARGO_MANIFEST_DIR").to_string() + "/checkpoints/encoder-lstm";
    let base = [
        "rollout",
        "--checkpoint",
        &dir,
        "--fork-at",
        "20",
        "--fork",
        "fail:ankle_3",
    ];
    let out = gaitscope(&[&base[..], &["--episodes", "1", "--condition", "severe"]].concat());
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 2, "{text}");
    assert!(lines[0].starts_with("episode") && lines[1].trim_start().starts_with("fork episode"));
    // The hand-failed joint never triggers by fatigue in the fork; the line names only the
    // joints that did, with their steps, and how the episode ended.
    assert!(!lines[1].contains("ankle_3 at step"), "{text}");
    assert!(lines[1].contains("fatigue triggers: "), "{text}");
    assert!(
        !text.contains("@-") && !text.contains("unhealthy"),
        "{text}"
    );
    assert!(
        ["success", "leapt", "collapsed", "timeout"]
            .iter()
            .any(|e| lines[0].contains(e)),
        "{text}"
    );
    let out = gaitscope(
        &[
            &base[..],
            &["--episodes", "1", "--condition", "severe", "--json"],
        ]
        .concat(),
    );
    let objs: Vec<Value> = stdout(&out)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(objs.len(), 2);
    assert!(objs[0].get("lane").is_none());
    assert_eq!(objs[1]["lane"], "fork");
    assert!(objs[1]["trigger_steps"]["ankle_3"].is_null());
}

/// Several episodes' step lines tell apart: each names its episode and reset seed.
#[test]
fn jsonl_lines_carry_their_episode_and_seed() {
    let lines = common::gaitscope_json_lines([
        "rollout",
        "--episodes",
        "3",
        "--seed",
        "7",
        "--max-steps",
        "20",
        "--jsonl",
    ])
    .unwrap();
    for k in 0..3u64 {
        let of_k: Vec<&Value> = lines.iter().filter(|l| l["episode"] == k).collect();
        assert!(!of_k.is_empty(), "episode {k} has lines");
        assert!(of_k.iter().all(|l| l["seed"] == 7 + k));
        // Its steps count from 0 in order.
        let steps: Vec<u64> = of_k.iter().map(|l| l["step"].as_u64().unwrap()).collect();
        assert_eq!(steps, (0..steps.len() as u64).collect::<Vec<_>>());
    }
}

/// Numbers past their ranges are refused with the range, before anything runs.
#[test]
fn out_of_range_numbers_are_refused() {
    let dir = env!("CARGO_MANIFEST_DIR").to_string() + "/checkpoints/baseline";
    let huge = u64::MAX.to_string();
    let e = stderr(&gaitscope(&[
        "eval",
        "--checkpoint",
        &dir,
        "--episodes",
        &huge,
    ]));
    assert!(e.contains("--episodes must lie in 1..=100000"), "{e}");
    let tmp = tempfile::tempdir().unwrap();
    let config = write(
        tmp.path(),
        "c.json",
        r#"{"env": {"frame_skip": 100000000}}"#,
    );
    let e = stderr(&gaitscope(&["rollout", "--config", &config]));
    assert!(e.contains("env.frame_skip must lie in 1..=1000"), "{e}");
    let config = write(tmp.path(), "g.json", r#"{"env": {"goal": [1e308, 1e308]}}"#);
    let e = stderr(&gaitscope(&[
        "train",
        "--check",
        "--config",
        &config,
        "--out",
        "/tmp/never",
    ]));
    assert!(e.contains("env.goal"), "{e}");
}

/// `gaitscope explain`: integrated gradients of z over the window at step K, complete per output
/// dimension, exactly zero in the slots the window has not filled yet (K < 16); clear errors.
#[test]
fn explain_attributes_z_to_the_window() {
    let dir = env!("CARGO_MANIFEST_DIR").to_string() + "/checkpoints/encoder-lstm";
    let out = gaitscope(&[
        "explain",
        "--checkpoint",
        &dir,
        "--step",
        "10",
        "--seed",
        "4",
        "--condition",
        "severe",
        "--json",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let v: Value = serde_json::from_str(stdout(&out).trim()).unwrap();
    assert_eq!(v["step"], 10);
    assert_eq!(v["target"], "z");
    assert_eq!(v["complete"], true);
    let a = v["attribution"].as_array().unwrap();
    assert_eq!(a.len(), 32, "one row per z dimension");
    let (out_now, base) = (
        v["output"].as_array().unwrap(),
        v["baseline_output"].as_array().unwrap(),
    );
    for (d, dim) in a.iter().enumerate() {
        let slots = dim.as_array().unwrap();
        assert_eq!(slots.len(), 16);
        assert!(slots.iter().all(|s| s.as_array().unwrap().len() == 37));
        // Ten steps taken: the six oldest slots are the reset's zeros, exactly.
        for s in &slots[..6] {
            assert!(
                s.as_array()
                    .unwrap()
                    .iter()
                    .all(|x| x.as_f64() == Some(0.0))
            );
        }
        let total: f64 = slots
            .iter()
            .flat_map(|s| s.as_array().unwrap())
            .map(|x| x.as_f64().unwrap())
            .sum();
        let change = out_now[d].as_f64().unwrap() - base[d].as_f64().unwrap();
        assert!(
            (total - change).abs() <= (0.01 * change.abs()).max(1e-3),
            "dim {d}: Σ attribution {total} vs output change {change}"
        );
    }
    let groups = v["summary"]["per_group"].as_array().unwrap();
    assert_eq!(groups.len(), 10, "8 joints, torso, goal");
    let base_dir = env!("CARGO_MANIFEST_DIR").to_string() + "/checkpoints/baseline";
    let e = stderr(&gaitscope(&[
        "explain",
        "--checkpoint",
        &base_dir,
        "--step",
        "3",
    ]));
    assert!(
        e.contains("has no latent z") && e.contains("--target action"),
        "{e}"
    );
    let e = stderr(&gaitscope(&[
        "explain",
        "--checkpoint",
        &dir,
        "--step",
        "100000",
        "--condition",
        "severe",
    ]));
    assert!(e.contains("beyond the episode"), "{e}");
    let e = stderr(&gaitscope(&[
        "explain",
        "--checkpoint",
        &dir,
        "--step",
        "3",
        "--ig-steps",
        "0",
    ]));
    assert!(e.contains("--ig-steps 0 must lie in 1..=10000"), "{e}");
}

/// A recording that cannot be written completely (here: a file-size limit, as a full disk) is a
/// clear error and leaves nothing under its name; a complete one is renamed into place whole.
#[test]
fn a_recording_that_cannot_be_written_leaves_no_truncated_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ant.rrd");
    let limited = Command::new("bash")
        .arg("-c")
        // 100 KB at most per file; SIGXFSZ ignored so the write fails with EFBIG instead.
        .arg(format!(
            "trap '' XFSZ; ulimit -f 100; exec {} record --episodes 2 --max-steps 400 --seed 1 --out {}",
            env!("CARGO_BIN_EXE_gaitscope"),
            out.display()
        ))
        .output()
        .unwrap();
    let e = stderr(&limited);
    assert_eq!(limited.status.code(), Some(1), "{e}");
    assert!(e.contains("could not be written completely"), "{e}");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
    let ok = gaitscope(&[
        "record",
        "--episodes",
        "1",
        "--max-steps",
        "40",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok.status.success(), "{}", stderr(&ok));
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, ["ant.rrd"]);
    // Whole: every message decodes, and the episode's 40 steps of distance are there.
    let chunks = common::read_rrd(&out);
    let distance = common::rows(&chunks, "/ant/goal/distance");
    assert!(distance > 0 && distance <= 40, "{distance} distance rows");
}

#[test]
fn curves_draw_a_model_per_colour_and_name_lost_log_lines() {
    let dir = tempfile::tempdir().unwrap();
    // Two seeds of one model, one of another; seed 1 lost its log after step 3000 of 10000.
    let run = |name: &str, last_update: u64, steps_done: u64| {
        let folder = dir.path().join(name);
        std::fs::create_dir(&folder).unwrap();
        let mut lines = String::new();
        for step in (1000..=last_update).step_by(1000) {
            lines += &format!(
                "{{\"global_step\":{step},\"charts/episodic_return\":{},\"charts/success\":{},\"charts/triggered_joints\":4}}\n",
                step as f64 / 100.0,
                step > 5000
            );
            lines += &format!(
                "{{\"global_step\":{step},\"losses/qf1\":1,\"losses/qf2\":2,\"losses/actor_loss\":-3,\"losses/alpha\":0.1}}\n"
            );
        }
        write(&folder, "metrics.jsonl", &lines);
        write(
            &folder,
            "checkpoint.json",
            &format!("{{\"steps_done\":{steps_done}}}"),
        );
        folder.to_string_lossy().into_owned()
    };
    let runs = [
        run("lstm-s0", 10_000, 10_000),
        run("lstm-s1", 3_000, 10_000),
        run("baseline", 10_000, 10_000),
    ];
    let out = dir.path().join("curves.png");
    let result = gaitscope(&[
        "curves",
        "--run",
        &runs[0],
        &runs[1],
        &runs[2],
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(result.status.success(), "{}", stderr(&result));
    let err = stderr(&result);
    assert!(
        err.contains("lstm-s1: metrics.jsonl has no lines between steps 3000 and 10000"),
        "{err}"
    );
    assert!(
        !err.contains("lstm-s0:") && !err.contains("baseline:"),
        "{err}"
    );
    // Two models, two colours (Okabe–Ito blue, vermilion), and no third.
    let (blue, size) = common::count_colour(&out, [0, 114, 178]);
    let (vermilion, _) = common::count_colour(&out, [213, 94, 0]);
    let (green, _) = common::count_colour(&out, [0, 158, 115]);
    assert_eq!(size, (1120, 1140));
    assert!(blue > 500 && vermilion > 500, "{blue} {vermilion}");
    assert_eq!(green, 0);
    // A broken metrics line is an error naming the file and line.
    write(
        Path::new(&runs[2]),
        "metrics.jsonl",
        "{oops\n{\"global_step\":1}\n",
    );
    let result = gaitscope(&["curves", "--run", &runs[2], "--out", out.to_str().unwrap()]);
    assert!(!result.status.success());
    let err = stderr(&result);
    assert!(err.contains("metrics.jsonl line 1"), "{err}");
}

/// The CLI's rough edges, each message read back (issue 46).
#[test]
fn cli_edges_say_why() {
    let bundled = concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-lstm");
    // A conflict with its reason, not only the flags' names.
    let dir = tempfile::tempdir().unwrap();
    let state = write(dir.path(), "s.json", "{}");
    for flag in [["--episodes", "3"], ["--seed", "4"]] {
        let out = gaitscope(&[
            "rollout",
            "--checkpoint",
            bundled,
            "--init-state",
            &state,
            flag[0],
            flag[1],
        ]);
        assert!(!out.status.success());
        let err = stderr(&out);
        assert!(
            err.contains(&format!("{} does not apply with --init-state", flag[0]))
                && err.contains("one episode"),
            "{err}"
        );
    }
    // An unknown joint suggests `all`.
    let out = gaitscope(&[
        "rollout",
        "--checkpoint",
        bundled,
        "--episodes",
        "1",
        "--max-steps",
        "5",
        "--fork-at",
        "2",
        "--fork",
        "heal:everything",
    ]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("unknown joint 'everything'") && err.contains("or `all` for every joint"),
        "{err}"
    );
    // explain at step 0 says the window is empty; later, the damage at that step and units.
    let out = gaitscope(&["explain", "--checkpoint", bundled, "--step", "0"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("the window is empty at step 0"), "{text}");
    assert!(!text.contains("per window slot"), "{text}");
    let out = gaitscope(&[
        "explain",
        "--checkpoint",
        bundled,
        "--step",
        "60",
        "--condition",
        "severe",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    assert!(text.contains("condition severe; at this step"), "{text}");
    assert!(text.contains("scale 0.10"), "{text}");
    assert!(text.contains("in units of z"), "{text}");
    assert!(text.contains("16 of 16 slots hold steps"), "{text}");
    // One thread is one thread.
    let out = gaitscope(&[
        "eval",
        "--checkpoint",
        bundled,
        "--episodes",
        "1",
        "--conditions",
        "healthy",
        "--max-steps",
        "20",
        "--threads",
        "1",
        "--out",
        dir.path().join("eval").to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(
        err.contains("1 thread)") && !err.contains("1 threads"),
        "{err}"
    );
}

/// Issue 49: FIFOs and devices where a file is expected are refused at once with a clear line,
/// never waited on (a FIFO's open blocks until a writer comes; the command must not). Each run
/// gets 20 s; any that hangs fails the test instead of the suite.
#[test]
fn fifos_and_devices_given_as_files_are_refused_not_waited_on() {
    let dir = tempfile::tempdir().unwrap();
    let fifo = dir.path().join("state.json");
    assert!(
        Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let rrd = dir.path().join("session.rrd");
    assert!(Command::new("mkfifo").arg(&rrd).status().unwrap().success());
    // A checkpoint folder whose weights are a FIFO and whose meta is a device.
    let ckpt = dir.path().join("ckpt");
    std::fs::create_dir(&ckpt).unwrap();
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("checkpoints/baseline/checkpoint.json"),
        ckpt.join("checkpoint.json"),
    )
    .unwrap();
    assert!(
        Command::new("mkfifo")
            .arg(ckpt.join("model.safetensors"))
            .status()
            .unwrap()
            .success()
    );
    let zero_meta = dir.path().join("zero-meta");
    std::fs::create_dir(&zero_meta).unwrap();
    std::os::unix::fs::symlink("/dev/zero", zero_meta.join("checkpoint.json")).unwrap();
    let actions = write(dir.path(), "actions.json", "[[0,0,0,0,0,0,0,0]]");
    let fifo_s = fifo.to_string_lossy().into_owned();
    // A checkpoint whose probe.json is a FIFO (record reads the probe beside the weights), a
    // run folder whose metrics.jsonl is one, and an SB3 archive that is one.
    let probed = dir.path().join("probed");
    std::fs::create_dir(&probed).unwrap();
    for name in ["checkpoint.json", "model.safetensors"] {
        std::fs::copy(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("checkpoints/encoder-lstm")
                .join(name),
            probed.join(name),
        )
        .unwrap();
    }
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    let zip = dir.path().join("sac_ant.zip");
    for f in [
        probed.join("probe.json"),
        run.join("metrics.jsonl"),
        zip.clone(),
    ] {
        assert!(Command::new("mkfifo").arg(&f).status().unwrap().success());
    }
    let path = |p: &Path| p.to_string_lossy().into_owned();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "record".into(),
                "--checkpoint".into(),
                path(&probed),
                "--episodes".into(),
                "1".into(),
                "--max-steps".into(),
                "5".into(),
                "--out".into(),
                path(&dir.path().join("p.rrd")),
            ],
            "not a regular file",
        ),
        (
            vec![
                "curves".into(),
                "--run".into(),
                path(&run),
                "--out".into(),
                path(&dir.path().join("c.png")),
            ],
            "not a regular file",
        ),
        (
            vec![
                "eval".into(),
                "--checkpoint".into(),
                "checkpoints/baseline".into(),
                "--scenario".into(),
                fifo_s.clone(),
                "--episodes".into(),
                "1".into(),
            ],
            "not a regular file",
        ),
        (
            vec![
                "train".into(),
                "--check".into(),
                "--config".into(),
                fifo_s.clone(),
                "--out".into(),
                path(&dir.path().join("never")),
            ],
            "not a regular file",
        ),
        (
            vec![
                "import-sb3".into(),
                path(&zip),
                "--out".into(),
                path(&dir.path().join("imported")),
            ],
            "not a regular file",
        ),
        (
            vec![
                "rollout".into(),
                "--init-state".into(),
                fifo_s.clone(),
                "--actions".into(),
                actions.clone(),
            ],
            "not a regular file",
        ),
        (
            vec![
                "record".into(),
                "--init-state".into(),
                fifo_s.clone(),
                "--out".into(),
                dir.path().join("o.rrd").to_string_lossy().into_owned(),
            ],
            "not a regular file",
        ),
        (
            vec![
                "rollout".into(),
                "--init-state".into(),
                "/dev/zero".into(),
                "--actions".into(),
                actions.clone(),
            ],
            "not a regular file",
        ),
        (
            vec![
                "explain".into(),
                "--checkpoint".into(),
                ckpt.to_string_lossy().into_owned(),
                "--step".into(),
                "3".into(),
            ],
            "not a regular file",
        ),
        (
            vec![
                "eval".into(),
                "--checkpoint".into(),
                zero_meta.to_string_lossy().into_owned(),
                "--episodes".into(),
                "1".into(),
            ],
            "not a regular file",
        ),
        (
            vec!["view".into(), rrd.to_string_lossy().into_owned()],
            "not a regular file",
        ),
    ];
    for (args, want) in cases {
        let started = std::time::Instant::now();
        let mut child = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
            .args(&args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break status;
            }
            if started.elapsed() > std::time::Duration::from_secs(20) {
                child.kill().unwrap();
                child.wait().unwrap();
                panic!("gaitscope {} hung on a FIFO or device", args.join(" "));
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        };
        let out = child.wait_with_output().unwrap();
        let said = stderr(&out);
        assert!(!status.success(), "gaitscope {} succeeded", args.join(" "));
        assert!(said.contains(want), "gaitscope {}: {said}", args.join(" "));
        assert!(!said.contains("panicked"), "{said}");
    }
}

/// `live --save` names its file only if it reads back whole when a sink did not flush: Rerun's
/// decoder finds a file cut off by a failed write (here: cut by hand) and says where it stays.
#[test]
fn a_saved_stream_cut_off_mid_message_does_not_read_back_whole() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ant.rrd");
    let ok = gaitscope(&[
        "record",
        "--episodes",
        "1",
        "--max-steps",
        "60",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok.status.success(), "{}", stderr(&ok));
    let bytes = std::fs::read(&out).unwrap();
    let session = dir.path().join("session.rrd");
    let file = gaitscope::telemetry::PartialFile::new(&session);
    std::fs::write(file.partial(), &bytes).unwrap();
    let messages = file.check_whole().unwrap();
    assert!(messages > 10, "{messages} messages");
    for cut in [bytes.len() - 7, bytes.len() / 2, 100] {
        std::fs::write(file.partial(), &bytes[..cut]).unwrap();
        let e = file.check_whole().unwrap_err().to_string();
        assert!(e.contains("breaks off after"), "cut at {cut}: {e}");
        assert!(e.contains("session.rrd.partial"), "{e}");
        assert!(!session.exists());
    }
}
