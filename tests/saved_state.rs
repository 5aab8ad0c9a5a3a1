//! Saved states (issue 32, part 3): `rollout --save-state-at K FILE` writes the lane before
//! step K; `--init-state FILE` starts from it, damage and window included; the MJCF key loads in
//! MuJoCo itself.

use serde_json::Value;
use std::path::Path;

mod common;

const CHECKPOINT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-lstm");
const K: usize = 40;

fn rollout(extra: &[&str]) -> Result<Vec<Value>, String> {
    let base = ["rollout", "--max-steps", "150", "--jsonl"];
    common::gaitscope_json_lines(base.iter().copied().chain(extra.iter().copied()))
}

/// Every number of two step lines agrees to `tol` (and every other field exactly).
fn assert_close(a: &Value, b: &Value, tol: f64, at: &str) {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= tol, "{at}: {x} vs {y}");
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len(), "{at}");
            for (i, (x, y)) in x.iter().zip(y).enumerate() {
                assert_close(x, y, tol, &format!("{at}[{i}]"));
            }
        }
        (Value::Object(x), Value::Object(y)) => {
            for (k, v) in x {
                if let Some(w) = y.get(k) {
                    assert_close(v, w, tol, &format!("{at}.{k}"));
                }
            }
        }
        _ => assert_eq!(a, b, "{at}"),
    }
}

/// The checkpoint's episode from a state file.
fn from_state(file: &Path) -> Result<Vec<Value>, String> {
    rollout(&[
        "--checkpoint",
        CHECKPOINT,
        "--init-state",
        file.to_str().unwrap(),
    ])
}

/// The checkpoint's severe episode from seed 3, its state before step `k` saved to `file`.
fn save_at(k: usize, file: &Path) -> Result<Vec<Value>, String> {
    rollout(&[
        "--checkpoint",
        CHECKPOINT,
        "--condition",
        "severe",
        "--episodes",
        "1",
        "--seed",
        "3",
        "--save-state-at",
        &k.to_string(),
        file.to_str().unwrap(),
    ])
}

fn saved_episode(dir: &Path) -> (Vec<Value>, std::path::PathBuf) {
    let file = dir.join("state.json");
    let rows = save_at(K, &file).unwrap();
    assert!(rows.len() > K + 20, "{} steps", rows.len());
    (rows, file)
}

#[test]
fn a_saved_state_and_the_episodes_own_actions_replay_the_rest_of_it() {
    let dir = tempfile::tempdir().unwrap();
    let (rows, file) = saved_episode(dir.path());
    let state: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    assert_eq!(state["format"], "gaitscope-state/1");
    assert_eq!(state["step"], K);
    assert_eq!(state["seed"], 3);
    assert_eq!(state["checkpoint"], "encoder-lstm");
    assert_eq!(state["damage"]["condition"], "severe");
    // The state before step K is the state after step K − 1.
    assert_eq!(state["qpos"], rows[K - 1]["qpos"]);
    assert_eq!(state["damage"]["fatigue"], rows[K - 1]["fatigue"]);
    assert_eq!(state["damage"]["triggered"], rows[K - 1]["triggered"]);
    assert!(
        rows[K - 1]["triggered"]
            .as_array()
            .unwrap()
            .iter()
            .any(|t| t == true),
        "a severe episode has a damaged joint by step {K}: the damage state must carry over"
    );
    // The episode's own actions from K on, replayed from the file.
    let actions: Vec<&Value> = rows[K..].iter().map(|r| &r["action"]).collect();
    let actions_file = dir.path().join("actions.json");
    std::fs::write(&actions_file, serde_json::to_string(&actions).unwrap()).unwrap();
    let replay = rollout(&[
        "--init-state",
        file.to_str().unwrap(),
        "--actions",
        actions_file.to_str().unwrap(),
    ])
    .unwrap();
    assert_eq!(replay.len(), rows.len() - K);
    for (t, (r, orig)) in replay.iter().zip(&rows[K..]).enumerate() {
        assert_eq!(r["step"], K + t, "steps count on from the saved step");
        for key in [
            "qpos",
            "qvel",
            "obs",
            "fatigue",
            "applied_action",
            "reward",
            "torso_xy",
        ] {
            assert_close(&r[key], &orig[key], 1e-9, &format!("step {} {key}", K + t));
        }
        assert_eq!(r["triggered"], orig["triggered"]);
        assert_eq!(r["terminated"], orig["terminated"]);
        assert_eq!(r["truncated"], orig["truncated"]);
    }
}

