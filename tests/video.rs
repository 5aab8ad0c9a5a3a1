//! `gaitscope video` (cargo feature `video`; needs EGL and ffmpeg): frames at the asked size and
//! rate, not blank, and the damage tint where the damage is.
#![cfg(feature = "video")]

use gaitscope::damage::Edit;
use gaitscope::video::{FrameRenderer, FrameSpec};
use gaitscope::{AntEnv, GaitConfig};
use std::process::Command;

mod common;

const SPEC: FrameSpec = FrameSpec {
    width: 320,
    height: 240,
    fps: 20,
    camera: gaitscope::video::CameraMode::Track,
};

/// Pixels of the damaged-joint red (the viewer's palette: 220, 40, 40, shaded by the light).
fn red_pixels(rgb: &[u8]) -> usize {
    rgb.as_chunks::<3>()
        .0
        .iter()
        .filter(|[r, g, b]| *r > 120 && *g < 70 && *b < 70)
        .count()
}

fn variance(rgb: &[u8]) -> f64 {
    let n = rgb.len() as f64;
    let mean = rgb.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
    rgb.iter()
        .map(|&v| (f64::from(v) - mean).powi(2))
        .sum::<f64>()
        / n
}

#[test]
fn frames_show_the_ant_and_its_damage() {
    let mut env = AntEnv::new(GaitConfig::default(), 0).unwrap();
    env.reset_with_seed(0);
    env.set_fatigue_triggers(false);
    let mut renderer = FrameRenderer::new(&env, SPEC).unwrap();
    env.step(&[0.0; 8]).unwrap();
    let healthy = renderer.frame(&env).unwrap();
    assert_eq!(healthy.len(), 320 * 240 * 3);
    assert!(variance(&healthy) > 100.0, "not a blank frame");
    for edit in Edit::parse_list("fail:all=0.1").unwrap() {
        env.apply_edit(&edit).unwrap();
    }
    env.step(&[0.0; 8]).unwrap();
    let damaged = renderer.frame(&env).unwrap();
    let (before, after) = (red_pixels(&healthy), red_pixels(&damaged));
    assert!(
        before < 20 && after > 200,
        "red leg pixels: healthy {before}, failed {after}"
    );
}

/// Runs `gaitscope video ARGS --out OUT`; its stderr, or a panic with it if it fails.
fn video(args: &[&str], out: &std::path::Path) -> String {
    let run = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .arg("video")
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(run.status.success(), "{stderr}");
    stderr
}

/// ffprobe's `entries` of the first video stream, counted frames included, as CSV.
fn probe(path: &std::path::Path, entries: &str) -> String {
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args([
            "-show_entries",
            &format!("stream={entries}"),
            "-of",
            "csv=p=0",
        ])
        .arg(path)
        .output()
        .unwrap();
    String::from_utf8_lossy(&probe.stdout).trim().to_string()
}

