//! `gaitscope search` on a real checkpoint, end to end: the files, byte-identical reruns
//! (whatever the thread count), a kill -9 resumed to the same result, written scenarios that
//! `eval --scenario` replays to the same episodes, and refused bad input.

mod common;

use serde_json::Value;
use std::path::Path;
use std::process::{Command, Output};
use std::time::{Duration, Instant};

const ARGS: [&str; 18] = [
    "search",
    "--checkpoint",
    "checkpoints/baseline",
    "--evaluations",
    "6",
    "--episodes",
    "4",
    "--held-out",
    "6",
    "--top",
    "2",
    "--shrink-evaluations",
    "4",
    "--max-steps",
    "150",
    "--latest-onset",
    "40",
    "--budget=1.5",
];

fn gaitscope(args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_gaitscope"));
    c.current_dir(env!("CARGO_MANIFEST_DIR")).args(args);
    c
}

fn search(out: &Path, threads: &str) -> Output {
    let o = gaitscope(&ARGS)
        .args(["--threads", threads, "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    o
}

fn lines(path: &Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

#[test]
fn a_search_writes_replayable_scenarios_and_reruns_byte_for_byte() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    search(&a, "2");
    search(&b, "1");
    for f in [
        "candidates.jsonl",
        "summary.md",
        "top-1.json",
        "minimal.json",
        "search.json",
    ] {
        assert_eq!(
            std::fs::read_to_string(a.join(f)).unwrap(),
            std::fs::read_to_string(b.join(f)).unwrap(),
            "{f} differs between a 2-thread and a 1-thread run"
        );
    }
    let log = lines(&a.join("candidates.jsonl"));
    let phase = |p: &str| log.iter().filter(|c| c["phase"] == p).count();
    // The budget: 6 searched, 6 random, at most 4 shrink.
    assert_eq!(phase("search"), 6);
    assert_eq!(phase("reference"), 6);
    assert_eq!(phase("held-out"), 5); // top 2, reference best, minimal, no damage
    // The search seeds with no damage, once, last: the search column's reference.
    assert_eq!(phase("undamaged"), 1);
    let last = log.last().unwrap();
    assert_eq!(last["phase"], "undamaged");
    assert_eq!(last["outcomes"][0].as_array().unwrap().len(), 4);
    assert!(phase("shrink") <= 4);
    for c in &log {
        assert!(c["severity"].as_f64().unwrap() <= 1.5 + 1e-9, "{c}");
        assert_eq!(c["models"][0]["label"], "baseline");
    }
    // top-1.json replays under eval --scenario to the held-out episodes, seed for seed.
    let top: Value =
        serde_json::from_str(&std::fs::read_to_string(a.join("top-1.json")).unwrap()).unwrap();
    assert_eq!(top["fatigue"], false);
    let held = log.iter().find(|c| c["phase"] == "held-out").unwrap();
    assert_eq!(
        held["schedule"]["scales"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|s| s.as_f64().unwrap() < 1.0)
            .count(),
        top["edits"].as_array().unwrap().len()
    );
    let (replayed, searched) = replayed_vs_searched(&a, "top-1.json");
    assert_eq!(replayed, searched);
    let summary = std::fs::read_to_string(a.join("summary.md")).unwrap();
    assert!(summary.contains("| `top-1.json` | cma |"), "{summary}");
    let undamaged = last["success"][0].as_f64().unwrap();
    assert!(
        summary.contains(&format!(
            "| (no damage) | – | – | 0 | – | {:.1} % |",
            100.0 * undamaged
        )),
        "{summary}"
    );
    assert!(
        summary.contains("`reference-best.json` | random"),
        "{summary}"
    );
    assert!(a.join("search-curve.png").exists());
    // worst.rrd: top-1's worst held-out episode, its scenario's edits as damage events, one per
    // damaged joint, each at its onset's step.
    let events = common::text_log(&common::read_rrd(&a.join("worst.rrd")), "/ant/events");
    let edits = events
        .iter()
        .filter(|(_, t)| t.contains("scenario search-top-1:"))
        .count();
    assert_eq!(edits, top["edits"].as_array().unwrap().len(), "{events:?}");
    let worst_seed: u64 = summary
        .split("worst held-out episode (seed ")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .and_then(|s| s.parse().ok())
        .unwrap();
    assert!(searched.iter().any(|(s, ..)| *s == worst_seed));

    // Killed (SIGKILL) once a few candidates are in, then run again: the same files.
    let c = dir.path().join("c");
    let mut child = gaitscope(&ARGS)
        .args(["--threads", "1", "--out", c.to_str().unwrap()])
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while std::fs::read_to_string(c.join("candidates.jsonl")).map_or(0, |t| t.lines().count()) < 3 {
        assert!(Instant::now() < deadline, "no candidates after 120 s");
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    search(&c, "2");
    for f in ["candidates.jsonl", "summary.md", "minimal.json"] {
        assert_eq!(
            std::fs::read_to_string(a.join(f)).unwrap(),
            std::fs::read_to_string(c.join(f)).unwrap(),
            "{f} after a kill and a resume"
        );
    }
}

#[test]
fn bad_search_input_is_refused_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x");
    let out = out.to_str().unwrap();
    for (args, says) in [
        (vec!["--budget", "0"], "--budget must lie in (0, 8]"),
        (vec!["--budget", "nan"], "--budget must lie in (0, 8]"),
        (vec!["--evaluations", "0"], "--evaluations must lie in 1..="),
        (
            vec!["--latest-onset", "600"],
            "must come before the step limit",
        ),
        (vec!["--reverse"], "--against"),
        (
            vec!["--push-impulse", "0"],
            "--push-impulse must lie in (0, 500] N·s",
        ),
        (vec!["--push-impulse", "501"], "--push-impulse must lie in"),
        (vec!["--push-impulse", "inf"], "--push-impulse must lie in"),
        (
            vec!["--method", "annealing"],
            "possible values: cma, random",
        ),
    ] {
        let o = gaitscope(&[
            "search",
            "--checkpoint",
            "checkpoints/baseline",
            "--out",
            out,
        ])
        .args(&args)
        .output()
        .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(says), "{args:?}: {err}");
    }
    let o = gaitscope(&["search", "--checkpoint", "/nonexistent", "--out", out])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("/nonexistent"));
}