#[test]
fn the_policy_from_a_saved_state_continues_its_episode() {
    // The window travels with the state: the LSTM sees the same 16 steps and acts the same.
    let dir = tempfile::tempdir().unwrap();
    let (rows, file) = saved_episode(dir.path());
    let resumed = from_state(&file).unwrap();
    assert_eq!(resumed.len(), rows.len() - K);
    for (r, orig) in resumed.iter().zip(&rows[K..]) {
        for key in ["qpos", "action", "fatigue", "reward"] {
            assert_close(
                &r[key],
                &orig[key],
                1e-6,
                &format!("step {} {key}", r["step"]),
            );
        }
    }
}

#[test]
fn the_mjcf_key_loads_in_mujoco_to_the_same_pose() {
    let dir = tempfile::tempdir().unwrap();
    let (_, file) = saved_episode(dir.path());
    let state: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let key = state["mjcf_key"].as_str().unwrap();
    assert!(
        key.starts_with(&format!("<key name=\"gaitscope-step-{K}\"")),
        "{key}"
    );
    let ant =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/assets/ant.xml")).unwrap();
    let xml = ant.replace("</mujoco>", &format!("<keyframe>{key}</keyframe></mujoco>"));
    let model = mujoco_rs::prelude::MjModel::from_xml_string(&xml).unwrap();
    let mut data = mujoco_rs::prelude::MjData::new(Box::new(model));
    data.reset_keyframe(0).unwrap();
    let want: Vec<f64> = serde_json::from_value(state["qpos"].clone()).unwrap();
    assert_eq!(data.qpos(), want.as_slice(), "qpos from the key");
    let want: Vec<f64> = serde_json::from_value(state["qvel"].clone()).unwrap();
    assert_eq!(data.qvel(), want.as_slice(), "qvel from the key");
}

#[test]
fn bad_state_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let (_, file) = saved_episode(dir.path());
    let good: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let with = |edit: &dyn Fn(&mut Value)| {
        let mut v = good.clone();
        edit(&mut v);
        let path = dir.path().join("bad.json");
        std::fs::write(&path, v.to_string()).unwrap();
        match rollout(&[
            "--checkpoint",
            CHECKPOINT,
            "--init-state",
            path.to_str().unwrap(),
        ]) {
            Ok(rows) => panic!("accepted, {} steps", rows.len()),
            Err(e) => e,
        }
    };
    for (edit, reason) in [
        (
            &(|v: &mut Value| v["format"] = "gaitscope-state/9".into()) as &dyn Fn(&mut Value),
            "format 'gaitscope-state/9'",
        ),
        (
            &|v: &mut Value| v["qpos"] = Value::Array(vec![0.into(); 3]),
            "qpos has 3 numbers",
        ),
        (
            &|v: &mut Value| v["damage"]["scale"][2] = 1.5.into(),
            "torque scale 1.5",
        ),
        (
            &|v: &mut Value| v["damage"]["fatigue"][0] = (-1.0).into(),
            "fatigue -1",
        ),
        (
            &|v: &mut Value| v["step"] = 100000.into(),
            "past this episode's step limit",
        ),
        (
            &|v: &mut Value| v["window"]["entries"][0] = Value::Array(vec![0.into(); 5]),
            "a window entry has 5 numbers",
        ),
        (
            &|v: &mut Value| v["extra"] = 1.into(),
            "unknown field `extra`",
        ),
        (
            &|v: &mut Value| v["qacc_warmstart"] = Value::Null,
            "qacc_warmstart",
        ),
        (
            // A goal this far made the reward infinite (issue 49 #9).
            &|v: &mut Value| v["goal_distance"] = 1e308.into(),
            "goal_distance is 100000000000000000000000000000000",
        ),
        (
            &|v: &mut Value| v["qvel"][3] = 1e300.into(),
            "qvel[3] is 1000000000000000",
        ),
        (
            &|v: &mut Value| v["torso_xy"][1] = (-2e4).into(),
            "torso_xy[1] is -20000, expected a number in [-10000, 10000]",
        ),
        (
            // The red team's: a label that disagrees with the damage it names was taken.
            &|v: &mut Value| v["condition"] = "healthy".into(),
            "condition: 'healthy', but the state's damage says 'severe'",
        ),
    ] {
        let err = with(edit);
        assert!(err.contains(reason), "{reason}: {err}");
    }
    // A key given twice is refused, not the last one kept.
    let twice = dir.path().join("twice.json");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&twice, text.replacen('{', r#"{"seed": 5, "#, 1)).unwrap();
    let err = from_state(&twice).unwrap_err();
    assert!(err.contains("duplicate key \"seed\""), "{err}");
    // A saved state brings its condition; another one is refused, not silently mixed.
    let err = rollout(&[
        "--checkpoint",
        CHECKPOINT,
        "--init-state",
        file.to_str().unwrap(),
        "--condition",
        "mild",
    ])
    .unwrap_err();
    assert!(err.contains("condition is severe, not mild"), "{err}");
    // A bare state still needs one.
    let bare = dir.path().join("bare.json");
    std::fs::write(
        &bare,
        serde_json::json!({"qpos": good["qpos"], "qvel": good["qvel"]}).to_string(),
    )
    .unwrap();
    let err = from_state(&bare).unwrap_err();
    assert!(err.contains("needs --condition"), "{err}");
    // Saving past the episode's end says so, and writes nothing.
    let late = dir.path().join("late.json");
    let err = save_at(400, &late).unwrap_err();
    assert!(err.contains("before step 400: no state to save"), "{err}");
    assert!(!late.exists());
}