#[test]
fn a_30_step_episode_is_a_30_frame_mp4_at_the_asked_size_and_rate() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ant.mp4");
    let size = ["--width", "320", "--height", "240"];
    let said = video(
        &[
            &["--policy", "zero", "--max-steps", "30", "--fps", "20"][..],
            &size,
        ]
        .concat(),
        &out,
    );
    // It says how the episode ended: the zero policy stands still until the step limit.
    assert!(
        said.contains("zero policy: timeout after 30 steps, ")
            && said.contains("m from the goal (episode 1, seed 0)"),
        "{said}"
    );
    assert_eq!(
        probe(&out, "width,height,nb_read_frames,r_frame_rate"),
        "320,240,20/1,30"
    );
    assert!(!dir.path().join("ant.mp4.partial").exists());
    // A fork before step 10 beside the main lane: one frame per step, both halves in it.
    let forked = dir.path().join("fork.mp4");
    let fork = [
        "--policy",
        "zero",
        "--max-steps",
        "20",
        "--fork-at",
        "10",
        "--fork",
        "fail:all=0.1",
    ];
    let said = video(&[&fork[..], &size].concat(), &forked);
    assert!(
        said.contains("fork at step 10: fail:all=0.1: timeout after 20 steps"),
        "{said}"
    );
    assert_eq!(probe(&forked, "width,height,nb_read_frames"), "320,240,20");
    // From a state saved before step 20 of a 30-step episode: the 10 steps left, 10 frames.
    let state = dir.path().join("state.json");
    let lstm = concat!(env!("CARGO_MANIFEST_DIR"), "/checkpoints/encoder-lstm");
    let saved = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args([
            "rollout",
            "--checkpoint",
            lstm,
            "--condition",
            "severe",
            "--seed",
            "3",
        ])
        .args([
            "--episodes",
            "1",
            "--max-steps",
            "30",
            "--save-state-at",
            "20",
        ])
        .arg(&state)
        .output()
        .unwrap();
    assert!(
        saved.status.success(),
        "{}",
        String::from_utf8_lossy(&saved.stderr)
    );
    let resumed = dir.path().join("resumed.mp4");
    let from_state = ["--checkpoint", lstm, "--max-steps", "30", "--init-state"];
    video(
        &[&from_state[..], &[state.to_str().unwrap()], &size].concat(),
        &resumed,
    );
    assert_eq!(probe(&resumed, "width,height,nb_read_frames"), "320,240,10");
    // Bad sizes are refused before anything is written.
    let bad = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["video", "--width", "321", "--out"])
        .arg(dir.path().join("odd.mp4"))
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&bad.stderr).contains("must be even numbers"));
    assert!(!dir.path().join("odd.mp4").exists());
    let bad = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args([
            "video",
            "--width",
            "322",
            "--fork-at",
            "3",
            "--fork",
            "heal:all",
            "--out",
        ])
        .arg(dir.path().join("half.mp4"))
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&bad.stderr).contains("multiple of 4"));
    // An unwritable folder and a machine without GL: one clear error each, no file left.
    let missing = dir.path().join("no-such-folder").join("ant.mp4");
    let bad = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["video", "--policy", "zero", "--max-steps", "3", "--out"])
        .arg(&missing)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("cannot write"));
    let no_gl = dir.path().join("no-gl.mp4");
    let bad = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .args(["video", "--policy", "zero", "--max-steps", "3", "--out"])
        .arg(&no_gl)
        // glvnd finds no EGL vendor: what a machine without Mesa's EGL looks like.
        .env(
            "__EGL_VENDOR_LIBRARY_FILENAMES",
            dir.path().join("none.json"),
        )
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&bad.stderr).contains("no OpenGL for offscreen rendering"));
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("partial") || n.starts_with("no-gl") || n.starts_with("odd"))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// `--compare` runs each model in its own world (the lane core's one rule): a second model
/// trained with τ = 10 and a window of 8 gets those, not the first model's, and both lanes step
/// exactly the episodes `rollout` gives each checkpoint alone.
#[test]
fn compared_lanes_each_run_in_their_own_world() {
    use gaitscope::lane::Actor;
    use gaitscope::rollout::{Start, run_policy_episode};
    use gaitscope::video::VideoLane;
    let tmp = tempfile::tempdir().unwrap();
    let save = |name: &str, threshold: f64, len: usize| {
        let dir = tmp.path().join(name);
        common::save_checkpoint_in_world(&dir, threshold, len);
        Actor::load(&dir).unwrap()
    };
    let mut requested = GaitConfig::default();
    requested.damage.condition =
        gaitscope::damage::ConditionChoice::Fixed(gaitscope::damage::Condition::Severe);
    requested.env.max_episode_steps = 200;
    let actors = [save("a", 30.0, 16), save("b", 10.0, 8)];
    let mut lanes: Vec<VideoLane> = actors
        .iter()
        .zip(["a", "b"])
        .map(|(actor, name)| VideoLane::new(name.into(), actor.clone(), &requested, 4, SPEC))
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(lanes[0].world().damage.threshold, 30.0);
    assert_eq!(
        (
            lanes[1].world().damage.threshold,
            lanes[1].world().context.len
        ),
        (10.0, 8)
    );
    // Lockstep, as render_episode steps them; each lane's fatigue and applied actions.
    let mut seen = [Vec::new(), Vec::new()];
    while lanes.iter().any(|l| !l.is_done()) {
        for (k, lane) in lanes.iter_mut().enumerate() {
            if let Some(r) = lane.step().unwrap() {
                seen[k].push((r.fatigue, r.outcome.applied_action));
            }
        }
    }
    for (k, actor) in actors.iter().enumerate() {
        let mut alone = Vec::new();
        run_policy_episode(actor, &requested, 0, 4, Start::Reset, None, None, |line| {
            alone.push((line.record.fatigue, line.record.applied_action));
            Ok(())
        })
        .unwrap();
        assert_eq!(seen[k], alone, "lane {k}");
    }
    // Two worlds, two different episodes (the same seed).
    assert_ne!(seen[0], seen[1]);
}