/// An episode as (seed, success, steps).
type Episode = (u64, bool, u64);

/// eval --scenario's replay of a search folder's `file`, and the held-out outcomes of its
/// schedule in the log (`top-1.json`'s held-out run is the log's first).
fn replayed_vs_searched(dir: &Path, file: &str) -> (Vec<Episode>, Vec<Episode>) {
    let log = lines(&dir.join("candidates.jsonl"));
    let held = log.iter().find(|c| c["phase"] == "held-out").unwrap();
    let stem = file.trim_end_matches(".json");
    let out = dir.join(format!("eval-{stem}"));
    let o = gaitscope(&[
        "eval",
        "--checkpoint",
        "checkpoints/baseline",
        "--scenario",
        dir.join(file).to_str().unwrap(),
        "--conditions",
        "healthy",
        "--episodes",
        "6",
        "--max-steps",
        "150",
        "--out",
        out.to_str().unwrap(),
    ])
    .output()
    .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let eval: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("eval.json")).unwrap()).unwrap();
    let triple = |e: &Value| {
        (
            e["seed"].as_u64().unwrap(),
            e["success"].as_bool().unwrap(),
            e["steps"].as_u64().unwrap(),
        )
    };
    let replayed = eval["episodes"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["condition"] == format!("search-{stem}"))
        .map(triple)
        .collect();
    let searched = held["outcomes"][0]
        .as_array()
        .unwrap()
        .iter()
        .map(triple)
        .collect();
    (replayed, searched)
}

#[test]
fn a_search_with_pushes_writes_pushes_that_replay_and_stay_within_the_impulse() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a");
    let o = gaitscope(&ARGS)
        .args([
            "--push-impulse",
            "30",
            "--threads",
            "2",
            "--out",
            a.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let log = lines(&a.join("candidates.jsonl"));
    let mut pushes = 0;
    for c in &log {
        if let Some(p) = c["schedule"].get("push") {
            pushes += 1;
            let impulse = p["newtons"].as_f64().unwrap() * p["steps"].as_f64().unwrap() * 0.05;
            assert!(impulse <= 30.0 + 1e-9, "{c}");
            assert!(p["onset"].as_u64().unwrap() <= 40, "{c}");
        }
    }
    assert!(
        pushes >= 6,
        "only {pushes} of {} candidates pushed",
        log.len()
    );
    let search: Value =
        serde_json::from_str(&std::fs::read_to_string(a.join("search.json")).unwrap()).unwrap();
    assert_eq!(search["pushes"]["impulse"], 30.0);
    assert_eq!(search["pushes"]["step_seconds"], 0.05);
    // top-1.json holds its push as a scenario push, and eval --scenario replays it seed for seed.
    let top: Value =
        serde_json::from_str(&std::fs::read_to_string(a.join("top-1.json")).unwrap()).unwrap();
    let held = log.iter().find(|c| c["phase"] == "held-out").unwrap();
    let push_edits = top["edits"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e.get("push").is_some())
        .count();
    assert_eq!(push_edits, held["schedule"].get("push").is_some() as usize);
    let (replayed, searched) = replayed_vs_searched(&a, "top-1.json");
    assert_eq!(replayed, searched);
    // The same rerun writes the same bytes.
    let b = dir.path().join("b");
    let o = gaitscope(&ARGS)
        .args([
            "--push-impulse",
            "30",
            "--threads",
            "1",
            "--out",
            b.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for f in [
        "candidates.jsonl",
        "summary.md",
        "top-1.json",
        "minimal.json",
    ] {
        assert_eq!(
            std::fs::read_to_string(a.join(f)).unwrap(),
            std::fs::read_to_string(b.join(f)).unwrap(),
            "{f}"
        );
    }
}

#[test]
fn searched_pushes_name_the_bundled_ants_torso_and_legs() {
    // The search space is built before any env, so it names its bodies itself: they must be the
    // bundled model's torso and the four legs' upper bodies (the panel's push targets).
    let env = gaitscope::env::AntEnv::new(gaitscope::GaitConfig::default(), 0).unwrap();
    let (torso, legs) = gaitscope::search::space::PUSH_BODIES.split_first().unwrap();
    assert_eq!(*torso, "torso");
    assert!(env.body_names().contains(torso));
    let mut searched: Vec<&str> = legs.to_vec();
    let mut model: Vec<&str> = env.leg_names().iter().map(String::as_str).collect();
    searched.sort_unstable();
    model.sort_unstable();
    assert_eq!(searched, model);
}