/// `record` of the checkpoint (severe, 150 steps) from a state file to `out`.
fn record_from(state: &Path, out: &Path) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args([
            "record",
            "--checkpoint",
            CHECKPOINT,
            "--condition",
            "severe",
        ])
        .args(["--max-steps", "150", "--init-state"])
        .arg(state)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// `record --init-state`: the recording starts where the state was saved, damage included —
/// its first step is the saved episode's step K (the same session start `live` uses).
#[test]
fn a_recording_starts_from_a_saved_state() {
    let dir = tempfile::tempdir().unwrap();
    let (rows, file) = saved_episode(dir.path());
    let out = dir.path().join("from-state.rrd");
    let status = record_from(&file, &out);
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    let chunks = common::read_rrd(&out);
    let fatigue = common::joint_series(&chunks, "/ant/joints/fatigue");
    assert_eq!(fatigue.len(), rows.len() - K, "the steps from K to the end");
    // Global step 1 is env step K.
    for (t, orig) in rows[K..].iter().enumerate() {
        let want: Vec<f64> = serde_json::from_value(orig["fatigue"].clone()).unwrap();
        for (a, b) in fatigue[&(t as i64 + 1)].iter().zip(&want) {
            assert!((a - b).abs() < 1e-9, "step {}: {a} vs {b}", K + t);
        }
    }
    // A state the episode refuses at its start (a step past its limit) stops the recording
    // with its reason and leaves no file, not even `.partial` (issue 49 #8).
    let mut late: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    late["step"] = 100_000.into();
    let late_file = dir.path().join("late.json");
    std::fs::write(&late_file, late.to_string()).unwrap();
    let refused = dir.path().join("refused.rrd");
    let o = record_from(&late_file, &refused);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("step limit"), "{err}");
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with("refused"))
        .collect();
    assert!(left.is_empty(), "left {left:?}");
}

/// Another model than the one that saved a state may start from it, with a warning that says
/// so; a fork before the state's step says where the episode
/// starts instead of calling it "beyond the episode".
#[test]
fn a_state_names_who_saved_it_and_where_it_starts() {
    let dir = tempfile::tempdir().unwrap();
    let (_, file) = saved_episode(dir.path());
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["rollout", "--max-steps", "60", "--jsonl", "--checkpoint"])
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/baseline"))
        .arg("--init-state")
        .arg(&file)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("the state was saved with encoder-lstm acting; baseline acts from it now"),
        "{err}"
    );
    let err = rollout(&[
        "--checkpoint",
        CHECKPOINT,
        "--init-state",
        file.to_str().unwrap(),
        "--fork-at",
        "10",
        "--fork",
        "heal:all",
    ])
    .unwrap_err();
    assert!(
        err.contains(&format!(
            "--fork-at 10 comes before step {K}, where this episode starts"
        )),
        "{err}"
    );
}
